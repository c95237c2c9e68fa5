"""Peer detectors for the side-by-side detection benchmark, on a common footing.

Every detector here is an object with

* ``name`` - the row label of the benchmark table;
* ``artwork`` - ``None`` for our own cards, else ``id -> CardArtwork``: what is printed on
  the card when this detector is measured (``app.sim.scenes.scenario_frame(..., artwork=)``
  then renders the same geometry and degradations with that artwork in place of ours);
* ``available`` / ``reason`` - whether it can run here (our own detector and the blob
  baseline need ``app/core/detection/candidates.py`` and ``app/core/detection/targets.py``);
* ``detect(gray) -> list[(id, points (4, 2))]`` - points in pixels (centre of the top-left
  pixel at (0, 0), docs/map-format.md) in the order 0 top-left, 1 top-right,
  2 bottom-right, 3 bottom-left *as printed*: our disc centres, or the four outer corners
  of a tag's black square (the projections of ``CardArtwork.points_uv``).

Artwork (same printed card side as ours, white card, marker centred):

* The tag's outer black square spans 0.075..0.925 of the card, the outer extent of our
  discs (0.2 +- 0.125), so every marker gets the same printed footprint; the white margin
  of the card is the tag's quiet zone.
* Textures are 480 px (as our cards in the simulator) and built by nearest-neighbour
  upscaling of the bit grid by an integer factor (51 px per AprilTag cell, 68 px per ArUco
  cell), so every edge falls on a texel edge: the renderer's area sampling is then exact.

Detectors:

* AprilTag 3 via ``pupil_apriltags.Detector(families="tag36h11", nthreads=1,
  quad_decimate=1.0 | 2.0, refine_edges=1)``, other settings at their defaults
  (``decode_sharpening=0.25``, up to 2 corrected bits). apriltag reports coordinates with
  the centre of the top-left pixel at (0.5, 0.5); we subtract 0.5 (a convention, not an
  error of the detector). Its corners wrap the other way round from ours (for a tag as
  printed: TR, TL, BL, BR); we reorder them.
* OpenCV ArUco (``cv2.aruco.ArucoDetector``, default ``DetectorParameters``, optionally
  ``cornerRefinementMethod=CORNER_REFINE_SUBPIX``). Dictionary: OpenCV's 4x4 markers, the
  fewest bits per side of the standard dictionaries, so the biggest cells for a given
  printed size - the fairest choice for small and far markers. ``DICT_4X4_50`` has only 50
  ids but our family has 60, so we use the first 60 of OpenCV's 4x4 list (ids 0-49 are
  exactly ``DICT_4X4_50``, 50-59 the next ones of ``DICT_4X4_100``) with the same
  ``maxCorrectionBits`` (1) as those dictionaries. Corners come as TL, TR, BR, BL.
* Our live detector as another checkout of fidotrack has it (``CheckoutDetector``, the
  benchmark's ``--baseline``): a worker process (``bench/detector_worker.py``) with that
  tree on ``PYTHONPATH`` detects the same frames, and times ``Detector.detect`` itself.
* The blob baseline: our own cards, disc candidates from an adaptive threshold and
  connected components (dark, filled, elliptical blobs) instead of the learned classifier,
  then the same ``assemble_targets`` grouping, verification and identification as our
  detector - what the learned candidate stage buys.
"""

from __future__ import annotations

import functools
import importlib
import os
import pickle
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from app.core.detection.blobs import BlobParams, blob_candidates
from app.core.markers import DEFAULT_FAMILY, get_family
from app.sim.scenes import CARD_TEXTURE_PX, CardArtwork
# A tag's black square spans the outer extent of our discs across the card (0.075..0.925).
from app.sim.truth import FOOTPRINT_HI as TAG_HI, FOOTPRINT_LO as TAG_LO, FOOTPRINT_UV as TAG_CORNERS_UV

Detection = tuple[int, np.ndarray]

N_IDS = len(get_family(DEFAULT_FAMILY))  # 60: every id a fido3x3 scene may draw


# --------------------------------------------------------------------------------------
# Artwork
# --------------------------------------------------------------------------------------


@functools.cache
def apriltag_dictionary() -> cv2.aruco.Dictionary:
    return cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)


@functools.cache
def aruco_dictionary(n_ids: int = N_IDS) -> cv2.aruco.Dictionary:
    """The first ``n_ids`` of OpenCV's 4x4 markers (= DICT_4X4_50 for ids < 50)."""
    base = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_1000)
    reference = cv2.aruco.getPredefinedDictionary(
        cv2.aruco.DICT_4X4_50 if n_ids <= 50 else cv2.aruco.DICT_4X4_100 if n_ids <= 100 else cv2.aruco.DICT_4X4_1000
    )
    return cv2.aruco.Dictionary(np.ascontiguousarray(base.bytesList[:n_ids]), 4, reference.maxCorrectionBits)


