"""Compiled kernel of the verification (`verification`): the order statistics and
means of a card's samples, every proposal in one loop. Flags and conventions: `_numba`;
the numpy reference is in the verification tests."""

from __future__ import annotations

import numpy as np
from numba import njit

from app.core.detection._numba import JIT


@njit(**JIT)
def measure_stats(vals: np.ndarray, inside: np.ndarray, sorted_index: np.ndarray, bounds: np.ndarray,
                  stats_lo: np.ndarray, stats_hi: np.ndarray, stats_frac: np.ndarray, disc: np.ndarray,
                  edge: np.ndarray, core: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The measurements of `verification._measures_from` but the code cells, for samples
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


def warm_up() -> None:
    """Compile (or load from the cache) `measure_stats` on tiny inputs, with the
    argument types the verification passes."""
    index, stats = np.arange(5, dtype=np.intp), np.zeros(7, np.intp)
    measure_stats(np.ones((2, 5), np.float32), np.ones((2, 5), np.bool_), index, np.arange(6, dtype=np.intp), stats,
                  stats.copy(), np.zeros(7, np.float32), index[:4].reshape(4, 1).copy(), index[4:].copy(), index)
