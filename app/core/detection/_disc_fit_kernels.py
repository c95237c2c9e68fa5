"""Compiled kernels of the disc fit (`disc_fit`): the smeared model of a disc's corner of
the card, its residuals and its normal equations, every pixel of every disc in one loop.
Flags and conventions: `_numba`. The numpy reference (the model and its Jacobian written
out as array operations) is in the disc fit's tests: the two agree to rounding, not to
the bit (the sums run in another order).

The parameters of each disc (``theta``, 10): the centre's offset (2), the white, the
disc's contrast, the background, the blur s, the two card edges' offsets and the smear
(2). ``ts`` are the points along the smear, as fractions of it, at which the printed card
is sampled; a single 0 is no smear.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from app.core.detection._numba import JIT

_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
_INV_SQRT_2 = 1.0 / math.sqrt(2.0)
#: Beyond this many blur widths from an edge, the blurred edge is flat (Phi is 0 or 1 to
#: 1e-12, its density below 1e-11).
_FLAT_Z = 7.0


@njit(**JIT)
def _cdf_pdf(z: float) -> tuple[float, float]:
    """The standard normal CDF Phi(z) and density phi(z), from one exponential:
    Abramowitz and Stegun 7.1.26 for erf (absolute error below 1.5e-7; Phi's below
    7.5e-8, a ten-thousandth of a grey level on the card's white)."""
    if z > _FLAT_Z:
        return 1.0, 0.0
    if z < -_FLAT_Z:
        return 0.0, 0.0
    pdf = math.exp(-0.5 * z * z) * _INV_SQRT_2PI
    x = abs(z) * _INV_SQRT_2
    t = 1.0 / (1.0 + 0.3275911 * x)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))))
    tail = 0.5 * poly * pdf / _INV_SQRT_2PI  # 0.5 erfc(x) = 0.5 poly exp(-x^2)
    return (1.0 - tail if z > 0.0 else tail), pdf


@njit(**JIT)
def _disc_distance(x0: float, x1: float, q00: float, q01: float, q11: float) -> tuple[float, float, float]:
    """Signed first-order distance of the point x (relative to the ellipse's centre) to
    the ellipse ``x^T Q x = 1`` (``(qq - sqrt(qq)) / |Q x|``), and its derivatives with
    respect to the centre's position."""
    g0 = q00 * x0 + q01 * x1
    g1 = q01 * x0 + q11 * x1
    qq = x0 * g0 + x1 * g1
    sq = math.sqrt(qq) + 1e-12
    gn = math.sqrt(g0 * g0 + g1 * g1) + 1e-12
    d = (qq - sq) / gn
    h0 = q00 * g0 + q01 * g1
    h1 = q01 * g0 + q11 * g1
    a = (2.0 - 1.0 / sq) / gn
    b = (qq - sq) / (gn * gn * gn)
    return d, -(a * g0 - b * h0), -(a * g1 - b * h1)


