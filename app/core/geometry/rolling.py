"""Camera pose through a rolling shutter: each row of a frame read at its own moment.

A phone's sensor reads its rows from top to bottom over the readout (10-30 ms at 30
frames a second), so a camera that turns or moves during it sees each row from a
slightly different pose: a pan shears the picture, a tilt stretches it. A card's four
discs then fit no single pose, and one card alone, whose pose hangs on small differences
between its discs, can be put tens of centimetres off.

The model here: the frame's pose is the one at the middle row; a row read ``tau`` frame
intervals later sees the pose moved by ``tau`` times the camera's motion (`CameraMotion`,
a constant velocity through the readout). The motion is fitted with the pose
(`rolling_shutter_pose`): several cards spread over the frame's rows pin it down; with
one card the track decides, the motion tied to the step from the track's previous pose.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import cv2
import numpy as np

from app.core.geometry.camera import Camera, Pose
from app.core.geometry.pose import PoseEstimate, TargetObservation, _stack, estimate_pose

__all__ = [
    "CameraMotion",
    "PoseHistory",
    "RollingPose",
    "RollingShutter",
    "TrackedMotion",
    "rolling_shutter_pose",
    "undo_rolling_shutter",
]

#: The disc centres' noise the motion is weighed against (pixels, 1 sigma).
DISC_SIGMA_PX = 0.2
#: How far the motion may be from the track's last step (1 sigma, per frame interval):
#: a hand-held camera's turn rate and speed change by about this much from frame to frame.
STEP_SIGMA_RAD = 0.005
STEP_SIGMA_M = 0.005
#: Without a track: the motion is drawn towards none, loosely (a turn of about 90
#: degrees a second, a walk of 1.5 m/s at 30 frames a second).
STILL_SIGMA_RAD = 0.05
STILL_SIGMA_M = 0.05
#: The motion now from the last two steps: 1.5 times the last less half the one before
#: (the last step's velocity is half a step old).
EXTRAPOLATE = 1.5
#: Posed frames in a row (each within `MAX_GAP` of the last) before the motion is carried
#: on from the last two steps: at a track's start its poses still swing about the truth,
#: and the change between steps would amplify the swing.
STEADY_FRAMES = 8
#: The most frame intervals back a pose may lie to give this frame its motion.
MAX_GAP = 3
#: Gauss-Newton iterations of the joint fit of pose and motion, and its stop (pixels).
ITERATIONS = 8
CONVERGED_PX = 1e-4


@dataclass(frozen=True)
class RollingShutter:
    """A sensor's readout.

    Attributes
    ----------
    readout : float
        Time from the first row's read to the last's, in frame intervals (the readout's
        seconds times the frame rate): 0 is a global shutter, at most 1.
    """

    readout: float

    def __post_init__(self) -> None:
        if not 0.0 <= self.readout <= 1.0:
            raise ValueError(f"the readout is {self.readout} frame intervals; it must be within [0, 1]")

    @classmethod
    def from_seconds(cls, readout_s: float, fps: float) -> RollingShutter:
        """The readout of `readout_s` seconds at `fps` frames a second.

        Parameters
        ----------
        readout_s : float
            First row's read to the last's, seconds.
        fps : float
            Frames a second.

        Returns
        -------
        RollingShutter
        """
        return cls(readout_s * fps)

    def row_times(self, rows: np.ndarray, height: int) -> np.ndarray:
        """When each row was read, frame intervals from the middle row's read.

        Parameters
        ----------
        rows : (N,) ndarray
            Image rows (pixels, as observed).
        height : int
            The image's height in rows.

        Returns
        -------
        (N,) ndarray
        """
        return (np.asarray(rows, np.float64) / max(height - 1.0, 1.0) - 0.5) * self.readout


@dataclass(frozen=True)
class CameraMotion:
    """A camera's velocity, in its own axes, per frame interval.

    A point seen at ``P`` (camera coordinates) at the frame's moment is seen at
    ``exp(tau [angular]x) P + tau * linear`` ``tau`` frame intervals later.

    Attributes
    ----------
    angular : (3,) ndarray
        Rotation per frame interval (axis times angle, radians); or (N, 3), one per
        point `seen` is given.
    linear : (3,) ndarray
        Translation per frame interval (metres); or (N, 3).
    """

    angular: np.ndarray
    linear: np.ndarray

    @classmethod
    def still(cls) -> CameraMotion:
        """No motion.

        Returns
        -------
        CameraMotion
        """
        return cls(np.zeros(3), np.zeros(3))

    @classmethod
    def between(cls, before: Pose, after: Pose, frames: float) -> CameraMotion:
        """The constant motion that takes `before` to `after` in `frames` frame intervals.

        Parameters
        ----------
        before, after : Pose
            Two poses (map to camera).
        frames : float
            Frame intervals between them (positive).

        Returns
        -------
        CameraMotion
        """
        step = after.R @ before.R.T
        return cls(cv2.Rodrigues(step)[0].ravel() / frames, (after.t - step @ before.t) / frames)

    @property
    def vector(self) -> np.ndarray:
        """(6,) ndarray: angular then linear."""
        return np.concatenate([self.angular, self.linear])

    def seen(self, points: np.ndarray, times: np.ndarray) -> np.ndarray:
        """Camera-frame points as seen `times` frame intervals away from the frame's moment.

        Parameters
        ----------
        points : (N, 3) ndarray
            Camera coordinates at the frame's moment.
        times : (N,) ndarray
            Frame intervals.

        Returns
        -------
        (N, 3) ndarray
        """
        angle_axis = times[:, None] * self.angular
        theta = np.linalg.norm(angle_axis, axis=1, keepdims=True)
        safe = np.where(theta > 1e-12, theta, 1.0)
        k = angle_axis / safe
        cos, sin = np.cos(theta), np.sin(theta)
        # Rodrigues' formula, one rotation per point.
        rotated = (points * cos + np.cross(k, points) * sin
                   + k * np.sum(k * points, axis=1, keepdims=True) * (1 - cos))
        return rotated + times[:, None] * self.linear


class TrackedMotion(NamedTuple):
    """What a track knows of the camera's motion before a frame."""

    previous: Pose  # its last pose
    frames_since: float  # frame intervals from it to this frame
    earlier: CameraMotion | None  # the step before, once the track is steady


