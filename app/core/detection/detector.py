"""The whole fiducial detector of the paper (§4), frame in, identified targets out: disc
candidates (`candidates`: a fast classifier and a condensed nearest neighbour over a
4-level pyramid), then targets (`targets.assemble_targets`: grouping, verification,
subpixel centres, identification, completion), on the whole frame or on the regions a
tracked pose predicts (the crops scanned as one mosaic); optionally, for the survey,
dark blobs as candidates too (`blobs`) and small discs' centres fitted (`disc_fit`)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from app.core.detection.blobs import GRAZING_BLOBS, blob_candidates
from app.core.detection.candidates import MIN_SIDE, DiscClassifier, detect_windows
from app.core.detection.disc_fit import fit_disc_centres
from app.core.detection.targets import DetectedTarget, assemble_targets
from app.core.geometry import Region, homographies
from app.core.markers import DEFAULT_FAMILY, get_family

__all__ = ["THOROUGH_LEVEL0_BLOB", "Detection", "Detector"]

#: The thorough (survey) detector's stage-1a threshold at pyramid level 0. A card with
#: 3-4 px discs turned about 45 degrees in its plane has its neighbouring discs in the
#: corners of each disc's 12x12 window, which lowers the disc's blob score (median 0.27
#: against 0.31 upright): the classifier's 0.25 keeps 56 % of them, 0.18 86 %. The screen
#: and stage 2, trained on windows above 0.25, judge the extra windows by their looks as
#: well. It lets ~50 % more windows of a textured frame through (about 1 ms a frame):
#: worth it for the survey, which maps far cards once, not for live tracking.
THOROUGH_LEVEL0_BLOB = 0.18


@dataclass(frozen=True)
class Detection:
    """Targets found in one frame, every candidate disc, and where the time went.

    Parameters
    ----------
    targets : list of DetectedTarget
        The identified targets, by id.
    candidates : ndarray, shape (N, 4)
        Every disc candidate ``[u, v, radius, score]`` in full-frame pixels.
    timing_ms : dict
        Milliseconds of ``candidates``, ``targets`` (and of its sub-stages, as
        ``targets.group`` etc.; ``targets.fit`` with `Detector.fit_discs`) and the
        whole ``detect``; ``regions``: how many crops were scanned (absent for a
        full-frame scan).
    """

    targets: list[DetectedTarget]
    candidates: np.ndarray  # (N, 4) [u, v, radius, score]
    timing_ms: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class Detector:
    """The detector: a disc classifier and the code family of the targets.

    Parameters
    ----------
    classifier : DiscClassifier
        The candidate stage's classifier (`load_default_classifier`, or one adapted to
        a site).
    family : str
        The code family of the targets; KeyError if there is none of that name.
    fit_discs : bool
        Fit the centres of small discs (semi-major axis up to 8 px) with a model of the
        card around each (`disc_fit`) instead of keeping the refined centroids: median
        error 0.010 px instead of 0.014 on the survey bench's walks, 0.018 instead of
        0.029 on discs of 1.5-2 px minor semi-axis (bench/bench_disc_fit.py); ~13 ms
        more per frame. For the survey, not for live tracking.
    thorough : bool
        Look harder, for about twice the time a frame: add dark elliptical blobs
        (`blobs.blob_candidates`, `GRAZING_BLOBS`) to the learned candidates, so that
        cards at grazing angles, whose discs the learned stage does not take for discs,
        are found too; and run stage 1a at level 0 at `THOROUGH_LEVEL0_BLOB` at most,
        for the small discs of rolled cards. For the survey, not for live tracking.
    """

    classifier: DiscClassifier
    family: str = DEFAULT_FAMILY
    fit_discs: bool = False
    thorough: bool = False
    _scanning: DiscClassifier = field(init=False, repr=False)  # the classifier the candidate stage runs

    def __post_init__(self) -> None:
        get_family(self.family)  # KeyError now rather than at the first frame
        scanning = self.classifier
        if self.thorough:
            thresholds = np.array(self.classifier.blob_thresholds, np.float32)
            thresholds[0] = min(float(thresholds[0]), THOROUGH_LEVEL0_BLOB)
            scanning = self.classifier.replace(blob_thresholds=thresholds)
        object.__setattr__(self, "_scanning", scanning)

    @classmethod
    def for_survey(cls, classifier: DiscClassifier, family: str = DEFAULT_FAMILY) -> Detector:
        """The survey's detector: blobs as candidates too, small discs' centres fitted.

        Parameters
        ----------
        classifier : DiscClassifier
        family : str

        Returns
        -------
        Detector
        """
        return cls(classifier, family, fit_discs=True, thorough=True)

    def detect(self, gray: np.ndarray, regions: Sequence[Region] | None = None) -> Detection:
        """Detect targets in a frame; with `regions`, only in those crops.

        Disc candidates are searched in the crops only; targets are then assembled from
        them on the whole frame, in full-frame pixels. Crops should start at multiples
        of 8 pixels (see `app.core.geometry.predict_regions`): then a disc well inside a
        crop gets the same candidate, and its target the same disc centres, as in a full
        scan. A disc seen by two overlapping crops counts once.

        Parameters
        ----------
        gray : ndarray
            The frame, uint8 greyscale; ValueError otherwise.
        regions : sequence of Region, optional
            Crops to search (full-frame pixels); None: the whole frame.

        Returns
        -------
        Detection
            The targets, the candidates and the timings.
        """
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise ValueError(f"expected a uint8 greyscale image, got {gray.dtype} {gray.shape}")
        if regions is None:
            return self._detect(gray)
        return self._detect_regions(gray, regions)

    def _detect(self, gray: np.ndarray) -> Detection:
        start = time.perf_counter()
        candidates, s1, _ = detect_windows(gray, self._scanning)
        if self.thorough:
            candidates = _with_blobs(candidates, blob_candidates(gray, GRAZING_BLOBS))
        found = time.perf_counter()
        stages: dict[str, float] = {}
        # The candidate stage's pyramid serves the targets' sampling too.
        targets = assemble_targets(gray, candidates, self.family, timing=stages, pyramid=s1.levels)
        if self.fit_discs:
            targets = _fitted(gray, targets, stages)
        done = time.perf_counter()
        timing = {"candidates": (found - start) * 1e3, "targets": (done - found) * 1e3}
        timing.update({f"targets.{k}": v for k, v in stages.items()})  # group, verify, refine, identify
        timing["detect"] = (done - start) * 1e3
        return Detection(targets=targets, candidates=candidates, timing_ms=timing)

    def _detect_regions(self, gray: np.ndarray, regions: Sequence[Region]) -> Detection:
        # Disc candidates in the crops only (the stage whose cost grows with the pixels
        # scanned), then one target stage over all of them on the whole frame: its cost
        # is per proposal plus a fixed overhead per call that crops would pay again and
        # again, and on the whole frame a card is measured exactly as in a full scan
        # (same image, same pyramid), even where it reaches past its crop.
        start = time.perf_counter()
        height, width = gray.shape
        boxes = [b for b in (_fit(r, width, height) for r in regions)
                 if b[2] - b[0] >= MIN_SIDE and b[3] - b[1] >= MIN_SIDE]
        candidates = np.zeros((0, 4), np.float32)
        if boxes:
            # The candidate stage has a fixed cost per call (~40 small OpenCV and numpy
            # calls over 4 levels) worth a 170x170 crop: the crops go side by side into
            # one mosaic, scanned once. Each sits at a multiple of 8 as in the frame,
            # so its pyramid samples are the frame's away from its edges.
            mosaic, places = _pack(gray, boxes)
            rows, _, _ = detect_windows(mosaic, self._scanning)
            candidates = _unpack(rows, boxes, places, width, height)
            if self.thorough:  # the blobs of the same mosaic, back in the frame the same way
                blobs = blob_candidates(mosaic, GRAZING_BLOBS).astype(np.float32)
                candidates = _with_blobs(candidates, _unpack(blobs, boxes, places, width, height))
        found = time.perf_counter()
        stages: dict[str, float] = {}
        targets = assemble_targets(gray, candidates, self.family, timing=stages)
        if self.fit_discs:
            targets = _fitted(gray, targets, stages)
        done = time.perf_counter()
        timing = {"candidates": (found - start) * 1e3, "targets": (done - found) * 1e3}
        timing.update({f"targets.{k}": v for k, v in stages.items()})
        timing["detect"] = (done - start) * 1e3
        timing["regions"] = float(len(boxes))
        return Detection(targets=targets, candidates=candidates, timing_ms=timing)


#: A blob within this distance (px) of a learned candidate is the same disc: the learned
#: candidate stands for it.
_SAME_DISC_PX = 1.5
#: The score column of the blob candidates: below every learned candidate's.
_BLOB_SCORE = -1.0


def _with_blobs(candidates: np.ndarray, blobs: np.ndarray) -> np.ndarray:
    """The learned candidates, then the blobs that are no learned candidate's disc."""
    if len(blobs) == 0:
        return candidates
    if len(candidates):
        d2 = ((blobs[:, None, :2] - candidates[None, :, :2].astype(np.float64)) ** 2).sum(axis=2).min(axis=1)
        blobs = blobs[d2 > _SAME_DISC_PX**2]
    extra = blobs.astype(np.float32)
    extra[:, 3] = _BLOB_SCORE
    return np.vstack([candidates.astype(np.float32).reshape(-1, 4), extra])


