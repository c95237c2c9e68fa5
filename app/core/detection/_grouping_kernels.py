"""Compiled kernels of the grouping (`grouping`): the sweep that finds the candidate
graph's edges, the pruning of crowded candidates' edges, and the search of the graph for
card corners and disc quadrilaterals. Flags and conventions: `_numba`; the vectorised
numpy references are in the grouping tests."""

from __future__ import annotations

import numpy as np
from numba import njit

from app.core.detection._numba import JIT


@njit(**JIT)
def edge_sweep(pts: np.ndarray, rad: np.ndarray, reach: float, ratio_max: float, d2_lo: float, d2_hi: float,
               keep: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                   np.ndarray]:
    """Candidate edges of `grouping._edges`: a sweep along x (stable sort) over points
    `pts` (N, 2) with radii `rad` (N,) float64, each point looking right within
    ``reach * radius``; a pair (a, b) is an edge when ``rb <= ratio_max * ra``,
    ``ra <= ratio_max * rb`` and its squared distance d2 lies in ``[d2_lo, d2_hi]``
    times the squared mean radius rs2. Returns the edges' ends a, b (input indices, a
    the one earlier in x order) in sweep order, their d2, rs2, ra, rb, and which points
    have more than `keep` edges (crowded), every value as the vectorised sweep computed
    it (one loop instead of ~25 numpy calls on a few thousand pairs)."""
    n = pts.shape[0]
    x = pts[:, 0].copy()
    order = np.argsort(x, kind="mergesort")  # stable
    xs, ys, rs = x[order], pts[:, 1].copy()[order], rad[order]
    cap = 0
    for s in range(n):
        limit = xs[s] + reach * rs[s]
        t = s + 1
        while t < n and xs[t] <= limit:  # as searchsorted(xs, limit, "right") bounds it
            t += 1
        cap += t - s - 1
    a, b = np.empty(cap, np.intp), np.empty(cap, np.intp)
    d2s, rs2s = np.empty(cap), np.empty(cap)
    ras, rbs = np.empty(cap), np.empty(cap)
    deg = np.zeros(n, np.intp)
    m = 0
    for s in range(n):
        limit = xs[s] + reach * rs[s]
        ra = rs[s]
        t = s + 1
        while t < n and xs[t] <= limit:
            rb = rs[t]
            dx, dy = xs[t] - xs[s], ys[t] - ys[s]
            d2 = dx * dx + dy * dy
            rs2 = (ra + rb) * 0.5
            rs2 *= rs2
            ok = (rb <= ratio_max * ra) & (ra <= ratio_max * rb) & (d2 >= d2_lo * rs2) & (d2 <= d2_hi * rs2)
            # written whatever ok is, kept by counting it (no unpredictable branch)
            a[m], b[m] = order[s], order[t]
            d2s[m], rs2s[m], ras[m], rbs[m] = d2, rs2, ra, rb
            deg[order[s]] += ok
            deg[order[t]] += ok
            m += ok
            t += 1
    return a[:m], b[:m], d2s[:m], rs2s[:m], ras[:m], rbs[:m], deg > keep


@njit(**JIT)
def edge_ranks_keep(a: np.ndarray, b: np.ndarray, crowded: np.ndarray, inc: np.ndarray, bad: np.ndarray,
                    keep: int) -> np.ndarray:
    """bool (E,): which edges (a, b) `grouping._edges` keeps among crowded points. Each
    end ranks the edges `inc` (every edge with a crowded end) it belongs to by `bad`
    (ties: a-ends' entries before b-ends', then by position), as
    ``np.lexsort((concat(bad, bad), concat(a[inc], b[inc])))`` orders them: a stable
    sort by `bad`, then a stable counting sort by end. An edge goes when both its ends
    are crowded and neither ranks it below `keep`."""
    m = inc.shape[0]
    n = crowded.shape[0]
    ends = np.empty(2 * m, np.intp)
    bad2 = np.empty(2 * m)
    for q in range(m):
        ends[q], ends[m + q] = a[inc[q]], b[inc[q]]
        bad2[q], bad2[m + q] = bad[q], bad[q]
    by_bad = np.argsort(bad2, kind="mergesort")  # stable
    start = np.zeros(n + 1, np.intp)
    for q in range(2 * m):
        start[ends[q] + 1] += 1
    for e in range(n):
        start[e + 1] += start[e]
    fill = start[:-1].copy()
    rank = np.empty(2 * m, np.intp)
    for q in by_bad:
        e = ends[q]
        rank[q] = fill[e] - start[e]
        fill[e] += 1
    out = np.ones(a.shape[0], np.bool_)
    for q in range(m):
        e = inc[q]
        if rank[q] >= keep and rank[m + q] >= keep and crowded[a[e]] and crowded[b[e]]:
            out[e] = False
    return out


