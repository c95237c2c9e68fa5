"""Compiled kernels of the whole-card code reader (`code_reader`): where a card's pixels
are and which of them are read, the printed card's channels over a patch of pixels (each
pixel's footprint sub-sampled), and the fit of every pattern. Flags and conventions:
`_numba`; the numpy references are in the reader's tests."""

from __future__ import annotations

import numpy as np
from numba import njit

from app.core.detection._numba import JIT
from app.core.geometry import _kernels as geometry_kernels


_CENTRE = np.array([[0.5, 0.5]])


@njit(**JIT)
def card_side(h: np.ndarray) -> float:
    """The side (pixels) of a unit square at the card's centre under homography `h`
    (card units to pixels): the square root of its Jacobian's determinant there (the
    geometry's own compiled Jacobian; numba's cache keys on this file only, so after
    changing that kernel, clear the cache)."""
    j = geometry_kernels.jacobians(h.reshape(1, 3, 3), _CENTRE)[0, 0]
    return np.sqrt(abs(j[0, 0] * j[1, 1] - j[0, 1] * j[1, 0]))


@njit(**JIT)
def _inverse(h: np.ndarray) -> np.ndarray:
    """The inverse of a 3x3 matrix by its adjugate (NaN where singular)."""
    a, b, c = h[0, 0], h[0, 1], h[0, 2]
    d, e, f = h[1, 0], h[1, 1], h[1, 2]
    g, k, m = h[2, 0], h[2, 1], h[2, 2]
    out = np.empty((3, 3))
    out[0, 0], out[0, 1], out[0, 2] = e * m - f * k, c * k - b * m, b * f - c * e
    out[1, 0], out[1, 1], out[1, 2] = f * g - d * m, a * m - c * g, c * d - a * f
    out[2, 0], out[2, 1], out[2, 2] = d * k - e * g, b * g - a * k, a * e - b * d
    det = a * out[0, 0] + b * out[1, 0] + c * out[2, 0]
    if det == 0.0 or not np.isfinite(det):
        out[:] = np.nan
    else:
        out /= det
    return out


@njit(**JIT)
def card_pixels(img: np.ndarray, h: np.ndarray, margin: float, origin: float, size: float, clipped: bool,
                saturated: float) -> tuple[bool, np.ndarray, int, int, int, int, np.ndarray, np.ndarray, np.ndarray,
                                           np.ndarray, np.ndarray]:
    """The pixels of a card read in `img` (uint8), `h` mapping card units to its pixels:
    those whose centres lie at least `margin` (card units) inside the card's edges and in
    the image. Returns (ok, hinv, x0, y0, width, height, rows, cols, values, sat_rows,
    sat_cols): `ok` False when the card is degenerate or its code area (`origin` ..
    `origin + size`) is not wholly in the image; the box (x0, y0, width, height) around the
    read region clipped to the image, the read pixels' rows and columns in it and their
    values; on a `clipped` card the pixels at `saturated` or above are left out of those
    and listed apart."""
    hinv = _inverse(h)
    empty_i = np.zeros(0, np.intp)
    empty_f = np.zeros(0)
    ih, iw = img.shape
    lo_x = lo_y = np.inf
    hi_x = hi_y = -np.inf
    ok = np.isfinite(hinv[0, 0])
    for corner in range(8):
        s = margin if corner < 4 else origin
        t = 1.0 - margin if corner < 4 else origin + size
        u = s if corner % 4 in (0, 3) else t
        v = s if corner % 4 in (0, 1) else t
        w = h[2, 0] * u + h[2, 1] * v + h[2, 2]
        x = (h[0, 0] * u + h[0, 1] * v + h[0, 2]) / w
        y = (h[1, 0] * u + h[1, 1] * v + h[1, 2]) / w
        if not (np.isfinite(x) and np.isfinite(y)):
            ok = False
        elif corner < 4:
            lo_x, hi_x, lo_y, hi_y = min(lo_x, x), max(hi_x, x), min(lo_y, y), max(hi_y, y)
        elif not (0.0 <= x <= iw - 1 and 0.0 <= y <= ih - 1):
            ok = False  # the code itself must be in the image; the rest of the card may leave it
    if not ok:
        return False, hinv, 0, 0, 0, 0, empty_i, empty_i, empty_f, empty_i, empty_i
    x0, y0 = max(int(np.floor(lo_x)), 0), max(int(np.floor(lo_y)), 0)
    x1, y1 = min(int(np.ceil(hi_x)), iw - 1), min(int(np.ceil(hi_y)), ih - 1)
    width, height = x1 - x0 + 1, y1 - y0 + 1
    rows = np.empty(width * height, np.intp)
    cols = np.empty(width * height, np.intp)
    values = np.empty(width * height)
    sat_rows = np.empty(width * height, np.intp)
    sat_cols = np.empty(width * height, np.intp)
    n = m = 0
    for py in range(height):
        y = float(y0 + py)
        for px in range(width):
            x = float(x0 + px)
            d = hinv[2, 0] * x + hinv[2, 1] * y + hinv[2, 2]
            u = (hinv[0, 0] * x + hinv[0, 1] * y + hinv[0, 2]) / d
            v = (hinv[1, 0] * x + hinv[1, 1] * y + hinv[1, 2]) / d
            if margin <= u <= 1.0 - margin and margin <= v <= 1.0 - margin:
                value = float(img[y0 + py, x0 + px])
                if clipped and value >= saturated:
                    sat_rows[m], sat_cols[m] = py, px
                    m += 1
                else:
                    rows[n], cols[n], values[n] = py, px, value
                    n += 1
    return True, hinv, x0, y0, width, height, rows[:n], cols[:n], values[:n], sat_rows[:m], sat_cols[:m]


