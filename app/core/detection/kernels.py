"""Compiled (numba) kernels of the detector's hot loops.

Each kernel replaces a chain of small numpy/OpenCV calls by one fused loop with the
same meaning and the same arithmetic: results are bit-identical to the code they
replace (tests/test_kernels.py holds the numpy/OpenCV references).

Why: at 640x480 the detector runs ~40 whole-image OpenCV calls for stage 1a and a few
hundred numpy calls on small arrays for the targets; each pass over an image-sized
int32/float32 buffer, and each ~1 us of numpy call overhead, costs more than the
arithmetic. A fused loop touches each pixel once.

Compilation: ``cache=True`` keeps the machine code in ``__pycache__`` (or
``NUMBA_CACHE_DIR``); a fresh process still loads it, and with a cold cache compiles
it (seconds). `warm_up` does either on tiny inputs: call it once at service start-up,
before the first frame.

Conventions: ``error_model="numpy"`` (a float division by zero gives inf/NaN instead of
raising; without it numba adds a branch that stops the loops from vectorising), no
``fastmath`` (it would reorder float arithmetic and change results), ``nogil`` (frames
of several cameras run on threads).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from app.core.geometry import _kernels as geometry_kernels

_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


# --------------------------------------------------------------------------------------
# Stage 1a (app.core.detection.candidates)
# --------------------------------------------------------------------------------------


@njit(**_JIT, inline="always")
def _blob_row(integral: np.ndarray, dil: np.ndarray, ero: np.ndarray, eps: np.float32, y: int,
              out: np.ndarray) -> None:
    """Row y of `blob_ratio` into `out` (ow,)."""
    c16 = np.float32(1.0 / 16.0)
    c144 = np.float32(-1.0 / 144.0)
    r0, r4, r8, r12 = integral[y], integral[y + 4], integral[y + 8], integral[y + 12]
    dr, er = dil[y + 6, 6:], ero[y + 6, 6:]
    for x in range(out.shape[0]):
        sum12 = (r12[x + 12] - r0[x + 12]) - (r12[x] - r0[x])
        sum4 = (r8[x + 8] - r4[x + 8]) - (r8[x + 4] - r4[x + 4])
        num = np.float32(sum4) * c16 + np.float32(sum12) * c144
        out[x] = num / ((np.float32(dr[x]) - np.float32(er[x])) + eps)


@njit(**_JIT)
def blob_ratio(integral: np.ndarray, dil: np.ndarray, ero: np.ndarray, eps: np.float32, out: np.ndarray) -> None:
    """Stage-1a score of every window from the integral image of the top-hat and the
    12x12 max (`dil`) and min (`ero`) of the padded level, written into `out` (oh, ow)
    float32: window (y, x) (top-left in the padded level) scores

        (centre 4x4 sum / 16 - window 12x12 sum / 144) / (max - min + eps),

    the window sums exact in int32 and the rest in float32, operation for operation as
    ``cv2.addWeighted(sum4, 1/16, sum12, -1/144)``, ``cv2.add`` and ``cv2.divide``
    compute it (one pass instead of eight image-sized int32/float32 ones)."""
    for y in range(out.shape[0]):
        _blob_row(integral, dil, ero, eps, y, out[y])


@njit(**_JIT, inline="always")
def _max3_row(s: np.ndarray, out: np.ndarray) -> None:
    """out[x] = max(s[x - 1], s[x], s[x + 1]), clipped to the row."""
    w = s.shape[0]
    if w == 1:
        out[0] = s[0]
        return
    out[0] = max(s[0], s[1])
    for x in range(1, w - 1):
        out[x] = max(max(s[x - 1], s[x]), s[x + 1])
    out[w - 1] = max(s[w - 2], s[w - 1])


@njit(**_JIT, inline="always")
def _maxima_row(s: np.ndarray, above: np.ndarray, here: np.ndarray, below: np.ndarray, threshold: np.float32,
                y: int, row_mask: np.ndarray, ys: np.ndarray, xs: np.ndarray, n: int) -> int:
    """Append the local maxima of score row `s` (y) to ``ys, xs`` from position n, given
    the 3-wide maxima of the rows above, here and below; returns the new count. The
    mask is built with vectorised comparisons, then scanned 8 bytes at a time (maxima
    are sparse: ~1000 of 400k windows)."""
    for x in range(s.shape[0]):
        row_mask[x] = s[x] >= max(max(max(above[x], here[x]), below[x]), threshold)
    words = row_mask.view(np.uint64)
    for k in range(words.shape[0]):
        if words[k] != 0:
            for x in range(8 * k, 8 * k + 8):
                if row_mask[x]:
                    ys[n] = y
                    xs[n] = x
                    n += 1
    return n


@njit(**_JIT, inline="always")
def _maxima_pass(score: np.ndarray, y: int, threshold: np.float32, max3: np.ndarray, row_mask: np.ndarray,
                 ys: np.ndarray, xs: np.ndarray, n: int) -> int:
    """Step y (0..oh) of a rolling 3x3 maxima scan: the 3-wide maxima of row y (rows
    are ready up to y), then the maxima of row y - 1, whose neighbours are known."""
    oh = score.shape[0]
    if y < oh:
        _max3_row(score[y], max3[y % 3])
    if y >= 1:
        r = y - 1
        here = max3[r % 3]
        above = max3[(r - 1) % 3] if r >= 1 else here  # the image edge: no row beyond
        below = max3[y % 3] if y < oh else here
        n = _maxima_row(score[r], above, here, below, threshold, r, row_mask, ys, xs, n)
    return n


@njit(**_JIT)
def local_maxima(score: np.ndarray, threshold: np.float32, max3: np.ndarray, row_mask: np.ndarray,
                 ys: np.ndarray, xs: np.ndarray) -> int:
    """3x3 local maxima of `score` (oh, ow) at or above `threshold`, in row-major order:
    their count n, rows and columns in ``ys[:n]``, ``xs[:n]`` (capacity oh * ow).

    A local maximum is ``score >= max(dilate3x3(score), threshold)`` with pixels
    outside the image ignored (as cv2.dilate does; the scores are finite), as
    np.nonzero would list them. Scratch: `max3` (3, ow) float32, the 3-wide maxima of
    three consecutive rows (rolling); `row_mask` uint8, at least ow entries and a
    multiple of 8."""
    row_mask[score.shape[1]:] = 0
    n = 0
    for y in range(score.shape[0] + 1):
        n = _maxima_pass(score, y, threshold, max3, row_mask, ys, xs, n)
    return n


@njit(**_JIT)
def blob_maxima(integral: np.ndarray, dil: np.ndarray, ero: np.ndarray, eps: np.float32, threshold: np.float32,
                rows: np.ndarray, max3: np.ndarray, row_mask: np.ndarray, ys: np.ndarray, xs: np.ndarray,
                vals: np.ndarray) -> int:
    """The `local_maxima` of the `blob_ratio` scores (oh, ow) and their scores, fused:
    count n, rows, columns and scores in ``ys[:n]``, ``xs[:n]``, ``vals[:n]``. Only a
    rolling three rows of scores are kept (`rows` (3, ow) float32), not the image (1.2
    MB at 640x480, written and read back through the cache: ~0.2 ms a frame); `max3`,
    `row_mask` as for `local_maxima`."""
    oh, ow = integral.shape[0] - 12, rows.shape[1]
    row_mask[ow:] = 0
    n = 0
    for y in range(oh + 1):
        if y < oh:
            _blob_row(integral, dil, ero, eps, y, rows[y % 3])
            _max3_row(rows[y % 3], max3[y % 3])
        if y >= 1:
            r = y - 1
            here = max3[r % 3]
            above = max3[(r - 1) % 3] if r >= 1 else here  # the image edge: no row beyond
            below = max3[y % 3] if y < oh else here
            m = n
            n = _maxima_row(rows[r % 3], above, here, below, threshold, r, row_mask, ys, xs, n)
            for i in range(m, n):
                vals[i] = rows[r % 3, xs[i]]
    return n


# --------------------------------------------------------------------------------------
# Stage 1b (app.core.detection.candidates)
# --------------------------------------------------------------------------------------


@njit(**_JIT)
def gather_windows(padded: np.ndarray, ys: np.ndarray, xs: np.ndarray, raw: np.ndarray, flat: np.ndarray,
                   sums: np.ndarray, sums_sq: np.ndarray) -> None:
    """The 12x12 windows with top-left ``(ys[i], xs[i])`` of a padded level: raw copies
    into `raw` (n, 12, 12) uint8, as float32 rows into `flat` (n, 144), and each
    window's pixel sum and sum of squares into `sums`, `sums_sq` (n,) int64 (exact;
    below 2**24, so exact in float32 too: the window sum and ``einsum(w, w)`` that the
    screen needs, whatever order they would be added in)."""
    for i in range(ys.shape[0]):
        y, x = ys[i], xs[i]
        total = 0
        total_sq = 0
        for r in range(12):
            src = padded[y + r, x : x + 12]
            for c in range(12):
                v = src[c]
                raw[i, r, c] = v
                flat[i, r * 12 + c] = np.float32(v)
                total += np.int64(v)
                total_sq += np.int64(v) * np.int64(v)
        sums[i] = total
        sums_sq[i] = total_sq


@njit(**_JIT)
def screen_hidden(product: np.ndarray, sums: np.ndarray, sums_sq: np.ndarray, w1_sum: np.ndarray, b1: np.ndarray,
                  norm_eps: np.float32) -> None:
    """The screen's hidden layer from ``product = w @ W1`` (n, H) of raw windows w, in
    place: ``relu((product - mean(w) 1 W1) / |w - mean(w)| + b1)``, i.e. the product of
    the normalised window, each step in float32 as the numpy expression did it:
    mean = sum / 144, |.|^2 = sum_sq - (144 mean) mean (floored at 0, its root at
    `norm_eps`)."""
    dim = np.float32(144.0)
    for i in range(product.shape[0]):
        mean = np.float32(sums[i]) / dim
        sq = np.float32(sums_sq[i]) - (dim * mean) * mean
        sq = sq if not sq < 0 else np.float32(0.0)  # np.maximum(sq, 0): NaN stays NaN
        root = np.sqrt(sq)
        inv = np.float32(1.0) / (root if not root < norm_eps else norm_eps)
        row = product[i]
        for j in range(row.shape[0]):
            h = ((row[j] - mean * w1_sum[j]) * inv) + b1[j]
            row[j] = h if not h < 0 else np.float32(0.0)


# --------------------------------------------------------------------------------------
# Disc geometry in the window (app.core.detection.candidates)
# --------------------------------------------------------------------------------------


@njit(**_JIT)
def ring_radius(prof: np.ndarray, ring_mid: np.ndarray, gain: np.float32, radius: np.ndarray, half: np.ndarray
                ) -> None:
    """`candidates.window_radius` after its ring product ``prof = w @ RINGS`` (n, R)
    float32: per window the half level and the interpolated, scaled half-level
    crossing, into `radius`, `half` (n,) float32; the ~15 numpy calls on short arrays it
    replaces each cost more than this loop (same float32 steps)."""
    nr = prof.shape[1]
    lo = np.float32(1e-6)
    for i in range(prof.shape[0]):
        p = prof[i]
        dark = p[0] if p[0] <= p[1] or p[0] != p[0] else p[1]
        top = p[2]
        for j in range(3, nr):
            top = top if top >= p[j] or top != top else p[j]
        h = np.float32(0.5) * (dark + top)
        first = nr
        for j in range(nr):
            if not p[j] < h:
                first = j
                break
        k = min(max(first, 1), nr - 1)
        p0, p1 = p[k - 1], p[k]
        step = p1 - p0 if abs(p1 - p0) > lo else lo
        t = (h - p0) / step
        t = t if not t < 0 else np.float32(0.0)  # np.maximum / np.minimum: NaN stays NaN
        t = t if not t > 1 else np.float32(1.0)
        r = ring_mid[k - 1] + t
        if first == 0:
            r = np.float32(0.5)
        radius[i] = r * gain
        half[i] = h


@njit(**_JIT)
def centroid_weights(w: np.ndarray, half: np.ndarray, reach2: np.ndarray, dx: np.ndarray, dy: np.ndarray,
                     dist2: np.ndarray, offset: np.ndarray, first: bool, weight: np.ndarray, total: np.ndarray
                     ) -> None:
    """One pass of `candidates.window_centroid` up to its moment product: `weight` (n,
    144) = darkness ``max(half - w, 0)`` inside the aperture ``d2 <= reach2`` about the
    offset (d2 = `dist2` on the `first` pass), else 0, and `total` (n,) its numpy
    pairwise row sum (five array passes in one)."""
    for i in range(w.shape[0]):
        hi, r2 = half[i], reach2[i]
        ox, oy = offset[i, 0], offset[i, 1]
        row = weight[i]
        for j in range(w.shape[1]):
            d = hi - w[i, j]
            d = d if not d < 0 else np.float32(0.0)
            if first:
                d2 = dist2[j]
            else:
                ex, ey = dx[j] - ox, dy[j] - oy
                d2 = ex * ex + ey * ey
            row[j] = d if d2 <= r2 else np.float32(0.0) * d
        total[i] = np.float32(0.0) + pairwise_sum(row, 0, row.shape[0])


@njit(**_JIT)
def centroid_offset(moments: np.ndarray, total: np.ndarray, offset: np.ndarray) -> None:
    """The end of one `candidates.window_centroid` pass, in place: where the weight is
    > 1e-6 the offset becomes the moments over it, clipped to +-2 px."""
    for i in range(total.shape[0]):
        t = total[i]
        if t > np.float32(1e-6):
            for c in range(2):
                v = moments[i, c] / t
                v = v if not v < -2 else np.float32(-2.0)
                v = v if not v > 2 else np.float32(2.0)
                offset[i, c] = v


# --------------------------------------------------------------------------------------
# Non-maximum suppression (app.core.detection.candidates)
# --------------------------------------------------------------------------------------


@njit(**_JIT)
def clash_pairs(rows: np.ndarray, claims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i, j), i < j, of rows ``[u, v, radius, ...]`` (N, >= 3) float32 in priority
    order where i suppresses j: j's centre lies inside i's disc and, unless i claims its
    disc (`claims` (N,) bool), i's centre inside j's too. A sweep along x (stable sort,
    each row looks within its own radius): the pairs come out as the vectorised sweep
    listed them, by sorted position of i, then of j."""
    n = rows.shape[0]
    x = rows[:, 0].copy()
    order = np.argsort(x, kind="mergesort")  # stable
    xs = x[order]
    r = rows[:, 2].copy()[order]
    lo = np.searchsorted(xs, xs - r, side="left")
    hi = np.searchsorted(xs, xs + r, side="right")
    cap = 0
    for s in range(n):
        cap += max(hi[s] - lo[s], 0)
    first = np.empty(cap, np.intp)
    second = np.empty(cap, np.intp)
    m = 0
    for s in range(n):
        a = order[s]
        ua, va, ra = rows[a, 0], rows[a, 1], rows[a, 2]
        for t in range(lo[s], hi[s]):
            b = order[t]
            if a < b:
                du, dv = ua - rows[b, 0], va - rows[b, 1]
                reach = ra if claims[a] else min(ra, rows[b, 2])
                if du * du + dv * dv < reach * reach:
                    first[m] = a
                    second[m] = b
                    m += 1
    return first[:m], second[:m]