@njit(**JIT, inline="always")
def _quad_ok(px: np.ndarray, py: np.ndarray, rad: np.ndarray, v: np.ndarray, area_lo: float, area_hi: float,
             ratio_max: float, side2: float, cos2: float) -> bool:
    """The grouping's cheap geometry checks of the quadrilateral with vertices v (4,)
    (layout orientation): area over the mean radius squared in [area_lo, area_hi],
    radius ratio, side ratio (squared), convex and every interior angle in range
    (cos^2 below cos2); each sum over the four vertices in the vectorised code's
    order (the grouping tests: `_reference_quad_geometry_ok`)."""
    x0, x1, x2, x3 = px[v[0]], px[v[1]], px[v[2]], px[v[3]]
    y0, y1, y2, y3 = py[v[0]], py[v[1]], py[v[2]], py[v[3]]
    r0, r1, r2, r3 = rad[v[0]], rad[v[1]], rad[v[2]], rad[v[3]]
    area = 0.5 * ((((x0 * y1 - x1 * y0) + (x1 * y2 - x2 * y1)) + (x2 * y3 - x3 * y2)) + (x3 * y0 - x0 * y3))
    rm = 0.25 * (((r0 + r1) + r2) + r3)
    if not (area >= area_lo * rm * rm and area <= area_hi * rm * rm):
        return False
    if not max(max(r0, r1), max(r2, r3)) <= ratio_max * min(min(r0, r1), min(r2, r3)):
        return False
    ex0, ex1, ex2, ex3 = x1 - x0, x2 - x1, x3 - x2, x0 - x3
    ey0, ey1, ey2, ey3 = y1 - y0, y2 - y1, y3 - y2, y0 - y3
    s0, s1, s2, s3 = ex0 * ex0 + ey0 * ey0, ex1 * ex1 + ey1 * ey1, ex2 * ex2 + ey2 * ey2, ex3 * ex3 + ey3 * ey3
    if not min(min(s0, s1), min(s2, s3)) >= side2 * max(max(s0, s1), max(s2, s3)):
        return False
    for exa, eya, sa, exb, eyb, sb in ((ex0, ey0, s0, ex1, ey1, s1), (ex1, ey1, s1, ex2, ey2, s2),
                                       (ex2, ey2, s2, ex3, ey3, s3), (ex3, ey3, s3, ex0, ey0, s0)):
        cross = exa * eyb - eya * exb
        dot = exa * exb + eya * eyb
        if not (cross > 0 and dot * dot < cos2 * sa * sb):
            return False
    return True


