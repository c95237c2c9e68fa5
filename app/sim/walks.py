"""Camera walks through a box room: how a hand-held camera moves while it films.

A walk is one pose per frame (map-to-camera, ``x_cam = R @ X_map + t``), drawn from a
random stream. Its kind (`WalkKind`) says how the camera moves:

* ``"calibration"``: two loops round the room near the walls, looking across the room
  at two heights and swinging left and right (the survey video the paper asks for).
  More frames make the same path denser, not longer.
* ``"tracking"``: a smooth random path through the middle of the room looking at random
  points on the walls, turning anew about every 40 frames.
* ``"centre_loop"``: a person near the middle of the room walking a small loop (radius
  0.8-1.2 m) and filming the walls outward from it, as people film a room when nobody
  tells them how: the view turns at `TURN_DEG_S`, swings a little left and right and
  tilts up and down; the camera bobs with the steps.
* ``"pan"``: a person standing at one point near the middle turning round on the spot:
  rotation about one fixed camera centre, no baseline at all.

The last two move at a person's speed whatever their length (`FPS` frames a second): a
turn of `TURN_DEG_S` (a full turn in 10 s, 300 frames), walking at 0.5-0.75 m/s, so a
longer walk goes further round rather than slower. Heights stay within 1.2-1.8 m.

Any walk can be hand-held (`Shake`): a small, fast rotation and translation jitter
drawn after the walk from the same stream, so the walk under it is the one drawn without
it. A hand-held walk is a function of time (`Walk.poses_at`), so the camera's motion
during an exposure gives each frame its motion blur (`Walk.exposure_blur`); a frame's
pose is the one at mid-exposure.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from itertools import pairwise
from typing import Literal, get_args

import cv2
import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

from app.core.geometry import Camera, Pose
from app.sim.shutter import READOUT_SAMPLES, RollingReadout

__all__ = [
    "FPS",
    "TURN_DEG_S",
    "WALK_KINDS",
    "ExposureBlur",
    "Shake",
    "ShakeMotion",
    "Walk",
    "WalkKind",
    "camera_walk",
    "draw_walk",
    "exposure_average",
    "room_hits",
    "walk_speeds",
]

#: How a walk moves (module docstring).
WalkKind = Literal["calibration", "tracking", "centre_loop", "pan"]
#: Every walk kind.
WALK_KINDS: tuple[WalkKind, ...] = get_args(WalkKind)

#: Frames a second of a walk's clock: the speeds of the centre loop and the pan, the
#: frequencies of the shake and the length of an exposure are in seconds.
FPS = 30.0
#: How fast the centre loop and the pan turn, degrees a second: a full turn in 10 s.
TURN_DEG_S = 36.0

# The centre loop and the pan: the gaze swings left and right and tilts up and down
# (degrees, seconds a cycle), slowly enough that with the turn it stays under ~46 deg/s
# (about 60 with a hand's shake); the tilt brings cards hung low and high into view.
_SWING_DEG, _SWING_S = 6.0, 4.0
_TILT_DEG, _TILT_S = 8.0, 7.0
# Walking bob of the centre loop: metres, steps a second.
_BOB_M, _STEP_HZ = 0.015, 1.8
# How far the loop's centre or the pan's point lies from the middle of the room, metres
# at most along each axis, and how close the camera comes to a wall.
_OFF_CENTRE_M, _WALL_CLEARANCE_M = 0.5, 0.5


# --- hand-held shake ---------------------------------------------------------------


@dataclass(frozen=True)
class Shake:
    """Hand-held shake: small, fast jitter added to a walk.

    Each of the three rotation axes (in the camera's frame) and the three translation
    axes (in the map's) gets its own sum of sinusoids with frequencies drawn
    log-uniformly in `band_hz` and random phases, scaled to the given RMS: smooth from
    frame to frame yet several cycles a second, as a hand holds a phone.

    Attributes
    ----------
    rotation_deg : float
        RMS rotation about each axis, degrees.
    translation_m : float
        RMS displacement along each axis, metres (0: the camera centre stays on the walk,
        so a pan stays a pure rotation).
    band_hz : tuple of float
        (lowest, highest) frequency of the jitter, Hz.

    Raises
    ------
    ValueError
        If an amplitude is negative or the band is not 0 < lowest <= highest.
    """

    rotation_deg: float = 0.2
    translation_m: float = 0.0015
    band_hz: tuple[float, float] = (1.5, 6.0)

    def __post_init__(self) -> None:
        if not (self.rotation_deg >= 0 and self.translation_m >= 0):
            raise ValueError(f"shake amplitudes must be >= 0, got {self.rotation_deg} deg, {self.translation_m} m")
        lo, hi = self.band_hz
        if not (0 < lo <= hi and math.isfinite(hi)):
            raise ValueError(f"shake band must be 0 < lowest <= highest Hz, got {self.band_hz}")


#: Sinusoids per axis of a drawn shake.
_SHAKE_TERMS = 5


@dataclass(frozen=True, eq=False)
class ShakeMotion:
    """One drawn shake: the jitter as a function of time.

    Attributes
    ----------
    frequency_hz : (6, K) ndarray
        Frequency of each sinusoid: rows 0-2 rotation about the camera's x, y, z, rows
        3-5 translation along the map's x, y, z.
    phase_rad : (6, K) ndarray
        Their phases.
    amplitude : (6,) ndarray
        Each row's sinusoids' amplitude: radians (rows 0-2), metres (rows 3-5).
    """

    frequency_hz: np.ndarray
    phase_rad: np.ndarray
    amplitude: np.ndarray

    @classmethod
    def draw(cls, rng: np.random.Generator, shake: Shake) -> ShakeMotion:
        """A shake drawn from `rng`.

        Parameters
        ----------
        rng : numpy.random.Generator
            Draws the frequencies, then the phases.
        shake : Shake
            Its amplitudes and band.

        Returns
        -------
        ShakeMotion
        """
        lo, hi = shake.band_hz
        frequency = np.exp(rng.uniform(math.log(lo), math.log(hi), (6, _SHAKE_TERMS)))
        phase = rng.uniform(0.0, 2 * math.pi, (6, _SHAKE_TERMS))
        # K unit sinusoids of distinct frequencies have an RMS of sqrt(K / 2).
        per_term = math.sqrt(2.0 / _SHAKE_TERMS)
        amplitude = np.repeat([math.radians(shake.rotation_deg) * per_term, shake.translation_m * per_term], 3)
        return cls(frequency, phase, amplitude)

    def at(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The jitter at times `t_s`.

        Parameters
        ----------
        t_s : (N,) ndarray
            Seconds from the walk's first frame.

        Returns
        -------
        rotation : (N, 3) ndarray
            Rotation vector in the camera's frame, radians.
        offset : (N, 3) ndarray
            Displacement of the camera centre in the map's frame, metres.
        """
        t = np.asarray(t_s, np.float64)[:, None, None]
        jitter = (np.sin(2 * math.pi * self.frequency_hz * t + self.phase_rad).sum(axis=2)
                  * self.amplitude)
        return jitter[:, :3], jitter[:, 3:]


# --- the walk as a function of time ------------------------------------------------


@dataclass(frozen=True)
class ExposureBlur:
    """The motion blur of one frame: the smear of the image over the exposure.

    Attributes
    ----------
    length_px : float
        Length of the smear, pixels.
    angle_rad : float
        Its direction, radians from +x towards +y, in [0, pi).
    """

    length_px: float
    angle_rad: float
    path: tuple[Pose, ...] = ()  # the camera's poses through the exposure, evenly in time


#: Poses per pixel of smear when a frame is rendered along its exposure's path
#: (`ExposureBlur.path`), and the fewest and most of them.
PATH_SAMPLES_PER_PX = 1.0
PATH_SAMPLES = (3, 24)


def exposure_average(path: Sequence[Pose]) -> Pose:
    """The pose averaged over an exposure: the mean camera centre and the rotation
    nearest the mean rotation matrix (what an image integrated over the exposure
    shows, to first order).

    Parameters
    ----------
    path : sequence of Pose
        The poses through the exposure, evenly in time.

    Returns
    -------
    Pose
    """
    centre = np.mean([p.position for p in path], axis=0)
    U, _, Vt = np.linalg.svd(np.sum([p.R for p in path], axis=0))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return Pose(R, -R @ centre)


@dataclass(frozen=True, eq=False)
class Walk:
    """A drawn walk: the poses of its frames and, between them, of any moment.

    Attributes
    ----------
    kind : WalkKind
    base : list of Pose
        The walk's poses before any shake, one per frame.
    shake : ShakeMotion or None
        The hand-held jitter on top; None: none.
    fps : float
        Frames a second.
    poses : list of Pose
        The frames' poses, shake included (the base poses themselves without shake).
    """

    kind: WalkKind
    base: list[Pose]
    shake: ShakeMotion | None = None
    fps: float = FPS
    poses: list[Pose] = field(init=False)

    def __post_init__(self) -> None:
        poses = list(self.base) if self.shake is None else self.poses_at(np.arange(len(self.base), dtype=np.float64))
        object.__setattr__(self, "poses", poses)

    def poses_at(self, frames: np.ndarray) -> list[Pose]:
        """The poses at (fractional) frame times.

        Between frames the base walk is a cubic spline through its frames' poses (the
        centre a `CubicSpline`, the rotation a `RotationSpline`): a camera in a hand
        moves smoothly, its velocity changing continuously, not at each frame. Beyond the
        ends it is extrapolated from the nearest two frames; the shake is evaluated at
        the exact time.

        Parameters
        ----------
        frames : (N,) array_like
            Times in frames from the first (frame k is at k / fps seconds).

        Returns
        -------
        list of Pose
            At a whole frame without shake, that frame's base pose itself.
        """
        frames = np.asarray(frames, np.float64).reshape(-1)
        n = len(self.base)
        rotation = offset = None
        if self.shake is not None:
            rotation, offset = self.shake.at(frames / self.fps)
        out = []
        for k, f in enumerate(frames):
            i = min(max(math.floor(f), 0), max(n - 2, 0))
            frac = float(f - i)
            pose: Pose | None = None
            if n == 1 or (frac == 0.0 and f == i):
                pose = self.base[i]
                R, centre = pose.R, pose.position
            elif n >= 3 and 0.0 <= f <= n - 1:
                R = self._rotation_spline(f).as_matrix()
                centre = self._centre_spline(f)
            else:
                a, b = self.base[i], self.base[i + 1]
                step, _ = cv2.Rodrigues(b.R @ a.R.T)
                turn, _ = cv2.Rodrigues(frac * step)
                R = turn @ a.R
                centre = a.position + frac * (b.position - a.position)
            if rotation is not None and offset is not None:
                jitter, _ = cv2.Rodrigues(rotation[k].reshape(3, 1))
                R = jitter @ R
                centre = centre + offset[k]
                pose = None
            out.append(pose if pose is not None else Pose(R, -R @ centre))
        return out

    @functools.cached_property
    def _centre_spline(self) -> CubicSpline:
        return CubicSpline(np.arange(len(self.base), dtype=np.float64), [p.position for p in self.base])

    @functools.cached_property
    def _rotation_spline(self) -> RotationSpline:
        return RotationSpline(np.arange(len(self.base), dtype=np.float64),
                              Rotation.from_matrix([p.R for p in self.base]))

    def _within_a_frame(self, what: str, seconds: float) -> None:
        """Refuse a duration (an exposure, a readout) outside [0, 1 / fps]."""
        if not (0.0 <= seconds <= 1.0 / self.fps + 1e-12):
            raise ValueError(f"{what} must be in [0, 1 / fps] s, got {seconds}")

    def readouts(self, readout_s: float, samples: int = READOUT_SAMPLES) -> list[RollingReadout]:
        """Each frame's poses through a rolling shutter's readout, centred on the frame's
        time (the middle row is read at the frame's pose).

        Parameters
        ----------
        readout_s : float
            Time from the first row's read to the last's, seconds, at most a frame's
            (1 / fps).
        samples : int, optional
            Poses drawn through each readout (the rows between them are interpolated).

        Returns
        -------
        list of RollingReadout
            One per frame.

        Raises
        ------
        ValueError
            If the readout is negative or longer than a frame.
        """
        self._within_a_frame("readout", readout_s)
        offsets = (np.linspace(0.0, 1.0, samples) - 0.5) * readout_s * self.fps
        return [RollingReadout(tuple(self.poses_at(k + offsets))) for k in range(len(self.poses))]

    def exposure_blur(self, camera: Camera, exposure_s: float,
                      room_size: tuple[float, float, float] | None = None) -> list[ExposureBlur]:
        """Each frame's motion blur: how far the image moves during its exposure.

        The exposure is centred on the frame's time (its pose is the one at
        mid-exposure). Points the frame sees are taken on the room's faces (a 5 x 4 grid
        over the image, each pixel's ray to the wall it meets) and projected from the
        poses at the start and the end of the exposure; their mean displacement is the
        smear. One straight smear for the whole image: a roll about the optical axis
        or depth differences across the image, which blur parts of the image
        differently, are averaged.

        Parameters
        ----------
        camera : Camera
            The camera that films the walk.
        exposure_s : float
            Exposure time, seconds, at most a frame's (1 / fps).
        room_size : tuple of float, optional
            (W, D, H) of the box room, metres; without it the points are 3 m in front
            of the camera.

        Returns
        -------
        list of ExposureBlur
            One per frame.

        Raises
        ------
        ValueError
            If the exposure is negative or longer than a frame.
        """
        self._within_a_frame("exposure", exposure_s)
        n = len(self.poses)
        half = 0.5 * exposure_s * self.fps
        frames = np.arange(n, dtype=np.float64)
        start, end = self.poses_at(frames - half), self.poses_at(frames + half)
        u, v = np.meshgrid(np.linspace(0.1, 0.9, 5) * (camera.width - 1),
                           np.linspace(0.1, 0.9, 4) * (camera.height - 1))
        ideal = camera.undistort_pixels(np.stack([u.ravel(), v.ravel()], axis=1))
        rays = np.column_stack([(ideal[:, 0] - camera.cx) / camera.fx, (ideal[:, 1] - camera.cy) / camera.fy,
                                np.ones(len(ideal))])
        out = []
        for k, (pose, p0, p1) in enumerate(zip(self.poses, start, end, strict=True)):
            if room_size is None:
                points = pose.inverse().transform(3.0 * rays)
            else:
                points = room_hits(pose.position, rays @ pose.R, room_size)
            shift = (camera.project_map(points, p1) - camera.project_map(points, p0)).mean(axis=0)
            length = float(np.hypot(*shift))
            n = int(np.clip(math.ceil(PATH_SAMPLES_PER_PX * length), *PATH_SAMPLES))
            path = tuple(self.poses_at(k + np.linspace(-half, half, n))) if half > 0 else ()
            out.append(ExposureBlur(length, float(math.atan2(shift[1], shift[0]) % math.pi), path))
        return out


def room_hits(eye: np.ndarray, directions: np.ndarray, room_size: tuple[float, float, float]) -> np.ndarray:
    """Where rays from `eye` (inside the box room) along `directions` (N, 3) meet its
    faces, (N, 3)."""
    bound = np.where(directions > 0, np.asarray(room_size, np.float64), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        distance = np.where(directions != 0, (bound - eye) / directions, np.inf)
    reach = np.maximum(distance.min(axis=1), 1e-3)
    return eye + reach[:, None] * directions


def walk_speeds(poses: Sequence[Pose], fps: float = FPS) -> tuple[np.ndarray, np.ndarray]:
    """How fast a walk moves between consecutive frames.

    Parameters
    ----------
    poses : sequence of Pose
        The walk.
    fps : float, optional
        Frames a second.

    Returns
    -------
    speed : (N - 1,) ndarray
        Speed of the camera centre, metres a second.
    turn : (N - 1,) ndarray
        Rate of rotation, degrees a second.
    """
    centres = np.array([p.position for p in poses])
    speed = np.linalg.norm(np.diff(centres, axis=0), axis=1) * fps
    turn = np.array([np.degrees(np.linalg.norm(cv2.Rodrigues(b.R @ a.R.T)[0])) for a, b in pairwise(poses)])
    return speed, turn * fps


# --- the kinds of walk ---------------------------------------------------------------


def _smooth_path(rng: np.random.Generator, n_frames: int, n_knots: int, low: np.ndarray,
                 high: np.ndarray) -> np.ndarray:
    knots = rng.uniform(low, high, size=(n_knots, 3))
    spline = CubicSpline(np.linspace(0, 1, n_knots), knots, bc_type="natural")
    return spline(np.linspace(0, 1, n_frames))


def _room_walk(rng: np.random.Generator, room_size: tuple[float, float, float], n_frames: int,
               kind: str) -> list[Pose]:
    """The calibration and tracking walks: paths over the whole walk, denser with more frames."""
    w, d, _ = room_size
    centre = np.array([w / 2, d / 2, 0.0])
    up = np.array([0.0, 0.0, 1.0])
    poses = []
    if kind == "calibration":
        # Two loops near the walls looking across the room, at two heights, swinging
        # left and right: every wall is seen from far, from widely spaced viewpoints.
        s = np.linspace(0, 1, n_frames)
        angle = 4 * np.pi * s + rng.uniform(0, 2 * np.pi)
        radius = 0.8 + 0.1 * np.sin(6 * np.pi * s)
        eye = np.stack([
            centre[0] + radius * (w / 2 - 0.6) * np.cos(angle),
            centre[1] + radius * (d / 2 - 0.6) * np.sin(angle),
            1.5 - 0.2 * np.cos(2 * np.pi * s) + 0.1 * np.sin(10 * np.pi * s),
        ], axis=1)
        yaw = angle + np.pi + 0.9 * np.sin(7 * np.pi * s)
        look = eye + np.stack([np.cos(yaw), np.sin(yaw), 0.1 * np.sin(5 * np.pi * s)], axis=1)
    else:
        knots = max(4, n_frames // 40)
        eye = _smooth_path(rng, n_frames, knots, np.array([1.5, 1.5, 1.1]), np.array([w - 1.5, d - 1.5, 1.9]))
        look = _smooth_path(rng, n_frames, knots, np.array([-2.0, -2.0, 0.6]), np.array([w + 2.0, d + 2.0, 2.2]))
        # Keep the gaze at least 1 m ahead so the view direction never degenerates.
        gaze = look - eye
        gaze[:, 2] *= 0.3
        norm = np.linalg.norm(gaze, axis=1, keepdims=True)
        look = eye + gaze / np.maximum(norm, 1e-9)
    for e, t in zip(eye, look, strict=True):
        poses.append(Pose.look_at(e, t, up))
    return poses


def _near_middle(rng: np.random.Generator, room_size: tuple[float, float, float], reach_m: float) -> np.ndarray:
    """A point (x, y) near the middle of the room, at least `reach_m` + a clearance from every wall."""
    w, d, _ = room_size
    half = np.array([w / 2, d / 2])
    spare = half - reach_m - _WALL_CLEARANCE_M
    if (spare < 0).any():
        raise ValueError(f"a room of {w} x {d} m is too small for a walk reaching {reach_m} m from its middle")
    room_for = np.minimum(spare, _OFF_CENTRE_M)
    return half + rng.uniform(-room_for, room_for)


def _gaze(rng: np.random.Generator, t_s: np.ndarray, swing: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """Yaw (radians, before the turn's start) and pitch of the centre loop and the pan, and
    the turn's direction: a steady turn, optionally swinging, tilting up and down."""
    direction = float(rng.choice([-1.0, 1.0]))
    swing_phase, tilt_phase = rng.uniform(0.0, 2 * math.pi, 2)
    yaw = direction * math.radians(TURN_DEG_S) * t_s
    if swing:
        yaw = yaw + math.radians(_SWING_DEG) * np.sin(2 * math.pi * t_s / _SWING_S + swing_phase)
    pitch = math.radians(_TILT_DEG) * np.sin(2 * math.pi * t_s / _TILT_S + tilt_phase)
    return yaw, pitch, direction


def _looking(eye: np.ndarray, yaw: np.ndarray, pitch: np.ndarray) -> list[Pose]:
    gaze = np.stack([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)], axis=1)
    up = np.array([0.0, 0.0, 1.0])
    return [Pose.look_at(e, e + g, up) for e, g in zip(eye, gaze, strict=True)]


def _centre_loop(rng: np.random.Generator, room_size: tuple[float, float, float], n_frames: int,
                 fps: float) -> list[Pose]:
    radius = float(rng.uniform(0.8, 1.2))
    middle = _near_middle(rng, room_size, radius)
    height = float(rng.uniform(1.3, 1.7))
    start = float(rng.uniform(0.0, 2 * math.pi))
    bob_phase = float(rng.uniform(0.0, 2 * math.pi))
    t = np.arange(n_frames) / fps
    yaw, pitch, direction = _gaze(rng, t, swing=True)
    # Walking round the loop while facing out of it: the loop's angle is the turn.
    angle = start + direction * math.radians(TURN_DEG_S) * t
    eye = np.column_stack([middle[0] + radius * np.cos(angle), middle[1] + radius * np.sin(angle),
                           height + _BOB_M * np.sin(2 * math.pi * _STEP_HZ * t + bob_phase)])
    return _looking(eye, start + yaw, pitch)


def _pan(rng: np.random.Generator, room_size: tuple[float, float, float], n_frames: int, fps: float) -> list[Pose]:
    point = _near_middle(rng, room_size, 0.0)
    height = float(rng.uniform(1.2, 1.8))
    start = float(rng.uniform(0.0, 2 * math.pi))
    yaw, pitch, _ = _gaze(rng, np.arange(n_frames) / fps, swing=False)
    eye = np.tile([point[0], point[1], height], (n_frames, 1))
    return _looking(eye, start + yaw, pitch)


def draw_walk(
    rng: np.random.Generator,
    room_size: tuple[float, float, float],
    n_frames: int,
    kind: WalkKind = "calibration",
    shake: Shake | None = None,
    fps: float = FPS,
) -> Walk:
    """A walk through a room, drawn from `rng`.

    Parameters
    ----------
    rng : numpy.random.Generator
        Draws the walk, then its shake.
    room_size : tuple of float
        (W, D, H) of the room, metres.
    n_frames : int
        Frames of the walk.
    kind : WalkKind, optional
        How the camera moves (module docstring).
    shake : Shake, optional
        Hand-held jitter on top of the walk; none by default.
    fps : float, optional
        Frames a second: the speed of the centre loop and the pan per frame, and the
        shake's frequencies.

    Returns
    -------
    Walk

    Raises
    ------
    ValueError
        If `kind` is unknown, or the room is too small for a centre loop.
    """
    if kind in ("calibration", "tracking"):
        base = _room_walk(rng, room_size, n_frames, kind)
    elif kind == "centre_loop":
        base = _centre_loop(rng, room_size, n_frames, fps)
    elif kind == "pan":
        base = _pan(rng, room_size, n_frames, fps)
    else:
        raise ValueError(f"unknown walk kind {kind!r}: one of {', '.join(WALK_KINDS)}")
    return Walk(kind, base, ShakeMotion.draw(rng, shake) if shake is not None else None, fps)


def camera_walk(
    rng: np.random.Generator,
    room_size: tuple[float, float, float],
    n_frames: int,
    kind: WalkKind = "calibration",
    shake: Shake | None = None,
    fps: float = FPS,
) -> list[Pose]:
    """The poses of a walk through a room (`draw_walk`).

    Parameters
    ----------
    rng : numpy.random.Generator
        Draws the walk, then its shake.
    room_size : tuple of float
        (W, D, H) of the room, metres.
    n_frames : int
        Poses in the walk.
    kind : WalkKind, optional
        "calibration": two loops around the room looking outward at the walls, at two
        heights, so every wall is seen from widely spaced viewpoints (as the paper asks
        of a survey video). "tracking": a random smooth path looking at random wall
        points. "centre_loop": a small loop near the middle of the room looking out at
        the walls. "pan": turning round on one spot.
    shake : Shake, optional
        Hand-held jitter on top of the walk; none by default.
    fps : float, optional
        Frames a second (the centre loop's and the pan's speeds, the shake).

    Returns
    -------
    list of Pose
        Map-to-camera transforms, one per frame.

    Raises
    ------
    ValueError
        If `kind` is unknown.
    """
    return draw_walk(rng, room_size, n_frames, kind, shake, fps).poses