class PoseHistory:
    """A track's last poses, for the camera's motion through the next frame's readout.

    Frames are numbered by their place in the stream (dropped ones count); a frame
    without a pose, or a gap of more than `MAX_GAP`, starts the history again.
    """

    def __init__(self) -> None:
        self._poses: list[tuple[int, Pose]] = []  # (frame, pose), the last two
        self._run = 0  # posed frames in a row

    def add(self, frame: int, pose: Pose | None) -> None:
        """Remember a frame's pose.

        Parameters
        ----------
        frame : int
            The frame's place in the stream.
        pose : Pose or None
            Its pose; None: it had none.
        """
        if pose is None:
            self._poses, self._run = [], 0
            return
        if self._poses and not 0 < frame - self._poses[-1][0] <= MAX_GAP:
            self._poses, self._run = [], 0
        self._poses = [*self._poses[-1:], (frame, pose)]
        self._run += 1

    def motion_for(self, frame: int) -> TrackedMotion | None:
        """What the track knows of the camera's motion before a frame.

        Parameters
        ----------
        frame : int
            The frame's place in the stream.

        Returns
        -------
        TrackedMotion or None
            The track's last pose and steps; None without a pose within `MAX_GAP`.
        """
        if not self._poses or not 0 < frame - self._poses[-1][0] <= MAX_GAP:
            return None
        last_frame, last = self._poses[-1]
        earlier = None
        if self._run >= STEADY_FRAMES and len(self._poses) >= 2:
            before_frame, before = self._poses[-2]
            earlier = CameraMotion.between(before, last, last_frame - before_frame)
        return TrackedMotion(last, float(frame - last_frame), earlier)


