"""Compiled (numba) kernels of the bundle adjustment with feature points (`bundle`):
the feature observations' normal equations, and eliminating the feature points from them.

Each observation adds a few tiny (6x6, 6x3, 3x3) products, and eliminating a point seen
in k frames adds k^2 6x6 blocks to the reduced system: hundreds of thousands of tiny
products for a survey with thousands of feature points, which numpy can only batch
through temporaries several times the size of the result. One loop over the
observations, and one over the points, does each in place. Flags as the detector's
kernels (`app.core.detection._numba`): cached, ``nogil``, ``error_model="numpy"``, no
``fastmath``; `warm_up` compiles the kernels (or loads them from the cache).
"""

from __future__ import annotations

import numpy as np
from numba import njit

_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**_JIT)
def _intrinsics_schur(j: int, Wj: np.ndarray, H: np.ndarray, g: np.ndarray, C_i: np.ndarray, g_p: np.ndarray,
                      CW: np.ndarray) -> None:
    """Point j's Schur complement on the intrinsics' rows (0 .. n_intr - 1 of ``H`` and
    ``g``), in place; leaves C_j W_j^-1 in ``CW`` (n_intr, 3)."""
    n_intr = C_i.shape[1]
    for m in range(n_intr):
        for t in range(3):
            CW[m, t] = C_i[j, m, 0] * Wj[0, t] + C_i[j, m, 1] * Wj[1, t] + C_i[j, m, 2] * Wj[2, t]
    for m in range(n_intr):
        g[m] -= CW[m, 0] * g_p[j, 0] + CW[m, 1] * g_p[j, 1] + CW[m, 2] * g_p[j, 2]
        for q in range(n_intr):
            H[m, q] -= CW[m, 0] * C_i[j, q, 0] + CW[m, 1] * C_i[j, q, 1] + CW[m, 2] * C_i[j, q, 2]


@njit(**_JIT)
def _coupling(a: int, Wj: np.ndarray, F_c: np.ndarray, G: np.ndarray) -> None:
    """G = F_a W_j^-1 (6, 3), in place."""
    for i in range(6):
        for t in range(3):
            G[i, t] = F_c[a, i, 0] * Wj[0, t] + F_c[a, i, 1] * Wj[1, t] + F_c[a, i, 2] * Wj[2, t]


@njit(**_JIT)
def _point_terms(a: int, H: np.ndarray, g: np.ndarray, W: np.ndarray, g_p: np.ndarray, F_c: np.ndarray,
                 C_i: np.ndarray, J_c: np.ndarray, J_i: np.ndarray, J_p: np.ndarray, w: np.ndarray, r: np.ndarray,
                 op: np.ndarray) -> None:
    """Feature observation a's terms that do not depend on where its camera is stored:
    its camera-point coupling ``F_c[a]``, its point's block and gradient, and the
    intrinsics' own rows (0 .. n_intr - 1 of ``H`` and ``g``) and point coupling."""
    n_intr = J_i.shape[2]
    wa = w[a]
    j = op[a]
    for i in range(6):
        for t in range(3):
            F_c[a, i, t] = wa * (J_c[a, 0, i] * J_p[a, 0, t] + J_c[a, 1, i] * J_p[a, 1, t])
    for s in range(3):
        g_p[j, s] += wa * (J_p[a, 0, s] * r[a, 0] + J_p[a, 1, s] * r[a, 1])
        for t in range(3):
            W[j, s, t] += wa * (J_p[a, 0, s] * J_p[a, 0, t] + J_p[a, 1, s] * J_p[a, 1, t])
    for m in range(n_intr):
        g[m] += wa * (J_i[a, 0, m] * r[a, 0] + J_i[a, 1, m] * r[a, 1])
        for t in range(3):
            C_i[j, m, t] += wa * (J_i[a, 0, m] * J_p[a, 0, t] + J_i[a, 1, m] * J_p[a, 1, t])
        for q in range(n_intr):
            H[m, q] += wa * (J_i[a, 0, m] * J_i[a, 0, q] + J_i[a, 1, m] * J_i[a, 1, q])