@njit(**JIT)
def _pixel(theta: np.ndarray, ts: np.ndarray, px: float, py: float, du: float, dv: float, m0: float, m1: float,
           q00: float, q01: float, q11: float, u0: float, u1: float, v0: float, v1: float,
           jac: np.ndarray, with_jacobian: bool) -> float:
    """The model's grey level at one pixel; its derivatives in `jac` (10) when asked."""
    s = theta[5]
    inv_s = 1.0 / s
    white, contrast, back = theta[2], theta[3], theta[4]
    step = white - back
    sm0, sm1 = theta[8], theta[9]
    n_t = ts.shape[0]
    scale = 1.0 / n_t
    ink = 0.0
    card = 0.0
    if with_jacobian:
        for k in range(10):
            jac[k] = 0.0
    for i in range(n_t):
        t = ts[i]
        d, dd0, dd1 = _disc_distance(px - (m0 + theta[0] + t * sm0), py - (m1 + theta[1] + t * sm1), q00, q01, q11)
        shift_u = t * (u0 * sm0 + u1 * sm1)  # an edge's distance moves by t n.v
        shift_v = t * (v0 * sm0 + v1 * sm1)
        zi = -d * inv_s
        zu = -(du - shift_u - theta[6]) * inv_s
        zv = -(dv - shift_v - theta[7]) * inv_s
        ik, gi = _cdf_pdf(zi)
        pu, gu = _cdf_pdf(zu)
        pv, gv = _cdf_pdf(zv)
        ink += ik
        card += pu * pv
        if with_jacobian:
            dink = -contrast * gi * scale  # d pred / d zi
            eu = step * pv * gu * scale  # d pred / d zu
            ev = step * pu * gv * scale  # d pred / d zv
            a0 = -dink * dd0 * inv_s
            a1 = -dink * dd1 * inv_s
            jac[0] += a0
            jac[1] += a1
            jac[5] -= (dink * zi + eu * zu + ev * zv) * inv_s  # z = -x / s: dz/ds = -z / s
            jac[6] += eu * inv_s
            jac[7] += ev * inv_s
            jac[8] += t * (a0 + (eu * u0 + ev * v0) * inv_s)  # the disc moves by t v, the edges by t n.v
            jac[9] += t * (a1 + (eu * u1 + ev * v1) * inv_s)
    ink *= scale
    card *= scale
    if with_jacobian:
        jac[2] = card
        jac[3] = -ink
        jac[4] = 1.0 - card
    # The disc lies inside the card: the blurred disc is subtracted from the blurred card.
    return back + card * step - contrast * ink


@njit(**JIT)
def normal_equations(px: np.ndarray, py: np.ndarray, wgt: np.ndarray, vals: np.ndarray, du: np.ndarray,
                     dv: np.ndarray, centres: np.ndarray, shapes: np.ndarray, edge_u: np.ndarray, edge_v: np.ndarray,
                     theta: np.ndarray, ts: np.ndarray, with_jacobian: bool
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each disc's weighted sum of squared residuals and, when asked, its normal
    equations ``J^T W J`` and ``J^T W r`` (r = observed - model).

    Pixel arrays are (n, K) (padding has weight 0); `centres` (n, 2) and `shapes`
    (n, 2, 2) are the discs' image ellipses, `edge_u`, `edge_v` (n, 2) the card edges'
    unit normals, `theta` (n, 10) the parameters.
    """
    n, k_max = px.shape
    cost = np.zeros(n)
    normal = np.zeros((n, 10, 10))
    rhs = np.zeros((n, 10))
    jac = np.zeros(10)
    for i in range(n):
        th = theta[i]
        m0, m1 = centres[i, 0], centres[i, 1]
        q00, q01, q11 = shapes[i, 0, 0], shapes[i, 0, 1], shapes[i, 1, 1]
        u0, u1, v0, v1 = edge_u[i, 0], edge_u[i, 1], edge_v[i, 0], edge_v[i, 1]
        for k in range(k_max):
            w = wgt[i, k]
            if w == 0.0:
                continue
            pred = _pixel(th, ts, px[i, k], py[i, k], du[i, k], dv[i, k], m0, m1, q00, q01, q11, u0, u1, v0, v1,
                          jac, with_jacobian)
            r = vals[i, k] - pred
            cost[i] += w * r * r
            if with_jacobian:
                for a in range(10):
                    wa = w * jac[a]
                    rhs[i, a] += wa * r
                    for b in range(a + 1):
                        normal[i, a, b] += wa * jac[b]
        if with_jacobian:
            for a in range(10):
                for b in range(a):
                    normal[i, b, a] = normal[i, a, b]
    return cost, normal, rhs


def warm_up() -> None:
    """Compile (or load from the cache) the kernels on tiny inputs, with the argument
    types the fit passes."""
    pixels = np.ones((1, 2))
    shape = np.eye(2).reshape(1, 2, 2)
    theta = np.zeros((1, 10))
    theta[0, 5] = 1.0
    for ts in (np.zeros(1), np.zeros(5)):
        for with_jacobian in (True, False):
            normal_equations(pixels, pixels, pixels, pixels, pixels, pixels, np.zeros((1, 2)), shape,
                             np.ones((1, 2)), np.ones((1, 2)), theta, ts, with_jacobian)