class RollingPose(NamedTuple):
    """A rolling-shutter frame's pose (at its middle row) and the camera's motion through it."""

    estimate: PoseEstimate
    motion: CameraMotion


def undo_rolling_shutter(observations: Sequence[TargetObservation], camera: Camera, shutter: RollingShutter,
                         pose: Pose, motion: CameraMotion) -> list[TargetObservation]:
    """The observations moved to where a global shutter at the frame's moment would see
    them: each disc less its rolling shutter's displacement, as `pose` and `motion`
    predict it.

    Parameters
    ----------
    observations : sequence of TargetObservation
    camera : Camera
    shutter : RollingShutter
    pose : Pose
        The frame's pose (at its middle row).
    motion : CameraMotion

    Returns
    -------
    list of TargetObservation
    """
    out = []
    for o in observations:
        at_frame = o.map @ pose.R.T + pose.t
        times = shutter.row_times(o.image[:, 1], camera.height)
        shift = camera.project(motion.seen(at_frame, times)) - camera.project(at_frame)
        out.append(replace(o, image=o.image - shift))
    return out


def _skew(v: np.ndarray) -> np.ndarray:
    """(N, 3) -> (N, 3, 3) cross-product matrices."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], -1), np.stack([v[:, 2], z, -v[:, 0]], -1),
                     np.stack([-v[:, 1], v[:, 0], z], -1)], 1)


def _perturbed(pose: Pose, delta: np.ndarray) -> Pose:
    """`pose` moved by a twist in camera axes (rotation first three)."""
    R = cv2.Rodrigues(delta[:3].reshape(3, 1))[0]
    return Pose(R @ pose.R, R @ pose.t + delta[3:])


def _fit_motion(camera: Camera, world: np.ndarray, ideal: np.ndarray, times: np.ndarray, pose: Pose,
                motion: CameraMotion, track: TrackedMotion | None) -> tuple[Pose, CameraMotion]:
    """Pose and motion minimising the reprojection error through the readout plus the
    motion's prior (Gauss-Newton on 12 parameters, in pixels with the lens distortion
    removed: `ideal` are the observed discs undistorted, `times` their rows' times)."""
    K = camera.K
    still = track is None
    sigma = np.repeat([STILL_SIGMA_RAD, STILL_SIGMA_M] if still else [STEP_SIGMA_RAD, STEP_SIGMA_M], 3)
    prior_weight = DISC_SIGMA_PX / sigma  # the prior's residuals in the pixels' units
    for _ in range(ITERATIONS):
        P = motion.seen(world @ pose.R.T + pose.t, times)
        z = P[:, 2]
        projected = (P @ K.T)[:, :2] / z[:, None]
        # d pixel / d P (pinhole), then d P / d(twist) = [-[P]x, I].
        d_pixel = np.zeros((len(P), 2, 3))
        d_pixel[:, 0, 0] = K[0, 0] / z
        d_pixel[:, 0, 1] = K[0, 1] / z
        d_pixel[:, 0, 2] = -(projected[:, 0] - K[0, 2]) / z
        d_pixel[:, 1, 1] = K[1, 1] / z
        d_pixel[:, 1, 2] = -(projected[:, 1] - K[1, 2]) / z
        d_twist = np.concatenate([-_skew(P), np.broadcast_to(np.eye(3), (len(P), 3, 3))], axis=2)
        J_pose = d_pixel @ d_twist  # (N, 2, 6)
        J = np.concatenate([J_pose, times[:, None, None] * J_pose], axis=2).reshape(-1, 12)
        if still:
            expected, lead = np.zeros(6), 0.0
        else:
            # The step from the track's last pose moves with this pose.
            expected = CameraMotion.between(track.previous, pose, track.frames_since).vector
            lead = 1.0 / track.frames_since
            if track.earlier is not None:
                # The velocity now, not half a step ago: the last step's carried on by
                # its change from the one before.
                expected = EXTRAPOLATE * expected - (EXTRAPOLATE - 1.0) * track.earlier.vector
                lead *= EXTRAPOLATE
        J_prior = np.concatenate([-lead * np.eye(6), np.eye(6)], axis=1) * prior_weight[:, None]
        r_all = np.concatenate([(projected - ideal).ravel(), (motion.vector - expected) * prior_weight])
        step = np.linalg.lstsq(np.vstack([J, J_prior]), -r_all, rcond=None)[0]
        pose = _perturbed(pose, step[:6])
        motion = CameraMotion(motion.angular + step[6:9], motion.linear + step[9:])
        if float(np.abs(J @ step).max()) < CONVERGED_PX:
            break
    return pose, motion