@njit(**_JIT)
def eliminate_points(H: np.ndarray, g: np.ndarray, W_inv: np.ndarray, F_c: np.ndarray, C_i: np.ndarray,
                     g_p: np.ndarray, by_point: np.ndarray, bounds: np.ndarray, col: np.ndarray) -> None:
    """Subtract every feature point's Schur complement from the reduced system, in place.

    For point j with block W_j, camera couplings F_a (6x3, one per observation a),
    intrinsics coupling C_j (n_intr x 3) and gradient g_j: H -= B W_j^-1 B^T and
    g -= B W_j^-1 g_j, B being the point's column of couplings at the cameras' and the
    intrinsics' rows (intrinsics first, at rows 0 .. n_intr - 1).

    ``H`` (n, n), ``g`` (n,); ``W_inv`` (P, 3, 3) the (damped) blocks' inverses; ``F_c``
    (K, 6, 3); ``C_i`` (P, n_intr, 3); ``g_p`` (P, 3); ``by_point`` (K,) the observations
    sorted by point, point j's at ``by_point[bounds[j]:bounds[j + 1]]``; ``col`` (K,)
    each observation's camera's first row, -1 for the held camera (not in the system).
    """
    n_intr = C_i.shape[1]
    G = np.empty((6, 3))
    CW = np.empty((n_intr, 3))
    for j in range(W_inv.shape[0]):
        Wj = W_inv[j]
        _intrinsics_schur(j, Wj, H, g, C_i, g_p, CW)
        for ia in range(bounds[j], bounds[j + 1]):
            a = by_point[ia]
            ca = col[a]
            if ca < 0:
                continue
            _coupling(a, Wj, F_c, G)
            for i in range(6):
                g[ca + i] -= G[i, 0] * g_p[j, 0] + G[i, 1] * g_p[j, 1] + G[i, 2] * g_p[j, 2]
                for m in range(n_intr):
                    v = G[i, 0] * C_i[j, m, 0] + G[i, 1] * C_i[j, m, 1] + G[i, 2] * C_i[j, m, 2]
                    H[ca + i, m] -= v
                    H[m, ca + i] -= v
            for ib in range(bounds[j], bounds[j + 1]):
                b = by_point[ib]
                cb = col[b]
                if cb < 0:
                    continue
                for i in range(6):
                    for k in range(6):
                        H[ca + i, cb + k] -= G[i, 0] * F_c[b, k, 0] + G[i, 1] * F_c[b, k, 1] + G[i, 2] * F_c[b, k, 2]


@njit(**_JIT)
def add_observations(H: np.ndarray, g: np.ndarray, W: np.ndarray, g_p: np.ndarray, F_c: np.ndarray,
                     C_i: np.ndarray, J_c: np.ndarray, J_i: np.ndarray, J_p: np.ndarray, w: np.ndarray,
                     r: np.ndarray, col: np.ndarray, op: np.ndarray) -> None:
    """Add every feature observation's terms to the normal equations, in place.

    Observation a (Jacobians ``J_c`` (K, 2, 6) over its camera, ``J_i`` (K, 2, n_intr)
    over the intrinsics, ``J_p`` (K, 2, 3) over its point ``op[a]``; weight ``w[a]``;
    residual ``r[a]`` (2,)) adds J^T w J and J^T w r to the camera's block and the
    intrinsics' (``H`` (n, n), ``g`` (n,): intrinsics at rows 0 .. n_intr - 1, the camera
    at ``col[a]``, none for -1, the held camera) and to its point's (``W`` (P, 3, 3),
    ``g_p`` (P, 3)), and sets its couplings: ``F_c[a]`` = J_c^T w J_p (6, 3), and adds
    J_i^T w J_p to ``C_i[op[a]]`` (n_intr, 3).
    """
    n_intr = J_i.shape[2]
    for a in range(J_c.shape[0]):
        _point_terms(a, H, g, W, g_p, F_c, C_i, J_c, J_i, J_p, w, r, op)
        wa = w[a]
        c = col[a]
        if c < 0:
            continue
        for i in range(6):
            g[c + i] += wa * (J_c[a, 0, i] * r[a, 0] + J_c[a, 1, i] * r[a, 1])
            for k in range(6):
                H[c + i, c + k] += wa * (J_c[a, 0, i] * J_c[a, 0, k] + J_c[a, 1, i] * J_c[a, 1, k])
            for m in range(n_intr):
                v = wa * (J_c[a, 0, i] * J_i[a, 0, m] + J_c[a, 1, i] * J_i[a, 1, m])
                H[c + i, m] += v
                H[m, c + i] += v