def _fitted(gray: np.ndarray, targets: list[DetectedTarget], stages: dict[str, float]) -> list[DetectedTarget]:
    """`targets` with their small discs' centres fitted by `disc_fit` (timed as
    ``fit``)."""
    if not targets:
        return targets
    start = time.perf_counter()
    discs = np.array([t.discs for t in targets])
    fit = fit_disc_centres(gray, discs, homographies(discs))
    out = [dataclasses.replace(t, discs=fit.centres[k]) for k, t in enumerate(targets)]
    stages["fit"] = (time.perf_counter() - start) * 1e3
    return out


#: Mosaic sides are rounded up to this (fewer distinct shapes for the candidate stage's
#: per-shape buffers); crops are placed on multiples of 8 (the pyramid's alignment).
_MOSAIC_STEP = 16
_MOSAIC_FILL = 128  # flat grey: no blob scores there


def _shelves(sizes: list[tuple[int, int]], order: list[int], shelf_width: int) -> tuple[list[tuple[int, int]], int]:
    """Place crops (in `order`) left to right on shelves `shelf_width` wide: their
    top-left corners and the total height."""
    places: list[tuple[int, int]] = [(0, 0)] * len(sizes)
    x = y = shelf = 0
    for k in order:
        w, h = sizes[k]
        if x and x + w > shelf_width:
            x, y, shelf = 0, y + shelf, 0
        places[k] = (x, y)
        x += -(-w // 8) * 8
        shelf = max(shelf, -(-h // 8) * 8)
    return places, y + shelf


def _pack(gray: np.ndarray, boxes: list[tuple[int, int, int, int]]) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Shelf-pack the crops into one image: (mosaic, top-left (x, y) of each crop in it).
    Tallest first; of a few shelf widths the one giving the smallest mosaic."""
    sizes = [(x1 - x0, y1 - y0) for x0, y0, x1, y1 in boxes]
    order = sorted(range(len(sizes)), key=lambda k: -sizes[k][1])
    widest = max(w for w, _ in sizes)
    total = sum(-(-w // 8) * 8 for w, _ in sizes)
    step = _MOSAIC_STEP
    best: tuple[int, int, list[tuple[int, int]]] | None = None
    for width in sorted({widest, total, *(int(widest + f * (total - widest)) for f in (0.25, 0.5, 0.75))}):
        width = -(-width // step) * step
        places, height = _shelves(sizes, order, width)
        used = max(x + -(-sizes[k][0] // 8) * 8 for k, (x, _) in enumerate(places))
        cost = (-(-used // step) * step) * (-(-height // step) * step)
        if best is None or cost < best[0] * best[1]:
            best = (-(-used // step) * step, -(-height // step) * step, places)
    assert best is not None
    mosaic_w, mosaic_h, places = best
    mosaic = np.full((mosaic_h, mosaic_w), _MOSAIC_FILL, np.uint8)
    for (x0, y0, x1, y1), (px, py) in zip(boxes, places, strict=True):
        mosaic[py:py + y1 - y0, px:px + x1 - x0] = gray[y0:y1, x0:x1]
    return mosaic, places


def _unpack(rows: np.ndarray, boxes: list[tuple[int, int, int, int]], places: list[tuple[int, int]],
            width: int, height: int) -> np.ndarray:
    """Mosaic candidates -> frame candidates, best score first. A disc that is not wholly
    inside its crop (where the crop's edge is not the frame's) is dropped: next to it
    the mosaic holds another crop, so its centre and radius are not the frame's; its
    card, if it matters, lies in a crop of its own. A disc that two overlapping crops
    both see counts once."""
    out = []
    owner = []
    u, v, r = rows[:, 0], rows[:, 1], rows[:, 2]
    for k, ((x0, y0, x1, y1), (px, py)) in enumerate(zip(boxes, places, strict=True)):
        w, h = x1 - x0, y1 - y0
        lo_x = np.where(x0 > 0, u - r, u) >= px - 0.5
        hi_x = np.where(x1 < width, u + r, u) <= px + w - 0.5
        lo_y = np.where(y0 > 0, v - r, v) >= py - 0.5
        hi_y = np.where(y1 < height, v + r, v) <= py + h - 0.5
        mine = rows[lo_x & hi_x & lo_y & hi_y].copy()
        mine[:, 0] += np.float32(x0 - px)
        mine[:, 1] += np.float32(y0 - py)
        out.append(mine)
        owner.append(np.full(mine.shape[0], k))
    cand = np.concatenate(out) if out else np.zeros((0, 4), np.float32)
    crop = np.concatenate(owner) if owner else np.zeros(0, int)
    order = np.argsort(-cand[:, 3], kind="stable")
    cand, crop = cand[order], crop[order]
    if _overlap(boxes) and cand.shape[0] > 1:
        # The same disc from two crops: (nearly) the same centre, another crop. Keep the
        # first (best score); discs of one crop are left as the candidate stage made them.
        d = np.hypot(cand[:, None, 0] - cand[None, :, 0], cand[:, None, 1] - cand[None, :, 1])
        same = (d < np.maximum(1.0, 0.5 * np.minimum(cand[:, None, 2], cand[None, :, 2]))) & (crop[:, None] != crop)
        same &= np.tri(cand.shape[0], k=-1, dtype=bool)  # j < i: an earlier (better) copy
        cand = cand[~same.any(axis=1)]
    return cand


def _overlap(boxes: list[tuple[int, int, int, int]]) -> bool:
    return any(a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]
               for i, a in enumerate(boxes) for b in boxes[i + 1:])


def _fit(region: Region, width: int, height: int) -> tuple[int, int, int, int]:
    """The region clipped to the frame, each side grown to the detector's minimum
    (24 px) where the frame allows, keeping the start on a multiple of 8."""
    x0, y0 = max(0, int(region.x0)), max(0, int(region.y0))
    x1, y1 = min(width, int(region.x1)), min(height, int(region.y1))
    if x1 - x0 < MIN_SIDE:
        x1 = min(width, max(x1, x0 + MIN_SIDE))
        x0 = max(0, min(x0, (x1 - MIN_SIDE) // 8 * 8))
    if y1 - y0 < MIN_SIDE:
        y1 = min(height, max(y1, y0 + MIN_SIDE))
        y0 = max(0, min(y0, (y1 - MIN_SIDE) // 8 * 8))
    return x0, y0, x1, y1
