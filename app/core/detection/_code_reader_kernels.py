"""Compiled kernel of the whole-card code reader (`code_reader`): the printed card's
channels over a patch of pixels, each pixel's footprint sub-sampled. Flags and
conventions: `_numba`; the numpy reference (`code_reader._labels`) is in the reader's
tests."""

from __future__ import annotations

import numpy as np
from numba import njit

from app.core.detection._numba import JIT


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
    out = np.zeros((height, width, n2 + 2), np.float32)
    step = size / n
    r2 = radius * radius
    w = np.float32(1.0 / (sub * sub))
    for py in range(height):
        for px in range(width):
            for j in range(sub):
                y = y0 + py - 0.5 + (j + 0.5) / sub
                for i in range(sub):
                    x = x0 + px - 0.5 + (i + 0.5) / sub
                    d = hinv[2, 0] * x + hinv[2, 1] * y + hinv[2, 2]
                    u = (hinv[0, 0] * x + hinv[0, 1] * y + hinv[0, 2]) / d
                    v = (hinv[1, 0] * x + hinv[1, 1] * y + hinv[1, 2]) / d
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
                    out[py, px, label] += w
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
    gram = np.zeros((n_k, d, d))
    sse = np.empty((n_k, n_t))
    contrast = np.empty((n_k, n_t))
    free = np.empty(n_k)
    w = np.empty(d)
    for k in range(n_k):
        gk = gram[k]
        for p in range(rows.shape[0]):
            px = stack[k, rows[p], cols[p]]
            w[0] = 1.0
            w[1] = px[n_card]
            for c in range(n_card):
                w[2 + c] = px[c]
            w[d - 1] = y[p]
            for i in range(d):
                wi = w[i]
                for j in range(i, d):
                    gk[i, j] += wi * w[j]
        for i in range(d):
            for j in range(i):
                gk[i, j] = gk[j, i]
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
        ridge = np.ascontiguousarray(gcc.copy())
        scale = 0.0
        for i in range(n_card):
            scale += gcc[i, i]
        for i in range(n_card):
            ridge[i, i] += 1e-9 * scale / n_card + 1e-9
        x = np.linalg.solve(ridge, gcy)
        free[k] = max(yy - np.dot(gcy, x), 0.0)
        for t in range(n_t):
            lin = 0.0
            quad = 0.0
            for i in range(n_card):
                vi = tmpl[t, i]
                if vi == 0.0:
                    continue
                lin += vi * gcy[i]
                row = 0.0
                for j in range(n_card):
                    row += gcc[i, j] * tmpl[t, j]
                quad += vi * row
            ct = lin / quad
            contrast[k, t] = ct
            sse[k, t] = max(yy - lin * ct, 0.0) if ct > 0 else np.inf
    return gram, sse, contrast, free


@njit(**JIT)
def region(hinv: np.ndarray, x0: int, y0: int, width: int, height: int, margin: float) -> np.ndarray:
    """Which pixels (x0 .. x0 + width - 1, y0 .. y0 + height - 1) have their centres on the
    card at least `margin` (card units) inside its edges; `hinv` maps pixels to card
    units. Returns (height, width) bool."""
    out = np.zeros((height, width), np.bool_)
    for py in range(height):
        y = float(y0 + py)
        for px in range(width):
            x = float(x0 + px)
            d = hinv[2, 0] * x + hinv[2, 1] * y + hinv[2, 2]
            u = (hinv[0, 0] * x + hinv[0, 1] * y + hinv[0, 2]) / d
            v = (hinv[1, 0] * x + hinv[1, 1] * y + hinv[1, 2]) / d
            out[py, px] = margin <= u <= 1.0 - margin and margin <= v <= 1.0 - margin
    return out


def warm_up() -> None:
    """Compile (or load from the cache) the kernels on tiny inputs, with the argument
    types the reader passes."""
    card_channels(np.eye(3), 0, 0, 2, 2, 2, 3, 0.35, 0.3, np.zeros((4, 2)), 0.125)
    region(np.eye(3), 0, 0, 2, 2, 0.06)
    idx = np.zeros(3, np.intp)
    pattern_fits(np.ones((1, 2, 2, 11), np.float32), idx, idx, np.arange(3.0), np.ones((2, 10)))
