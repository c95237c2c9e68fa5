"""Compiled kernels of the candidate stage (`candidates`): stage 1a's blob score and its
local maxima, the window copies and the screen's correction of stage 1b, the disc's
radius and centroid in its window, and the sweep and greedy pass of non-maximum
suppression. Flags and conventions: `_numba`; the numpy/OpenCV references are in the
candidate stage's kernel tests."""

from __future__ import annotations

import numpy as np
from numba import njit

from app.core.detection._numba import JIT, pairwise_sum

# --------------------------------------------------------------------------------------
# Stage 1a
# --------------------------------------------------------------------------------------


@njit(**JIT, inline="always")
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


@njit(**JIT)
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


@njit(**JIT, inline="always")
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


@njit(**JIT, inline="always")
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


@njit(**JIT, inline="always")
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


@njit(**JIT)
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


@njit(**JIT)
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
# Stage 1b
# --------------------------------------------------------------------------------------


@njit(**JIT)
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


@njit(**JIT)
def screen_hidden(product: np.ndarray, sums: np.ndarray, sums_sq: np.ndarray, w1_sum: np.ndarray, b1: np.ndarray,
                  norm_eps: np.float32) -> None:
    """The screen's hidden layer from ``product = w @ W1`` (n, H) of raw windows w, in
    place: ``relu((product - mean(w) 1 W1) / |w - mean(w)| + b1)``, i.e. the product of
    the normalised window, each step in float32 as the numpy reference does it:
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
# Disc geometry in the window
# --------------------------------------------------------------------------------------


@njit(**JIT)
def ring_radius(prof: np.ndarray, ring_mid: np.ndarray, gain: np.float32, radius: np.ndarray, half: np.ndarray
                ) -> None:
    """`candidates.window_radius` after its ring product ``prof = w @ RINGS`` (n, R)
    float32: per window the half level and the interpolated, scaled half-level
    crossing, into `radius`, `half` (n,) float32; each of the ~15 numpy calls on short
    arrays of the reference costs more than this loop (same float32 steps)."""
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


@njit(**JIT)
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


@njit(**JIT)
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
# Non-maximum suppression
# --------------------------------------------------------------------------------------


@njit(**JIT)
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


@njit(**JIT)
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


def warm_up() -> None:
    """Compile (or load from the cache) every kernel of the candidate stage on tiny
    inputs, with the argument types the stage passes."""
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
    bias = np.ones(3, np.float32)
    bias.setflags(write=False)  # as the classifier's arrays are: numba types read-only arrays apart
    screen_hidden(np.ones((2, 4), np.float32)[:, :3], sums, sums_sq, np.ones(3, np.float32), bias, np.float32(1e-3))
    prof = np.ones((2, 6), np.float32)
    radius, half = np.empty(2, np.float32), np.empty(2, np.float32)
    ring_radius(prof, prof[0], np.float32(1.0), radius, half)
    windows, offset = np.ones((2, 144), np.float32), np.zeros((2, 2), np.float32)
    grid = windows[0]
    for first_pass in (True, False):
        centroid_weights(windows, half, radius, grid, grid, grid, offset, first_pass, windows.copy(), radius.copy())
    centroid_offset(offset.copy(), radius, offset)
    rows = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0]], np.float32)
    first, second = clash_pairs(rows, np.ones(2, np.bool_))
    greedy(first, second, np.ones(2, np.bool_))
