"""One frame: its plan (camera, regions, how small to decode it), its targets and pose."""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field, replace

import numpy as np

from app.core.detection import DetectedTarget, Detection, Detector
from app.core.geometry import (
    Camera,
    MapTargets,
    Pose,
    PoseEstimate,
    PoseUndetermined,
    PredictedTarget,
    Region,
    RollingShutter,
    TargetObservation,
    TrackedMotion,
    decode_reduction,
    estimate_pose,
    reduce_regions,
    rolling_shutter_pose,
)
from app.core.tracking.state import ScanReason, TrackState

#: Smallest predicted disc diameter, pixels of the decoded frame, for a stream's frame to
#: be decoded smaller (see `plan_frame`): the detector finds discs from 3.5 px across.
REDUCED_MIN_DISC_PX = 5.0
#: Smallest side of a frame decoded smaller, pixels: 1280x720 at 1/4 (320x180) gave a
#: 90th-percentile position error of 15 mm instead of 3 on the bench walk.
REDUCED_MIN_SIDE = 360
#: The factors a stream's frame may be decoded smaller by.
REDUCTIONS = (1, 2, 4)


@dataclass(frozen=True, eq=False)
class TrackingMap:
    """What tracking needs of a map: its camera and each target's discs (and their
    uncertainty, where the map has it)."""

    camera: Camera
    discs: dict[int, np.ndarray]  # target id -> (4, 3) map coordinates, metres
    std: dict[int, np.ndarray] = field(default_factory=dict)  # target id -> (4,) std_m

    @functools.cached_property
    def targets(self) -> MapTargets:
        """The map's discs stacked for region prediction (built on first use)."""
        return MapTargets.from_discs(self.discs)


@dataclass(frozen=True)
class TrackOptions:
    """How a client wants its frames tracked."""

    method: str = "nonlinear"  # `app.core.geometry.METHODS`
    estimate_focal: bool = False  # free the focal length per frame (a zoom lens)
    intrinsics: Camera | None = None  # in place of the map's camera
    regions: bool = True  # search around the predicted targets (a stream's frames)
    full_scan_every: int = 30  # a whole scan at least this often, in frames
    tilt_from_track: bool = True  # the track's expected pose decides a lone card's tilt
    shutter: RollingShutter | None = None  # a rolling shutter's readout, modelled in the pose


@dataclass(frozen=True)
class FramePlan:
    """How a frame is scanned, decided from its size before it is decoded.

    Attributes
    ----------
    camera : Camera
        The camera at the frame's own size.
    regions : list of Region or None
        Crops to search, the frame's pixels; None: the whole frame.
    reason : ScanReason
        Why.
    reduction : int
        Decode a JPEG at 1 / this (1: whole).
    ms : float
        Milliseconds the plan took.
    """

    camera: Camera
    regions: list[Region] | None
    reason: ScanReason
    reduction: int
    ms: float


@dataclass(frozen=True)
class TrackedFrame:
    """One frame's outcome, in the frame's own pixels whatever its reduction.

    Attributes
    ----------
    targets : list of DetectedTarget
        The targets found.
    estimate : PoseEstimate or None
        The camera pose; None: `pose_error` says why.
    pose_error : str or None
        Why there is no pose.
    timing_ms : dict
        Milliseconds of the plan, the detector's stages and the pose, and the reduction
        when the frame was decoded smaller.
    regions : bool
        Whether the frame was scanned in regions (else whole).
    reason : ScanReason
        Why it was scanned so.
    """

    targets: list[DetectedTarget]
    estimate: PoseEstimate | None
    pose_error: str | None
    timing_ms: dict[str, float]
    regions: bool
    reason: ScanReason


def frame_camera(track_map: TrackingMap, options: TrackOptions, width: int, height: int) -> Camera:
    """The camera of a `width` x `height` frame.

    Parameters
    ----------
    track_map : TrackingMap
        The map, whose camera is taken unless `options` give intrinsics.
    options : TrackOptions
        The client's options.
    width, height : int
        The frame's size, pixels.

    Returns
    -------
    Camera
        The map's camera, or the options' intrinsics, scaled to the frame's size.
    """
    camera = options.intrinsics if options.intrinsics is not None else track_map.camera
    if (width, height) != (camera.width, camera.height):
        camera = camera.scaled_to(width, height)
    return camera


