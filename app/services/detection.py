"""Detection for the API: run the environment's (or a chosen) classifier on a client
image and shape the reply, as JSON or as the image with the detections drawn over it.
Detectors are built once and shared.

The detector's compiled kernels (`DetectorKernels`) load, or on a machine's first start
compile, in a thread of their own while the server already answers.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import cv2
from numba.core import event as numba_event
from sqlalchemy.orm import Session

from app.core.detection import Detection, Detector, draw_detections, warm_up
from app.core.markers import FAMILIES
from app.schemas import DetectedTargetOut, DetectResponse
from app.services import classifiers, images
from app.services.errors import MAX_ID, Invalid, NotFound
from app.settings import Settings

log = logging.getLogger(__name__)

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
