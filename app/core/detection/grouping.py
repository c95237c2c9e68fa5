"""Grouping: disc candidates into proposed disc quadrilaterals, one per possible card.

The paper takes a true target to be two adjacent triangles of the Delaunay
triangulation of the candidates. Our own code cells (and clutter next to a card) are
candidates too and cut Delaunay edges between discs, so a graph is searched instead:
an edge joins two candidates that could be neighbouring discs of one card (similar
radii, a distance consistent with them; found by a sweep along x, `_edges`), and it
must look like a card side in the image (`_side_test`: white between two dark
candidates, five points on pyramid level 1), which removes three quarters of the edges
among texture. A card is a 4-cycle of edges, found once, from its lowest-indexed disc:
two of its edges are the adjacent discs and the fourth disc is a neighbour of one of
them near the parallelogram prediction. Cheap geometry (convex, interior angles, side
ratio, area over radius) prunes the proposals. The graph and its card corners are
kept (`_Graph`) for completing cards of which only three discs have candidates
(`completion`). The sweep and the search are compiled (`_grouping_kernels`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from app.core.detection import _grouping_kernels as kernels
from app.core.detection.verification import MIN_CONTRAST_GREY, _mean

__all__ = [
    "ANGLE_RANGE_DEG",
    "APEX_AREA_OVER_RADIUS",
    "EDGE_KEEP",
    "EDGE_OVER_RADIUS",
    "FOURTH_TOLERANCE",
    "RADIUS_RATIO_MAX",
    "SIDE_DISC_SPREAD",
    "SIDE_RATIO_MIN",
    "SIDE_WHITE_MIN",
    "SIDE_WHITE_SPREAD",
    "SQRT_AREA_OVER_RADIUS",
    "group_candidates",
]


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

#: Every pair of candidates that could be neighbouring discs of one card
#: (similar radius, distance consistent with the radii) is an edge; each candidate keeps
#: at most `EDGE_KEEP` edges, those that look most like a card side (4.8 radii apart,
#: equal radii): a tight cluster of similar blobs (gravel) cannot blow up the triples.
EDGE_KEEP = 10
#: The fourth disc is looked up near the parallelogram prediction j + l - i, within this
#: fraction of the shorter apex side (perspective moves it off the parallelogram).
FOURTH_TOLERANCE = 0.35

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

#: cos^2 of the smallest interior angle (`ANGLE_RANGE_DEG`; the largest is its supplement).
_COS2_ANGLE = float(np.cos(np.deg2rad(ANGLE_RANGE_DEG[0])) ** 2)
#: Vertex k + 1 of a quadrilateral.
_NEXT = np.array([1, 2, 3, 0])
#: (x, y) -> (-y, x) / 16: the offset across a side (`_side_test`).
_ACROSS = np.array([-1.0 / 16.0, 1.0 / 16.0])
#: `kernels.group_graph`'s corner checks: cos^2 of the smallest interior angle, the
#: smallest squared side ratio, the apex parallelogram's area over the apex radius
#: squared (bounds), the largest radius ratio of j and l (completion's corners).
_CORNER_LIMITS = (_COS2_ANGLE, SIDE_RATIO_MIN**2, APEX_AREA_OVER_RADIUS[0] ** 2, APEX_AREA_OVER_RADIUS[1] ** 2,
                  RADIUS_RATIO_MAX)
#: and its quadrilateral checks (with the corner's angle and side ratio): area over the
#: mean radius squared (bounds; sqrt(area) / radius is the same for every affine view of
#: a card).
_QUAD_LIMITS = (SQRT_AREA_OVER_RADIUS[0] ** 2, SQRT_AREA_OVER_RADIUS[1] ** 2)
#: No white levels: the search without the side test.
_NO_WHITE = np.zeros(0, np.float32)


def group_candidates(candidates: np.ndarray) -> np.ndarray:
    """Proposed disc quadrilaterals from disc candidates, by geometry alone.

    Every pair of candidates that could be neighbouring discs of one card is an edge
    (`_edges`); a card is a 4-cycle of edges, found from its lowest-indexed disc i (the
    apex): two of its edges, to j and l, span a plausible corner of a card (angle, side
    ratio, area over radius), and the fourth disc k is a neighbour of j near the
    parallelogram prediction j + l - i, with k > i, so each cycle is reported once.
    Proposals pass cheap geometric checks (convex, interior angles, side ratio, area
    over radius). `assemble_targets` groups with the side test on the image as well.

    Parameters
    ----------
    candidates : ndarray, shape (N, 4) or (N, 3)
        Disc candidates ``[u, v, radius, score]`` in full-resolution pixels. Of
        candidates in one half-pixel cell one is used: the best scored (the first
        without a score column).

    Returns
    -------
    ndarray of intp, shape (P, 4)
        Rows of `candidates`, four per proposal, in the layout's orientation
        (clockwise on screen, like discs 0-1-2-3 of a card seen from the front),
        starting at any disc. Degenerate input (fewer than 4 usable candidates, NaN)
        gives shape (0, 4).
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


def _group(candidates: np.ndarray, img: np.ndarray | None = None, scale: float = 1.0
           ) -> tuple[np.ndarray, _Graph | None]:
    """`group_candidates` and the candidate graph it searched (None if too few). With
    `img` (a pyramid level, `scale` its pixels per full-resolution pixel) an edge must
    also look like a card side (`_side_test`), and the graph keeps the card corners at
    every apex for completion (`completion._corner_triples`)."""
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
