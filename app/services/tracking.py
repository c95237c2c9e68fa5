"""Tracking: per frame, detect targets and compute the camera pose from the map.

An environment's map and detector are loaded once and shared by every client; a new
map (survey, import) is picked up by the next connection or ``locate`` call.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.core.camera import Camera
from app.core.detector import Detection
from app.core.pose import METHODS, PoseUndetermined, TargetObservation, estimate_pose
from app.models import Environment, SurveyMap
from app.schemas import CameraModel, MapDocument
from app.services import classifiers
from app.services.detection import MAX_ID, DetectorCache, decode
from app.services.errors import Invalid, NotFound
from app.settings import Settings


class TrackConfig(BaseModel):
    """What a client may change with a ``{"type": "config", ...}`` message."""

    model_config = ConfigDict(extra="forbid")

    type: Literal["config"] = "config"
    method: Literal["nonlinear", "posit", "mean", "single"] = "nonlinear"
    estimate_focal: bool = Field(False, description="Free the focal length per frame (zoom lens).")
    intrinsics: CameraModel | None = Field(None, description="Override the map's camera (K, dist, size).")


assert set(TrackConfig.model_fields["method"].annotation.__args__) == set(METHODS)  # type: ignore[union-attr]


@dataclass(frozen=True, eq=False)
class TrackingContext:
    """Everything one environment needs per frame, loaded once."""

    environment_id: int
    map_version: str
    camera: Camera
    discs: dict[int, np.ndarray]  # target id -> (4, 3) map coordinates
    detector_key: tuple[int, str]
    camera_dict: dict[str, Any] = field(default_factory=dict)


class TrackingContexts:
    """Shared contexts by environment; reloaded when the stored map changes."""

    def __init__(self, detectors: DetectorCache) -> None:
        self.detectors = detectors
        self._lock = threading.Lock()
        self._contexts: dict[int, TrackingContext] = {}

    def get(self, session: Session, environment_id: int) -> TrackingContext:
        if not 0 <= environment_id <= MAX_ID:  # the driver would raise OverflowError
            raise NotFound(f"environment {environment_id} not found")
        environment = session.get(Environment, environment_id)
        if environment is None:
            raise NotFound(f"environment {environment_id} not found")
        stored = session.scalar(select(SurveyMap).where(SurveyMap.environment_id == environment_id))
        if stored is None:
            raise Invalid(f"environment {environment_id} has no map yet: run a survey or PUT a map first")
        version = f"{stored.id}:{stored.updated_at.isoformat()}"
        classifier_id = environment.classifier_id or classifiers.default_id(session)
        with self._lock:
            cached = self._contexts.get(environment_id)
        if cached is not None and cached.map_version == version and cached.detector_key == (
            classifier_id, environment.marker_family
        ):
            return cached
        document = MapDocument.model_validate(stored.document)
        camera = Camera.from_dict(document.camera.model_dump())
        context = TrackingContext(
            environment_id=environment_id,
            map_version=version,
            camera=camera,
            discs={t.id: np.asarray(t.discs, np.float64) for t in document.targets},
            detector_key=(classifier_id, environment.marker_family),
            camera_dict=document.camera.model_dump(),
        )
        self.detectors.get(session, classifier_id, environment.marker_family)  # load once, now
        with self._lock:
            self._contexts[environment_id] = context
        return context


@dataclass(frozen=True)
class FrameResult:
    targets: list[dict[str, Any]]
    pose: dict[str, Any] | None
    pose_error: str | None
    timing_ms: dict[str, float]
    width: int
    height: int


def locate_frame(
    context: TrackingContext,
    detections: DetectorCache,
    session_factory: Any,
    settings: Settings,
    data: bytes,
    config: TrackConfig,
) -> FrameResult:
    """Decode, detect, and estimate the pose of one frame (runs in a worker thread)."""
    start = time.perf_counter()
    gray = decode(data, settings)
    decoded = time.perf_counter()
    detector = detections.get_loaded(context.detector_key)
    if detector is None:
        with session_factory() as session:
            detector = detections.get(session, *context.detector_key)
    detection: Detection = detector.detect(gray)
    camera = context.camera
    if config.intrinsics is not None:
        camera = Camera.from_dict(config.intrinsics.model_dump())
    if (gray.shape[1], gray.shape[0]) != (camera.width, camera.height):
        camera = camera.scaled_to(gray.shape[1], gray.shape[0])
    observations = [
        TargetObservation(t.id, t.discs, context.discs[t.id]) for t in detection.targets if t.id in context.discs
    ]
    pose: dict[str, Any] | None = None
    pose_error: str | None = None
    posed = time.perf_counter()
    try:
        estimate = estimate_pose(observations, camera, config.method, config.estimate_focal)
        pose = estimate.to_dict()
    except PoseUndetermined as exc:
        pose_error = str(exc)
    done = time.perf_counter()
    timing = {"decode": (decoded - start) * 1e3, **detection.timing_ms, "pose": (done - posed) * 1e3,
              "total": (done - start) * 1e3}
    return FrameResult(
        targets=[t.to_dict() for t in detection.targets],
        pose=pose,
        pose_error=pose_error,
        timing_ms={k: round(v, 3) for k, v in timing.items()},
        width=gray.shape[1],
        height=gray.shape[0],
    )