def reducible(width: int, height: int) -> bool:
    """Whether a frame is large enough to be decoded smaller (640x480 is not).

    Parameters
    ----------
    width, height : int
        The frame's size, pixels.

    Returns
    -------
    bool
        True when some reduction keeps both sides at least `REDUCED_MIN_SIDE`.
    """
    return any(-(-min(width, height) // f) >= REDUCED_MIN_SIDE for f in REDUCTIONS[1:])


def plan_frame(track_map: TrackingMap, options: TrackOptions, width: int, height: int,
               state: TrackState | None = None, seq: int = 0) -> FramePlan:
    """The plan of a `width` x `height` frame: its camera, its regions and why, and how
    much smaller it may be decoded.

    A stream's frame is decoded at 1/2 or 1/4 when its poses predict every mapped disc
    in view at least `REDUCED_MIN_DISC_PX` across at that scale: the detector's cost
    follows the pixels it scans and the decoder's follows the pixels it writes, while the
    disc centres of large discs stay well measured in a smaller frame. Without poses to
    predict from (a first frame, a lost track, a new camera, whole scans asked for), and
    for lone images, the frame is decoded whole: nothing says how small its discs are.

    Parameters
    ----------
    track_map : TrackingMap
        The map.
    options : TrackOptions
        The client's options.
    width, height : int
        The frame's size from its header, pixels.
    state : TrackState, optional
        The stream's memory; None: a lone image, scanned whole.
    seq : int
        The frame's number in the stream.

    Returns
    -------
    FramePlan
        The plan.
    """
    started = time.perf_counter()
    camera = frame_camera(track_map, options, width, height)
    if state is None:
        return FramePlan(camera, None, ScanReason.SINGLE, 1, (time.perf_counter() - started) * 1e3)
    if not reducible(width, height):
        regions, reason = state.plan(seq, camera, track_map.targets, regions=options.regions,
                                     full_scan_every=options.full_scan_every)
        return FramePlan(camera, regions, reason, 1, (time.perf_counter() - started) * 1e3)
    in_view: list[PredictedTarget] = []
    regions, reason = state.plan(seq, camera, track_map.targets, regions=options.regions,
                                 full_scan_every=options.full_scan_every, in_view=in_view)
    reduction = decode_reduction(in_view, width, height, REDUCED_MIN_DISC_PX, REDUCTIONS,
                                 REDUCED_MIN_SIDE) if in_view else 1
    return FramePlan(camera, regions, reason, reduction, (time.perf_counter() - started) * 1e3)


def reduced_camera(camera: Camera, factor: int, width: int, height: int) -> Camera:
    """`camera` for the frame decoded at 1 / `factor`.

    Pixel centres scale about the top-left pixel's corner by exactly 1 / `factor`, as
    the decoder's pixels do (`Camera.scaled_to` would scale by the rounded size).

    Parameters
    ----------
    camera : Camera
        The camera at the frame's own size.
    factor : int
        The reduction.
    width, height : int
        The decoded frame's size (the decoder's rounded-up size), pixels.

    Returns
    -------
    Camera
        The camera of the decoded pixels.
    """
    K = camera.K.copy()
    K[0, 0], K[0, 1], K[1, 1] = K[0, 0] / factor, K[0, 1] / factor, K[1, 1] / factor
    K[0, 2] = (K[0, 2] + 0.5) / factor - 0.5
    K[1, 2] = (K[1, 2] + 0.5) / factor - 0.5
    return Camera(K, camera.dist, int(width), int(height))


def full_scale_targets(targets: list[DetectedTarget], factor: int) -> list[DetectedTarget]:
    """Targets found in the frame decoded at 1 / `factor`, in the frame's own pixels.

    Parameters
    ----------
    targets : list of DetectedTarget
        As found in the decoded pixels.
    factor : int
        The reduction.

    Returns
    -------
    list of DetectedTarget
        The same targets, disc centres and radii scaled back.
    """
    return [replace(t, discs=(np.asarray(t.discs) + 0.5) * factor - 0.5, disc_radii=np.asarray(t.disc_radii) * factor)
            for t in targets]


def full_scale_estimate(estimate: PoseEstimate, factor: int) -> PoseEstimate:
    """A pose estimated in the frame decoded at 1 / `factor`, with its pixel quantities
    in the frame's own pixels.

    The pose and the position's covariance do not depend on the scale; the reprojection
    error, the focal length and its variance do.

    Parameters
    ----------
    estimate : PoseEstimate
        As estimated in the decoded pixels.
    factor : int
        The reduction.

    Returns
    -------
    PoseEstimate
        The estimate in the frame's own pixels.
    """
    covariance = np.array(estimate.covariance, np.float64, copy=True)
    if covariance.shape[0] > 6:  # (rvec, tvec, f): the focal length's row and column are pixels
        covariance[6:, :] *= factor
        covariance[:, 6:] *= factor
    return replace(estimate, rms_px=estimate.rms_px * factor, focal_px=estimate.focal_px * factor,
                   covariance=covariance)


def detect_and_pose(detector: Detector, gray: np.ndarray, regions: list[Region] | None, track_map: TrackingMap,
                    camera: Camera, options: TrackOptions, prior: Pose | None = None,
                    motion: TrackedMotion | None = None) -> tuple[Detection, PoseEstimate | None, str | None, float]:
    """Detect the targets in `gray` (in `regions`, or whole) and estimate the pose from
    those in the map.

    Parameters
    ----------
    detector : Detector
        The environment's detector.
    gray : ndarray
        The frame as decoded, uint8 greyscale.
    regions : list of Region or None
        Crops of `gray` to search; None: all of it.
    track_map : TrackingMap
        The map.
    camera : Camera
        The camera of `gray`'s pixels.
    options : TrackOptions
        The client's options.
    prior : Pose, optional
        The track's expected pose: it decides a lone card's tilt.
    motion : TrackedMotion, optional
        The track's last pose and steps: the start of the camera's motion through a
        rolling shutter's readout.

    Returns
    -------
    detection : Detection
        What the detector found.
    estimate : PoseEstimate or None
        The pose; None when the targets do not determine one.
    error : str or None
        Why there is no pose.
    pose_ms : float
        Milliseconds spent on the pose.
    """
    detection = detector.detect(gray, regions)
    observations = [
        TargetObservation(t.id, t.discs, track_map.discs[t.id], track_map.std.get(t.id))
        for t in detection.targets if t.id in track_map.discs
    ]
    posed = time.perf_counter()
    estimate: PoseEstimate | None
    try:
        if options.shutter is not None and observations:
            estimate = rolling_shutter_pose(observations, camera, options.shutter, motion, prior, options.method,
                                            options.estimate_focal).estimate
        else:
            estimate = estimate_pose(observations, camera, options.method, options.estimate_focal, prior)
        error = None
    except PoseUndetermined as exc:
        estimate, error = None, str(exc)
    return detection, estimate, error, (time.perf_counter() - posed) * 1e3


def track_frame(detector: Detector, gray: np.ndarray, reduction: int, plan: FramePlan, track_map: TrackingMap,
                options: TrackOptions, state: TrackState | None = None, seq: int = 0) -> TrackedFrame:
    """A decoded frame's targets and pose, as `plan` says to scan it.

    Detection and the pose run on the frame as decoded, through the camera scaled to it;
    when the regions give no pose (fast motion, a wrong prior) the whole frame is scanned
    at once. The stream's state, the targets and the pose come back in the frame's own
    pixels whatever its reduction.

    Parameters
    ----------
    detector : Detector
        The environment's detector.
    gray : ndarray
        The frame as decoded (at 1 / `reduction`), uint8 greyscale.
    reduction : int
        The factor it was decoded smaller by (1: whole).
    plan : FramePlan
        The frame's plan (`plan_frame`).
    track_map : TrackingMap
        The map.
    options : TrackOptions
        The client's options.
    state : TrackState, optional
        The stream's memory, updated with the frame's outcome; None: a lone image.
    seq : int
        The frame's number in the stream.

    Returns
    -------
    TrackedFrame
        The targets, the pose or why there is none, timings and how it was scanned.
    """
    camera, regions, reason = plan.camera, plan.regions, plan.reason
    scan_camera, scan_regions = camera, regions
    if reduction > 1:
        scan_camera = reduced_camera(camera, reduction, gray.shape[1], gray.shape[0])
        if regions is not None:
            scan_regions = reduce_regions(regions, reduction, gray.shape[1], gray.shape[0])
    prior = state.prior(seq) if state is not None and options.tilt_from_track else None
    motion = state.motion(seq) if state is not None else None
    detection, estimate, pose_error, pose_ms = detect_and_pose(detector, gray, scan_regions, track_map, scan_camera,
                                                               options, prior, motion)
    timing = {"plan": plan.ms, **detection.timing_ms}
    if estimate is None and regions is not None:
        reason, regions = ScanReason.FALLBACK, None
        detection, estimate, pose_error, more_ms = detect_and_pose(detector, gray, None, track_map, scan_camera,
                                                                   options, prior, motion)
        pose_ms += more_ms
        for key, value in detection.timing_ms.items():
            timing[key] = timing.get(key, 0.0) + value
    targets = detection.targets
    if reduction > 1:
        timing["reduction"] = float(reduction)
        targets = full_scale_targets(targets, reduction)
        if estimate is not None:
            estimate = full_scale_estimate(estimate, reduction)
    if state is not None:
        state.update(seq, camera, estimate, full=regions is None)
    timing["pose"] = pose_ms
    return TrackedFrame(targets, estimate, pose_error, timing, regions is not None, reason)
