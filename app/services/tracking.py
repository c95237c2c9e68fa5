"""Tracking: per frame, detect targets and compute the camera pose from the map.

An environment's map and detector are loaded once and shared by every client; a new
map (survey, import, alignment) is picked up by the next connection or ``locate`` call,
and by open /track connections, which ask for the context every ``map_poll_s``.

A /track connection also has a memory (`TrackState`): its last two poses predict where
the map's targets appear in the next frame, and only regions around them are searched
(app.core.geometry.regions). The whole frame is scanned when there is no usable pose (the first
frame, track lost, too many frames dropped since), when the camera changed, when the
predicted regions would cover most of the frame anyway, every ``full_scan_every``
frames (targets not in the map, a wrong prior), and again, at once, when a region scan
gives no pose. ``POST /environments/{id}/locate`` (one image, no history) always scans
the whole frame.

The detector's compiled kernels (`DetectorKernels`) load, or on a machine's first start
compile, in a thread of their own while the server already answers.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from datetime import datetime
from typing import Literal

import numpy as np
from numba.core import event as numba_event
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app.core.detection import Detection, Detector, warm_up
from app.core.geometry import (
    METHODS,
    Camera,
    PoseHistory,
    RollingShutter,
    TrackedMotion,
    MapTargets,
    Pose,
    PoseEstimate,
    PoseUndetermined,
    Region,
    RegionParams,
    TargetObservation,
    decode_reduction,
    estimate_pose,
    extrapolate,
    plan_regions,
    rolling_shutter_pose,
    predict_in_view,
    predict_regions,
    reduce_regions,
    rotation_angle,
)
from app.schemas import (
    CameraModel,
    DetectedTargetOut,
    LocateResponse,
    MapDocument,
    PoseOut,
    ScanReason,
    TrackConfig,
)
from app.models import SurveyMap
from app.services import classifiers, environments, images
from app.services.detection import DetectorCache, DetectorKey
from app.services.errors import NoMap
from app.settings import Settings

assert set(TrackConfig.model_fields["method"].annotation.__args__) == set(METHODS)  # type: ignore[union-attr]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class TrackingContext:
    """Everything one environment needs per frame, loaded once."""

    environment_id: int
    map_version: str
    camera: Camera
    camera_model: CameraModel  # the map's camera as clients get it
    map_frame: Literal["survey", "world"]
    discs: dict[int, np.ndarray]  # target id -> (4, 3) map coordinates
    detector_key: DetectorKey
    std: dict[int, np.ndarray] = field(default_factory=dict)  # target id -> (4,) std_m, where the map has it

    @functools.cached_property
    def targets(self) -> MapTargets:
        """The map's discs stacked for region prediction (built on first use)."""
        return MapTargets.from_discs(self.discs)


# --------------------------------------------------------------------------------------
# Per-connection state
# --------------------------------------------------------------------------------------


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
    """One /track connection's memory between frames: its last two poses (for a
    position and a velocity), the camera of its last frame, and frames since the last
    full scan. Frames of one connection are processed one at a time, but the lock keeps
    the state whole whatever calls it."""

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

    def plan(self, seq: int, camera: Camera, config: TrackConfig, targets: MapTargets,
             in_view: list | None = None) -> tuple[list[Region] | None, str]:
        """Regions to search in frame `seq` (None: the whole frame) and why.

        `in_view`: a list that receives the map targets (`PredictedTarget`) the last
        poses predict in the frame, whenever there are poses to predict from, full scans
        due by ``full_scan_every`` or covering most of the frame included: how large
        their discs will be, which says how small the frame may be decoded."""
        with self._lock:
            if not config.regions:
                return None, "off"
            if self._camera is None:
                return None, "first"
            if camera is not self._camera and camera != self._camera:
                return None, "camera"
            last, before = self._last, self._before
            if last is None:
                return None, "lost"
            periodic = self._since_full + 1 >= config.full_scan_every
            if periodic and in_view is None:
                return None, "periodic"
            steps = seq - last.seq
            if not 0 < steps <= self.params.max_steps:
                return None, "periodic" if periodic else "stale"
            gap = last.seq - before.seq if before is not None else 0
            if before is None or not 0 < gap <= self.params.max_steps:
                before, gap = None, 1
        # (prediction outside the lock: it only reads the snapshot taken above)
        if in_view is None:
            regions = predict_regions(targets, last.camera, last.pose, steps, before.pose if before else None, gap,
                                      self.params)
        else:
            predicted = predict_in_view(targets, last.camera, last.pose, steps, before.pose if before else None, gap,
                                        self.params)
            in_view.extend(predicted)
            if periodic:
                return None, "periodic"
            regions = plan_regions(predicted, last.camera.width, last.camera.height, self.params)
        if regions is None:
            return None, "wide"
        return regions, "regions"

    def prior(self, seq: int) -> Pose | None:
        """The pose the track expects in frame `seq` (constant velocity from the last two
        poses), or None without a recent pose. A pose maps the map into the camera, so it
        holds whatever the frame's size or intrinsics.

        A track that took a lone card's tilt against its reprojection error for
        `TILT_OVERRULED_LIMIT` frames in a row gives no prior for one frame: the error
        then decides. A residual picks the wrong tilt in one frame of several at most,
        independently from frame to frame, so a run of disagreements means the track
        itself started on the wrong tilt (a first frame after a loss, say) and would
        otherwise hold it for as long as the card is seen alone."""
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
        """The track's last pose and steps before frame `seq` (for a rolling shutter), or
        None without a recent pose."""
        with self._lock:
            return self._history.motion_for(seq)

    def update(self, seq: int, camera: Camera, estimate: PoseEstimate | None, full: bool) -> None:
        """Remember frame `seq`'s outcome."""
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


