"""Tracking for the API: each environment's map and detector, loaded once and shared by
every client; one frame decoded and tracked (`app.core.tracking`), its reply shaped.

A new map (survey, import, alignment) is picked up by the next connection or ``locate``
call, and by open /track connections, which ask for the context every ``map_poll_s``.

A frame's way: its header gives its size; `app.core.tracking.plan_frame` says from the
size and the connection's `TrackState` where to search and how small a JPEG may be
decoded; the frame is decoded so; `app.core.tracking.track_frame` finds its targets and
pose. ``POST /environments/{id}/locate`` (one image, no state) scans the whole frame.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from app.core.detection import DetectedTarget
from app.core.geometry import METHODS, Camera, PoseEstimate, RollingShutter
from app.core.tracking import (
    ScanReason,
    TrackedFrame,
    TrackingMap,
    TrackOptions,
    TrackState,
    plan_frame,
    track_frame,
)
from app.schemas import (
    CameraModel,
    DetectedTargetOut,
    LocateResponse,
    MapDocument,
    PoseOut,
    TrackConfig,
)
from app.schemas import ScanReason as ScanReasonOut
from app.services import classifiers, environments, images
from app.services.detection import DetectorCache, DetectorKey
from app.services.errors import NoMap
from app.settings import Settings

assert set(TrackConfig.model_fields["method"].annotation.__args__) == set(METHODS)  # type: ignore[union-attr]
assert set(ScanReasonOut.__args__) | {"single"} == {r.value for r in ScanReason}  # type: ignore[attr-defined]


@dataclass(frozen=True, eq=False)
class TrackingContext:
    """Everything one environment needs per frame, loaded once."""

    environment_id: int
    map_version: str
    map: TrackingMap
    camera_model: CameraModel  # the map's camera as clients get it
    map_frame: Literal["survey", "world"]
    detector_key: DetectorKey


@dataclass(frozen=True)
class StreamFrame:
    """A frame of a /track connection: its config, its seq and the connection's state
    (`TrackingService.locate_frame` takes it in place of a bare config)."""

    config: TrackConfig
    seq: int
    state: TrackState


@dataclass(frozen=True)
class FrameResult:
    """One frame tracked: what `track_frame` found, in the frame's own pixels, with the
    service's timings (decoding, the whole) added."""

    tracked: TrackedFrame
    timing_ms: dict[str, float]
    width: int
    height: int

    @property
    def scan(self) -> Literal["full", "regions"]:
        """How the frame was scanned, as the reply says it."""
        return "regions" if self.tracked.regions else "full"

    @property
    def targets(self) -> list[DetectedTargetOut]:
        """The targets as the reply gives them."""
        return targets_out(self.tracked.targets)

    @property
    def pose_error(self) -> str | None:
        """Why there is no pose."""
        return self.tracked.pose_error


def targets_out(targets: list[DetectedTarget]) -> list[DetectedTargetOut]:
    """Targets as the replies give them."""
    return [DetectedTargetOut(**t.to_dict()) for t in targets]


def pose_out(estimate: PoseEstimate | None) -> PoseOut | None:
    """A pose estimate as the replies give it."""
    return PoseOut(**estimate.to_dict()) if estimate is not None else None


def track_options(config: TrackConfig) -> TrackOptions:
    """What `app.core.tracking` takes of a client's config."""
    shutter = None
    if config.rolling_shutter is not None:
        shutter = RollingShutter.from_seconds(config.rolling_shutter.readout_ms / 1e3,
                                              config.rolling_shutter.frame_rate)
    return TrackOptions(
        method=config.method, estimate_focal=config.estimate_focal,
        intrinsics=Camera.from_dict(config.intrinsics.model_dump()) if config.intrinsics is not None else None,
        regions=config.regions, full_scan_every=config.full_scan_every, tilt_from_track=config.tilt == "track",
        shutter=shutter)


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
            version = environments.map_version(session, environment_id)
            if version is None:
                raise NoMap(environment_id)
            detector_key = (classifiers.for_environment(session, environment), environment.marker_family)
            with self._lock:
                cached = self._contexts.get(environment_id)
            if cached is not None and cached.map_version == version and cached.detector_key == detector_key:
                return cached
            stored = environments.stored_map(session, environment_id)
            if stored is None:  # deleted since
                raise NoMap(environment_id)
            document = MapDocument.model_validate(stored.document)
            context = TrackingContext(
                environment_id=environment_id,
                # the document's own version (it may be newer than the one read first)
                map_version=environments.version_of(stored.id, stored.updated_at),
                map=TrackingMap(
                    camera=Camera.from_dict(document.camera.model_dump()),
                    discs={t.id: np.asarray(t.discs, np.float64) for t in document.targets},
                    std={t.id: np.asarray(t.std_m, np.float64) for t in document.targets if t.std_m is not None},
                ),
                camera_model=document.camera,
                map_frame=document.frame,
                detector_key=detector_key,
            )
            self.detectors.get(session, *detector_key)  # load once, now
        _ = context.map.targets  # stacked for region prediction once, now
        with self._lock:
            self._contexts[environment_id] = context
        return context

    def locate(self, environment_id: int, data: bytes, config: TrackConfig) -> LocateResponse:
        """Detections and the camera pose in one client image (no history: the whole
        frame is scanned)."""
        result = self.locate_frame(self.context(environment_id), data, config)
        return LocateResponse(width=result.width, height=result.height, targets=result.targets,
                              pose=pose_out(result.tracked.estimate), pose_error=result.pose_error,
                              timing_ms=result.timing_ms)

    def locate_frame(self, context: TrackingContext, data: bytes, config: TrackConfig | StreamFrame) -> FrameResult:
        """Decode, detect, and estimate the pose of one frame (runs in a worker thread).

        `config`: a TrackConfig for a lone image (whole-frame scan), or a `StreamFrame` for
        a /track frame (regions predicted from the connection's previous poses). The plan
        is made from the frame's header, before any pixel is decoded: a /track JPEG whose
        predicted discs are large enough is decoded smaller."""
        stream = config if isinstance(config, StreamFrame) else None
        track_config = stream.config if stream is not None else config
        assert isinstance(track_config, TrackConfig)
        options = track_options(track_config)
        state, seq = (stream.state, stream.seq) if stream is not None else (None, 0)
        start = time.perf_counter()
        header = images.frame_header(data, self.settings)
        plan = plan_frame(context.map, options, header.width, header.height, state, seq)
        with images.decoded_frame(data, self.settings, self.memory, header=header, reduction=plan.reduction) as frame:
            decoded = time.perf_counter()
            detector = self.detectors.get_loaded(context.detector_key)
            if detector is None:
                with self.sessions() as session:
                    detector = self.detectors.get(session, *context.detector_key)
            tracked = track_frame(detector, frame.gray, frame.reduction, plan, context.map, options, state, seq)
            timing = {"decode": (decoded - start) * 1e3 - plan.ms, **tracked.timing_ms,
                      "total": (time.perf_counter() - start) * 1e3}
            return FrameResult(tracked, {k: round(v, 3) for k, v in timing.items()}, frame.width, frame.height)
