"""Compiled kernel of the card completion (`completion`): the points of a card guessed
as a parallelogram from three discs. Flags and conventions: `_numba`; the numpy
reference is in the completion tests."""

from __future__ import annotations

import numpy as np
from numba import njit

from app.core.detection._numba import JIT


@njit(**JIT)
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


def warm_up() -> None:
    """Compile (or load from the cache) `affine_points` on tiny inputs, with the
    argument types completion passes."""
    pts = np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 5.0], [0.0, 5.0]])
    affine_points(pts[:1], pts[1:2], pts[3:], pts, 8, 8)