def tag_artwork(dictionary: cv2.aruco.Dictionary, marker_id: int, card_px: int = CARD_TEXTURE_PX) -> CardArtwork:
    """A white card with the marker's black square over 0.075..0.925 of its side.

    The bit grid (black border included) is upscaled by an integer factor with
    nearest-neighbour sampling, so all edges lie on texel edges.
    """
    cells = dictionary.markerSize + 2  # one black border cell each side
    grid = cv2.aruco.generateImageMarker(dictionary, int(marker_id), cells)  # one pixel per cell
    lo, hi = round(TAG_LO * card_px), round(TAG_HI * card_px)
    if abs(lo - TAG_LO * card_px) > 1e-9 or (hi - lo) % cells:
        raise ValueError(f"card_px {card_px} does not put the {cells} cells on texel edges")
    scale = (hi - lo) // cells
    texture = np.ones((card_px, card_px), np.float32)
    texture[lo:hi, lo:hi] = np.kron(grid.astype(np.float32) / 255.0, np.ones((scale, scale), np.float32))
    texture.setflags(write=False)
    return CardArtwork(texture=texture, points_uv=TAG_CORNERS_UV)


@functools.cache
def apriltag_artwork(marker_id: int) -> CardArtwork:
    """AprilTag tag36h11 ``marker_id`` on our card (8 cells of 51 texels)."""
    return tag_artwork(apriltag_dictionary(), marker_id)


@functools.cache
def aruco_artwork(marker_id: int) -> CardArtwork:
    """ArUco 4x4 ``marker_id`` on our card (6 cells of 68 texels)."""
    return tag_artwork(aruco_dictionary(), marker_id)


# --------------------------------------------------------------------------------------
# Detectors
# --------------------------------------------------------------------------------------


@dataclass
class PeerDetector:
    name: str
    artwork: Callable[[int], CardArtwork] | None
    available: bool = True
    reason: str = ""
    #: Milliseconds of the last `detect` by stage, for detectors that report them (ours).
    last_stages: dict[str, float] = field(default_factory=dict, repr=False)
    #: The last `detect`'s time as the detector measured it (a detector in another
    #: process: its own clock, without the pipe); None: the caller's wall time stands.
    last_ms: float | None = field(default=None, repr=False)

    def detect(self, gray: np.ndarray) -> list[Detection]:  # pragma: no cover - interface
        raise NotImplementedError


# pupil_apriltags corners for a tag as printed come as TR, TL, BL, BR: this picks
# TL, TR, BR, BL out of them.
_APRILTAG_ORDER = np.array([1, 0, 3, 2])


@dataclass
class AprilTagDetector(PeerDetector):
    quad_decimate: float = 1.0
    _detector: Any = field(default=None, repr=False)

    def __post_init__(self) -> None:
        try:
            import pupil_apriltags
        except ImportError as exc:  # pragma: no cover - the bench extra is installed
            self.available, self.reason = False, f"n/a (pupil-apriltags: {exc})"
            return
        self._detector = pupil_apriltags.Detector(
            families="tag36h11", nthreads=1, quad_decimate=self.quad_decimate, refine_edges=1
        )

    def detect(self, gray: np.ndarray) -> list[Detection]:
        found = self._detector.detect(np.ascontiguousarray(gray, dtype=np.uint8))
        return [(int(d.tag_id), np.asarray(d.corners, np.float64)[_APRILTAG_ORDER] - 0.5) for d in found]


@dataclass
class ArucoDetector(PeerDetector):
    refinement: str = "none"  # "none" (OpenCV's default) or "subpix"
    _detector: Any = field(default=None, repr=False)

    def __post_init__(self) -> None:
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = {
            "none": cv2.aruco.CORNER_REFINE_NONE, "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
        }[self.refinement]
        self._detector = cv2.aruco.ArucoDetector(aruco_dictionary(), params)

    def detect(self, gray: np.ndarray) -> list[Detection]:
        corners, ids, _ = self._detector.detectMarkers(gray)
        if ids is None:
            return []
        return [(int(i), np.asarray(c, np.float64).reshape(4, 2)) for i, c in zip(ids.ravel(), corners, strict=True)]


def _import(module: str) -> Any:
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name == module:
            return None
        raise


