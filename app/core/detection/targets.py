"""Targets from disc candidates: grouping, verification, subpixel disc centres and
identification (Claus & Fitzgibbon, WACV 2005, section 4, after the learned disc stage).

Pipeline of `assemble_targets`:

1. Grouping (`group_candidates`). The paper relies on the Delaunay triangulation of the
   candidates holding each true target as two adjacent triangles. Our own code cells
   (and clutter next to a card) are candidates too and break that, so a graph is used
   instead: an edge joins two candidates that could be neighbouring discs of one card
   (similar radii, distance consistent with them; found by a sweep along x). A card is
   a 4-cycle, found once, from its lowest-indexed disc: two of its edges are the
   adjacent discs and the fourth disc is a neighbour of one of them near the
   parallelogram prediction. Cheap vectorised geometry (convex, similar radii, disc
   size vs quadrilateral size, angles) prunes the proposals. An edge must also look
   like a card side in the image (`_side_test`: white between two dark candidates, five
   points on pyramid level 1), which removes three quarters of the edges among texture.
2. Verification (`_measure`). The homography from the card layout to the four points
   is used to sample a fixed set of card points (discs, the white card around and
   between them, the white gap around the code, the code cells) from a pyramid level
   matched to the card's size (no aliasing), all proposals at once with one
   `cv2.remap` (the quick check's 16 points ride along in the same pass). Thresholds on
   the normalised measurements were set on simulator data (bench/bench_targets.py prints
   the distributions); before refinement the disc levels are judged loosely (a
   candidate may sit half a disc radius off), after it every check is strict.
3. Subpixel centres (`refine_centres`): background-corrected intensity-weighted
   centroid in a window that is the image of a circle around the disc (through the
   homography of the four discs), minus the perspective bias of the ellipse centroid
   (exact, from the image conic of the disc), iterated.
4. Identification (`identify`, `decode_cells`): the code is read through the refined
   homography, normalised by the card's own black (discs) and white levels and fitted
   by every code of the family in all four rotations, each as it reads through a few
   amounts of blur (a far card's 2 px cells are never read as clean black and white);
   a read whose best fit is poor, or that another code or rotation fits nearly as well,
   is refused.
5. Completion (`_complete`): a card of which only three discs have usable candidates
   (blur, a highlight, a candidate radius far off) is proposed from those three (a
   corner of card sides among the candidates no target uses), its fourth disc predicted
   by the parallelogram; the proposal has to pass a cheap affine read of the card and
   the coarse checks, then it is refined and judged exactly like the others, the
   predicted disc held to the same photometric checks as a candidate's.

Coordinates: full-resolution pixels, centre of the top-left pixel at (0, 0). Disc order
of the output follows DESIGN.md: 0 top-left, 1 top-right, 2 bottom-right, 3 bottom-left
as printed, the card upright as its code defines.

numpy/OpenCV/SciPy, and numba kernels (`app.core.detection.kernels`) where a fused loop over
small arrays beats numpy's per-call overhead (the grouping's sweep and search, the
verification's order statistics, the affine points of completion, the refinement's
centroid step), with identical results. No I/O.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from app.core.detection import kernels
from app.core.geometry.homography import (
    apply_homographies,
    homogeneous,
    homographies,
    jacobians,
    perspective_bias,
)
from app.core.markers import CODE_ORIGIN, CODE_SIZE, DEFAULT_FAMILY, DISC_CENTRES, DISC_RADIUS, get_family

# --------------------------------------------------------------------------------------
# Public types
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)  # eq=False: ndarray fields make a generated __eq__ useless
class DetectedTarget:
    """One identified target in an image.

    discs: (4, 2) subpixel disc centres (projections of the printed disc centres), in
    DESIGN.md order; score: confidence 0..1; disc_radii: (4,) imaged radii in pixels
    (sqrt of the disc's dark area / pi).
    """

    id: int
    discs: np.ndarray
    score: float
    disc_radii: np.ndarray = field(default_factory=lambda: np.zeros(4))

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": int(self.id),
            "discs": [[float(u), float(v)] for u, v in np.asarray(self.discs, np.float64)],
            "score": float(self.score),
        }


# --------------------------------------------------------------------------------------
# Tunables (set on simulator data, see bench/bench_targets.py)
# --------------------------------------------------------------------------------------

#: Largest ratio of two candidate radii joined by an edge / within one quadrilateral.
#: The candidate stage's radius is coarse (~15%, worse under blur) and a tilted card
#: shows its near discs larger than its far ones.
RADIUS_RATIO_MAX = 2.0
#: Edge length between two discs of a card over their mean candidate radius: 4.8 for a
#: fronto-parallel card (side 0.6 / radius 0.125), 6.8 for the diagonal; foreshortening
#: shortens a side by up to cos(70 deg) while the radius (a mean of the ellipse axes)
#: shrinks less, and the radius may be off by ~1.5x.
EDGE_OVER_RADIUS = (2.2, 10.0)
#: sqrt(quadrilateral area) / mean candidate radius: 4.8 whatever the affine view (area
#: ratios are affine invariant), within the radius error and perspective.
SQRT_AREA_OVER_RADIUS = (3.3, 7.0)
#: sqrt(|cross product|) of the two sides at an apex over the apex's radius: the same
#: 4.8 nominal, looser (one radius, and perspective skews the parallelogram).
APEX_AREA_OVER_RADIUS = (2.2, 9.0)
#: Interior angles of the disc quadrilateral (degrees): a square tilted by 70 degrees
#: about its diagonal shows 38 and 142.
ANGLE_RANGE_DEG = (22.0, 158.0)
#: Shortest over longest side.
SIDE_RATIO_MIN = 0.22

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
#: Largest move of a disc centre in refinement, in predicted disc radii (2 px at least).
MAX_REFINE_SHIFT = 0.8

#: Subpixel refinement: window (in disc radii, card units) and white ring.
REFINE_WINDOW = 1.1
REFINE_TAPER = 0.1
REFINE_RING = (1.15, 1.4)
REFINE_ITERATIONS = 2
#: Up to this many more while the last one still moved a centre by `REFINE_SETTLED` px
#: or more (a candidate far off its disc); the white ring is measured again while the
#: last move exceeded `REFINE_WHITE_AGAIN` px (else the first pass's median is kept).
REFINE_EXTRA_ITERATIONS = 3
REFINE_SETTLED = 0.1
REFINE_WHITE_AGAIN = 0.5
REFINE_CONVERGED = 0.01  # px: stop early when no centre moved more
REFINE_MAX_HALF = 16  # larger windows are measured on a pyramid level


# --------------------------------------------------------------------------------------
# Grouping
# --------------------------------------------------------------------------------------


def _clean(candidates: np.ndarray) -> np.ndarray:
    """Indices of usable candidates: finite, positive radius, one per half-pixel cell
    (of duplicates the better score stays)."""
    c = np.asarray(candidates, dtype=np.float64)
    if c.ndim != 2 or c.shape[0] == 0 or c.shape[1] < 3:
        return np.zeros(0, np.intp)
    # |u|, |v| < 1e6 is False for NaN and inf too
    usable = (np.abs(c[:, :2]) < 1e6).all(axis=1) & (c[:, 2] > 0) & (c[:, 2] < np.inf)
    if c.shape[1] >= 4:
        usable &= np.isfinite(c[:, 3])
    idx = np.flatnonzero(usable)
    if idx.size < 2:
        return idx
    cell = np.rint((c if idx.size == c.shape[0] else c.take(idx, axis=0))[:, :2] * 2.0)
    key = cell[:, 0] * 4_000_003.0 + cell[:, 1]  # exact in float64 for |u|, |v| < 1e6
    ks = np.sort(key)
    if (ks[1:] != ks[:-1]).all():
        return idx  # no duplicates (the candidate stage suppresses them already)
    # by cell, then best score first (ties: lower index) within each cell
    order = np.lexsort((-c[idx, 3], key)) if c.shape[1] >= 4 else np.argsort(key, kind="stable")
    ks = key[order]
    first = order[np.concatenate(([True], ks[1:] != ks[:-1]))]
    return np.sort(idx[first])


#: cos^2 of the smallest interior angle (`ANGLE_RANGE_DEG`; the largest is its supplement).
_COS2_ANGLE = float(np.cos(np.deg2rad(ANGLE_RANGE_DEG[0])) ** 2)
#: Vertex k + 1 of a quadrilateral.
_NEXT = np.array([1, 2, 3, 0])


#: Grouping: every pair of candidates that could be neighbouring discs of one card
#: (similar radius, distance consistent with the radii) is an edge; each candidate keeps
#: at most `EDGE_KEEP` edges, those that look most like a card side (4.8 radii apart,
#: equal radii): a tight cluster of similar blobs (gravel) cannot blow up the triples.
EDGE_KEEP = 10
#: The fourth disc is looked up near the parallelogram prediction j + l - i, within this
#: fraction of the shorter apex side (perspective moves it off the parallelogram).
FOURTH_TOLERANCE = 0.35


def _edges(pts: np.ndarray, rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges (a, b), a < b, between radius-compatible candidates at a
    plausible distance (`EDGE_OVER_RADIUS`), at most `EDGE_KEEP` per candidate (kept
    when either end keeps it).

    Sweep along x: two compatible discs are at most ``EDGE_OVER_RADIUS[1] * (ra + rb)
    / 2 <= 1.5 * EDGE_OVER_RADIUS[1] * min(ra, rb)`` apart, so each candidate only
    looks right, within that reach of its own radius; a few thousand pairs per frame,
    cheaper than k nearest-neighbour queries."""
    # the sweep and the distance / radius tests: one compiled loop (`kernels.edge_sweep`)
    a, b, d2, rs2, ra, rb, crowded = kernels.edge_sweep(
        pts, rad, 1.5 * EDGE_OVER_RADIUS[1], RADIUS_RATIO_MAX, EDGE_OVER_RADIUS[0] ** 2, EDGE_OVER_RADIUS[1] ** 2,
        EDGE_KEEP)
    if a.size == 0:
        return a, b
    if crowded.any():
        # An edge goes when both its ends are crowded and neither ranks it among its
        # `EDGE_KEEP` most side-like (4.8 radii apart, equal radii).
        ca, cb = crowded.take(a), crowded.take(b)
        if (ca & cb).any():
            inc = np.flatnonzero(ca | cb)  # every edge of a crowded end
            bad = np.abs(np.log(d2[inc] / (23.04 * rs2[inc]))) * 0.5 + 0.5 * np.abs(np.log(rb[inc] / ra[inc]))
            keep = kernels.edge_ranks_keep(a, b, crowded, inc, bad, EDGE_KEEP)
            a, b = a[keep], b[keep]
    return np.minimum(a, b), np.maximum(a, b)


def group_candidates(candidates: np.ndarray) -> np.ndarray:
    """Proposed disc quadrilaterals: (P, 4) indices into `candidates` (N, 4) rows
    ``[u, v, radius, score]``, each in the layout's orientation (clockwise on screen,
    like discs 0-1-2-3 of a card seen from the front), starting anywhere.

    The paper takes a true target to be two adjacent triangles of the Delaunay
    triangulation of the candidates; our own code cells (and clutter next to a card) are
    candidates too and cut Delaunay edges between discs. Here every pair of candidates
    that could be neighbouring discs of one card is an edge (`_edges`); a card is a
    4-cycle of edges. It is found from its lowest-indexed disc i (the apex): two of its
    edges, to j and l, span a plausible corner of a card (angle, side ratio, area over
    radius), and the fourth disc k is a neighbour of j near the parallelogram
    prediction j + l - i, with k > i, so each cycle is reported once. Proposals pass
    cheap geometric checks (convex, interior angles, side ratio, area over radius).
    Degenerate input (fewer than 4 usable candidates, NaN) gives (0, 4).
    """
    return _group(candidates)[0]


@dataclass(frozen=True, eq=False)
class _Graph:
    """The grouping's candidate graph, kept for card completion: usable candidates
    (rows `idx` of the input), their points and radii, and the edges in CSR form (both
    directions, each row sorted by neighbour; local indices). With the side test
    (`_side_test`): the grey level at each candidate and the plausible card corners at
    every apex, for completion."""

    idx: np.ndarray
    pts: np.ndarray
    rad: np.ndarray
    src: np.ndarray
    dst: np.ndarray
    dark: np.ndarray | None = None  # (N,) grey level at each candidate (`_side_test`)
    #: (3, C) apex triples (i, j, l) of two edges at i that make a plausible card corner
    #: (`_CORNER_LIMITS`; j, l oriented) with similar radii at j and l; in CSR order
    #: (apex, then its edges)
    corners: np.ndarray | None = None
    corner_white: np.ndarray | None = None  # (C,) the darker of the two sides' darkest white points


#: A side of a card (`_side_test`): five points on the white between two discs (halfway,
#: 0.4 and 0.6 of the way, and halfway +-1/16 of the side across it), read on pyramid
#: level 1, against the two disc centres; normalised by the contrast (mean white - mean
#: disc): the darkest white point at least `SIDE_WHITE_MIN` above the lighter disc, the
#: five within `SIDE_WHITE_SPREAD`, the two discs within `SIDE_DISC_SPREAD` of each
#: other, and a contrast of `MIN_CONTRAST_GREY`. True sides on the bench (7000, every
#: condition, the real candidate stage): worst 0.67, 0.39, 0.65; a quarter of the other
#: edges pass.
SIDE_WHITE_MIN = 0.6
SIDE_WHITE_SPREAD = 0.45
SIDE_DISC_SPREAD = 0.7
#: (x, y) -> (-y, x) / 16: the offset across a side (`_side_test`).
_ACROSS = np.array([-1.0 / 16.0, 1.0 / 16.0])


def _side_test(pts: np.ndarray, a: np.ndarray, b: np.ndarray, img: np.ndarray, scale: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which edges (a, b) between candidates `pts` could be a side of a card, looked at
    in `img` (`scale`: its pixels per full-resolution pixel): (bool (E,), the grey level
    at each candidate (N,), the darkest white point of each edge (E,))."""
    pa, pb = pts.take(a, axis=0), pts.take(b, axis=0)
    v = pb - pa
    mp = 0.5 * (pa + pb)
    across = v[:, ::-1] * _ACROSS
    look = np.concatenate([pts, mp, pa + 0.4 * v, pa + 0.6 * v, mp + across, mp - across]) * scale
    # one remap, a two-channel map (cheaper than two strided single-channel ones)
    vals = cv2.remap(img, look.astype(np.float32).reshape(1, -1, 2), None, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).reshape(-1).astype(np.float32)
    n, e = pts.shape[0], a.size
    dark = vals[:n]
    w = vals[n:].reshape(5, e)
    da, db = dark[a], dark[b]
    wmin, wmax = w.min(axis=0), w.max(axis=0)
    con = np.maximum(_mean(w, 0) - 0.5 * (da + db), 1e-3)
    ok = (con >= MIN_CONTRAST_GREY) & (wmin - np.maximum(da, db) >= SIDE_WHITE_MIN * con)
    ok &= (wmax - wmin <= SIDE_WHITE_SPREAD * con) & (np.abs(da - db) <= SIDE_DISC_SPREAD * con)
    return ok, dark, wmin


def _group(candidates: np.ndarray, img: np.ndarray | None = None, scale: float = 1.0
           ) -> tuple[np.ndarray, _Graph | None]:
    """`group_candidates` and the candidate graph it searched (None if too few). With
    `img` (a pyramid level, `scale` its pixels per full-resolution pixel) an edge must
    also look like a card side (`_side_test`), and the graph keeps the card corners at
    every apex for completion (`_corner_triples`)."""
    empty = np.zeros((0, 4), np.intp)
    idx = _clean(candidates)
    n = idx.size
    if n < 3:
        return empty, None
    c = np.asarray(candidates, np.float64).take(idx, axis=0)
    pts, rad = c[:, :2].copy(), c[:, 2].copy()  # contiguous: for ndarray.take
    ea, eb = _edges(pts, rad)
    dark = white = None
    if img is not None and ea.size:
        keep, dark, white = _side_test(pts, ea, eb, img, scale)
        ea, eb, white = ea[keep], eb[keep], white[keep]
    # The search, compiled (`kernels.group_graph`): the adjacency in CSR form (both
    # directions, each row sorted by neighbour index); every apex pair (two edges at
    # i, to j and l) as a card corner (angle, side ratio, area over the apex radius:
    # `_CORNER_LIMITS`), oriented so that j follows i clockwise; with the side test, the
    # corners for completion (any apex, similar radii at j and l too); and for the
    # corners whose apex is the lowest index (i < j, l) every neighbour k > i of j near
    # the parallelogram prediction j + l - i (`FOURTH_TOLERANCE`), the quadrilateral
    # (i, j, k, l) kept if it passes `_QUAD_LIMITS`.
    with_corners = dark is not None
    src, dst, n_pairs, corners, corner_white, quads = kernels.group_graph(
        pts, rad, ea, eb, white if with_corners else _NO_WHITE, with_corners, *_CORNER_LIMITS,
        FOURTH_TOLERANCE**2, *_QUAD_LIMITS)
    if n_pairs == 0:
        return empty, _Graph(idx=idx, pts=pts, rad=rad, src=src, dst=dst, dark=dark)
    graph = _Graph(idx=idx, pts=pts, rad=rad, src=src, dst=dst, dark=dark, corners=corners if with_corners else None,
                   corner_white=corner_white if with_corners else None)
    if n < 4 or ea.size < 2:
        return empty, graph
    return idx.take(quads), graph


#: `kernels.group_graph`'s corner checks: cos^2 of the smallest interior angle, the
#: smallest squared side ratio, the apex parallelogram's area over the apex radius
#: squared (bounds), the largest radius ratio of j and l (completion's corners).
_CORNER_LIMITS = (_COS2_ANGLE, SIDE_RATIO_MIN**2, APEX_AREA_OVER_RADIUS[0] ** 2, APEX_AREA_OVER_RADIUS[1] ** 2,
                  RADIUS_RATIO_MAX)
#: and its quadrilateral checks (with the corner's angle and side ratio): area over the
#: mean radius squared (bounds; sqrt(area) / radius is the same for every affine view of
#: a card).
_QUAD_LIMITS = (SQRT_AREA_OVER_RADIUS[0] ** 2, SQRT_AREA_OVER_RADIUS[1] ** 2)
_NO_WHITE = np.zeros(0, np.float32)


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


@functools.cache
def _rotation_perms(n: int) -> np.ndarray:
    """perm[s] (4, n*n): the cell read at row-major position p, when the quadrilateral's
    vertex m is the card's disc (m + s) % 4, is printed cell perm[s][p].

    Shifting the vertex order by one is the card turned by 90 degrees about its centre:
    layout point (x, y) -> (1 - y, x) takes disc m to disc m + 1.
    """
    step = CODE_SIZE / n
    rc = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2)
    xy = np.stack([CODE_ORIGIN + (rc[:, 1] + 0.5) * step, CODE_ORIGIN + (rc[:, 0] + 0.5) * step], 1)
    perms = []
    for s in range(4):
        p = xy.copy()
        for _ in range(s):
            p = np.stack([1.0 - p[:, 1], p[:, 0]], 1)
        col = np.rint((p[:, 0] - CODE_ORIGIN) / step - 0.5).astype(int)
        row = np.rint((p[:, 1] - CODE_ORIGIN) / step - 0.5).astype(int)
        perms.append(row * n + col)
    return np.array(perms)


@functools.cache
def _templates(family: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T, n*n) float32 templates (black = 0, white = 1, as the normalised image reads),
    and the id and vertex shift of each: every code in every rotation."""
    fam = get_family(family)
    flat = fam.codes.reshape(len(fam), -1)
    perms = _rotation_perms(fam.cells)
    tmpl = np.concatenate([1.0 - flat[:, perms[s]] for s in range(4)]).astype(np.float32)
    ids = np.tile(np.arange(len(fam)), 4)
    shifts = np.repeat(np.arange(4), len(fam))
    return tmpl, ids, shifts


# --------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------


class _Pyramid:
    """Lazily built cv2.pyrDown levels of a uint8 image (level L pixel i is centred on
    full-resolution pixel i * 2**L)."""

    def __init__(self, gray: np.ndarray, levels: int = 4, built: Sequence[np.ndarray] = ()) -> None:
        # `built`: levels already made (the candidate stage's pyramid: the same pyrDown
        # chain of the same frame), reused rather than computed again.
        self.levels: list[np.ndarray] = [gray, *list(built)[1:levels]]
        self.max_level = levels - 1

    def get(self, level: int) -> np.ndarray:
        while len(self.levels) <= level:
            prev = self.levels[-1]
            if min(prev.shape) < 4:
                break
            self.levels.append(cv2.pyrDown(prev))
        return self.levels[min(level, len(self.levels) - 1)]


def _sample(pyr: _Pyramid, hs: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
# Verification measurements
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


def _quick_check(pyr: _Pyramid, hs: np.ndarray) -> np.ndarray:
    """bool (P,): could this be a card at all? 16 samples per proposal."""
    return _quick_from(*_sample(pyr, hs, _QUICK_POINTS))


def _quick_from(vals: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """`_quick_check` of the samples (P, 16) of `_QUICK_POINTS` and their mask."""
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

    def as_dict(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__ if not k.startswith("cell")}


def _mean(x: np.ndarray, axis: int) -> np.ndarray:
    """``x.mean(axis)`` by np.mean's own arithmetic (the sum divided by an intp count)
    without its Python overhead (~5 us a call)."""
    s = x.sum(axis=axis)
    return np.true_divide(s, np.intp(x.shape[axis]), out=s, casting="unsafe")


def _quantile_sorted(v: np.ndarray, q: float) -> np.ndarray:
    """Quantile q of each row of the row-sorted array v (linear interpolation)."""
    pos = q * (v.shape[1] - 1)
    lo = int(np.floor(pos))
    hi = min(lo + 1, v.shape[1] - 1)
    return v[:, lo] + (pos - lo) * (v[:, hi] - v[:, lo])


def _measure(pyr: _Pyramid, hs: np.ndarray, n: int) -> _Measures:
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
# Identification
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CodeMatch:
    """A decoded code: the id, the vertex shift s (quadrilateral vertex m is card disc
    (m + s) % 4), the summed squared error of the best template fit and how much worse
    the best other (code, rotation) fits."""

    id: int
    shift: int
    fit: float
    gap: float


#: Identification by template fit: the cells read (normalised: discs 0, card white 1)
#: are compared with every code of the family in every rotation, each as it would read
#: through an isotropic blur of `CODE_BLUR_CELLS` cell widths (sigma; a far card's 2 px
#: cells, the optics, the pyramid level), white around the code and black discs at the
#: corners. A read is accepted when the best fit's summed squared error is at most
#: `CODE_FIT_MAX` and every other (code, rotation) fits worse by at least `CODE_GAP_MIN`.
#: Set on simulator frames (true geometry, 1400 cards): true fits stay below 0.15 for
#: 99%+ of default/far/dark cards; no wrong id at any gap >= 0.1.
CODE_BLUR_CELLS = (0.0, 0.25, 0.4, 0.55, 0.7)
CODE_FIT_MAX = 0.15
CODE_GAP_MIN = 0.15


@functools.cache
def _blurred_templates(family: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(B * T, n*n) float32 predicted cell reads of every template under every blur of
    `CODE_BLUR_CELLS`, and the id and vertex shift of each row. The read of a cell is
    the mean of its sub-samples (`_plan`), each the blurred card: a 9x9 grid of offsets
    with Gaussian weights, each offset looked up in the card layout."""
    tmpl, ids, shifts = _templates(family)
    n = get_family(family).cells
    plan = _plan(n)
    step = CODE_SIZE / n
    subs = plan.points[plan.cells]  # (n*n, S, 2)
    g = np.linspace(-2.0, 2.0, 9)
    preds = []
    for s in CODE_BLUR_CELLS:
        if s == 0:
            off, w = np.zeros((1, 2)), np.ones(1)
        else:
            x, y = np.meshgrid(g * s * step, g * s * step)
            w = np.exp(-0.5 * (x * x + y * y) / (s * step) ** 2).ravel()
            off, w = np.stack([x.ravel(), y.ravel()], 1), w / w.sum()
        p = subs[:, :, None, :] + off[None, None]  # (n*n, S, K, 2)
        col = np.floor((p[..., 0] - CODE_ORIGIN) / step).astype(int)
        row = np.floor((p[..., 1] - CODE_ORIGIN) / step).astype(int)
        inside = (col >= 0) & (col < n) & (row >= 0) & (row < n)
        cell = np.where(inside, row * n + col, -1)
        disc = np.zeros(cell.shape, bool)
        for c in DISC_CENTRES:
            disc |= ((p - c) ** 2).sum(-1) <= DISC_RADIUS**2
        ww = np.broadcast_to(w, cell.shape) / subs.shape[1]
        a = np.zeros((n * n, n * n))
        for cc in range(n * n):
            a[:, cc] = (ww * ((cell == cc) & ~disc)).sum(axis=(1, 2))
        b = (ww * ((cell < 0) & ~disc)).sum(axis=(1, 2))  # white card around the code
        preds.append(tmpl @ a.T + b)
    nb = len(CODE_BLUR_CELLS)
    return (np.concatenate(preds).astype(np.float32), np.tile(ids, nb), np.tile(shifts, nb))


def _decode(cells: np.ndarray, family: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vectorised `decode_cells`: for cells (P, n*n) normalised (black 0, white 1):
    (ok (P,), id (P,), shift (P,), fit (P,) summed squared error of the best template,
    gap (P,) how much worse the best other (id, rotation) fits)."""
    preds, ids, shifts = _blurred_templates(family)
    tmpl, _, _ = _templates(family)
    n_t = tmpl.shape[0]
    cells = np.asarray(cells, np.float32).reshape(-1, preds.shape[1])
    p = cells.shape[0]
    if p == 0:
        z = np.zeros(0)
        return z.astype(bool), z.astype(int), z.astype(int), z, z
    diff = cells[:, None, :] - preds[None]
    sse = np.einsum("ptk,ptk->pt", diff, diff).reshape(p, -1, n_t).min(axis=1)  # best blur per template
    rows = np.arange(p)
    best = np.argmin(sse, axis=1)
    fit = sse[rows, best]
    sse[rows, best] = np.inf
    gap = sse.min(axis=1) - fit
    ok = np.isfinite(fit) & (fit <= CODE_FIT_MAX) & (gap >= CODE_GAP_MIN)
    return ok, ids[best], shifts[best], fit, gap


#: Motion blur: a card the isotropic templates cannot read is tried again against every
#: code as it reads through a straight smear of `MOTION_LENGTHS_PX` image pixels in each
#: of `MOTION_ANGLES` directions (a line kernel, plus a little isotropic blur), mapped
#: onto the card by the homography's local affine map at the code. A hand-held camera
#: smears a small card's 2-4 px cells by one or two cell widths, in one direction, which
#: the isotropic templates cannot follow (bench: 6 of 8 blur misses were such reads). The
#: acceptance rule is the same (`CODE_FIT_MAX`, `CODE_GAP_MIN`), the gap taken over
#: every blur, so a smear that leaves two codes alike is still refused; or a near-exact
#: fit with a smaller margin (`MOTION_FIT_TIGHT`).
MOTION_LENGTHS_PX = (3.0, 5.0, 7.0, 9.0, 11.0, 13.0)
MOTION_ANGLES = 12
MOTION_STEPS = 9  # samples along the smear
MOTION_ISO_CELLS = 0.0  # isotropic blur (cell widths) added to the smear (0: none)
#: At most this many reads per frame go through the (~2.5 ms each) motion fallback.
MOTION_MAX_READS = 4
#: A smeared read is also accepted when a smeared template fits it almost exactly
#: (summed squared error <= `MOTION_FIT_TIGHT`) and every other (code, rotation) fits
#: worse by `MOTION_GAP_TIGHT`: a smear along a code's rows can leave two codes only
#: ~0.1 apart while the read matches one of them to 0.01. Sweep (77k rendered cards of
#: every id, 36-90 px, random perspective, smears of 2-16 px at any angle, extra blur,
#: exposure 0.3-1, noise; the motion fallback reached by 9.7k): this rule adds 220
#: reads, none wrong; of the 279 wrong best reads none has fit <= 0.05 with a margin
#: above 0.04, or a margin >= 0.05 with fit below 0.06.
MOTION_FIT_TIGHT = 0.02
MOTION_GAP_TIGHT = 0.10


@functools.cache
def _motion_offsets() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit smear kernels in image pixels: (O, K, 2) offsets per pixel of length for
    each (length, angle) option, their weights (K,), and the lengths (O,) and the
    isotropic part (K, 2) in cell widths, so ``offset = length * unit @ Jinv.T + iso``."""
    t = np.linspace(-0.5, 0.5, MOTION_STEPS)
    angles = np.arange(MOTION_ANGLES) * (np.pi / MOTION_ANGLES)
    if MOTION_ISO_CELLS > 0:
        iso = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]], np.float64) * MOTION_ISO_CELLS
        iso_w = np.array([0.4, 0.15, 0.15, 0.15, 0.15])
    else:
        iso, iso_w = np.zeros((1, 2)), np.ones(1)
    lengths = np.repeat(np.asarray(MOTION_LENGTHS_PX, np.float64), angles.size)
    ang = np.tile(angles, len(MOTION_LENGTHS_PX))
    d = np.stack([np.cos(ang), np.sin(ang)], 1) * lengths[:, None]  # (O, 2) image px
    line = t[None, :, None] * d[:, None, :]  # (O, L, 2)
    unit = np.repeat(line, iso.shape[0], axis=1)  # (O, K, 2), K = L * 5
    iso_k = np.tile(iso, (t.size, 1))  # (K, 2)
    w = np.repeat(np.full(t.size, 1.0 / t.size), iso.shape[0]) * np.tile(iso_w, t.size)
    return unit, iso_k, w


def _decode_motion(cells: np.ndarray, hs: np.ndarray, family: str
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`_decode` of cells (R, n*n) against templates smeared by motion blur (see
    `MOTION_LENGTHS_PX`), for the cards of homographies `hs` (R, 3, 3)."""
    tmpl, ids, shifts = _templates(family)
    n = get_family(family).cells
    plan = _plan(n)
    step = CODE_SIZE / n
    subs = plan.points[plan.cells]  # (n*n, S, 2)
    n2, n_s = subs.shape[:2]
    unit, iso, w = _motion_offsets()
    n_o, n_k = unit.shape[:2]
    r = cells.shape[0]
    out = [np.zeros(r, bool), np.zeros(r, np.intp), np.zeros(r, np.intp), np.full(r, np.inf), np.zeros(r)]
    jac = jacobians(hs, np.array([[CODE_ORIGIN + 0.5 * CODE_SIZE] * 2]))[:, 0]  # (R, 2, 2)
    for q in range(r):
        try:
            jinv = np.linalg.inv(jac[q])
        except np.linalg.LinAlgError:
            continue
        off = unit @ jinv.T + iso[None] * step  # (O, K, 2) card units
        p = subs[None, :, :, None, :] + off[:, None, None, :, :]  # (O, n2, S, K, 2)
        col = np.floor((p[..., 0] - CODE_ORIGIN) / step).astype(np.intp)
        row = np.floor((p[..., 1] - CODE_ORIGIN) / step).astype(np.intp)
        inside = (col >= 0) & (col < n) & (row >= 0) & (row < n)
        disc = np.zeros(p.shape[:-1], bool)
        for c in DISC_CENTRES:
            dx, dy = p[..., 0] - c[0], p[..., 1] - c[1]
            disc |= dx * dx + dy * dy <= DISC_RADIUS**2
        # where each sub-sample's kernel point lands: code cell 0..n2-1, white card n2,
        # a disc n2 + 1 (black: contributes 0)
        target = np.where(disc, n2 + 1, np.where(inside, row * n + col, n2))
        o_idx = np.arange(n_o)[:, None, None, None]
        c_idx = np.arange(n2)[None, :, None, None]
        flat = (o_idx * n2 + c_idx) * (n2 + 2) + target
        weights = np.broadcast_to(w / n_s, flat.shape)
        a = np.bincount(flat.ravel(), weights.ravel(), minlength=n_o * n2 * (n2 + 2)).reshape(n_o, n2, n2 + 2)
        a = a.astype(np.float32)
        res = a[..., :n2] @ tmpl.T  # (O, n2, T) predicted reads
        res += (a[..., n2] - cells[q][None, :])[..., None]  # minus the read: residuals
        np.multiply(res, res, out=res)
        sse = res.sum(axis=1).min(axis=0)  # (T,) best smear per template
        best = int(np.argmin(sse))
        fit = sse[best]
        sse[best] = np.inf
        margin = sse.min() - fit
        out[0][q] = ((fit <= CODE_FIT_MAX and margin >= CODE_GAP_MIN)
                     or (fit <= MOTION_FIT_TIGHT and margin >= MOTION_GAP_TIGHT))
        out[1][q], out[2][q], out[3][q], out[4][q] = ids[best], shifts[best], fit, sse.min() - fit
    return tuple(out)  # type: ignore[return-value]


def decode_cells(cells: np.ndarray, family: str = DEFAULT_FAMILY) -> CodeMatch | None:
    """Match code cell values (n, n) or (n*n,), normalised to black 0 / white 1 and read
    row-major through the quadrilateral's homography, against every code of `family`
    in every rotation (each as read through a few amounts of blur). None when the read
    is ambiguous: the best fit's summed squared error above `CODE_FIT_MAX`, or another
    code (or rotation) within `CODE_GAP_MIN` of it."""
    ok, ids, shifts, fit, gap = _decode(np.asarray(cells, np.float32).reshape(1, -1), family)
    if not ok[0]:
        return None
    return CodeMatch(id=int(ids[0]), shift=int(shifts[0]), fit=float(fit[0]), gap=float(gap[0]))


#: `_DESIGN_ORDER[s][j]`: the quadrilateral vertex (j - s) % 4 that is card disc j.
_DESIGN_ORDER = (np.arange(4)[None, :] - np.arange(4)[:, None]) % 4


def _reorder(quad: np.ndarray, shift: int) -> np.ndarray:
    """A quadrilateral's rows (4, ...) in DESIGN order, for vertex shift `shift` (vertex
    m is card disc (m + shift) % 4)."""
    return quad[_DESIGN_ORDER[shift]]


def identify(gray: np.ndarray, discs: np.ndarray, family: str = DEFAULT_FAMILY
             ) -> tuple[int, np.ndarray, CodeMatch] | None:
    """Read and match the code of the card whose disc centres are `discs` (4, 2), in
    the layout's orientation starting at any disc. Returns (id, discs reordered to
    DESIGN order, the match) or None when the code is not read unambiguously."""
    gray = _as_gray(gray)
    q = np.asarray(discs, np.float64).reshape(1, 4, 2)
    if not np.isfinite(q).all():
        return None
    hs = homographies(q)
    m = _measure(_Pyramid(gray), hs, get_family(family).cells)
    match = decode_cells(m.cells[0], family)
    if match is None:
        return None
    return match.id, _reorder(q[0], match.shift), match


# --------------------------------------------------------------------------------------
# Subpixel disc centres
# --------------------------------------------------------------------------------------


def refine_centres(gray: np.ndarray, discs: np.ndarray, iterations: int = REFINE_ITERATIONS,
                   correct_perspective: bool = True, _pyramid: _Pyramid | None = None,
                   _homographies: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Subpixel disc centres of cards: `discs` (T, 4, 2) approximate centres (layout
    orientation, any start) -> (centres (T, 4, 2), radii (T, 4) in pixels).

    Each disc's centre is the centroid of darkness ``max(0, white - I)`` over the pixels
    of an elliptical window: the image of a circle of `REFINE_WINDOW` disc radii around
    the disc on the card (local affine map of the homography of the four current
    centres), with a soft edge, centred on the current centroid. The white level is the
    median of a ring around the disc on the card. Symmetric blur keeps a centroid, and
    a window symmetric about the centroid truncates the blurred tails symmetrically.
    Big discs are measured on a pyramid level (cv2.pyrDown: a symmetric blur, so the
    centroid stays; level pixel i is full-resolution pixel i * 2**L) that keeps the
    window within `REFINE_MAX_HALF` pixels: subsampling full-resolution pixels instead
    would alias the disc edge (~0.1 px errors).

    The area centroid of an imaged disc is the centre of its image ellipse, which under
    perspective is not the projection of the disc's centre; that offset follows exactly
    from the homography (the image conic of the circle) and is subtracted
    (`correct_perspective`). Iterated `iterations` times, each with the homography of
    the previous centres, and up to `REFINE_EXTRA_ITERATIONS` more while centres still
    move (a candidate far off its disc); the ring's white level is kept from the
    previous pass once the centres have settled. Radii: sqrt(dark area / pi), the area being the summed
    darkness over the disc-vs-white contrast. `_homographies`: those of `discs`, if known.
    """
    gray = _as_gray(gray)
    pyr = _pyramid if _pyramid is not None else _Pyramid(gray)
    cur = np.array(discs, np.float64).reshape(-1, 4, 2)
    t = cur.shape[0]
    if t == 0 or not np.isfinite(cur).all():
        return cur, np.zeros((t, 4))
    centroid = cur.copy()  # the image-ellipse centres (what the window is centred on)
    reach = REFINE_WINDOW + REFINE_TAPER
    white = np.full((t, 4), np.nan)  # ring medians, measured again only while centres move
    total = contrast = None  # of the last pass: the radii
    groups: list[tuple[int, np.ndarray | None]] = []
    moved = np.inf
    for it in range(max(1, iterations) + REFINE_EXTRA_ITERATIONS):
        if it >= max(1, iterations) and moved < REFINE_SETTLED:
            break
        hs = _homographies if it == 0 and _homographies is not None else homographies(cur)
        jac = jacobians(hs, DISC_CENTRES)  # (T, 4, 2, 2) image offset per card offset
        det = np.abs(jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0])
        if not (det.min() > 1e-9 and det.max() < np.inf):  # False for NaN too
            break
        if not groups:
            # Half-extent of each window along x and y: reach * R * |row of J|; the level
            # is chosen once.
            ext = reach * DISC_RADIUS * np.sqrt(np.maximum(jac[..., 0, 0] ** 2 + jac[..., 0, 1] ** 2,
                                                           jac[..., 1, 0] ** 2 + jac[..., 1, 1] ** 2)).max(axis=1)
            level = np.minimum(np.ceil(np.log2(np.maximum((ext + 1.0) / REFINE_MAX_HALF, 1.0))),
                               pyr.max_level).astype(int)
            levels = sorted(set(level.tolist()))
            groups = [(lv, None if len(levels) == 1 else np.flatnonzero(level == lv)) for lv in levels]
        # The white ring is measured around the current centroid: again while the centres
        # still move (a candidate far off its disc puts the first ring partly on it).
        fresh = moved > REFINE_WHITE_AGAIN
        if len(groups) == 1:
            lv = groups[0][0]
            scale = 2.0**lv
            c, tot, con, wh = _centroid_step(pyr.get(lv), centroid / scale if lv else centroid,
                                             jac / scale if lv else jac, reach, None if fresh else white)
            new_centroid = c * scale if lv else c
            total = tot * (scale * scale)
            contrast = con
            white = wh
        else:
            new_centroid = centroid.copy()
            total = np.zeros((t, 4))
            contrast = np.ones((t, 4))
            for lv, rows in groups:
                scale = 2.0**lv
                c, tot, con, wh = _centroid_step(pyr.get(lv), centroid[rows] / scale, jac[rows] / scale, reach,
                                                 None if fresh else white[rows])
                new_centroid[rows] = c * scale
                total[rows] = tot * scale * scale
                contrast[rows] = con
                white[rows] = wh
        good = (total > 1e-6)[..., None]
        centroid = np.where(good, new_centroid, centroid)
        new = centroid - perspective_bias(hs) if correct_perspective else centroid
        prev, cur = cur, np.where(good, new, cur)
        moved = float(np.abs(cur - prev).max())
        if moved < REFINE_CONVERGED:
            break
    if total is None:
        return cur, np.zeros((t, 4))
    return cur, np.sqrt(np.maximum(total / np.maximum(contrast, 1e-3), 0.0) / np.pi)


def _windows_u8(img: np.ndarray, x0: np.ndarray, y0: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The `size` x `size` pixel windows of `img` with top-left pixels (x0, y0) (D,):
    (D, size, size) uint8, and where they overhang the image (None if none does) a mask
    of the pixels inside, the others repeating the nearest edge pixel. A window inside
    is a view of the image: one fancy index of a strided view copies them all (cheaper
    than gathering flat pixel indices)."""
    h, w = img.shape
    xs, ys = x0.tolist(), y0.tolist()  # (a few: Python's min and max are cheaper)
    if xs and min(xs) >= 0 and min(ys) >= 0 and max(xs) + size <= w and max(ys) + size <= h:
        s0, s1 = img.strides
        shape, strides = (h - size + 1, w - size + 1, size, size), (s0, s1, s0, s1)
        if img.flags.c_contiguous:  # (np.ndarray on the buffer: as_strided costs ~4 us more)
            view = np.ndarray(shape, np.uint8, img, 0, strides)
        else:
            view = np.lib.stride_tricks.as_strided(img, shape, strides)
        return view[y0, x0], None
    offs = np.arange(size)
    xi = x0[:, None, None] + offs[None, None, :]  # (D, 1, S)
    yi = y0[:, None, None] + offs[None, :, None]  # (D, S, 1)
    valid = ((xi >= 0) & (xi < w)) & ((yi >= 0) & (yi < h))
    return img[np.clip(yi, 0, h - 1), np.clip(xi, 0, w - 1)], valid


def _centroid_step(img: np.ndarray, centroid: np.ndarray, jac: np.ndarray, reach: float,
                   white: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One centroid update of discs at `centroid` (T, 4, 2) in the pixels of `img`, with
    `jac` (T, 4, 2, 2) the image offset per card offset at each disc: (new centroids,
    summed darkness (T, 4), white - black (T, 4), white (T, 4)).

    Each disc's window is the image of a circle of `reach` disc radii around the
    centroid (a soft edge `REFINE_TAPER` wide); its white level the median of the ring
    `REFINE_RING` (measured when `white` is None), its black level the mean inside half
    a radius; the new centroid is that of the darkness ``max(0, white - I)`` in the
    window. One compiled loop over the discs (`kernels.centroid_step`: the float32
    arithmetic and summation order of the numpy code it replaced; sums of ~1000 terms
    stay far below 1e-3 px of centroid error)."""
    t = centroid.shape[0]
    d = t * 4
    new, total, contrast = np.empty((d, 2)), np.empty(d), np.empty(d)
    white_out = np.empty(d) if white is None else np.array(white, np.float64).reshape(d)
    kernels.centroid_step(np.ascontiguousarray(img), np.ascontiguousarray(centroid, np.float64).reshape(d, 2),
                          np.ascontiguousarray(jac, np.float64).reshape(d, 2, 2), float(reach), DISC_RADIUS,
                          _REFINE_RING2, np.float32(0.25), np.float32(1.0 / REFINE_TAPER), white_out, white is None,
                          new, total, contrast)
    return new.reshape(t, 4, 2), total.reshape(t, 4), contrast.reshape(t, 4), white_out.reshape(t, 4)


#: `REFINE_RING` squared, as the float32 bounds on squared distances (in disc radii).
_REFINE_RING2 = np.array([REFINE_RING[0] ** 2, REFINE_RING[1] ** 2], np.float32)


def _masked_median_u8(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Median of each row of the uint8 `values` (D, K) where `mask` is set (NaN if
    none): from the rows' 256-bin histograms (one bincount), cheaper than sorting."""
    d = values.shape[0]
    key = values + np.arange(0, 256 * d, 256, dtype=np.intp)[:, None]  # row r: 256 r + value
    hist = np.bincount(key[mask], minlength=d * 256).reshape(d, 256)
    cum = hist.cumsum(axis=1)
    count = cum[:, -1]
    # sorted position q holds the smallest value v with cum[v] > q
    lo = (cum <= np.maximum((count - 1) // 2, 0)[:, None]).sum(axis=1)
    hi = (cum <= (count // 2)[:, None]).sum(axis=1)
    return np.where(count > 0, 0.5 * (lo.astype(np.float64) + hi), np.nan)




# --------------------------------------------------------------------------------------
# The whole stage
# --------------------------------------------------------------------------------------


def _as_gray(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if a.ndim != 2:
        raise ValueError(f"expected a greyscale image, got shape {a.shape}")
    if a.dtype != np.uint8:
        a = np.clip(np.rint(a), 0, 255).astype(np.uint8)
    return a


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


def _score(m: _Measures, rows: np.ndarray, gap: np.ndarray) -> np.ndarray:
    """Confidence 0..1 from how clearly each check passed (the weakest one)."""
    parts = np.array([
        gap[rows] / (4 * CODE_GAP_MIN) if gap.size else np.ones(rows.size),
        (MAX_DISC_LEVEL + 0.15 - m.disc_level[rows]) / (MAX_DISC_LEVEL + 0.15),
        (m.white_low[rows] - MIN_WHITE_LOW + 0.1) / (1.1 - MIN_WHITE_LOW),
        (m.gap_low[rows] - MIN_GAP_LEVEL + 0.1) / (1.1 - MIN_GAP_LEVEL),
        (MAX_WHITE_SPREAD + 0.1 - m.uniformity[rows]) / (MAX_WHITE_SPREAD + 0.1),
    ])
    return np.clip(parts, 0, 1).min(axis=0) ** 0.5


def assemble_targets(gray: np.ndarray, candidates: np.ndarray, family: str = DEFAULT_FAMILY,
                     timing: dict[str, float] | None = None, counts: dict[str, int] | None = None,
                     pyramid: Sequence[np.ndarray] = ()) -> list[DetectedTarget]:
    """Identified targets in a uint8 greyscale frame from its disc candidates (N, 4)
    ``[u, v, radius, score]`` (full-resolution pixels): group, verify, refine, identify,
    then complete cards of which only three discs have candidates (`_complete`).

    Each id appears at most once (the best-scoring quadrilateral keeps it) and no
    candidate belongs to two targets. Degenerate input gives [].

    `timing`, when given, receives the milliseconds of each sub-stage ("group",
    "verify", "refine", "identify", "complete"); `counts` how many quadrilaterals each
    kept ("proposals", "quick", "verified", "identified"; "completed": targets found by
    completion, included in "identified"). `pyramid`: the ``cv2.pyrDown`` levels of
    `gray` if already made (level 0 first), e.g. by the candidate stage.
    """
    fam = get_family(family)
    gray = _as_gray(gray)
    cand = np.asarray(candidates, np.float64)
    clock = _Clock(timing, counts)
    if cand.ndim != 2 or cand.shape[0] < 3 or cand.shape[1] < 3:
        return clock.done([])
    pyr = _Pyramid(gray, built=pyramid)
    quads, graph = _group(cand, pyr.get(1), 0.5)
    clock.lap("group", proposals=quads.shape[0])
    out: list[DetectedTarget] = []
    used_ids: set[int] = set()
    used_cands: set[int] = set()
    judged: list[set[int]] = []
    motion_left = MOTION_MAX_READS
    if quads.shape[0]:
        res = _judge(gray, pyr, cand[quads, :2], fam.cells, family, motion_left, clock)
        if res is not None:
            keep, ok, m, decoded, ids, shifts, gap, refined, radii, motion_used = res
            motion_left -= motion_used
            judged = [set(q) for q in quads[keep].tolist()]
            out = _select(ok & decoded, m, gap, ids, shifts, quads[keep], refined, radii, used_ids, used_cands)
    n_main = len(out)
    clock.lap("identify", identified=n_main)
    if graph is not None:
        out += _complete(gray, pyr, graph, out, used_ids, used_cands, judged, fam.cells, family, motion_left)
    clock.lap("complete", identified=len(out), completed=len(out) - n_main)
    out.sort(key=lambda t: t.id)
    return clock.done(out)


def _judge(gray: np.ndarray, pyr: _Pyramid, pts: np.ndarray, n: int, family: str, motion_reads: int,
           clock: _Clock | None = None, max_shift: np.ndarray | float = MAX_REFINE_SHIFT) -> tuple | None:
    """Verify, refine and identify disc quadrilaterals `pts` (P, 4, 2) (layout
    orientation): None if none passes the coarse checks, else (rows of `pts` that
    were refined, and for those: ok (sound card), the final measures, decoded, ids,
    shifts, decode gaps, refined centres, radii, motion reads used). `max_shift`: how
    far each disc may move in refinement, in predicted disc radii (scalar or (4,))."""
    hs = homographies(pts)
    # one sampling pass: the quick check's 16 points and the full plan
    plan = _plan(n)
    vals, inside = _sample(pyr, hs, _plan_and_quick(n))
    n_plan = plan.points.shape[0]
    quick = np.flatnonzero(_quick_from(vals[:, n_plan:], inside[:, n_plan:]))
    if quick.size == 0:
        if clock is not None:
            clock.lap("verify", quick=0)
        return None
    m = _measures_from(vals.take(quick, axis=0), inside.take(quick, axis=0)[:, :n_plan], plan, cells=False)
    keep = quick[m.passed(coarse=True)]
    if clock is not None:
        clock.lap("verify", quick=quick.size, verified=keep.size)
    if keep.size == 0:
        return None
    pts = pts.take(keep, axis=0)
    refined, radii = refine_centres(gray, pts, _pyramid=pyr, _homographies=hs.take(keep, axis=0))
    if clock is not None:
        clock.lap("refine")
    hs = homographies(refined)
    m = _measure(pyr, hs, n)
    decoded, ids, shifts, fit, gap = _decode(m.cells, family)
    ok = m.passed() & np.isfinite(refined).all(axis=(1, 2))
    # With the centres refined, every sample inside every disc must be dark (a disc
    # half hidden by another card, or a blob that is no disc, has light ones).
    ok &= m.disc_max <= MAX_DISC_SAMPLE
    # Refinement must stay on its candidate's disc (not be pulled to a neighbour):
    # within 80% of the disc radius the homography predicts (a candidate may sit ~0.6
    # radii off its disc).
    d = refined - pts
    moved = np.hypot(d[..., 0], d[..., 1])
    pred = _predicted_radii(hs)
    ok &= (moved <= np.maximum(2.0, np.asarray(max_shift) * pred)).all(axis=1)
    # Four points fix a homography exactly, so a disc of another card (an overlapping
    # one) or a half-hidden disc still gives a consistent-looking quadrilateral; its dark
    # area, though, disagrees with the size the homography predicts for it. Blur and
    # exposure scale all four alike, so only the spread of the ratios is tested.
    ok &= _radius_spread(pred, radii) <= MAX_RADIUS_SPREAD
    # A sound card whose code the isotropic templates cannot read: motion blur?
    again = np.flatnonzero(ok & ~decoded)[:max(motion_reads, 0)]
    if again.size:
        d2, i2, s2, f2, g2 = _decode_motion(m.cells[again], hs[again], family)
        decoded[again], ids[again], shifts[again], fit[again], gap[again] = d2, i2, s2, f2, g2
    return keep, ok, m, decoded, ids, shifts, gap, refined, radii, int(again.size)


#: Card completion: a card whose fourth disc has no candidate (blur merged it with its
#: surroundings, a highlight, the candidate stage's miss) or a candidate the grouping
#: cannot use (radius off by more than `RADIUS_RATIO_MAX`) is proposed from the other
#: three: every corner (apex i with neighbours j, l; the same corner checks as the
#: grouping) of candidates no found target uses, the fourth disc predicted at
#: j + l - i, and the quadrilateral is judged like any other (quick check, coarse
#: verification, refinement, which pulls the predicted disc onto the dark disc, the
#: strict checks and identification): the predicted disc has to measure as a dark disc
#: of the size the homography predicts. At most `COMPLETE_MAX` corners per frame pass on
#: to verification (those whose quick-check read is clearest first).
COMPLETE_MAX = 8
#: A completed disc may move this far in refinement (predicted disc radii; the
#: parallelogram prediction is off by perspective).
COMPLETE_REFINE_SHIFT = 1.5


#: The predicted fourth disc: at most this far (normalised as above) above the mean of
#: the three discs (the parallelogram prediction may sit off the disc).
CORNER_FOURTH_LEVEL = 0.5


def _corner_triples(g: _Graph, free: np.ndarray, img: np.ndarray, scale: float, full: np.ndarray | None = None,
                    n_cells: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Corners of a possible card among the free candidates (local indices): apex
    triples (i, j, l), j following i clockwise on screen and l preceding it, that pass
    the grouping's corner checks and a cheap look at `img` (a pyramid level, `scale`
    its pixels per full-resolution pixel): both apex sides look like card sides (white
    between two dark discs, `SIDE_WHITE_MIN`) and the predicted fourth disc j + l - i is
    dark (`CORNER_FOURTH_LEVEL`) with white halfway to it from j and from l; then, if
    `full` (the full-resolution image) is given, the card the parallelogram i, j,
    j + l - i, l spans (the layout mapped affinely) is read there: `_corner_look`, then
    the coarse verification (`_Measures.passed`; codes of `n_cells` x `n_cells`).
    Returns i, j, l and the predictions (T, 2)."""
    z = np.zeros(0, np.intp)
    none = z, z, z, np.zeros((0, 2))
    if g.corners is None or g.corner_white is None or g.dark is None:
        return none
    # the grouping's corners (`_Graph.corners`) of free candidates only
    sel = np.flatnonzero(free.take(g.corners).all(axis=0))
    if sel.size == 0:
        return none
    tri = g.corners.take(sel, axis=1)  # (3, T): i, j, l
    i, j, l_ = tri
    pi, pj, pl = g.pts.take(tri, axis=0)  # (T, 2) each
    pred = pj + pl - pi
    dark = g.dark.take(tri)
    black = (dark[0] + dark[1] + dark[2]) * (1.0 / 3.0)
    con = g.corner_white.take(sel) - black
    # the fourth disc, and halfway to it from j and from l (the other two sides)
    q = (np.concatenate([pred, 0.5 * (pj + pred), 0.5 * (pl + pred)]) * scale).astype(np.float32).reshape(1, -1, 2)
    look4 = cv2.remap(img, q, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(3, -1).astype(np.float32)
    ok = look4[0] - black <= CORNER_FOURTH_LEVEL * con
    ok &= np.minimum(look4[1], look4[2]) - black >= SIDE_WHITE_MIN * con
    sel = np.flatnonzero(ok)
    if sel.size == 0:
        return none
    if full is not None:
        # a first look at the card (a parallelogram: the layout maps affinely) on `full`
        pi, pj, pl = pi.take(sel, axis=0), pj.take(sel, axis=0), pl.take(sel, axis=0)
        hf, wf = full.shape
        xy, _ = kernels.affine_points(pi, pj, pl, _corner_look_points(), wf, hf)
        vals = cv2.remap(full, xy, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        look = np.flatnonzero(_corner_look(vals.astype(np.float32)))
        sel = sel.take(look)
        if sel.size:
            # then the coarse verification, on the same affine guess
            pi, pj, pl = pi.take(look, axis=0), pj.take(look, axis=0), pl.take(look, axis=0)
            xy, inside = kernels.affine_points(pi, pj, pl, _plan_affine(n_cells), wf, hf)
            vals = cv2.remap(full, xy, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            coarse = _measures_from(vals.astype(np.float32), inside, _plan(n_cells), cells=False).passed(coarse=True)
            sel = sel.compress(coarse)
    return i.take(sel), j.take(sel), l_.take(sel), pred.take(sel, axis=0)


#: `_corner_look`: looser than the coarse verification (an affine guess of a card).
CORNER_WHITE_SPREAD = 0.5
CORNER_GAP_LEVEL = 0.45


CORNER_WHITE_LOW = 0.35
#: Ring points of `_corner_look` around the three discs that have candidates: 1.45 disc
#: radii out, towards the inside of the card only (the affine guess is off by
#: perspective; outwards the card edge is near).
CORNER_RING = 1.45


@functools.cache
def _plan_affine(n: int) -> np.ndarray:
    """The points of `_plan(n)` as affine coefficients along the sides from disc 0 to
    discs 1 and 3."""
    return (_plan(n).points - DISC_CENTRES[0]) / (DISC_CENTRES[2] - DISC_CENTRES[0])


@functools.cache
def _corner_look_points() -> np.ndarray:
    """(37, 2) affine coefficients (along the sides from disc 0 to discs 1 and 3) of
    the points `_corner_look` reads: the 4 disc centres, 12 between discs, 12 in the
    gap around the code, 9 on rings around discs 0, 1 and 3."""
    plan = _plan(3)
    ring = []
    for k in (0, 1, 3):
        inward = np.sign(0.5 - DISC_CENTRES[k])  # towards the card centre
        for d in ([inward[0], 0.0], [0.0, inward[1]], inward / np.sqrt(2.0)):
            ring.append(DISC_CENTRES[k] + CORNER_RING * DISC_RADIUS * np.asarray(d))
    pts = np.concatenate([DISC_CENTRES, plan.points[plan.between], plan.points[plan.gap], np.array(ring)])
    return (pts - DISC_CENTRES[0]) / (DISC_CENTRES[2] - DISC_CENTRES[0])


def _corner_look(vals: np.ndarray) -> np.ndarray:
    """bool (T,): samples (T, 37) of `_corner_look_points`: dark discs, and white
    between them, around the code and around the discs, uniform (the coarse checks of
    `_Measures`, looser)."""
    disc = vals[:, :4]
    black = _mean(disc, 1)
    w = np.sort(vals[:, 4:28], axis=1)  # 24 between and in the gap
    white = 0.5 * (w[:, 11] + w[:, 12])
    c = white - black
    cn = np.maximum(c, 1e-3)
    ok = (c >= MIN_CONTRAST_GREY) & (disc.max(axis=1) - black <= QUICK_DISC * cn)
    spread = _quantile_sorted(w, 0.9) - _quantile_sorted(w, 0.1)
    ok &= spread <= np.maximum(CORNER_WHITE_SPREAD * cn, NOISE_SPREAD_GREY)
    ok &= np.sort(vals[:, 16:28], axis=1)[:, 1] - black >= CORNER_GAP_LEVEL * cn
    allw = np.sort(vals[:, 4:], axis=1)  # 33
    ok &= _quantile_sorted(allw, 0.1) - black >= CORNER_WHITE_LOW * cn
    return ok


def _complete(gray: np.ndarray, pyr: _Pyramid, g: _Graph, found: list[DetectedTarget], used_ids: set[int],
              used_cands: set[int], judged: list[set[int]], n: int, family: str, motion_reads: int
              ) -> list[DetectedTarget]:
    """Targets completed from three discs (see `COMPLETE_MAX`); `found`: the targets
    found already (no candidate on one of their cards is used), `used_ids`, `used_cands`
    (input rows) of those are honoured and updated;
    `judged`: the candidate sets of the quadrilaterals the main pass refined (a corner of
    one of them is not judged again)."""
    free = np.ones(g.idx.size, bool)
    if found:
        # nothing on a card found already (its discs, its code cells) is free: inside the
        # card outline, approximated by the disc quadrilateral scaled about its centre by
        # 0.5 / 0.3 (a little more)
        q = np.array([t.discs for t in found])  # (F, 4, 2), clockwise on screen
        cen = _mean(q, 1)[:, None]
        c = cen + 1.7 * (q - cen)
        e = c[:, _NEXT] - c  # (F, 4, 2) outline edges
        d = g.pts[None, None, :, :] - c[:, :, None, :]  # (F, 4, N, 2)
        inside = (e[:, :, None, 0] * d[..., 1] - e[:, :, None, 1] * d[..., 0] >= 0).all(axis=1).any(axis=0)
        free &= ~inside
    i, j, l_, pred = _corner_triples(g, free, pyr.get(1), 0.5, gray, n)
    if i.size and judged:
        trip = zip(g.idx[i].tolist(), g.idx[j].tolist(), g.idx[l_].tolist(), strict=True)
        fresh = np.array([not any(a in q and b in q and c in q for q in judged) for a, b, c in trip])
        i, j, l_, pred = i[fresh], j[fresh], l_[fresh], pred[fresh]
    if i.size == 0:
        return []
    if i.size > COMPLETE_MAX:
        i, j, l_, pred = i[:COMPLETE_MAX], j[:COMPLETE_MAX], l_[:COMPLETE_MAX], pred[:COMPLETE_MAX]
    p = g.pts
    pts = np.stack([p[i], p[j], pred, p[l_]], axis=1)  # (T, 4, 2) layout orientation: a parallelogram
    # the predicted disc may move further in refinement than a candidate
    shift = np.array([MAX_REFINE_SHIFT, MAX_REFINE_SHIFT, COMPLETE_REFINE_SHIFT, MAX_REFINE_SHIFT])
    res = _judge(gray, pyr, pts, n, family, motion_reads, max_shift=shift)
    if res is None:
        return []
    keep, ok, m, decoded, ids, shifts, gap, refined, radii, _ = res
    members = np.stack([g.idx[i[keep]], g.idx[j[keep]], -1 - np.arange(keep.size), g.idx[l_[keep]]], axis=1)
    return _select(ok & decoded, m, gap, ids, shifts, members, refined, radii, used_ids, used_cands)


class _Clock:
    """Sub-stage wall times (ms) and survivor counts of `assemble_targets`."""

    STAGES = ("group", "verify", "refine", "identify", "complete")
    COUNTS = ("proposals", "quick", "verified", "identified", "completed")

    def __init__(self, timing: dict[str, float] | None, counts: dict[str, int] | None) -> None:
        self.timing, self.counts = timing, counts
        if timing is not None:
            for k in self.STAGES:
                timing[k] = 0.0
        if counts is not None:
            for k in self.COUNTS:
                counts[k] = 0
        self.last = time.perf_counter()

    def lap(self, stage: str, **counts: int) -> None:
        now = time.perf_counter()
        if self.timing is not None:
            self.timing[stage] = (now - self.last) * 1e3
        if self.counts is not None:
            self.counts.update({k: int(v) for k, v in counts.items()})
        self.last = now

    def done(self, out: list[DetectedTarget]) -> list[DetectedTarget]:
        return out


def _select(ok: np.ndarray, m: _Measures, gap: np.ndarray, ids: np.ndarray, shifts: np.ndarray, quads: np.ndarray,
            refined: np.ndarray, radii: np.ndarray, used_ids: set[int], used_cands: set[int]) -> list[DetectedTarget]:
    """The accepted quadrilaterals, best score first, each id and candidate used once
    (`used_ids`, `used_cands`: taken already; updated)."""
    rows = np.flatnonzero(ok)
    if rows.size == 0:
        return []
    score = _score(m, rows, gap)
    order = rows[np.argsort(-score, kind="stable")]
    score_of = dict(zip(rows.tolist(), score.tolist(), strict=True))
    out: list[DetectedTarget] = []
    for r in order.tolist():
        tid = int(ids[r])
        members = set(quads[r].tolist())
        if tid in used_ids or members & used_cands:
            continue
        used_ids.add(tid)
        used_cands |= members
        order = _DESIGN_ORDER[shifts[r]]
        out.append(DetectedTarget(id=tid, discs=refined[r][order], score=float(score_of[r]),
                                  disc_radii=radii[r][order]))
    return out


# --------------------------------------------------------------------------------------
# Simulated candidates (tests and benchmarks)
# --------------------------------------------------------------------------------------


def simulate_candidates(
    gray: np.ndarray,
    targets: Sequence[Any],
    rng: np.random.Generator,
    family: str = DEFAULT_FAMILY,
    n_random: int = 30,
    n_texture: int = 30,
    code_cells: bool = True,
    card_corners: bool = True,
    jitter_px: float = 1.0,
    radius_factor: tuple[float, float] = (0.7, 1.4),
) -> np.ndarray:
    """Candidates (N, 4) float32 as the candidate stage might report them, from ground
    truth (objects with ``id``, ``discs_px`` (4, 2), ``disc_visible`` (4,) and
    ``disc_diameter_px``, e.g. `scenes.TargetTruth`): every visible disc within
    ±`jitter_px` and its radius off by a random factor, plus false candidates: the
    black code cells of every card (its own homography), card corners, random points
    and dark texture spots of `gray`."""
    rows: list[list[float]] = []
    fam = get_family(family)
    n = fam.cells
    step = CODE_SIZE / n
    for t in targets:
        discs = np.asarray(t.discs_px, np.float64)
        vis = np.asarray(t.disc_visible, bool)
        r = 0.5 * float(t.disc_diameter_px)
        for k in range(4):
            if vis[k] and np.isfinite(discs[k]).all():
                u, v = discs[k] + rng.uniform(-jitter_px, jitter_px, 2)
                rows.append([u, v, r * rng.uniform(*radius_factor), rng.uniform(0.5, 1.0)])
        if not np.isfinite(discs).all():
            continue
        hs = homographies(discs[None])
        extra = []
        if code_cells and 0 <= int(t.id) < len(fam):
            code = fam.code(int(t.id))
            rr, cc = np.nonzero(code)
            extra.append(np.stack([CODE_ORIGIN + (cc + 0.5) * step, CODE_ORIGIN + (rr + 0.5) * step], 1))
        if card_corners:
            extra.append(np.array([[0.03, 0.03], [0.97, 0.03], [0.97, 0.97], [0.03, 0.97]]))
        if extra:
            p = apply_homographies(hs, np.concatenate(extra))[0]
            for u, v in p:
                rows.append([u, v, r * 0.45 * rng.uniform(*radius_factor), rng.uniform(0.0, 0.8)])
    h, w = gray.shape[:2]
    for _ in range(n_random):
        rows.append([rng.uniform(0, w - 1), rng.uniform(0, h - 1), float(np.exp(rng.uniform(np.log(2), np.log(25)))),
                     rng.uniform(0.0, 0.8)])
    if n_texture:
        g = cv2.GaussianBlur(np.asarray(gray, np.float32), (0, 0), 2.0)
        mins = (g <= cv2.erode(g, np.ones((5, 5), np.uint8))) & (g < cv2.blur(g, (15, 15)) - 3)
        ys, xs = np.nonzero(mins)
        if ys.size:
            pick = rng.choice(ys.size, size=min(n_texture, ys.size), replace=False)
            for y, x in zip(ys[pick], xs[pick], strict=True):
                rows.append([x + rng.uniform(-0.5, 0.5), y + rng.uniform(-0.5, 0.5),
                             rng.uniform(2.0, 12.0), rng.uniform(0.0, 0.8)])
    out = np.array(rows, np.float32).reshape(-1, 4)
    return out[rng.permutation(out.shape[0])]