@njit(**JIT)
def card_channels(hinv: np.ndarray, x0: int, y0: int, width: int, height: int, sub: int, n: int, origin: float,
                  size: float, discs: np.ndarray, radius: float) -> np.ndarray:
    """The share of each pixel's footprint (`sub` x `sub` sub-samples) that falls on each
    code cell (row-major, n x n of them, the code area ``origin .. origin + size`` in card
    units), on the white card and off the card; a disc (centres `discs` (4, 2), `radius`)
    adds to none. Pixels (x0 .. x0 + width - 1, y0 .. y0 + height - 1), their centres on
    whole coordinates; `hinv` maps pixels to card units. Returns (height, width, n*n + 2)
    float32."""
    n2 = n * n
    out = np.empty((height, width, n2 + 2), np.float32)
    step = size / n
    r2 = radius * radius
    w = np.float32(1.0 / (sub * sub))
    # the discs' extent in card units: a sample inside it in u or in v needs no disc test
    # (the discs sit in the card's corners)
    lo_u = lo_v = np.inf
    hi_u = hi_v = -np.inf
    for k in range(discs.shape[0]):
        lo_u, hi_u = min(lo_u, discs[k, 0] + radius), max(hi_u, discs[k, 0] - radius)
        lo_v, hi_v = min(lo_v, discs[k, 1] + radius), max(hi_v, discs[k, 1] - radius)
    offsets = np.empty(sub)
    for i in range(sub):
        offsets[i] = -0.5 + (i + 0.5) / sub
    counts = np.empty(n2 + 2, np.int32)
    for py in range(height):
        for px in range(width):
            counts[:] = 0
            for j in range(sub):
                y = y0 + py + offsets[j]
                for i in range(sub):
                    x = x0 + px + offsets[i]
                    rd = 1.0 / (hinv[2, 0] * x + hinv[2, 1] * y + hinv[2, 2])
                    u = (hinv[0, 0] * x + hinv[0, 1] * y + hinv[0, 2]) * rd
                    v = (hinv[1, 0] * x + hinv[1, 1] * y + hinv[1, 2]) * rd
                    if (u < lo_u or u > hi_u) and (v < lo_v or v > hi_v):
                        ink = False
                        for k in range(discs.shape[0]):
                            du, dv = u - discs[k, 0], v - discs[k, 1]
                            if du * du + dv * dv <= r2:
                                ink = True
                        if ink:
                            continue
                    if u < 0.0 or u > 1.0 or v < 0.0 or v > 1.0:
                        label = n2 + 1
                    else:
                        col = int(np.floor((u - origin) / step))
                        row = int(np.floor((v - origin) / step))
                        label = row * n + col if 0 <= col < n and 0 <= row < n else n2
                    counts[label] += 1
            cell = out[py, px]
            for c in range(n2 + 2):
                cell[c] = counts[c] * w
    return out


