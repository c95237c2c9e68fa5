"""Compiled kernel of the subpixel refinement (`refinement`): one centroid step of
every disc, its window, white ring, black level and darkness-weighted centroid in one
loop. Flags and conventions: `_numba`; the numpy reference is in the refinement tests."""

from __future__ import annotations

import numpy as np
from numba import njit

from app.core.detection._numba import JIT, pairwise_sum


@njit(**JIT)
def centroid_step(img: np.ndarray, centroid: np.ndarray, jac: np.ndarray, reach: float, disc_radius: float,
                  ring2: np.ndarray, inner2: np.float32, taper_gain: np.float32, white: np.ndarray,
                  measure_white: bool, new: np.ndarray, total: np.ndarray, contrast: np.ndarray) -> None:
    """`refinement._centroid_step` for D discs, fused: per disc, the window of (2k + 1)^2
    pixels around its rounded centroid (k from the largest extent of all D), the
    distance of each pixel from the centroid in disc radii on the card (float32, via
    the inverse Jacobian), the white level (median of the ring `ring2` = (lo^2, hi^2)
    when `measure_white`, else `white` as given; written back into `white`), the black
    level (mean inside `inner2`) and the tapered darkness-weighted centroid.

    centroid (D, 2), jac (D, 2, 2) float64 in the pixels of `img`; outputs (D, 2) new
    centroids, (D,) summed darkness (0 where the centroid did not move) and white -
    black. Every float step is the numpy expression's, in its order; sums of float32
    arrays follow numpy's (`pairwise_sum` along a row, sequential down the columns);
    pixels outside the image take no part (their weights are 0, as the reference's
    mask makes them)."""
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


def warm_up() -> None:
    """Compile (or load from the cache) `centroid_step` on tiny inputs, measuring the
    white ring and given it, as refinement calls it."""
    img = np.zeros((8, 8), np.uint8)
    centroid, jac = np.full((1, 2), 3.0), np.eye(2).reshape(1, 2, 2) * 8.0
    new, total, contrast = np.empty((1, 2)), np.empty(1), np.empty(1)
    for measure in (True, False):
        centroid_step(img, centroid, jac, 1.2, 0.125, np.array([1.3, 2.0], np.float32), np.float32(0.25),
                      np.float32(10.0), np.zeros(1), measure, new, total, contrast)