# --- the same over a block-sparse reduced system ------------------------------------------
#
# x = [border, cameras]: the border (intrinsics, then the discs: n_y columns) is kept dense
# over every row (``Hy`` (n, n_y): the border-border block, and the camera-border block
# below it; the border-camera block above is its transpose, not stored); the camera-camera
# block is kept as 6x6 blocks over the pairs of cameras that share a feature point
# (``blocks`` (nnzb, 6, 6), block row ``f`` at ``indices[indptr[f]:indptr[f + 1]]``, the
# block columns sorted; both (f, h) and (h, f) are stored). Cameras are numbered here
# among the free ones (``fcam``: -1 for the held camera); camera f's first row is
# n_y + 6 f.


@njit(**_JIT)
def _block(indptr: np.ndarray, indices: np.ndarray, f: int, h: int) -> int:
    """The index of block (f, h) in the block-sparse storage (binary search in row f)."""
    lo, hi = indptr[f], indptr[f + 1]
    while lo < hi:
        mid = (lo + hi) >> 1
        if indices[mid] < h:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(**_JIT)
def camera_pairs(cam_ptr: np.ndarray, cam_points: np.ndarray, by_point: np.ndarray, bounds: np.ndarray,
                 fcam: np.ndarray, n_free: int) -> tuple[np.ndarray, np.ndarray]:
    """The block pattern of the camera-camera block: (indptr (n_free + 1,), indices),
    each free camera's diagonal block and a block with every free camera that shares a
    feature point with it, sorted.

    ``cam_ptr`` (n_free + 1,), ``cam_points``: the feature points seen by each free camera
    (free camera f's at ``cam_points[cam_ptr[f]:cam_ptr[f + 1]]``); ``by_point``,
    ``bounds``, ``fcam`` as in `eliminate_points_sparse`.
    """
    mark = np.full(n_free, -1)
    counts = np.zeros(n_free + 1, np.int64)
    for f in range(n_free):
        mark[f] = f
        c = 1
        for q in range(cam_ptr[f], cam_ptr[f + 1]):
            j = cam_points[q]
            for ib in range(bounds[j], bounds[j + 1]):
                h = fcam[by_point[ib]]
                if h >= 0 and mark[h] != f:
                    mark[h] = f
                    c += 1
        counts[f + 1] = c
    indptr = np.cumsum(counts)
    indices = np.empty(indptr[-1], np.int64)
    mark[:] = -1
    for f in range(n_free):
        k = indptr[f]
        mark[f] = f
        indices[k] = f
        k += 1
        for q in range(cam_ptr[f], cam_ptr[f + 1]):
            j = cam_points[q]
            for ib in range(bounds[j], bounds[j + 1]):
                h = fcam[by_point[ib]]
                if h >= 0 and mark[h] != f:
                    mark[h] = f
                    indices[k] = h
                    k += 1
        indices[indptr[f] : indptr[f + 1]].sort()
    return indptr, indices


