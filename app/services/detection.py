"""Detection for the API: run the environment's (or a chosen) classifier on a client
image and shape the reply, as JSON or as the image with the detections drawn over it.
Detectors are built once and shared."""

from __future__ import annotations

import threading

import cv2
from sqlalchemy.orm import Session

from app.core.detection import Detection, Detector, draw_detections
from app.core.markers import FAMILIES
from app.schemas import DetectedTargetOut, DetectResponse
from app.services import classifiers, images
from app.services.errors import MAX_ID, Invalid, NotFound
from app.settings import Settings

#: A detector's key: (classifier id, marker family).
DetectorKey = tuple[int, str]


class DetectorCache:
    """Detectors by (classifier id, family). Classifiers never change once stored, so a
    loaded detector stays valid; it is read-only and shared by every request."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._detectors: dict[DetectorKey, Detector] = {}

    def get_loaded(self, key: DetectorKey) -> Detector | None:
        with self._lock:
            return self._detectors.get(key)

    def get(self, session: Session, classifier_id: int, family: str) -> Detector:
        key = (classifier_id, family)
        with self._lock:
            found = self._detectors.get(key)
        if found is None:
            found = Detector(classifiers.load(session, classifier_id), family)
            with self._lock:
                self._detectors.setdefault(key, found)
        return found


def to_response(detection: Detection, width: int, height: int, classifier_id: int,
                with_candidates: bool) -> DetectResponse:
    return DetectResponse(
        width=width,
        height=height,
        targets=[DetectedTargetOut(**t.to_dict()) for t in detection.targets],
        candidates=detection.candidates.astype(float).round(3).tolist() if with_candidates else None,
        classifier_id=classifier_id,
        timing_ms={k: round(v, 3) for k, v in detection.timing_ms.items()},
    )


def _detector(session: Session, cache: DetectorCache, classifier_id: int | None, family: str) -> tuple[int, Detector]:
    """The chosen classifier's id (the default's when None) and its detector for `family`."""
    if family not in FAMILIES:
        raise Invalid(f"family: unknown marker family {family!r}; known: {', '.join(FAMILIES)}")
    if classifier_id is not None:
        if not 0 <= classifier_id <= MAX_ID:
            raise NotFound(f"classifier {classifier_id} not found")
        # Checked even when its detector is cached: a deleted classifier is not used again.
        classifiers.get_row(session, classifier_id)
    chosen = classifier_id if classifier_id is not None else classifiers.default_id(session)
    return chosen, cache.get(session, chosen, family)


def detect(session: Session, cache: DetectorCache, settings: Settings, memory: images.MemoryBudget, data: bytes, *,
           classifier_id: int | None, family: str, with_candidates: bool) -> DetectResponse:
    """The targets in one client image (and every candidate disc, `with_candidates`)."""
    chosen, detector = _detector(session, cache, classifier_id, family)
    with images.decoded(data, settings, memory) as gray:
        detection = detector.detect(gray)
        return to_response(detection, gray.shape[1], gray.shape[0], chosen, with_candidates)


def detect_drawn(session: Session, cache: DetectorCache, settings: Settings, memory: images.MemoryBudget,
                 data: bytes, *, classifier_id: int | None, family: str) -> bytes:
    """The client image as a PNG of its size with its targets (quadrilateral, discs, id)
    and every candidate disc drawn over it."""
    _, detector = _detector(session, cache, classifier_id, family)
    with images.decoded(data, settings, memory) as gray:
        detection = detector.detect(gray)
        # Drawn and encoded inside the image's share of the memory budget: the colour copy
        # and the PNG (a few bytes a pixel) take less than detection held at its peak.
        drawn = draw_detections(gray, detection.targets, detection.candidates)
        ok, png = cv2.imencode(".png", drawn)
        if not ok:
            raise RuntimeError("OpenCV could not encode the drawn image as PNG")
        return png.tobytes()