def rolling_shutter_pose(
    observations: Sequence[TargetObservation],
    camera: Camera,
    shutter: RollingShutter,
    track: TrackedMotion | None = None,
    prior: Pose | None = None,
    method: str = "nonlinear",
    estimate_focal: bool = False,
) -> RollingPose:
    """The pose of a rolling-shutter frame at its middle row, and the camera's motion.

    1. The discs are moved to where a global shutter would see them, as the track
       predicts the pose and the motion (the step from its last pose, or none without
       one), and `estimate_pose` gives a first pose with its outliers and its tilt
       decided as for any frame.
    2. Pose and motion are fitted together on the targets kept: the reprojection error
       through the readout, with the motion tied by a prior to the step from the
       track's last pose (carried on by the change from the step before, once the track
       is steady), or to none without a track. Cards over several rows pin the motion
       down; one card leaves it to the prior.
    3. The discs are moved again with the fitted motion and `estimate_pose` gives the
       pose reported, with its covariance (the motion taken as known). Where step 1
       refused targets, steps 2-3 run on all of them too (the readout's shear alone can
       make a card look like an outlier), and the pose keeping more targets is taken.

    Parameters
    ----------
    observations : sequence of TargetObservation
    camera : Camera
    shutter : RollingShutter
    track : TrackedMotion, optional
        The track's last pose and steps (`PoseHistory.motion_for`); None: no track.
    prior : Pose, optional
        The pose the track expects in this frame (the start, and a lone card's tilt).
    method, estimate_focal
        As `estimate_pose`.

    Returns
    -------
    RollingPose

    Raises
    ------
    PoseUndetermined
        If the observations do not determine a pose.
    """
    if shutter.readout == 0.0:
        return RollingPose(estimate_pose(observations, camera, method, estimate_focal, prior), CameraMotion.still())
    first = None
    start = prior
    if start is None:
        first = estimate_pose(observations, camera, method, estimate_focal)
        start = first.pose
    if track is not None:
        moving = undo_rolling_shutter(observations, camera, shutter, start,
                                      CameraMotion.between(track.previous, start, track.frames_since))
        first = estimate_pose(moving, camera, method, estimate_focal, prior)
    elif first is None:
        first = estimate_pose(observations, camera, method, estimate_focal, prior)
    lens = camera if not estimate_focal else camera.with_focal(first.focal_px)
    start_motion = CameraMotion.still() if track is None else CameraMotion.between(track.previous, first.pose,
                                                                                      track.frames_since)
    # Targets refused as outliers may only be sheared by the readout: the motion is
    # fitted on all of them too, and the pose that keeps more targets (then fits
    # better) is taken.
    subsets = [set(first.target_ids)] + ([{o.id for o in observations}] if first.rejected_ids else [])
    best: RollingPose | None = None
    for ids in subsets:
        image, world, _ = _stack([o for o in observations if o.id in ids])
        pose, motion = _fit_motion(lens, world, lens.undistort_pixels(image),
                                   shutter.row_times(image[:, 1], camera.height), first.pose, start_motion, track)
        final = estimate_pose(undo_rolling_shutter(observations, lens, shutter, pose, motion), camera, method,
                              estimate_focal, prior)
        if best is None or (final.n_targets, -final.rms_px) > (best.estimate.n_targets, -best.estimate.rms_px):
            best = RollingPose(final, motion)
    assert best is not None
    return best
