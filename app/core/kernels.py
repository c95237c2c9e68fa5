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

_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


# --------------------------------------------------------------------------------------
# Stage 1a (app.core.candidates)
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
                out: np.ndarray, max3: np.ndarray, row_mask: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> int:
    """`blob_ratio` into `out` and its `local_maxima`, fused: each score row is
    scanned for maxima while it is still in cache (a 640x480 level's scores are 1.2 MB)."""
    row_mask[out.shape[1]:] = 0
    n = 0
    for y in range(out.shape[0] + 1):
        if y < out.shape[0]:
            _blob_row(integral, dil, ero, eps, y, out[y])
        n = _maxima_pass(out, y, threshold, max3, row_mask, ys, xs, n)
    return n


# --------------------------------------------------------------------------------------
# Stage 1b (app.core.candidates)
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
# Non-maximum suppression (app.core.candidates)
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
# Subpixel disc centres (app.core.targets)
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
    score = np.zeros((8, 8), np.float32)
    ys, xs = np.empty(score.size, np.intp), np.empty(score.size, np.intp)
    max3, row_mask = np.empty((3, 8), np.float32), np.zeros(8, np.uint8)
    blob_ratio(integral, level, level, np.float32(2.0), score)
    blob_maxima(integral, level, level, np.float32(2.0), np.float32(0.5), score, max3, row_mask, ys, xs)
    local_maxima(score, np.float32(0.5), max3, row_mask, ys, xs)
    raw, flat = np.empty((2, 12, 12), np.uint8), np.empty((2, 144), np.float32)
    sums, sums_sq = np.empty(2, np.int64), np.empty(2, np.int64)
    gather_windows(level, ys[:2] * 0, xs[:2] * 0, raw, flat, sums, sums_sq)
    rows = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0]], np.float32)
    first, second = clash_pairs(rows, np.ones(2, np.bool_))
    greedy(first, second, np.ones(2, np.bool_))
    img = np.zeros((8, 8), np.uint8)
    centroid, jac = np.full((1, 2), 3.0), np.eye(2).reshape(1, 2, 2) * 8.0
    new, total, contrast = np.empty((1, 2)), np.empty(1), np.empty(1)
    for measure in (True, False):
        centroid_step(img, centroid, jac, 1.2, 0.125, np.array([1.3, 2.0], np.float32), np.float32(0.25),
                      np.float32(10.0), np.zeros(1), measure, new, total, contrast)
    bias = np.ones(3, np.float32)
    bias.setflags(write=False)  # as the classifier's arrays are: numba types read-only arrays apart
    screen_hidden(np.ones((2, 4), np.float32)[:, :3], sums, sums_sq, np.ones(3, np.float32), bias, np.float32(1e-3))