@dataclass(frozen=True)
class StreamFrame:
    """A frame of a /track connection: its config, its seq and the connection's state
    (`TrackingService.locate_frame` takes it in place of a bare config)."""

    config: TrackConfig
    seq: int
    state: TrackState


@dataclass(frozen=True)
class FrameResult:
    """The outcome of one frame: its targets, the pose or why there is none, and how it was scanned."""

    targets: list[DetectedTargetOut]
    pose: PoseOut | None
    pose_error: str | None
    timing_ms: dict[str, float]
    width: int
    height: int
    scan: Literal["full", "regions"] = "full"
    scan_reason: ScanReason | Literal["single"] = "single"


class _OnCompile(numba_event.Listener):
    """Calls `callback` when numba starts compiling: a kernel not found in its cache."""

    def __init__(self, callback: Callable[[], None]) -> None:
        self.callback = callback

    def on_start(self, event: numba_event.Event) -> None:
        self.callback()

    def on_end(self, event: numba_event.Event) -> None:
        pass


class DetectorKernels:
    """The detector's compiled (numba) kernels, loaded in a thread of their own: from
    numba's cache in under a second, or compiled on a machine's first start (10-30 s)
    while the server already answers; `not_ready` says why until they are done. A frame
    that comes first does not fail: the kernels it calls compile on their first call,
    numba's compiler lock making it wait for the compilation under way."""

    COMPILING = "compiling the detector's kernels"
    LOADING = "loading the detector's kernels"

    def __init__(self, compile_all: Callable[[], None] = warm_up) -> None:
        self._compile_all = compile_all
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._compiling = threading.Event()
        self._settled = threading.Event()  # done, or found to need compiling
        self._error: str | None = None
        self.seconds: float | None = None

    def start(self) -> None:
        # A daemon: a server stopped during a first compilation exits without waiting for it.
        threading.Thread(target=self._run, name="detector-kernels", daemon=True).start()

    def _run(self) -> None:
        started = time.perf_counter()
        try:
            with numba_event.install_listener("numba:compile", _OnCompile(self._compiling_started)):
                self._compile_all()
        except Exception as exc:
            self._error = f"the detector's kernels failed to compile: {type(exc).__name__}: {exc}"
            log.exception("the detector's kernels failed to compile")
        else:
            self.seconds = time.perf_counter() - started
            log.info(f"kernels ready ({self.seconds:.1f} s)", extra={"fields": {"seconds": round(self.seconds, 2)}})
        finally:
            self._done.set()
            self._settled.set()

    def _compiling_started(self) -> None:
        with self._lock:
            if self._compiling.is_set():
                return
            self._compiling.set()
        log.info(f"{self.COMPILING}: 10-30 s on a machine's first start, then loaded from numba's cache")
        self._settled.set()

    def wait_unless_compiling(self, timeout: float) -> bool:
        """Wait for kernels loaded from numba's cache, but not for a compilation: until they
        are done, or found to need compiling, or `timeout` seconds; True once done."""
        self._settled.wait(timeout)
        return self._done.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait up to `timeout` seconds (None: until done); True once they are done."""
        return self._done.wait(timeout)

    @property
    def not_ready(self) -> str | None:
        """Why the detector cannot run at full speed yet, or None once it can."""
        if self._done.is_set():
            return self._error
        return self.COMPILING if self._compiling.is_set() else self.LOADING


class TrackingService:
    """Tracking for one application: each environment's context (map and detector),
    loaded once and shared by every client, reloaded when the stored map changes."""

    def __init__(self, *, detectors: DetectorCache, sessions: sessionmaker[Session], settings: Settings,
                 memory: images.MemoryBudget) -> None:
        self.detectors = detectors
        self.sessions = sessions
        self.settings = settings
        self.memory = memory
        self._lock = threading.Lock()
        self._contexts: dict[int, TrackingContext] = {}

    def context(self, environment_id: int) -> TrackingContext:
        """The environment's tracking context: NotFound without the environment, NoMap
        when it has no map yet."""
        with self.sessions() as session:
            environment = environments.get_row(session, environment_id)
            # The map's version alone first: open connections ask every map_poll_s, and the
            # document is read only when it changed.
            current = session.execute(select(SurveyMap.id, SurveyMap.updated_at)
                                      .where(SurveyMap.environment_id == environment_id)).one_or_none()
            if current is None:
                raise NoMap(environment_id)
            version = _map_version(current.id, current.updated_at)
            detector_key = (classifiers.for_environment(session, environment), environment.marker_family)
            with self._lock:
                cached = self._contexts.get(environment_id)
            if cached is not None and cached.map_version == version and cached.detector_key == detector_key:
                return cached
            stored = environments.stored_map(session, environment_id)
            if stored is None:  # deleted since
                raise NoMap(environment_id)
            version = _map_version(stored.id, stored.updated_at)  # the document's own (it may be newer)
            document = MapDocument.model_validate(stored.document)
            context = TrackingContext(
                environment_id=environment_id,
                map_version=version,
                camera=Camera.from_dict(document.camera.model_dump()),
                camera_model=document.camera,
                map_frame=document.frame,
                discs={t.id: np.asarray(t.discs, np.float64) for t in document.targets},
                detector_key=detector_key,
                std={t.id: np.asarray(t.std_m, np.float64) for t in document.targets if t.std_m is not None},
            )
            self.detectors.get(session, *detector_key)  # load once, now
        _ = context.targets  # stacked for region prediction once, now
        with self._lock:
            self._contexts[environment_id] = context
        return context

    def locate(self, environment_id: int, data: bytes, config: TrackConfig) -> LocateResponse:
        """Detections and the camera pose in one client image (no history: the whole
        frame is scanned)."""
        result = self.locate_frame(self.context(environment_id), data, config)
        return LocateResponse(width=result.width, height=result.height, targets=result.targets, pose=result.pose,
                              pose_error=result.pose_error, timing_ms=result.timing_ms)

    def locate_frame(self, context: TrackingContext, data: bytes, config: TrackConfig | StreamFrame) -> FrameResult:
        """Decode, detect, and estimate the pose of one frame (runs in a worker thread).

        `config`: a TrackConfig for a lone image (whole-frame scan), or a `StreamFrame` for
        a /track frame (regions predicted from the connection's previous poses). A /track
        JPEG whose predicted discs are large enough is decoded smaller (`_FramePlan`):
        the plan is made from the frame's header, before any pixel is decoded."""
        stream = config if isinstance(config, StreamFrame) else None
        if stream is not None:
            config = stream.config
        assert isinstance(config, TrackConfig)
        start = time.perf_counter()
        planned: list[_FramePlan] = []

        def reduction(width: int, height: int) -> int:
            if stream is None or not _reducible(width, height):
                return 1  # planned once decoded, as any frame decoded whole
            planned.append(_plan_frame(context, config, stream, width, height))
            return planned[0].reduction

        with images.decoded_frame(data, self.settings, self.memory, reduction=reduction) as frame:
            return self._locate_gray(context, frame, config, stream, start, planned[0] if planned else None)

    def _locate_gray(self, context: TrackingContext, frame: images.Frame, config: TrackConfig,
                     stream: StreamFrame | None, start: float, planned: _FramePlan | None = None) -> FrameResult:
        """`locate_frame` once the frame is decoded (at `start`, perf_counter seconds,
        decoding began), with its plan when one is made before decoding.

        Detection and the pose run on the frame as decoded, through the camera scaled to
        it; the connection's state, the targets and the pose of the reply are in the
        frame's own pixels whatever its reduction."""
        decoded = time.perf_counter()
        detector = self.detectors.get_loaded(context.detector_key)
        if detector is None:
            with self.sessions() as session:
                detector = self.detectors.get(session, *context.detector_key)
        # A plan made before decoding is timed as the plan's, not the decoder's.
        early_ms = planned.ms if planned is not None else 0.0
        if planned is None:
            planned = _plan_frame(context, config, stream, frame.width, frame.height)
        camera, regions, reason = planned.camera, planned.regions, planned.reason
        planned_at = time.perf_counter()
        gray, factor = frame.gray, frame.reduction
        scan_camera, scan_regions = camera, regions
        if factor > 1:
            scan_camera = _reduced_camera(camera, factor, gray.shape[1], gray.shape[0])
            if regions is not None:
                scan_regions = reduce_regions(regions, factor, gray.shape[1], gray.shape[0])
        # The track's expected pose decides a lone card's tilt (config `tilt`).
        prior = stream.state.prior(stream.seq) if stream is not None and config.tilt == "track" else None
        motion = stream.state.motion(stream.seq) if stream is not None else None
        detection, estimate, pose_error, pose_ms = _detect_and_pose(detector, gray, scan_regions, context,
                                                                    scan_camera, config, prior, motion)
        timing = {"decode": (decoded - start) * 1e3 - early_ms, "plan": early_ms + (planned_at - decoded) * 1e3,
                  **detection.timing_ms}
        if estimate is None and regions is not None:
            # Lost in the regions (fast motion, a wrong prior): the whole frame, now.
            reason, regions = "fallback", None
            detection, estimate, pose_error, more_ms = _detect_and_pose(detector, gray, None, context, scan_camera,
                                                                        config, prior, motion)
            pose_ms += more_ms
            for key, value in detection.timing_ms.items():
                timing[key] = timing.get(key, 0.0) + value
        targets = detection.targets
        if factor > 1:
            timing["reduction"] = float(factor)
            targets = _full_scale_targets(detection, factor)
            if estimate is not None:
                estimate = _full_scale_estimate(estimate, factor)
        if stream is not None:
            stream.state.update(stream.seq, camera, estimate, full=regions is None)
        timing.update(pose=pose_ms, total=(time.perf_counter() - start) * 1e3)
        return FrameResult(
            targets=[DetectedTargetOut(**t.to_dict()) for t in targets],
            pose=PoseOut(**estimate.to_dict()) if estimate is not None else None,
            pose_error=pose_error,
            timing_ms={k: round(v, 3) for k, v in timing.items()},
            width=frame.width,
            height=frame.height,
            scan="full" if regions is None else "regions",
            scan_reason=reason,  # type: ignore[arg-type]
        )


def _map_version(map_id: int, updated_at: datetime) -> str:
    """A stored map's version: a new one on every change, whichever process made it."""
    return f"{map_id}:{updated_at.isoformat()}"


def _detect_and_pose(detector: Detector, gray: np.ndarray, regions: list[Region] | None, context: TrackingContext,
                     camera: Camera, config: TrackConfig, prior: Pose | None = None,
                     motion: TrackedMotion | None = None) -> tuple[Detection, PoseEstimate | None, str | None, float]:
    """(detection, pose estimate or None, why not, milliseconds spent on the pose);
    `prior`, the track's expected pose, decides a lone card's tilt; `motion`, the track's
    last pose and steps, starts the camera's motion through a rolling shutter's readout."""
    detection = detector.detect(gray, regions)
    observations = [
        TargetObservation(t.id, t.discs, context.discs[t.id], context.std.get(t.id))
        for t in detection.targets if t.id in context.discs
    ]
    posed = time.perf_counter()
    try:
        estimate: PoseEstimate | None
        if config.rolling_shutter is not None and observations:
            shutter = RollingShutter.from_seconds(config.rolling_shutter.readout_ms / 1e3,
                                                  config.rolling_shutter.frame_rate)
            estimate = rolling_shutter_pose(observations, camera, shutter, motion, prior, config.method,
                                            config.estimate_focal).estimate
        else:
            estimate = estimate_pose(observations, camera, config.method, config.estimate_focal, prior)
        error = None
    except PoseUndetermined as exc:
        estimate, error = None, str(exc)
    return detection, estimate, error, (time.perf_counter() - posed) * 1e3


# --------------------------------------------------------------------------------------
# Frames decoded smaller
# --------------------------------------------------------------------------------------

#: Smallest predicted disc diameter, pixels of the decoded frame, for a /track frame to
#: be decoded smaller (see `_plan_frame`): the detector finds discs from 3.5 px across.
REDUCED_MIN_DISC_PX = 5.0
#: Smallest side of a /track frame decoded smaller, pixels: 1280x720 at 1/4 (320x180)
#: gave a 90th-percentile position error of 15 mm instead of 3 on the bench walk.
REDUCED_MIN_SIDE = 360
#: The factors a /track frame may be decoded smaller by.
REDUCTIONS = (1, 2, 4)


@dataclass(frozen=True)
class _FramePlan:
    """How a frame is scanned, decided from its size before it is decoded.

    Attributes
    ----------
    camera : Camera
        The camera at the frame's own size.
    regions : list of Region or None
        Crops to search, the frame's pixels; None: the whole frame.
    reason : str
        Why (a `ScanReason`, or "single" for a lone image).
    reduction : int
        Decode a JPEG at 1 / this (1: whole).
    ms : float
        Milliseconds the plan took.
    """

    camera: Camera
    regions: list[Region] | None
    reason: str
    reduction: int
    ms: float


def _frame_camera(context: TrackingContext, config: TrackConfig, width: int, height: int) -> Camera:
    """The map's camera, or the config's intrinsics, at the frame's size."""
    camera = context.camera
    if config.intrinsics is not None:
        camera = Camera.from_dict(config.intrinsics.model_dump())
    if (width, height) != (camera.width, camera.height):
        camera = camera.scaled_to(width, height)
    return camera


def _plan_frame(context: TrackingContext, config: TrackConfig, stream: StreamFrame | None, width: int,
                height: int) -> _FramePlan:
    """The plan of a `width` x `height` frame: its camera, its regions and why, and how
    much smaller it may be decoded.

    A /track frame is decoded at 1/2 or 1/4 when the connection's poses predict every
    mapped disc in view at least `REDUCED_MIN_DISC_PX` across at that scale: the
    detector's cost follows the pixels it scans and the decoder's follows the pixels
    it writes, while the disc centres of large discs stay well measured in a smaller
    frame. Without poses to predict from (a first frame, a lost track, a new camera,
    whole scans asked for), and for lone images, the frame is decoded whole: nothing
    says how small its discs are."""
    started = time.perf_counter()
    camera = _frame_camera(context, config, width, height)
    if stream is None:
        return _FramePlan(camera, None, "single", 1, (time.perf_counter() - started) * 1e3)
    if not _reducible(width, height):
        regions, reason = stream.state.plan(stream.seq, camera, config, context.targets)
        return _FramePlan(camera, regions, reason, 1, (time.perf_counter() - started) * 1e3)
    in_view: list = []
    regions, reason = stream.state.plan(stream.seq, camera, config, context.targets, in_view=in_view)
    reduction = decode_reduction(in_view, width, height, REDUCED_MIN_DISC_PX, REDUCTIONS,
                                 REDUCED_MIN_SIDE) if in_view else 1
    return _FramePlan(camera, regions, reason, reduction, (time.perf_counter() - started) * 1e3)


def _reducible(width: int, height: int) -> bool:
    """Whether a `width` x `height` frame is large enough to be decoded smaller (640x480
    is not)."""
    return any(-(-min(width, height) // f) >= REDUCED_MIN_SIDE for f in REDUCTIONS[1:])


def _reduced_camera(camera: Camera, factor: int, width: int, height: int) -> Camera:
    """`camera` for the frame decoded at 1 / `factor` (`width` x `height`, the decoder's
    rounded-up size): pixel centres scale about the top-left pixel's corner by exactly
    1 / `factor`, as the decoder's pixels do (`Camera.scaled_to` would scale by the
    rounded size)."""
    K = camera.K.copy()
    K[0, 0], K[0, 1], K[1, 1] = K[0, 0] / factor, K[0, 1] / factor, K[1, 1] / factor
    K[0, 2] = (K[0, 2] + 0.5) / factor - 0.5
    K[1, 2] = (K[1, 2] + 0.5) / factor - 0.5
    return Camera(K, camera.dist, int(width), int(height))


def _full_scale_targets(detection: Detection, factor: int) -> list:
    """The targets (`DetectedTarget`) found in the frame decoded at 1 / `factor`, in the
    frame's own pixels."""
    return [replace(t, discs=(np.asarray(t.discs) + 0.5) * factor - 0.5, disc_radii=np.asarray(t.disc_radii) * factor)
            for t in detection.targets]


def _full_scale_estimate(estimate: PoseEstimate, factor: int) -> PoseEstimate:
    """A pose estimated in the frame decoded at 1 / `factor`, with its pixel quantities
    (reprojection error, focal length and its variance) in the frame's own pixels; the
    pose and the position's covariance do not depend on the scale."""
    covariance = np.array(estimate.covariance, np.float64, copy=True)
    if covariance.shape[0] > 6:  # (rvec, tvec, f): the focal length's row and column are pixels
        covariance[6:, :] *= factor
        covariance[:, 6:] *= factor
    return replace(estimate, rms_px=estimate.rms_px * factor, focal_px=estimate.focal_px * factor,
                   covariance=covariance)
