"""A stream's memory between frames (`TrackState`): where to search the next frame, and
the pose the track expects there."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from app.core.geometry import (
    Camera,
    MapTargets,
    Pose,
    PoseEstimate,
    PoseHistory,
    PredictedTarget,
    Region,
    RegionParams,
    TrackedMotion,
    extrapolate,
    plan_regions,
    predict_in_view,
    predict_regions,
    rotation_angle,
)


class ScanReason(StrEnum):
    """Why a frame was scanned as it was: in regions, or whole and why."""

    REGIONS = "regions"  # around the targets the last poses predict
    OFF = "off"  # the client turned regions off
    FIRST = "first"  # the stream's first frame
    CAMERA = "camera"  # the frame's size or intrinsics changed
    LOST = "lost"  # the last frame had no pose
    PERIODIC = "periodic"  # a whole scan every `full_scan_every` frames
    STALE = "stale"  # too many frames since the last pose
    WIDE = "wide"  # the regions would cover most of the frame
    FALLBACK = "fallback"  # the regions gave no pose: scanned whole at once
    SINGLE = "single"  # a lone image, no stream


@dataclass(frozen=True, eq=False)
class _Seen:
    """A frame's pose, the seq of that frame, and the camera it was computed with."""

    seq: int
    pose: Pose
    camera: Camera


#: Frames in a row whose lone card's tilt the track chose against the reprojection error,
#: after which the error decides one frame (`TrackState.prior`).
TILT_OVERRULED_LIMIT = 3
#: A turn between two consecutive poses faster than this (rad per frame, 10 degrees: 300
#: degrees a second at 30 fps) is a jump between tilts, not a camera's motion.
MAX_TURN_PER_FRAME_RAD = np.radians(10.0)