@njit(**JIT)
def group_graph(pts: np.ndarray, rad: np.ndarray, ea: np.ndarray, eb: np.ndarray, white: np.ndarray,
                with_corners: bool, cos2: float, side2: float, apex_lo: float, apex_hi: float, ratio_max: float,
                fourth2: float, area_lo: float, area_hi: float
                ) -> tuple[np.ndarray, np.ndarray, int, np.ndarray, np.ndarray, np.ndarray]:
    """The search of `grouping._group` on the graph of edges (ea, eb) between points
    `pts` (N, 2) with radii `rad` (N,): the adjacency in CSR form (src, dst: both
    directions, sorted by (src, dst)); the number of apex pairs (two entries of one
    row); with `with_corners`, the plausible card corners (3, C) over every apex pair
    (j, l oriented so that j follows i clockwise; interior angle within `cos2`, squared
    side ratio `side2`, apex parallelogram area over the apex radius squared in
    [apex_lo, apex_hi]; then radii of j and l within `ratio_max`) and the darker of
    their two sides' `white` (per edge, float32); and the proposed quadrilaterals (Q, 4) (i, j, k, l):
    corners with i < j, l, the fourth disc k > i (k != l) a neighbour of j near
    j + l - i (within ``fourth2`` times the shorter side squared), passing the cheap
    geometry (`_quad_ok`). Every comparison and float operation is the vectorised
    code's, in its order; the outputs are listed in its order (apex pair by apex
    pair, then j's neighbours). Compiled: the vectorised version spends ~50 numpy
    calls (repeat / cumsum index bookkeeping) on a few thousand pairs."""
    n, e = pts.shape[0], ea.shape[0]
    src = np.concatenate((ea, eb))
    dst = np.concatenate((eb, ea))
    key = np.argsort(src * n + dst)  # unique keys: the order is unambiguous
    src, dst = src[key], dst[key]
    row_start = np.zeros(n + 1, np.intp)
    for p in range(2 * e):
        row_start[src[p] + 1] += 1
    for i in range(n):
        row_start[i + 1] += row_start[i]
    n_pairs = 0
    for i in range(n):
        deg = row_start[i + 1] - row_start[i]
        n_pairs += deg * (deg - 1) // 2
    px, py = pts[:, 0], pts[:, 1]
    corners = np.empty((3, n_pairs if with_corners else 0), np.intp)
    corner_white = np.empty(n_pairs if with_corners else 0, np.float32)
    apex = np.empty((4, n_pairs), np.intp)  # i, j, l and the first entry of the pair: for the quadrilaterals
    apex_short2 = np.empty(n_pairs)
    n_corners = n_apex = 0
    for first in range(2 * e):
        i, j0 = src[first], dst[first]
        xi, yi, r2 = px[i], py[i], rad[i] * rad[i]
        ax, ay = px[j0] - xi, py[j0] - yi
        for second in range(first + 1, row_start[i + 1]):
            l0 = dst[second]
            bx, by = px[l0] - xi, py[l0] - yi
            cross = ax * by - ay * bx
            j, l_ = (l0, j0) if cross < 0 else (j0, l0)
            cross = abs(cross)
            dot = ax * bx + ay * by
            l1, l2 = ax * ax + ay * ay, bx * bx + by * by
            short2 = min(l1, l2)
            ok = (dot * dot < cos2 * l1 * l2) and (short2 >= side2 * max(l1, l2))
            ok = ok and (cross >= apex_lo * r2) and (cross <= apex_hi * r2)
            if not ok:
                continue
            if with_corners and rad[j] <= ratio_max * rad[l_] and rad[l_] <= ratio_max * rad[j]:
                corners[0, n_corners], corners[1, n_corners], corners[2, n_corners] = i, j, l_
                corner_white[n_corners] = min(white[key[first] % e], white[key[second] % e])
                n_corners += 1
            if j0 > i:  # the grouping's apex is the lowest index of its card
                apex[0, n_apex], apex[1, n_apex], apex[2, n_apex] = i, j, l_
                apex_short2[n_apex] = short2
                n_apex += 1
    n_quads = 0
    for t in range(n_apex):
        j = apex[1, t]
        n_quads += row_start[j + 1] - row_start[j]
    quads = np.empty((n_quads, 4), np.intp)
    v = np.empty(4, np.intp)
    n_quads = 0
    for t in range(n_apex):
        i, j, l_ = apex[0, t], apex[1, t], apex[2, t]
        predx, predy = px[j] + px[l_] - px[i], py[j] + py[l_] - py[i]
        limit = fourth2 * apex_short2[t]
        for p in range(row_start[j], row_start[j + 1]):
            k = dst[p]
            ex, ey = px[k] - predx, py[k] - predy
            if ex * ex + ey * ey <= limit and k > i and k != l_:
                v[0], v[1], v[2], v[3] = i, j, k, l_
                if _quad_ok(px, py, rad, v, area_lo, area_hi, ratio_max, side2, cos2):
                    quads[n_quads] = v
                    n_quads += 1
    return src, dst, n_pairs, corners[:, :n_corners], corner_white[:n_corners], quads[:n_quads]


def warm_up() -> None:
    """Compile (or load from the cache) every kernel of the grouping on tiny inputs,
    with the argument types the grouping passes (with and without the side test's
    white levels)."""
    pts = np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 5.0], [0.0, 5.0]])
    rad = np.ones(4)
    a, b, d2, _, _, _, crowded = edge_sweep(pts, rad, 15.0, 2.0, 4.84, 100.0, 1)
    inc = np.flatnonzero(crowded.take(a) | crowded.take(b))
    edge_ranks_keep(a, b, crowded, inc, d2.take(inc), 1)
    ea, eb = np.minimum(a, b), np.maximum(a, b)
    for white in (np.ones(ea.size, np.float32), np.zeros(0, np.float32)):
        group_graph(pts, rad, ea, eb, white, white.size > 0, 0.86, 0.05, 4.84, 81.0, 2.0, 0.12, 10.89, 49.0)