@njit(**_JIT)
def add_observations_sparse(Hy: np.ndarray, blocks: np.ndarray, indptr: np.ndarray, indices: np.ndarray,
                            g: np.ndarray, W: np.ndarray, g_p: np.ndarray, F_c: np.ndarray, C_i: np.ndarray,
                            J_c: np.ndarray, J_i: np.ndarray, J_p: np.ndarray, w: np.ndarray, r: np.ndarray,
                            fcam: np.ndarray, op: np.ndarray) -> None:
    """`add_observations` into the block-sparse system: the intrinsics' terms into ``Hy``
    (rows 0 .. n_intr - 1 and, for the camera-intrinsics coupling, the camera's rows),
    each camera's own block into its diagonal block."""
    n_intr = J_i.shape[2]
    n_y = Hy.shape[1]
    for a in range(J_c.shape[0]):
        _point_terms(a, Hy, g, W, g_p, F_c, C_i, J_c, J_i, J_p, w, r, op)
        wa = w[a]
        f = fcam[a]
        if f < 0:
            continue
        c = n_y + 6 * f
        d = _block(indptr, indices, f, f)
        for i in range(6):
            g[c + i] += wa * (J_c[a, 0, i] * r[a, 0] + J_c[a, 1, i] * r[a, 1])
            for k in range(6):
                blocks[d, i, k] += wa * (J_c[a, 0, i] * J_c[a, 0, k] + J_c[a, 1, i] * J_c[a, 1, k])
            for m in range(n_intr):
                Hy[c + i, m] += wa * (J_c[a, 0, i] * J_i[a, 0, m] + J_c[a, 1, i] * J_i[a, 1, m])


@njit(**_JIT)
def eliminate_points_sparse(Hy: np.ndarray, blocks: np.ndarray, indptr: np.ndarray, indices: np.ndarray,
                            g: np.ndarray, W_inv: np.ndarray, F_c: np.ndarray, C_i: np.ndarray, g_p: np.ndarray,
                            by_point: np.ndarray, bounds: np.ndarray, fcam: np.ndarray) -> None:
    """`eliminate_points` into the block-sparse system, in place (``fcam``: each
    observation's free camera, -1 for the held one)."""
    n_intr = C_i.shape[1]
    n_y = Hy.shape[1]
    G = np.empty((6, 3))
    CW = np.empty((n_intr, 3))
    for j in range(W_inv.shape[0]):
        Wj = W_inv[j]
        _intrinsics_schur(j, Wj, Hy, g, C_i, g_p, CW)
        for ia in range(bounds[j], bounds[j + 1]):
            a = by_point[ia]
            fa = fcam[a]
            if fa < 0:
                continue
            ca = n_y + 6 * fa
            _coupling(a, Wj, F_c, G)
            for i in range(6):
                g[ca + i] -= G[i, 0] * g_p[j, 0] + G[i, 1] * g_p[j, 1] + G[i, 2] * g_p[j, 2]
                for m in range(n_intr):
                    Hy[ca + i, m] -= G[i, 0] * C_i[j, m, 0] + G[i, 1] * C_i[j, m, 1] + G[i, 2] * C_i[j, m, 2]
            for ib in range(bounds[j], bounds[j + 1]):
                b = by_point[ib]
                fb = fcam[b]
                if fb < 0:
                    continue
                k = _block(indptr, indices, fa, fb)
                for i in range(6):
                    for l in range(6):
                        blocks[k, i, l] -= G[i, 0] * F_c[b, l, 0] + G[i, 1] * F_c[b, l, 1] + G[i, 2] * F_c[b, l, 2]


