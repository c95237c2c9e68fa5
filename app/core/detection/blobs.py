"""Disc candidates from dark blobs: an adaptive threshold and the shape of each connected
dark region. The plain candidate finder that the learned stage (`candidates`) is measured
against, and its companion for the survey (`Detector.thorough`): a card seen at a
grazing angle (viewing cosine under about 0.3) images its discs as ellipses 4-8 times
longer than wide, which the learned stage's fixed 12x12 window at four scales does not
take for discs, while a thresholded blob keeps its shape whatever its elongation
(bench_detect, grazing frames: 57 % of the cards found with the learned candidates
alone, 71 % with both). It costs about as much again as the learned stage, so live
tracking does without it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["GRAZING_BLOBS", "BlobParams", "blob_candidates"]


@dataclass(frozen=True)
class BlobParams:
    """Parameters of the plain disc-candidate finder: one setting for every condition.

    Chosen on a small sweep (block 31/51/81 px x C 3/5/7/10, 25 frames of each condition,
    seeds apart from the benchmark's): every setting finds 93-100% of the true discs
    within a quarter diameter in default, far, blur and clutter with ~80-200 candidates a
    frame; 51/5 keeps 97% in dark, where larger C loses discs.
    """

    block_size: int = 51  # adaptive-threshold window (px): wider than the nearest discs
    c: float = 5.0  # a pixel is "dark" when this much below its local mean
    min_area: int = 6  # px: discs of ~3 px diameter and up
    max_area: int = 4000  # px: discs up to ~70 px across
    min_axis_ratio: float = 0.3  # minor / major axis: tilts up to ~70 degrees
    min_fill: float = 0.75  # pixel count / area of the moment ellipse (solid ellipse ~1)


#: The blobs the survey adds to the learned candidates: down to a minor / major axis of
#: 0.12, a disc seen at 83 degrees from face-on.
GRAZING_BLOBS = BlobParams(min_axis_ratio=0.12)


def blob_candidates(gray: np.ndarray, params: BlobParams = BlobParams()) -> np.ndarray:
    """Dark elliptical blobs as disc candidates.

    Adaptive mean threshold, 8-connected components, and per component its second
    moments: a solid ellipse fills the ellipse of its moments (area = 4 pi sqrt(det C));
    code cells (squares), merged blobs and thin structures do not.

    Parameters
    ----------
    gray : ndarray
        uint8 greyscale frame.
    params : BlobParams
        The threshold and the shapes kept.

    Returns
    -------
    ndarray of float64, shape (N, 4)
        Rows ``[u, v, radius, score]``, best score first: the blob's binary centroid, the
        radius of the circle of the same area, and in (0, 1] how ellipse-like it is.
    """
    gray = np.asarray(gray)
    dark = cv2.adaptiveThreshold(gray, 1, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY_INV,
                                 params.block_size, params.c)
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(dark, connectivity=8, ltype=cv2.CV_32S)
    area = stats[:, cv2.CC_STAT_AREA].astype(np.float64)
    keep = (area >= params.min_area) & (area <= params.max_area)
    keep[0] = False
    # Blobs touching the image border are cut: their moments say nothing.
    x0, y0 = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
    x1, y1 = x0 + stats[:, cv2.CC_STAT_WIDTH], y0 + stats[:, cv2.CC_STAT_HEIGHT]
    keep &= (x0 > 0) & (y0 > 0) & (x1 < gray.shape[1]) & (y1 < gray.shape[0])
    if not keep.any():
        return np.zeros((0, 4))
    ys, xs = np.nonzero(dark)
    lab = labels[ys, xs]
    sel = keep[lab]
    lab, xs, ys = lab[sel], xs[sel].astype(np.float64), ys[sel].astype(np.float64)
    dx, dy = xs - centroids[lab, 0], ys - centroids[lab, 1]
    sxx = np.bincount(lab, dx * dx, minlength=n)
    syy = np.bincount(lab, dy * dy, minlength=n)
    sxy = np.bincount(lab, dx * dy, minlength=n)
    idx = np.flatnonzero(keep)
    a = area[idx]
    cxx, cyy, cxy = sxx[idx] / a + 1 / 12, syy[idx] / a + 1 / 12, sxy[idx] / a  # + pixel extent
    det = np.maximum(cxx * cyy - cxy * cxy, 1e-12)
    half_tr = (cxx + cyy) / 2
    disc = np.sqrt(np.maximum(half_tr**2 - det, 0.0))
    ratio = np.sqrt(np.maximum(half_tr - disc, 0.0) / (half_tr + disc))
    fill = a / (4 * np.pi * np.sqrt(det))  # 1 for a solid ellipse, less for a square or ring
    score = np.clip(np.minimum(fill, 1 / fill), 0, 1)
    ok = (ratio >= params.min_axis_ratio) & (score >= params.min_fill)
    radius = np.sqrt(a / np.pi)
    out = np.column_stack([centroids[idx, 0], centroids[idx, 1], radius, score])[ok]
    return out[np.argsort(-out[:, 3], kind="stable")]
