"""Compiled (numba) kernels of the card homographies (`homography`): one fused loop per
stack of homographies instead of numpy broadcasts over small arrays, with the same
arithmetic operation for operation (the homography tests hold the numpy references).
Flags: cached, ``nogil``, ``error_model="numpy"`` (a division by zero gives inf/NaN and
the loops vectorise), no ``fastmath`` (it would reorder the arithmetic); `warm_up`
compiles them (or loads them from the cache) once at start-up."""

from __future__ import annotations

import numpy as np
from numba import njit

_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**_JIT)
def jacobians(hs: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(P, K, 2, 2) Jacobians d(image)/d(card) of each homography `hs` (P, 3, 3) at the
    card points `pts` (K, 2) (`homography.jacobians`): with x = H (px, py, 1) and w = x[2],
    row r is (H[r, :2] - x[r] / w * H[2, :2]) / w, operation for operation as the numpy
    broadcasts compute it."""
    p, k = hs.shape[0], pts.shape[0]
    out = np.empty((p, k, 2, 2))
    for i in range(p):
        h = hs[i]
        for j in range(k):
            px, py = pts[j, 0], pts[j, 1]
            x0 = h[0, 0] * px + h[0, 1] * py + h[0, 2]
            x1 = h[1, 0] * px + h[1, 1] * py + h[1, 2]
            w = h[2, 0] * px + h[2, 1] * py + h[2, 2]
            a0, a1 = x0 / w, x1 / w
            out[i, j, 0, 0] = (h[0, 0] - a0 * h[2, 0]) / w
            out[i, j, 0, 1] = (h[0, 1] - a0 * h[2, 1]) / w
            out[i, j, 1, 0] = (h[1, 0] - a1 * h[2, 0]) / w
            out[i, j, 1, 1] = (h[1, 1] - a1 * h[2, 1]) / w
    return out


@njit(**_JIT)
def ellipse_centres(hs: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
    """(P, K, 2) centres of the image ellipses of card circles (`centres` (K, 2),
    `radius`) under each homography `hs` (P, 3, 3) (`homography.ellipse_centres`): the
    image of the pole ``c - radius**2 (g, h) / (g cx + h cy + 1)``, each |denominator|
    not above 1e-12 (or NaN) replaced by 1e-12, operation for operation as the numpy
    code."""
    p, k = hs.shape[0], centres.shape[0]
    out = np.empty((p, k, 2))
    r2 = radius * radius
    for i in range(p):
        h = hs[i]
        g0, g1 = h[2, 0], h[2, 1]
        for j in range(k):
            cx, cy = centres[j, 0], centres[j, 1]
            w = g0 * cx + g1 * cy + h[2, 2]
            if not abs(w) > 1e-12:
                w = 1e-12
            kk = r2 / w
            qx, qy = cx - kk * g0, cy - kk * g1
            x0 = h[0, 0] * qx + h[0, 1] * qy + h[0, 2]
            x1 = h[1, 0] * qx + h[1, 1] * qy + h[1, 2]
            z = h[2, 0] * qx + h[2, 1] * qy + h[2, 2]
            if not abs(z) > 1e-12:
                z = 1e-12
            out[i, j, 0] = x0 / z
            out[i, j, 1] = x1 / z
    return out


def warm_up() -> None:
    """Compile (or load from the cache) both kernels on tiny inputs, for both the
    writable and the read-only card points (`markers.DISC_CENTRES` is read-only: numba
    types the two apart)."""
    hs = np.eye(3).reshape(1, 3, 3)
    pts = np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 5.0], [0.0, 5.0]])
    fixed = pts.copy()
    fixed.setflags(write=False)
    for card_pts in (pts, fixed):
        jacobians(hs, card_pts)
        ellipse_centres(hs, card_pts, 0.125)
