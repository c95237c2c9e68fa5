"""Verification: does a disc quadrilateral show a card?

The homography from the card layout to the four disc points maps a fixed set of card
points (`_plan`: the discs, the white card around and between them, the white gap
around the code, the card margin, the code cells) into the image; each proposal is
sampled on the pyramid level matched to its card's size (no aliasing), all proposals
at once with one `cv2.remap` (`_sample`). A quick check of 16 of those points
(`_quick_from`: dark disc centres, white between them) goes first and rides along in
the same pass. The measurements (`_Measures`: black and white levels, contrast,
uniformity of the white, disc levels, gap and margin levels, samples inside the
image) are normalised to black (discs) = 0 and white (card) = 1 and held to thresholds
set on simulator data (bench/bench_targets.py): loosely on
the disc levels before refinement (a candidate may sit half a disc radius off its
disc), strictly after it, with two more checks once the centres are refined
(`MAX_DISC_SAMPLE`, `MAX_RADIUS_SPREAD`). The order statistics of all proposals come
from one compiled loop (`_verification_kernels.measure_stats`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from app.core.detection import _verification_kernels as kernels
from app.core.detection._frame import Pyramid
from app.core.geometry import apply_homographies, homogeneous, jacobians
from app.core.markers import CODE_ORIGIN, CODE_SIZE, DISC_CENTRES, DISC_RADIUS

__all__ = [
    "MAX_DISC_LEVEL",
    "MAX_DISC_LEVEL_COARSE",
    "MAX_DISC_SAMPLE",
    "MAX_DISC_SPREAD",
    "MAX_DISC_SPREAD_COARSE",
    "MAX_RADIUS_SPREAD",
    "MAX_WHITE_SPREAD",
    "MIN_CONTRAST_GREY",
    "MIN_EDGE_LEVEL",
    "MIN_GAP_LEVEL",
    "MIN_VALID_FRACTION",
    "MIN_WHITE_LOW",
    "NOISE_SPREAD_GREY",
    "QUICK_DISC",
    "QUICK_WHITE",
    "SAMPLES_PER_CARD",
    "WHITE_LOW_PERCENTILE",
]


#: Canonical sampling density: samples per card side the pyramid level is matched to.
SAMPLES_PER_CARD = 40.0
#: Photometric verification thresholds on values normalised to black (discs) = 0,
#: white (card) = 1.
MIN_CONTRAST_GREY = 6.0  # white - black in grey levels
MAX_WHITE_SPREAD = 0.35  # P90 - P10 of the white samples between discs and in the gap,
NOISE_SPREAD_GREY = 15.0  # or this many grey levels: sensor noise on a dim card (sigma up to ~6)
MAX_DISC_LEVEL = 0.35  # mean of each disc's samples
MAX_DISC_SPREAD = 0.30  # darkest vs lightest disc
#: The same two before refinement: a candidate up to ~0.55 disc radii off its disc
#: (blur, a disc merged with its neighbourhood) puts some disc samples on the white; the
#: refined card is held to the strict values.
MAX_DISC_LEVEL_COARSE = 0.6
MAX_DISC_SPREAD_COARSE = 0.6
MAX_DISC_SAMPLE = 0.55  # lightest single disc sample, once the centres are refined
WHITE_LOW_PERCENTILE = 10.0
MIN_WHITE_LOW = 0.45  # that percentile of the white samples
MIN_GAP_LEVEL = 0.55  # every gap sample between the code and the discs (worst of 12: 2nd lowest)
MIN_EDGE_LEVEL = 0.5  # median of the card margin near the edge
MIN_VALID_FRACTION = 0.9  # of the card's samples inside the image

#: Largest log(max / min) over a card's discs of (dark area radius / radius predicted by
#: the homography): true cards stay below 0.1 (0.05 for 99.5%), a disc of an
#: overlapping card or a half-hidden one shows 0.14 and more.
MAX_RADIUS_SPREAD = 0.12


# --------------------------------------------------------------------------------------
# Canonical sample points (card units)
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _SamplePlan:
    """Card points sampled to verify and read a target, and which group each is in."""

    points: np.ndarray  # (M, 2) card units
    disc: np.ndarray  # (4, D) indices: samples inside each disc
    ring: np.ndarray  # white ring around each disc
    between: np.ndarray  # white between neighbouring discs
    gap: np.ndarray  # white gap between code and discs
    edge: np.ndarray  # card margin near its edge
    white: np.ndarray  # ring, between and gap: the card's white level
    cells: np.ndarray  # (n*n, S) samples in each code cell, row-major
    n: int
    core: np.ndarray  # discs and code: these must all lie in the image
    #: `_measures_from` sorts five groups of samples: discs, white, between and gap, gap,
    #: edge (last: outside the image it reads inf).
    sorted_index: np.ndarray  # (G,) sample indices, group after group
    sorted_bounds: np.ndarray  # (6,) each group's first column, then G
    #: Order statistics read off the sorted groups, each ``s[lo] + frac * (s[hi] - s[lo])``
    #: (np.quantile's linear rule): disc median, white median, P90 and P10 of between and
    #: gap, `WHITE_LOW_PERCENTILE` of white, 2nd lowest gap sample, lightest disc sample.
    stats_lo: np.ndarray
    stats_hi: np.ndarray
    stats_frac: np.ndarray  # float32, as the Python float a float32 array would be scaled by


@functools.cache
def _plan(n: int) -> _SamplePlan:
    """The sample plan of a card with a code of n x n cells: 7 points in each disc, 12
    on a ring around it, 3 between each pair of neighbouring discs, 3 in the gap on each
    side of the code, 16 on the card margin, 5 in each code cell."""
    pts: list[np.ndarray] = []

    def add(p: np.ndarray) -> np.ndarray:
        start = sum(len(a) for a in pts)
        pts.append(np.asarray(p, np.float64).reshape(-1, 2))
        return np.arange(start, start + len(pts[-1]))

    ang6 = np.linspace(0, 2 * np.pi, 6, endpoint=False)
    ang12 = np.linspace(0, 2 * np.pi, 12, endpoint=False) + np.pi / 12
    disc_in = np.concatenate([[[0.0, 0.0]], 0.5 * DISC_RADIUS * np.stack([np.cos(ang6), np.sin(ang6)], 1)])
    ring = 1.3 * DISC_RADIUS * np.stack([np.cos(ang12), np.sin(ang12)], 1)
    disc = np.stack([add(c + disc_in) for c in DISC_CENTRES])
    ring_ = np.concatenate([add(c + ring) for c in DISC_CENTRES])
    t = np.array([0.4, 0.5, 0.6])
    lo, hi = DISC_CENTRES[0, 0], DISC_CENTRES[2, 0]
    between = np.concatenate([add(np.stack([a, b], 1)) for a, b in  # between neighbouring discs
                              ((t, np.full(3, lo)), (np.full(3, hi), t), (t, np.full(3, hi)), (np.full(3, lo), t))])
    g = 0.5 * (lo + CODE_ORIGIN)  # middle of the gap between disc line and code
    g2 = 1.0 - g
    gap = np.concatenate([add(np.stack([a, b], 1)) for a, b in
                          ((t, np.full(3, g)), (np.full(3, g2), t), (t, np.full(3, g2)), (np.full(3, g), t))])
    # Card margin outside the discs, 0.05 from the card edge: white on a true card, but
    # it meets the background (blur, occlusion, image border), so it is judged loosely.
    e0, e1 = 0.05, 0.95
    te = np.array([0.35, 0.5, 0.65])
    edge = np.concatenate([add(np.stack([a, b], 1)) for a, b in
                           ((te, np.full(3, e0)), (np.full(3, e1), te), (te, np.full(3, e1)), (np.full(3, e0), te))]
                          + [add(np.array([[0.06, 0.06], [0.94, 0.06], [0.94, 0.94], [0.06, 0.94]]))])
    step = CODE_SIZE / n
    sub = 0.22 * step * np.array([[0, 0], [-1, -1], [1, -1], [1, 1], [-1, 1]], np.float64)
    cells = []
    for r in range(n):
        for c in range(n):
            centre = np.array([CODE_ORIGIN + (c + 0.5) * step, CODE_ORIGIN + (r + 0.5) * step])
            cells.append(add(centre + sub))
    cells_ = np.stack(cells)
    white = np.concatenate([ring_, between, gap])
    groups = [disc.ravel(), white, np.concatenate([between, gap]), gap, edge]
    bounds = np.cumsum([0] + [g.size for g in groups])
    stats = []
    for k, q in ((0, 0.5), (1, 0.5), (2, 0.9), (2, 0.1), (1, WHITE_LOW_PERCENTILE / 100.0), (3, None), (0, None)):
        size = groups[k].size
        if q is None:  # the 2nd lowest gap sample, the lightest disc sample
            at = 1 if k == 3 else size - 1
            stats.append((bounds[k] + at, bounds[k] + at, 0.0))
            continue
        pos = q * (size - 1)
        lo = int(np.floor(pos))
        stats.append((bounds[k] + lo, bounds[k] + min(lo + 1, size - 1), pos - lo))
    lo_, hi_, frac = zip(*stats, strict=True)
    plan = _SamplePlan(points=np.concatenate(pts), disc=disc, ring=ring_, between=between, gap=gap, edge=edge,
                       white=white, cells=cells_, n=n, core=np.concatenate([disc.ravel(), cells_.ravel()]),
                       sorted_index=np.concatenate(groups), sorted_bounds=bounds.astype(np.intp),
                       stats_lo=np.array(lo_), stats_hi=np.array(hi_), stats_frac=np.array(frac, np.float32))
    return plan


# --------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------


def _sample(pyr: Pyramid, hs: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples (P, M) float32 of card points `pts` (M, 2), or (M, 3)
    homogeneous, through homographies `hs`, each quadrilateral from the pyramid level
    whose pixel matches the sample spacing (so a big card is not aliased), and a mask
    (P, M) of samples inside the image."""
    p, m = hs.shape[0], pts.shape[0]
    if p == 0:
        return np.zeros((0, m), np.float32), np.zeros((0, m), bool)
    xy = apply_homographies(hs, pts)  # (P, M, 2) full-resolution pixels
    h, w = pyr.levels[0].shape
    # card side in pixels: sqrt(|det J|) at the card centre, det J = det H / w**3
    wc = 0.5 * (hs[:, 2, 0] + hs[:, 2, 1]) + hs[:, 2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        spacing = np.sqrt(np.abs(np.linalg.det(hs) / (wc * wc * wc))) / SAMPLES_PER_CARD
    spacing = np.where(np.isfinite(spacing), spacing, 1.0)
    level = np.minimum(np.floor(np.log2(np.maximum(spacing, 1.0))), pyr.max_level).astype(int)
    # NaN and inf compare False: outside
    inside = ((xy >= -0.5) & (xy <= np.array([w - 0.5, h - 0.5]))).all(axis=-1)
    if not np.isfinite(xy.sum()):
        xy = np.where(np.isfinite(xy).all(axis=-1)[..., None], xy, -10.0)
    xy = xy.astype(np.float32)
    lv0 = int(level[0])
    if (level == lv0).all():
        if lv0:
            xy *= np.float32(0.5**lv0)
        out = cv2.remap(pyr.get(lv0), xy, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return out.reshape(p, m).astype(np.float32), inside
    out = np.zeros((p, m), np.float32)
    for lv in np.unique(level).tolist():
        rows = np.flatnonzero(level == lv)
        out[rows] = cv2.remap(pyr.get(lv), xy[rows] * np.float32(0.5**lv), None, cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REPLICATE)
    return out, inside


# --------------------------------------------------------------------------------------
# Measurements
# --------------------------------------------------------------------------------------

# Quick check, on every proposal: the 4 disc centres, then 12 card points that are white
# on every card (between neighbouring discs, in the gap beside the code, and in the card
# corners outside the discs).
_QUICK_POINTS = np.concatenate([
    DISC_CENTRES,
    [[0.5, 0.2], [0.8, 0.5], [0.5, 0.8], [0.2, 0.5]],
    [[0.5, 0.275], [0.725, 0.5], [0.5, 0.725], [0.275, 0.5]],
    DISC_CENTRES + 1.3 * DISC_RADIUS * np.sqrt(0.5) * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]),
])
#: Quick check: every disc centre below this, and all but one of the white points above
#: QUICK_WHITE (values normalised so the mean disc centre is 0 and the median white 1).
QUICK_DISC = 0.4
QUICK_WHITE = 0.5


