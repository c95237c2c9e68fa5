"""Detection for the API: decode a client image safely, run the environment's (or a
chosen) classifier, shape the reply. Detectors are built once and shared."""

from __future__ import annotations

import threading

import numpy as np

from sqlalchemy.orm import Session

from app.core.detection import MIN_SIDE, Detection, Detector
from app.core.imagecodec import ImageError, decode_gray
from app.schemas import DetectedTargetOut, DetectResponse
from app.services import classifiers
from app.services.errors import Invalid, NotFound, TooLarge, UnsupportedMedia
from app.settings import Settings


# Database ids are signed 64-bit; a bigger one matches nothing (and must not reach the
# driver, which raises OverflowError: a 500).
MAX_ID = 2**63 - 1


class DetectorCache:
    """Detectors by (classifier id, family). Classifiers never change once stored, so a
    loaded detector stays valid; it is read-only and shared by every request."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._detectors: dict[tuple[int, str], Detector] = {}

    def get_loaded(self, key: tuple[int, str]) -> Detector | None:
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


def decode(data: bytes, settings: Settings) -> np.ndarray:
    """Client bytes to a greyscale frame, or a clear 4xx."""
    if len(data) > settings.max_image_bytes:
        raise TooLarge(f"image of {len(data)} bytes exceeds the limit of {settings.max_image_bytes} bytes")
    try:
        gray = decode_gray(data, settings.max_image_pixels)
    except ImageError as exc:
        if exc.kind == "too_large":
            raise TooLarge(str(exc)) from None
        if exc.kind == "unsupported":
            raise UnsupportedMedia(str(exc)) from None
        raise Invalid(str(exc)) from None
    if min(gray.shape) < MIN_SIDE:
        # The detector looks through a window of this size; a smaller frame is a client
        # error, not a detector failure (it used to surface as a 500).
        raise Invalid(
            f"the image is {gray.shape[1]}x{gray.shape[0]} pixels; both sides must be at least {MIN_SIDE}"
        )
    return gray


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


def detect(
    session: Session,
    cache: DetectorCache,
    settings: Settings,
    data: bytes,
    classifier_id: int | None,
    family: str,
    with_candidates: bool,
) -> DetectResponse:
    from app.core.markers import FAMILIES

    if family not in FAMILIES:
        raise Invalid(f"family: unknown marker family {family!r}; known: {', '.join(FAMILIES)}")
    if classifier_id is not None and not 0 <= classifier_id <= MAX_ID:
        raise NotFound(f"classifier {classifier_id} not found")
    gray = decode(data, settings)
    chosen = classifier_id if classifier_id is not None else classifiers.default_id(session)
    detector = cache.get(session, chosen, family)
    detection = detector.detect(gray)
    return to_response(detection, gray.shape[1], gray.shape[0], chosen, with_candidates)