class TrackState:
    """One stream's memory between frames: its last two poses (for a position and a
    velocity), the camera of its last frame, and frames since the last full scan.
    Frames of one stream are processed one at a time, but the lock keeps the state whole
    whatever calls it."""

    def __init__(self, params: RegionParams | None = None) -> None:
        self.params = params or RegionParams()
        self._lock = threading.Lock()
        self._last: _Seen | None = None
        self._before: _Seen | None = None
        self._camera: Camera | None = None  # intrinsics and size of the last frame
        self._since_full = 0
        self._overruled = 0  # consecutive frames whose tilt the track chose against the residual
        # The last two poses again, kept through frames without a pose (which clear the
        # ones above, for a whole scan): a card lost for a frame or two is still
        # expected where it was.
        self._posed: tuple[_Seen | None, _Seen | None] = (None, None)
        self._history = PoseHistory()  # the camera's motion through a rolling shutter's readout

    def plan(self, seq: int, camera: Camera, targets: MapTargets, *, regions: bool = True,
             full_scan_every: int = 30, in_view: list[PredictedTarget] | None = None
             ) -> tuple[list[Region] | None, ScanReason]:
        """Regions to search in frame `seq` and why.

        Parameters
        ----------
        seq : int
            The frame's number in the stream.
        camera : Camera
            The camera at the frame's size.
        targets : MapTargets
            The map's discs.
        regions : bool
            False: always the whole frame (`ScanReason.OFF`).
        full_scan_every : int
            A whole scan at least this often, in frames.
        in_view : list, optional
            Receives the map targets (`PredictedTarget`) the last poses predict in the
            frame, whenever there are poses to predict from, whole scans due by
            `full_scan_every` or covering most of the frame included: how large their
            discs will be says how small the frame may be decoded.

        Returns
        -------
        regions : list of Region or None
            The crops to search; None: the whole frame.
        reason : ScanReason
            Why.
        """
        with self._lock:
            if not regions:
                return None, ScanReason.OFF
            if self._camera is None:
                return None, ScanReason.FIRST
            if camera is not self._camera and camera != self._camera:
                return None, ScanReason.CAMERA
            last, before = self._last, self._before
            if last is None:
                return None, ScanReason.LOST
            periodic = self._since_full + 1 >= full_scan_every
            if periodic and in_view is None:
                return None, ScanReason.PERIODIC
            steps = seq - last.seq
            if not 0 < steps <= self.params.max_steps:
                return None, ScanReason.PERIODIC if periodic else ScanReason.STALE
            gap = last.seq - before.seq if before is not None else 0
            if before is None or not 0 < gap <= self.params.max_steps:
                before, gap = None, 1
        # (prediction outside the lock: it only reads the snapshot taken above)
        if in_view is None:
            crops = predict_regions(targets, last.camera, last.pose, steps, before.pose if before else None, gap,
                                    self.params)
        else:
            predicted = predict_in_view(targets, last.camera, last.pose, steps, before.pose if before else None, gap,
                                        self.params)
            in_view.extend(predicted)
            if periodic:
                return None, ScanReason.PERIODIC
            crops = plan_regions(predicted, last.camera.width, last.camera.height, self.params)
        if crops is None:
            return None, ScanReason.WIDE
        return crops, ScanReason.REGIONS

    def prior(self, seq: int) -> Pose | None:
        """The pose the track expects in frame `seq` (constant velocity from the last two
        poses), or None without a recent pose. A pose maps the map into the camera, so it
        holds whatever the frame's size or intrinsics.

        A track that took a lone card's tilt against its reprojection error for
        `TILT_OVERRULED_LIMIT` frames in a row gives no prior for one frame: the error
        then decides. A residual picks the wrong tilt in one frame of several at most,
        independently from frame to frame, so a run of disagreements means the track
        itself started on the wrong tilt (a first frame after a loss, say) and would
        otherwise hold it for as long as the card is seen alone.

        Parameters
        ----------
        seq : int
            The frame's number in the stream.

        Returns
        -------
        Pose or None
            The expected pose, map to camera.
        """
        with self._lock:
            (before, last), overruled = self._posed, self._overruled
        if last is None or not 0 < seq - last.seq <= self.params.max_steps or overruled >= TILT_OVERRULED_LIMIT:
            return None
        gap = last.seq - before.seq if before is not None else 0
        if before is None or not 0 < gap <= self.params.max_steps:
            return last.pose
        if rotation_angle(last.pose, before.pose) > MAX_TURN_PER_FRAME_RAD * gap:
            return last.pose  # a jump (a tilt changed between them), not a motion to go on with
        return extrapolate(before.pose, last.pose, (seq - last.seq) / gap)

    def motion(self, seq: int) -> TrackedMotion | None:
        """The track's last pose and steps before frame `seq`, for a rolling shutter.

        Parameters
        ----------
        seq : int
            The frame's number in the stream.

        Returns
        -------
        TrackedMotion or None
            None without a recent pose.
        """
        with self._lock:
            return self._history.motion_for(seq)

    def update(self, seq: int, camera: Camera, estimate: PoseEstimate | None, full: bool) -> None:
        """Remember frame `seq`'s outcome.

        Parameters
        ----------
        seq : int
            The frame's number in the stream.
        camera : Camera
            The camera at the frame's size.
        estimate : PoseEstimate or None
            The frame's pose, in the frame's own pixels; None: no pose.
        full : bool
            Whether the frame was scanned whole.
        """
        seen = None
        if estimate is not None:
            if abs(estimate.focal_px - camera.fx) > 1e-9 * camera.fx:
                # A zoom lens (estimate_focal): predict with the focal length just measured.
                seen = _Seen(seq, estimate.pose, camera.with_focal(estimate.focal_px))
            else:
                seen = _Seen(seq, estimate.pose, camera)
        with self._lock:
            if camera is not self._camera and camera != self._camera:
                self._camera, self._last, self._before = camera, None, None
            self._since_full = 0 if full else self._since_full + 1
            self._overruled = self._overruled + 1 if estimate is not None and estimate.tilt_from_track else 0
            if seen is None:
                self._last = self._before = None  # lost: the next frame is scanned whole
            elif self._last is None or seq > self._last.seq:
                self._before, self._last = self._last, seen
            if seen is not None and (self._posed[1] is None or seq > self._posed[1].seq):
                self._posed = (self._posed[1], seen)
            self._history.add(seq, None if seen is None else seen.pose)