@njit(**JIT)
def pattern_fits(stack: np.ndarray, rows: np.ndarray, cols: np.ndarray, y: np.ndarray, tmpl: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The fit of every pattern at every point-spread function (`code_reader._fit_codes`).

    `stack` (K, H, W, C) float32: the card's channels (C - 1 of the card: code cells and
    the white card; the last, off the card) blurred by each function; the read pixels at
    (`rows`, `cols`) with values `y` (P,); `tmpl` (T, C - 1) each pattern's weights on
    the card's channels. Returns the Gram matrix of [constant, off the card, card
    channels, read] per function (K, C + 2, C + 2); each pattern's summed squared
    residual (K, T) (inf where its fitted contrast is not positive) and fitted contrast
    (K, T); and the free card's summed squared residual (K,): every channel its own
    level."""
    n_k = stack.shape[0]
    n_c = stack.shape[3]
    n_card = n_c - 1
    d = n_c + 2
    n_t = tmpl.shape[0]
    gram = np.empty((n_k, d, d))
    sse = np.empty((n_k, n_t))
    contrast = np.empty((n_k, n_t))
    free = np.empty(n_k)
    design = np.empty((rows.shape[0], d))
    tmpl_t = np.ascontiguousarray(tmpl.T)
    for k in range(n_k):
        for p in range(rows.shape[0]):
            px = stack[k, rows[p], cols[p]]
            design[p, 0] = 1.0
            design[p, 1] = px[n_card]
            for c in range(n_card):
                design[p, 2 + c] = px[c]
            design[p, d - 1] = y[p]
        gk = design.T @ design
        gram[k] = gk
        # project the card and the read off the constant and the background (Schur complement)
        a, b, c2 = gk[0, 0] + 1e-9, gk[0, 1], gk[1, 1] + 1e-9
        det = a * c2 - b * b
        m = d - 2
        g = np.empty((m, m))
        for i in range(m):
            zi0, zi1 = gk[0, 2 + i], gk[1, 2 + i]
            s0, s1 = (c2 * zi0 - b * zi1) / det, (a * zi1 - b * zi0) / det
            for j in range(m):
                g[i, j] = gk[2 + i, 2 + j] - (gk[0, 2 + j] * s0 + gk[1, 2 + j] * s1)
        yy = g[m - 1, m - 1]
        gcc = np.ascontiguousarray(g[:n_card, :n_card])
        gcy = np.ascontiguousarray(g[:n_card, m - 1])
        # the free card; a whisker of ridge keeps a channel the read pixels hardly see solvable
        ridge = gcc.copy()
        scale = 0.0
        for i in range(n_card):
            scale += gcc[i, i]
        for i in range(n_card):
            ridge[i, i] += 1e-9 * scale / n_card + 1e-9
        x = np.linalg.solve(ridge, gcy)
        free[k] = max(yy - np.dot(gcy, x), 0.0)
        # every pattern's one-column regression: lin = v.g, quad = v.G.v
        lin = tmpl @ gcy
        quad_rows = tmpl @ gcc
        for t in range(n_t):
            quad = 0.0
            for i in range(n_card):
                quad += quad_rows[t, i] * tmpl_t[i, t]
            ct = lin[t] / quad
            contrast[k, t] = ct
            sse[k, t] = max(yy - lin[t] * ct, 0.0) if ct > 0 else np.inf
    return gram, sse, contrast, free


@njit(**JIT)
def censored_fits(stack: np.ndarray, sat_rows: np.ndarray, sat_cols: np.ndarray, tmpl: np.ndarray,
                  gram: np.ndarray, contrast: np.ndarray, sse: np.ndarray, saturated: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Each pattern's best summed squared residual (T,) over the point-spread functions
    and which function gives it (T,), the saturated pixels (`sat_rows`, `sat_cols` in
    `stack`) counted: such a pixel is at least `saturated`, so a fit below it there pays
    the shortfall squared, above it nothing. `gram`, `contrast`, `sse` from
    `pattern_fits`. The (function, pattern) pairs are completed in order of their fit
    without the saturated pixels, until none left can come in among the two best (the
    penalty only adds): those patterns' entries stay inf."""
    n_k, n_t = sse.shape
    n_s = sat_rows.shape[0]
    n_card = tmpl.shape[1]
    total = np.full(n_t, np.inf)
    best_k = np.zeros(n_t, np.intp)
    order = np.argsort(sse.ravel(), kind="mergesort")
    first_t, second_t = -1, -1
    first, second = np.inf, np.inf
    # per point-spread function, when first needed: the saturated pixels' channels, the
    # card's share of each pattern there (one product for all patterns)
    offcard = np.empty((n_k, n_s))
    printed = np.empty((n_k, n_t, n_s))
    ready = np.zeros(n_k, np.bool_)
    channels = np.empty((n_s, n_card))
    tmpl_t = np.ascontiguousarray(tmpl.T)
    for pair in order:
        k, t = pair // n_t, pair % n_t
        lower = sse[k, t]
        if not np.isfinite(lower) or lower >= second:
            break
        if not ready[k]:
            for s in range(n_s):
                px = stack[k, sat_rows[s], sat_cols[s]]
                offcard[k, s] = px[n_card]
                for c in range(n_card):
                    channels[s, c] = px[c]
            printed[k] = (channels @ tmpl_t).T
            ready[k] = True
        gk = gram[k]
        b = contrast[k, t]
        # the ink level and the background's with this pattern's contrast
        zu0 = zu1 = 0.0
        for c in range(n_card):
            zu0 += gk[0, 2 + c] * tmpl[t, c]
            zu1 += gk[1, 2 + c] * tmpl[t, c]
        r0, r1 = gk[0, -1] - b * zu0, gk[1, -1] - b * zu1
        a00, a01, a11 = gk[0, 0] + 1e-9, gk[0, 1], gk[1, 1] + 1e-9
        det = a00 * a11 - a01 * a01
        ink, beyond = (a11 * r0 - a01 * r1) / det, (a00 * r1 - a01 * r0) / det
        tot = lower
        card = printed[k, t]
        off = offcard[k]
        for s in range(n_s):
            short = saturated - (ink + beyond * off[s] + b * card[s])
            if short > 0.0:
                tot += short * short
        if tot < total[t]:
            total[t], best_k[t] = tot, k
            # the two best patterns so far (totals only fall)
            if t == first_t:
                first = tot
            elif tot < first:
                second_t, second, first_t, first = first_t, first, t, tot
            elif t == second_t or tot < second:
                second_t, second = t, tot
    return total, best_k


def warm_up() -> None:
    """Compile (or load from the cache) the kernels on tiny inputs, with the argument
    types the reader passes."""
    h = np.eye(3)
    card_side(h)
    card_pixels(np.zeros((4, 4), np.uint8), h, 0.06, 0.35, 0.3, True, 254.0)
    card_channels(h, 0, 0, 2, 2, 2, 3, 0.35, 0.3, np.zeros((4, 2)), 0.125)
    idx = np.zeros(3, np.intp)
    stack = np.ones((1, 2, 2, 11), np.float32)
    gram, sse, contrast, _ = pattern_fits(stack, idx, idx, np.arange(3.0), np.ones((2, 10)))
    censored_fits(stack, idx, idx, np.ones((2, 10)), gram, contrast, sse, 254.0)