def _quick_from(vals: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Could these be cards at all? bool (P,) from the samples (P, 16) of
    `_QUICK_POINTS` and their mask (P, 16): contrast, dark disc centres inside the image
    (`QUICK_DISC`) and white points (`QUICK_WHITE`)."""
    disc = vals[:, :4]
    black = _mean(disc, 1)
    wv = np.sort(vals[:, 4:], axis=1)
    white = 0.5 * (wv[:, 5] + wv[:, 6])  # median of 12
    c = white - black
    ok = (c >= MIN_CONTRAST_GREY) & inside[:, :4].all(axis=1)
    cn = np.maximum(c, 1e-3)[:, None]
    ok &= (disc.max(axis=1) - black) <= QUICK_DISC * cn[:, 0]
    whites = np.where(inside[:, 4:], (vals[:, 4:] - black[:, None]) / cn, 1.0)
    ok &= np.partition(whites, 1, axis=1)[:, 1] >= QUICK_WHITE
    return ok


@dataclass(frozen=True, eq=False)
class _Measures:
    """Photometric measurements of P card hypotheses; levels normalised so that the
    discs are 0 and the card's white 1."""

    black: np.ndarray  # (P,) grey level of the discs
    white: np.ndarray  # (P,) grey level of the card
    contrast: np.ndarray  # (P,) white - black, grey levels
    uniformity: np.ndarray  # (P,) spread (P90 - P10) of the white between discs and in the gap
    disc_level: np.ndarray  # (P,) mean of the lightest disc
    disc_spread: np.ndarray  # (P,) lightest - darkest disc mean
    disc_max: np.ndarray  # (P,) lightest single sample inside any disc (half-hidden discs)
    white_low: np.ndarray  # (P,) low percentile of all white samples
    gap_low: np.ndarray  # (P,) 2nd lowest gap sample
    edge_level: np.ndarray  # (P,) median of the card margin near its edge
    valid: np.ndarray  # (P,) fraction of samples inside the image (0 if discs or code are not)
    cells: np.ndarray | None  # (P, n*n) code cell means (None: not read)

    def passed(self, coarse: bool = False) -> np.ndarray:
        """All checks; `coarse`: before refinement, looser on the disc levels (a
        candidate may sit half a radius off its disc centre)."""
        return (
            (self.contrast >= MIN_CONTRAST_GREY)
            & (self.uniformity <= np.maximum(MAX_WHITE_SPREAD, NOISE_SPREAD_GREY / np.maximum(self.contrast, 1e-3)))
            & (self.disc_level <= (MAX_DISC_LEVEL_COARSE if coarse else MAX_DISC_LEVEL))
            & (self.disc_spread <= (MAX_DISC_SPREAD_COARSE if coarse else MAX_DISC_SPREAD))
            & (self.white_low >= MIN_WHITE_LOW)
            & (self.gap_low >= MIN_GAP_LEVEL)
            & (self.edge_level >= MIN_EDGE_LEVEL)
            & (self.valid >= MIN_VALID_FRACTION)
        )


def _mean(x: np.ndarray, axis: int) -> np.ndarray:
    """``x.mean(axis)`` by np.mean's own arithmetic (the sum divided by an intp count)
    without its Python overhead (~5 us a call)."""
    s = x.sum(axis=axis)
    return np.true_divide(s, np.intp(x.shape[axis]), out=s, casting="unsafe")


def _measure(pyr: Pyramid, hs: np.ndarray, n: int) -> _Measures:
    """Photometric measurements of the card hypotheses `hs` (P, 3, 3) (layout -> image)
    for a family of n x n codes."""
    plan = _plan(n)
    vals, inside = _sample(pyr, hs, _plan_points_h(n))
    return _measures_from(vals, inside, plan)


@functools.cache
def _plan_points_h(n: int) -> np.ndarray:
    """The sample points of `_plan(n)`, homogeneous."""
    return homogeneous(_plan(n).points)


@functools.cache
def _plan_and_quick(n: int) -> np.ndarray:
    """The sample points of `_plan(n)` followed by `_QUICK_POINTS`, homogeneous."""
    return homogeneous(np.concatenate([_plan(n).points, _QUICK_POINTS]))


def _measures_from(vals: np.ndarray, inside: np.ndarray, plan: _SamplePlan, cells: bool = True) -> _Measures:
    """`_measure` of the samples (P, M) of `plan.points` (whole grey levels: a uint8
    image read by cv2.remap) and their mask; `cells`: read the code cells too. The
    order statistics (np.median, np.percentile) come from a sort of each group of
    samples (`_SamplePlan.sorted_index`), all in one compiled loop over the rows
    (`kernels.measure_stats`)."""
    if vals.shape != inside.shape:  # the kernel reads both by the samples' count
        raise ValueError(f"samples {vals.shape} and their mask {inside.shape} differ")
    stats, valid = kernels.measure_stats(
        np.ascontiguousarray(vals, np.float32), np.ascontiguousarray(inside), plan.sorted_index, plan.sorted_bounds,
        plan.stats_lo, plan.stats_hi, plan.stats_frac, plan.disc, plan.edge, plan.core)
    black, white, contrast, c, uniformity, dmax, spread, disc_max, white_low, gap_low, edge_level = stats
    cell_means = None
    if cells:
        # (P, n*n, S); fancy indexing, not take: its (n*n, S, P) memory layout carries into
        # the template fit, whose float32 sums depend on it
        cell_vals = (vals[:, plan.cells] - black[:, None, None]) / c[:, None, None]
        cell_means = _mean(cell_vals, 2)
    return _Measures(
        black=black, white=white, contrast=contrast, uniformity=uniformity,
        disc_level=dmax, disc_spread=spread, disc_max=disc_max, white_low=white_low, gap_low=gap_low,
        edge_level=edge_level, valid=valid, cells=cell_means,
    )


# --------------------------------------------------------------------------------------
# Checks once the centres are refined
# --------------------------------------------------------------------------------------


def _predicted_radii(hs: np.ndarray) -> np.ndarray:
    """(P, 4) imaged disc radii the homographies predict (sqrt of the local area scale)."""
    jac = jacobians(hs, DISC_CENTRES)
    return DISC_RADIUS * np.sqrt(np.abs(jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]))


def _radius_spread(pred: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """(P,) log(max / min) over the four discs of measured radius / radius predicted by
    the homography (`_predicted_radii`)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.log(np.maximum(radii, 1e-9) / np.maximum(pred, 1e-9))
    spread = ratio.max(axis=1) - ratio.min(axis=1)
    return np.where(np.isfinite(spread), spread, np.inf)