@dataclass
class FidoDetector(PeerDetector):
    """Our detector: ``app.core.detection.detector.Detector`` if present, else the learned
    candidates (``app.core.detection.candidates``) and ``app.core.detection.targets.assemble_targets``."""

    family: str = DEFAULT_FAMILY
    thorough: bool = False  # the survey's detector: dark blobs as candidates too
    _detect: Any = field(default=None, repr=False)

    def __post_init__(self) -> None:
        candidates = _import("app.core.detection.candidates")
        targets = _import("app.core.detection.targets")
        if candidates is None:
            self.available, self.reason = False, "n/a (candidates.py missing)"
            return
        if targets is None:
            self.available, self.reason = False, "n/a (targets.py missing)"
            return
        try:  # half-written modules must not stop the peers' rows
            classifier = candidates.load_default_classifier()
            detector = _import("app.core.detection.detector")
            if detector is not None and hasattr(detector, "Detector"):
                self._detect = detector.Detector(classifier, self.family, thorough=self.thorough).detect
            kernels = _import("app.core.detection")
            if kernels is not None:
                kernels.warm_up()  # compile (or load) now: the first timed frame would pay it
            else:
                self._detect = lambda gray: targets.assemble_targets(
                    gray, candidates.find_candidates(gray, classifier), family=self.family
                )
        except Exception as exc:
            self.available, self.reason = False, f"n/a ({exc!r})"

    def detect(self, gray: np.ndarray) -> list[Detection]:
        found = self._detect(gray)
        self.last_stages = dict(getattr(found, "timing_ms", {}))
        found = getattr(found, "targets", found)  # Detector.detect -> Detection(targets=...)
        return [(int(t.id), np.asarray(t.discs, np.float64).reshape(4, 2)) for t in found]


@dataclass
class CheckoutDetector(PeerDetector):
    """Our live detector as another checkout of fidotrack has it (`checkout`: its root
    directory), run in a worker process (`bench/detector_worker.py` with that tree on
    ``PYTHONPATH``) on the same frames: the benchmark's before-and-after row. The time
    is the worker's own measure of ``Detector.detect``, as in-process rows measure it."""

    checkout: str = ""
    _worker: Any = field(default=None, repr=False)

    def __post_init__(self) -> None:
        root = Path(self.checkout).resolve()
        if not (root / "app" / "core" / "detection" / "detector.py").is_file():
            self.available, self.reason = False, f"n/a (no fidotrack detector under {root})"
            return
        worker = Path(__file__).resolve().with_name("detector_worker.py")
        env = {**os.environ, "PYTHONPATH": str(root)}
        self._worker = subprocess.Popen([sys.executable, str(worker)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        cwd=root, env=env)
        try:
            if pickle.load(self._worker.stdout) != "ready":
                raise RuntimeError("unexpected greeting")
        except Exception as exc:
            self.close()
            self.available, self.reason = False, f"n/a (worker did not start: {exc!r})"

    def detect(self, gray: np.ndarray) -> list[Detection]:
        pickle.dump(np.ascontiguousarray(gray, np.uint8), self._worker.stdin)
        self._worker.stdin.flush()
        found, self.last_ms, self.last_stages = pickle.load(self._worker.stdout)
        return found

    def close(self) -> None:
        if self._worker is not None and self._worker.poll() is None:
            try:
                pickle.dump(None, self._worker.stdin)
                self._worker.stdin.close()
            except OSError:
                pass
            self._worker.wait(timeout=30)


# --- plain threshold-and-blob baseline ------------------------------------------------


@dataclass
class BlobBaseline(PeerDetector):
    family: str = DEFAULT_FAMILY
    params: BlobParams = field(default_factory=BlobParams)
    _assemble: Any = field(default=None, repr=False)

    def __post_init__(self) -> None:
        targets = _import("app.core.detection.targets")
        if targets is None or not hasattr(targets, "assemble_targets"):
            self.available, self.reason = False, "n/a (targets.py missing)"
            return
        self._assemble = targets.assemble_targets

    def detect(self, gray: np.ndarray) -> list[Detection]:
        found = self._assemble(gray, blob_candidates(gray, self.params), family=self.family)
        return [(int(t.id), np.asarray(t.discs, np.float64).reshape(4, 2)) for t in found]


def all_detectors(family: str = DEFAULT_FAMILY) -> list[PeerDetector]:
    """The benchmark's rows: ours (as live tracking and as the survey run it), the blob
    baseline, AprilTag 3 (two decimations) and
    ArUco (two corner refinements). Unavailable ones carry ``available=False`` and a
    ``reason``."""
    return [
        FidoDetector("fidotrack (learned)", None, family=family),
        FidoDetector("fidotrack, survey (learned + blobs)", None, family=family, thorough=True),
        BlobBaseline("threshold+blob baseline", None, family=family),
        AprilTagDetector("AprilTag 3 tag36h11, decimate 1", apriltag_artwork, quad_decimate=1.0),
        AprilTagDetector("AprilTag 3 tag36h11, decimate 2", apriltag_artwork, quad_decimate=2.0),
        ArucoDetector("ArUco 4x4, default (no refine)", aruco_artwork, refinement="none"),
        ArucoDetector("ArUco 4x4, subpix refine", aruco_artwork, refinement="subpix"),
    ]