@njit(**_JIT)
def add_discs_sparse(Hy: np.ndarray, blocks: np.ndarray, indptr: np.ndarray, indices: np.ndarray, g: np.ndarray,
                     J_c: np.ndarray, J_i: np.ndarray, J_p: np.ndarray, w: np.ndarray, r: np.ndarray,
                     fcam: np.ndarray, op: np.ndarray) -> None:
    """The disc observations' normal equations into the block-sparse system, in place:
    their points are in the border (columns n_intr + 3 ``op[a]``), not eliminated;
    arguments as `add_observations_sparse`."""
    n_intr = J_i.shape[2]
    n_y = Hy.shape[1]
    for a in range(J_c.shape[0]):
        wa = w[a]
        q0 = n_intr + 3 * op[a]
        f = fcam[a]
        for m in range(n_intr):
            g[m] += wa * (J_i[a, 0, m] * r[a, 0] + J_i[a, 1, m] * r[a, 1])
            for q in range(n_intr):
                Hy[m, q] += wa * (J_i[a, 0, m] * J_i[a, 0, q] + J_i[a, 1, m] * J_i[a, 1, q])
            for t in range(3):
                v = wa * (J_i[a, 0, m] * J_p[a, 0, t] + J_i[a, 1, m] * J_p[a, 1, t])
                Hy[m, q0 + t] += v
                Hy[q0 + t, m] += v
        for s in range(3):
            g[q0 + s] += wa * (J_p[a, 0, s] * r[a, 0] + J_p[a, 1, s] * r[a, 1])
            for t in range(3):
                Hy[q0 + s, q0 + t] += wa * (J_p[a, 0, s] * J_p[a, 0, t] + J_p[a, 1, s] * J_p[a, 1, t])
        if f < 0:
            continue
        c = n_y + 6 * f
        d = _block(indptr, indices, f, f)
        for i in range(6):
            g[c + i] += wa * (J_c[a, 0, i] * r[a, 0] + J_c[a, 1, i] * r[a, 1])
            for k in range(6):
                blocks[d, i, k] += wa * (J_c[a, 0, i] * J_c[a, 0, k] + J_c[a, 1, i] * J_c[a, 1, k])
            for m in range(n_intr):
                Hy[c + i, m] += wa * (J_c[a, 0, i] * J_i[a, 0, m] + J_c[a, 1, i] * J_i[a, 1, m])
            for t in range(3):
                Hy[c + i, q0 + t] += wa * (J_c[a, 0, i] * J_p[a, 0, t] + J_c[a, 1, i] * J_p[a, 1, t])


def warm_up() -> None:
    """Compile (or load from the cache) every kernel on tiny inputs, with the argument
    types the bundle adjustment passes."""
    H, g = np.zeros((11, 11)), np.zeros(11)
    W_inv = np.broadcast_to(np.eye(3), (1, 3, 3)).copy()
    F_c = np.ones((2, 6, 3))
    idx = np.arange(2)
    C_i, g_p = np.ones((1, 5, 3)), np.ones((1, 3))
    eliminate_points(H, g, W_inv, F_c, C_i, g_p, idx, np.array([0, 2]), idx * 0 + 5)
    for n_intr in (5, 0):
        add_observations(H, g, W_inv.copy(), g_p, F_c, C_i[:, :n_intr].copy(), np.ones((2, 2, 6)),
                         np.ones((2, 2, n_intr)), np.ones((2, 2, 3)), np.ones(2), np.ones((2, 2)), idx * 0 + 5, idx * 0)
        eliminate_points(H, g, W_inv, F_c, C_i[:, :n_intr].copy(), g_p, idx, np.array([0, 2]), idx * 0 + 5)
    # The block-sparse kernels: two free cameras seeing one point.
    fcam, bounds = idx.copy(), np.array([0, 2])
    indptr, indices = camera_pairs(np.array([0, 1, 2]), np.zeros(2, np.int64), idx, bounds, fcam, 2)
    blocks, Hy = np.zeros((len(indices), 6, 6)), np.zeros((5 + 12, 5))
    for n_intr in (5, 0):
        add_observations_sparse(Hy, blocks, indptr, indices, np.zeros(17), W_inv.copy(), g_p, F_c,
                                C_i[:, :n_intr].copy(), np.ones((2, 2, 6)), np.ones((2, 2, n_intr)), np.ones((2, 2, 3)),
                                np.ones(2), np.ones((2, 2)), fcam, idx * 0)
        eliminate_points_sparse(Hy, blocks, indptr, indices, np.zeros(17), W_inv, F_c, C_i[:, :n_intr].copy(), g_p,
                                idx, bounds, fcam)
        add_discs_sparse(np.zeros((8 + 12, 8)), blocks, indptr, indices, np.zeros(20), np.ones((2, 2, 6)),
                         np.ones((2, 2, n_intr)), np.ones((2, 2, 3)), np.ones(2), np.ones((2, 2)), fcam, idx * 0)