@njit(**_JIT)
def greedy(first: np.ndarray, second: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Greedy suppression of rows 0..n-1 (priority order, n = active.size) given clash
    pairs ``first[k] < second[k]``: bool (n,), row j kept when it is `active` and no
    kept row i < j clashes with it. In order, each kept row striking out the rows it
    clashes with (the pairs grouped by i first, counting sort)."""
    n = active.shape[0]
    start = np.zeros(n + 1, np.intp)
    for k in range(first.shape[0]):
        start[first[k] + 1] += 1
    for i in range(n):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    victims = np.empty(first.shape[0], np.intp)
    for k in range(first.shape[0]):
        victims[fill[first[k]]] = second[k]
        fill[first[k]] += 1
    keep = active.copy()
    for i in range(n):
        if keep[i]:  # final: every row that could suppress i comes before it
            for k in range(start[i], start[i + 1]):
                keep[victims[k]] = False
    return keep


# --------------------------------------------------------------------------------------
# Grouping (app.core.detection.targets)
# --------------------------------------------------------------------------------------


@njit(**_JIT)
def edge_sweep(pts: np.ndarray, rad: np.ndarray, reach: float, ratio_max: float, d2_lo: float, d2_hi: float,
               keep: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                   np.ndarray]:
    """Candidate edges of `targets._edges`: a sweep along x (stable sort) over points
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


@njit(**_JIT)
def edge_ranks_keep(a: np.ndarray, b: np.ndarray, crowded: np.ndarray, inc: np.ndarray, bad: np.ndarray,
                    keep: int) -> np.ndarray:
    """bool (E,): which edges (a, b) `targets._edges` keeps among crowded points. Each
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


@njit(**_JIT, inline="always")
def _quad_ok(px: np.ndarray, py: np.ndarray, rad: np.ndarray, v: np.ndarray, area_lo: float, area_hi: float,
             ratio_max: float, side2: float, cos2: float) -> bool:
    """The grouping's cheap geometry checks of the quadrilateral with vertices v (4,)
    (layout orientation): area over the mean radius squared in [area_lo, area_hi],
    radius ratio, side ratio (squared), convex and every interior angle in range
    (cos^2 below cos2); each sum over the four vertices in the vectorised code's
    order (tests/test_kernels.py: `_reference_quad_geometry_ok`)."""
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


@njit(**_JIT)
def group_graph(pts: np.ndarray, rad: np.ndarray, ea: np.ndarray, eb: np.ndarray, white: np.ndarray,
                with_corners: bool, cos2: float, side2: float, apex_lo: float, apex_hi: float, ratio_max: float,
                fourth2: float, area_lo: float, area_hi: float
                ) -> tuple[np.ndarray, np.ndarray, int, np.ndarray, np.ndarray, np.ndarray]:
    """The search of `targets._group` on the graph of edges (ea, eb) between points
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


@njit(**_JIT)
def affine_points(pi: np.ndarray, pj: np.ndarray, pl: np.ndarray, coef: np.ndarray, width: int, height: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Points of S parallelograms with apex `pi` and sides to `pj`, `pl` (S, 2) float64
    at affine coefficients `coef` (M, 2): ``pi + c0 (pj - pi) + c1 (pl - pi)`` in
    float64, as (S, M, 2) float32 (a `cv2.remap` map), and whether each lies in a
    `width` x `height` image (within half a pixel of its edge pixels, from the float64
    point). Compiled: numpy's broadcasting over a trailing axis of 2 costs ~40 us for
    a few thousand points."""
    s_count, m = pi.shape[0], coef.shape[0]
    xy = np.empty((s_count, m, 2), np.float32)
    inside = np.empty((s_count, m), np.bool_)
    hi_x, hi_y = width - 0.5, height - 0.5
    for s in range(s_count):
        x0, y0 = pi[s, 0], pi[s, 1]
        ax, ay = pj[s, 0] - x0, pj[s, 1] - y0
        bx, by = pl[s, 0] - x0, pl[s, 1] - y0
        for k in range(m):
            x = x0 + coef[k, 0] * ax + coef[k, 1] * bx
            y = y0 + coef[k, 0] * ay + coef[k, 1] * by
            xy[s, k, 0], xy[s, k, 1] = np.float32(x), np.float32(y)
            inside[s, k] = x >= -0.5 and y >= -0.5 and x <= hi_x and y <= hi_y
    return xy, inside


# --------------------------------------------------------------------------------------
# Verification measurements (app.core.detection.targets)
# --------------------------------------------------------------------------------------


@njit(**_JIT)
def measure_stats(vals: np.ndarray, inside: np.ndarray, sorted_index: np.ndarray, bounds: np.ndarray,
                  stats_lo: np.ndarray, stats_hi: np.ndarray, stats_frac: np.ndarray, disc: np.ndarray,
                  edge: np.ndarray, core: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The measurements of `targets._measures_from` but the code cells, for samples
    `vals` (P, M) float32 (whole grey levels) and their mask `inside` (P, M): per row,
    the five groups of samples ``sorted_index[bounds[g] : bounds[g + 1]]`` sorted
    (the last, the card edge, reading inf outside the image), the order statistics
    ``s[lo] + frac * (s[hi] - s[lo])`` (`stats_lo`, ...: columns of the groups side by
    side), the disc means (`disc` (4, D): an exact float32 sum over a float64 division
    by D, as np.mean) and the edge median over the samples inside. Returns (11, P)
    float32 rows black, white, contrast, contrast floored at 1e-3, uniformity, disc
    level, disc spread, disc max, white low, gap low, edge level; and valid (P,)
    float64. Every float32 step is the vectorised code's (sorting whole grey levels is
    exact, however done). Compiled: ~35 numpy calls on a few rows otherwise."""
    p_count, m = vals.shape
    g_total = sorted_index.shape[0]
    edge_start = bounds[4]
    out = np.empty((11, p_count), np.float32)
    valid = np.empty(p_count)
    s = np.empty(g_total, np.float32)
    q = np.empty(stats_lo.shape[0], np.float32)
    eps = np.float32(1e-3)
    n_disc = disc.shape[1]
    for p in range(p_count):
        row, row_in = vals[p], inside[p]
        for k in range(g_total):
            s[k] = row[sorted_index[k]]
        n_in = 0
        for k in range(edge.shape[0]):
            if row_in[edge[k]]:
                n_in += 1
            else:
                s[edge_start + k] = np.inf  # outside the image: no evidence
        for g in range(bounds.shape[0] - 1):
            s[bounds[g] : bounds[g + 1]].sort()
        for k in range(q.shape[0]):
            lo = s[stats_lo[k]]
            q[k] = lo + stats_frac[k] * (s[stats_hi[k]] - lo)
        black, white = q[0], q[1]
        contrast = white - black
        c = max(contrast, eps)
        dmax, dmin = np.float32(-np.inf), np.float32(np.inf)
        for d in range(4):
            total = np.float32(0.0)
            for k in range(n_disc):
                total += row[disc[d, k]]
            mean = (np.float32(np.float64(total) / n_disc) - black) / c
            dmax, dmin = max(dmax, mean), min(dmin, mean)
        edge_med = s[edge_start + n_in // 2]
        out[0, p], out[1, p], out[2, p], out[3, p] = black, white, contrast, c
        out[4, p] = (q[2] - q[3]) / c
        out[5, p], out[6, p] = dmax, dmax - dmin
        out[7, p], out[8, p], out[9, p] = (q[6] - black) / c, (q[4] - black) / c, (q[5] - black) / c
        out[10, p] = (edge_med - black) / c if n_in >= 4 else np.float32(1.0)
        core_in = True
        for k in range(core.shape[0]):
            core_in = core_in and row_in[core[k]]
        n_inside = 0
        for k in range(m):
            n_inside += row_in[k]
        valid[p] = n_inside / m if core_in else 0.0
    return out, valid


# --------------------------------------------------------------------------------------
# Subpixel disc centres (app.core.detection.targets)
# --------------------------------------------------------------------------------------


@njit(**_JIT, inline="always")
def _block_sum(a: np.ndarray, start: int, n: int) -> np.float32:
    """numpy's pairwise sum of a run of at most 128 (its leaf case)."""
    if n < 8:
        res = np.float32(0.0)
        for i in range(n):
            res += a[start + i]
        return res
    r0, r1, r2, r3 = a[start], a[start + 1], a[start + 2], a[start + 3]
    r4, r5, r6, r7 = a[start + 4], a[start + 5], a[start + 6], a[start + 7]
    i = 8
    while i < n - n % 8:
        j = start + i
        r0 += a[j]
        r1 += a[j + 1]
        r2 += a[j + 2]
        r3 += a[j + 3]
        r4 += a[j + 4]
        r5 += a[j + 5]
        r6 += a[j + 6]
        r7 += a[j + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[start + i]
        i += 1
    return res


@njit(**_JIT)
def pairwise_sum(a: np.ndarray, start: int, n: int) -> np.float32:
    """``a[start : start + n]`` (float32) summed as numpy's ``add.reduce`` sums a
    contiguous run: halved recursively (the first half a multiple of 8) down to runs of
    at most 128, each summed in eight interleaved partial sums
    (numpy/_core/src/umath/loops_utils.h.src), so a kernel reproduces
    ``x.sum(axis=-1)`` bit for bit (numpy then adds the total to its initial 0: callers
    add 0 too). The recursion runs on an explicit stack: numba's cache cannot hold a
    recursive function (loading it crashes)."""
    if n <= 128:
        return _block_sum(a, start, n)
    # post-order walk of the halving tree: (start, n, children pushed) per node
    depth = 64
    node_start = np.empty(depth, np.int64)
    node_n = np.empty(depth, np.int64)
    node_stage = np.empty(depth, np.int64)
    values = np.empty(depth, np.float32)
    top, n_values = 0, 0
    node_start[0], node_n[0], node_stage[0] = start, n, 0
    while top >= 0:
        s, m = node_start[top], node_n[top]
        if m <= 128:
            values[n_values] = _block_sum(a, s, m)
            n_values += 1
            top -= 1
            continue
        half = m // 2
        half -= half % 8
        if node_stage[top] == 0:  # the first half
            node_stage[top] = 1
            top += 1
            node_start[top], node_n[top], node_stage[top] = s, half, 0
        elif node_stage[top] == 1:  # the second half
            node_stage[top] = 2
            top += 1
            node_start[top], node_n[top], node_stage[top] = s + half, m - half, 0
        else:  # both summed: first + second
            n_values -= 1
            values[n_values - 1] = values[n_values - 1] + values[n_values]
            top -= 1
    return values[0]


@njit(**_JIT)
def centroid_step(img: np.ndarray, centroid: np.ndarray, jac: np.ndarray, reach: float, disc_radius: float,
                  ring2: np.ndarray, inner2: np.float32, taper_gain: np.float32, white: np.ndarray,
                  measure_white: bool, new: np.ndarray, total: np.ndarray, contrast: np.ndarray) -> None:
    """`targets._centroid_step` for D discs, fused: per disc, the window of (2k + 1)^2
    pixels around its rounded centroid (k from the largest extent of all D), the
    distance of each pixel from the centroid in disc radii on the card (float32, via
    the inverse Jacobian), the white level (median of the ring `ring2` = (lo^2, hi^2)
    when `measure_white`, else `white` as given; written back into `white`), the black
    level (mean inside `inner2`) and the tapered darkness-weighted centroid.

    centroid (D, 2), jac (D, 2, 2) float64 in the pixels of `img`; outputs (D, 2) new
    centroids, (D,) summed darkness (0 where the centroid did not move) and white -
    black. Every float step is the numpy expression's, in its order; sums of float32
    arrays follow numpy's (`pairwise_sum` along a row, sequential down the columns);
    pixels outside the image take no part (their weights are 0, as the mask made
    them)."""
    d_count = centroid.shape[0]
    h, w = img.shape
    # half-size k of the common window: reach * R * longest row of J, over every disc
    ext_max = -np.inf
    for d in range(d_count):
        row0 = jac[d, 0, 0] * jac[d, 0, 0] + jac[d, 0, 1] * jac[d, 0, 1]
        row1 = jac[d, 1, 0] * jac[d, 1, 0] + jac[d, 1, 1] * jac[d, 1, 1]
        ext_max = max(ext_max, reach * disc_radius * np.sqrt(max(row0, row1)))
    k = int(np.ceil(ext_max)) + 1
    size = 2 * k + 1
    rho2 = np.empty(size * size, np.float32)
    pix = np.empty(size * size, np.uint8)
    inside = np.empty(size * size, np.bool_)
    weight = np.empty(size * size, np.float32)
    dx = np.empty(size, np.float32)
    dy = np.empty(size, np.float32)
    column = np.empty(size, np.float32)
    row_sum = np.empty(size, np.float32)
    hist = np.empty(256, np.int64)
    reach32 = np.float32(reach)
    for d in range(d_count):
        j00, j01, j10, j11 = jac[d, 0, 0], jac[d, 0, 1], jac[d, 1, 0], jac[d, 1, 1]
        s = 1.0 / ((j00 * j11 - j01 * j10) * disc_radius)  # inverse Jacobian over the disc radius
        a0, a1, a2, a3 = np.float32(j11 * s), np.float32(-j01 * s), np.float32(-j10 * s), np.float32(j00 * s)
        bx, by = np.rint(centroid[d, 0]), np.rint(centroid[d, 1])
        x0, y0 = int(bx) - k, int(by) - k
        off_x, off_y = np.float32(bx - centroid[d, 0]), np.float32(by - centroid[d, 1])
        for i in range(size):
            dx[i] = off_x + np.float32(i - k)
            dy[i] = off_y + np.float32(i - k)
        inner_sum = 0
        inner_count = 0
        for r in range(size):
            yy = y0 + r
            for c in range(size):
                xx = x0 + c
                q = r * size + c
                u = a0 * dx[c] + a1 * dy[r]
                v = a2 * dx[c] + a3 * dy[r]
                rho2[q] = u * u + v * v
                ok = yy >= 0 and yy < h and xx >= 0 and xx < w
                inside[q] = ok
                pix[q] = img[yy, xx] if ok else 0
                if ok and rho2[q] <= inner2:
                    inner_sum += np.int64(pix[q])
                    inner_count += 1
        if measure_white:  # median of the ring's pixels, from their histogram
            hist[:] = 0
            n_ring = 0
            for q in range(size * size):
                if inside[q] and rho2[q] >= ring2[0] and rho2[q] <= ring2[1]:
                    hist[pix[q]] += 1
                    n_ring += 1
            if n_ring == 0:
                white[d] = np.nan
            else:
                want_lo, want_hi = (n_ring - 1) // 2, n_ring // 2
                lo = hi = -1
                cum = 0
                for value in range(256):
                    cum += hist[value]
                    if lo < 0 and cum > want_lo:
                        lo = value
                    if cum > want_hi:
                        hi = value
                        break
                white[d] = 0.5 * (np.float64(lo) + np.float64(hi))
        wd = white[d]
        white32 = np.float32(wd if np.isfinite(wd) else 0.0)
        black = np.float64(inner_sum) / np.float64(max(inner_count, 1))
        for q in range(size * size):
            if inside[q]:
                taper = (reach32 - np.sqrt(rho2[q])) * taper_gain
                taper = min(taper, np.float32(1.0))
                taper = max(taper, np.float32(0.0))
                dark = white32 - np.float32(pix[q])
                weight[q] = max(dark, np.float32(0.0)) * taper
            else:
                weight[q] = np.float32(0.0)
        tot = np.float64(np.float32(0.0) + pairwise_sum(weight, 0, size * size))
        # first moments: column sums (down the rows, in order) against dx, row sums
        # (pairwise along each row) against dy
        column[:] = 0.0
        for r in range(size):
            for c in range(size):
                column[c] += weight[r * size + c]
            row_sum[r] = np.float32(0.0) + pairwise_sum(weight, r * size, size)
        for i in range(size):
            column[i] = column[i] * dx[i]
            row_sum[i] = row_sum[i] * dy[i]
        good = tot > 1e-6 and np.isfinite(wd)
        safe = tot if good else 1.0
        mx = np.float64(np.float32(0.0) + pairwise_sum(column, 0, size)) / safe
        my = np.float64(np.float32(0.0) + pairwise_sum(row_sum, 0, size)) / safe
        new[d, 0] = centroid[d, 0] + (mx if good else 0.0)
        new[d, 1] = centroid[d, 1] + (my if good else 0.0)
        total[d] = tot if good else 0.0
        contrast[d] = wd - black




# --------------------------------------------------------------------------------------
# Warm-up
# --------------------------------------------------------------------------------------


def warm_up() -> None:
    """Compile (or load from the cache) every kernel by calling it once on tiny inputs,
    so that the first frame does not pay for it. Call once at service start-up."""
    integral = np.zeros((21, 21), np.int32)
    level = np.zeros((20, 20), np.uint8)
    score = np.zeros((9, 9), np.float32)  # the windows of `level`
    ys, xs = np.empty(score.size, np.intp), np.empty(score.size, np.intp)
    max3, row_mask = np.empty((3, 9), np.float32), np.zeros(16, np.uint8)
    blob_ratio(integral, level, level, np.float32(2.0), score)
    blob_maxima(integral, level, level, np.float32(2.0), np.float32(0.5), max3.copy(), max3, row_mask, ys, xs,
                score.ravel())
    local_maxima(score, np.float32(0.5), max3, row_mask, ys, xs)
    raw, flat = np.empty((2, 12, 12), np.uint8), np.empty((2, 144), np.float32)
    sums, sums_sq = np.empty(2, np.int64), np.empty(2, np.int64)
    gather_windows(level, ys[:2] * 0, xs[:2] * 0, raw, flat, sums, sums_sq)
    rows = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0]], np.float32)
    first, second = clash_pairs(rows, np.ones(2, np.bool_))
    greedy(first, second, np.ones(2, np.bool_))
    pts = np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 5.0], [0.0, 5.0]])
    rad = np.ones(4)
    a, b, d2, _, _, _, crowded = edge_sweep(pts, rad, 15.0, 2.0, 4.84, 100.0, 1)
    inc = np.flatnonzero(crowded.take(a) | crowded.take(b))
    edge_ranks_keep(a, b, crowded, inc, d2.take(inc), 1)
    ea, eb = np.minimum(a, b), np.maximum(a, b)
    for white in (np.ones(ea.size, np.float32), np.zeros(0, np.float32)):
        group_graph(pts, rad, ea, eb, white, white.size > 0, 0.86, 0.05, 4.84, 81.0, 2.0, 0.12, 10.89, 49.0)
    affine_points(pts[:1], pts[1:2], pts[3:], pts, 8, 8)
    index, stats = np.arange(5, dtype=np.intp), np.zeros(7, np.intp)
    measure_stats(np.ones((2, 5), np.float32), np.ones((2, 5), np.bool_), index, np.arange(6, dtype=np.intp), stats,
                  stats.copy(), np.zeros(7, np.float32), index[:4].reshape(4, 1).copy(), index[4:].copy(), index)
    img = np.zeros((8, 8), np.uint8)
    centroid, jac = np.full((1, 2), 3.0), np.eye(2).reshape(1, 2, 2) * 8.0
    new, total, contrast = np.empty((1, 2)), np.empty(1), np.empty(1)
    for measure in (True, False):
        centroid_step(img, centroid, jac, 1.2, 0.125, np.array([1.3, 2.0], np.float32), np.float32(0.25),
                      np.float32(10.0), np.zeros(1), measure, new, total, contrast)
    prof = np.ones((2, 6), np.float32)
    radius, half = np.empty(2, np.float32), np.empty(2, np.float32)
    ring_radius(prof, prof[0], np.float32(1.0), radius, half)
    windows, offset = np.ones((2, 144), np.float32), np.zeros((2, 2), np.float32)
    grid = windows[0]
    for first_pass in (True, False):
        centroid_weights(windows, half, radius, grid, grid, grid, offset, first_pass, windows.copy(), radius.copy())
    centroid_offset(offset.copy(), radius, offset)
    geometry_kernels.warm_up()
    bias = np.ones(3, np.float32)
    bias.setflags(write=False)  # as the classifier's arrays are: numba types read-only arrays apart
    screen_hidden(np.ones((2, 4), np.float32)[:, :3], sums, sums_sq, np.ones(3, np.float32), bias, np.float32(1e-3))
