"""Card homographies (app.core.geometry.homography): the fast path for a few
quadrilaterals gives exactly what the vectorised one does, and the compiled point
kernels (`_kernels.jacobians`, `_kernels.ellipse_centres`) exactly what the numpy
broadcasts give."""

from __future__ import annotations

import numpy as np

from app.core.geometry import homography as hg
from app.core.markers import DISC_CENTRES, DISC_RADIUS


def test_homographies_of_a_few_quadrilaterals_match_the_vectorised_path() -> None:
    rng = np.random.default_rng(9)
    q = rng.uniform(-50, 700, (4 * hg._FEW, 4, 2))
    q[0] = [[0, 0], [1, 0], [2, 0], [3, 0]]  # collinear: the guarded denominator
    q[1, 2] = np.nan
    q[2] = q[2, :1]  # all on one spot
    with np.errstate(invalid="ignore"):
        many = hg.homographies(q)  # more than _FEW: vectorised
        for start in range(0, q.shape[0], hg._FEW):
            few = hg.homographies(q[start : start + hg._FEW])  # Python floats
            assert np.array_equal(few, many[start : start + hg._FEW], equal_nan=True)


def _reference_jacobians(hs: np.ndarray, pts: np.ndarray) -> np.ndarray:
    x = hs[:, None, :, 0] * pts[None, :, 0, None] + hs[:, None, :, 1] * pts[None, :, 1, None] + hs[:, None, :, 2]
    w = x[..., 2, None, None]  # (P, K, 1, 1)
    return (hs[:, None, :2, :2] - x[..., :2, None] / w * hs[:, None, None, 2, :2]) / w


def _reference_ellipse_centres(hs: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
    gh = hs[:, None, 2, :2]  # (P, 1, 2)
    w = gh[..., 0] * centres[None, :, 0] + gh[..., 1] * centres[None, :, 1] + hs[:, 2, 2, None]  # (P, K)
    w = np.where(np.abs(w) > 1e-12, w, 1e-12)
    k = (radius * radius) / w
    p = centres[None] - k[..., None] * gh  # (P, K, 2) the poles on the card
    x = hs[:, None, :, 0] * p[..., 0, None] + hs[:, None, :, 1] * p[..., 1, None] + hs[:, None, :, 2]  # (P, K, 3)
    z = x[..., 2:]
    z = np.where(np.abs(z) > 1e-12, z, 1e-12)
    return x[..., :2] / z


def test_homography_point_kernels_match_numpy() -> None:
    """`jacobians` and `ellipse_centres` (through `homography.jacobians`,
    `homography.ellipse_centres`) against the numpy broadcasts, on the homographies of
    random quadrilaterals, degenerate ones and non-finite entries included."""
    rng = np.random.default_rng(7)
    for trial in range(40):
        p = int(rng.integers(0, 12))
        quads = rng.uniform(0, 640, (p, 4, 2))
        if trial % 4 == 1 and p:
            quads[0] = quads[0, :1]  # all four corners at one point
        hs = hg.homographies(quads)
        if trial % 4 == 2 and p:
            hs[0, 2, :2] = 0.0
            hs[0, 2, 2] = 0.0
        if trial % 4 == 3 and p:
            hs[-1, 1, 1] = np.nan
        pts = rng.uniform(-1, 2, (int(rng.integers(1, 6)), 2))
        with np.errstate(all="ignore"):
            for card in (pts, DISC_CENTRES):
                got, expected = hg.jacobians(hs, card), _reference_jacobians(hs, card)
                assert got.shape == expected.shape
                np.testing.assert_array_equal(got, expected)
                got = hg.ellipse_centres(hs, card, DISC_RADIUS)
                expected = _reference_ellipse_centres(hs, card, DISC_RADIUS)
                assert got.shape == expected.shape
                np.testing.assert_array_equal(got, expected)
