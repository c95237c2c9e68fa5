"""Refinement (app.core.detection.refinement): subpixel disc centres on clean frames from
any start; and its compiled kernel (`_refinement_kernels.centroid_step`, with numpy's
pairwise sum `_numba.pairwise_sum`) against the numpy centroid step, bit for bit."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from app.core.detection import refinement as rf
from app.core.detection._numba import pairwise_sum
from app.core.geometry.homography import homographies
from app.core.markers import DISC_RADIUS


def test_subpixel_centres_on_clean_frames(clean_frames: list) -> None:
    rng = np.random.default_rng(4)
    errs = []
    for image, truth in clean_frames:
        for t in truth.targets:
            if not t.visible or t.disc_diameter_px < 8:
                continue
            start = t.discs_px + rng.uniform(-1.0, 1.0, (4, 2))
            start = np.roll(start, int(rng.integers(4)), axis=0)  # any starting disc
            refined, radii = rf.refine_centres(image, start[None])
            truth_rolled = np.roll(t.discs_px, 0, axis=0)
            # match each refined centre to its true disc
            d = np.hypot(*(refined[0][:, None, :] - truth_rolled[None]).transpose(2, 0, 1))
            errs.extend(d.min(axis=1).tolist())
            assert np.allclose(radii[0], t.disc_diameter_px / 2, rtol=0.15)
    errs = np.array(errs)
    assert errs.size >= 16
    rms = float(np.sqrt(np.mean(errs**2)))
    # about 0.003 px on this simulator, well inside the 0.1 px the detector is specified to
    assert rms <= 0.05, f"disc centre RMS {rms:.3f} px"


def test_refinement_given_its_homographies_is_the_same(clean_frames: list) -> None:
    image, truth = clean_frames[0]
    t = next(t for t in truth.targets if t.visible)
    start = t.discs_px[None] + np.random.default_rng(14).uniform(-1, 1, (1, 4, 2))
    a = rf.refine_centres(image, start)
    b = rf.refine_centres(image, start, _homographies=homographies(start))
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


# --------------------------------------------------------------------------------------
# The compiled kernel against the numpy centroid step: its window reader and ring
# median (`_windows_u8`, `_masked_median_u8`) checked against numpy first
# --------------------------------------------------------------------------------------


def _windows_u8(img: np.ndarray, x0: np.ndarray, y0: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The `size` x `size` pixel windows of `img` with top-left pixels (x0, y0) (D,):
    (D, size, size) uint8, and where they overhang the image (None if none does) a mask
    of the pixels inside, the others repeating the nearest edge pixel. A window inside
    is a view of the image: one fancy index of a strided view copies them all (cheaper
    than gathering flat pixel indices)."""
    h, w = img.shape
    xs, ys = x0.tolist(), y0.tolist()  # (a few: Python's min and max are cheaper)
    if xs and min(xs) >= 0 and min(ys) >= 0 and max(xs) + size <= w and max(ys) + size <= h:
        s0, s1 = img.strides
        shape, strides = (h - size + 1, w - size + 1, size, size), (s0, s1, s0, s1)
        if img.flags.c_contiguous:  # (np.ndarray on the buffer: as_strided costs ~4 us more)
            view = np.ndarray(shape, np.uint8, img, 0, strides)
        else:
            view = np.lib.stride_tricks.as_strided(img, shape, strides)
        return view[y0, x0], None
    offs = np.arange(size)
    xi = x0[:, None, None] + offs[None, None, :]  # (D, 1, S)
    yi = y0[:, None, None] + offs[None, :, None]  # (D, S, 1)
    valid = ((xi >= 0) & (xi < w)) & ((yi >= 0) & (yi < h))
    return img[np.clip(yi, 0, h - 1), np.clip(xi, 0, w - 1)], valid


def _masked_median_u8(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Median of each row of the uint8 `values` (D, K) where `mask` is set (NaN if
    none): from the rows' 256-bin histograms (one bincount), cheaper than sorting."""
    d = values.shape[0]
    key = values + np.arange(0, 256 * d, 256, dtype=np.intp)[:, None]  # row r: 256 r + value
    hist = np.bincount(key[mask], minlength=d * 256).reshape(d, 256)
    cum = hist.cumsum(axis=1)
    count = cum[:, -1]
    # sorted position q holds the smallest value v with cum[v] > q
    lo = (cum <= np.maximum((count - 1) // 2, 0)[:, None]).sum(axis=1)
    hi = (cum <= (count // 2)[:, None]).sum(axis=1)
    return np.where(count > 0, 0.5 * (lo.astype(np.float64) + hi), np.nan)




def test_masked_median_u8_matches_numpy() -> None:
    rng = np.random.default_rng(10)
    values = rng.integers(0, 256, (40, 90)).astype(np.uint8)
    mask = rng.uniform(size=values.shape) < rng.uniform(0, 1, (40, 1))
    mask[0] = False
    got = _masked_median_u8(values, mask)
    assert np.isnan(got[0])
    for r in range(1, 40):
        if mask[r].any():
            assert got[r] == np.median(values[r][mask[r]])


def test_windows_inside_and_overhanging_the_image_read_the_same_pixels() -> None:
    rng = np.random.default_rng(13)
    img = rng.integers(0, 256, (60, 80)).astype(np.uint8)
    size = 9
    for x0, y0 in ((np.array([0, 10, 71]), np.array([0, 20, 51])), (np.array([-3, 40, 75]), np.array([5, -2, 58]))):
        got, valid = _windows_u8(img, x0, y0, size)
        offs = np.arange(size)
        xi, yi = x0[:, None, None] + offs[None, None, :], y0[:, None, None] + offs[None, :, None]
        assert np.array_equal(got, img[np.clip(yi, 0, 59), np.clip(xi, 0, 79)])
        inside = (xi >= 0) & (xi < 80) & (yi >= 0) & (yi < 60)
        assert (valid is None and inside.all()) or np.array_equal(valid, inside)


def _reference_centroid_step(img: np.ndarray, centroid: np.ndarray, jac: np.ndarray, reach: float,
                             white: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    t = centroid.shape[0]
    f32 = np.float32
    j00, j01, j10, j11 = jac[..., 0, 0], jac[..., 0, 1], jac[..., 1, 0], jac[..., 1, 1]
    det = j00 * j11 - j01 * j10
    s = 1.0 / (det * DISC_RADIUS)
    a = (np.array([j11, -j01, -j10, j00]) * s).astype(f32)[..., None, None]
    ext = reach * DISC_RADIUS * np.sqrt((jac * jac).sum(axis=-1).max(axis=-1))
    k = int(np.ceil(ext.max())) + 1
    size = 2 * k + 1
    base = np.rint(centroid).astype(np.intp)
    pix8, valid = _windows_u8(img, base[..., 0].ravel() - k, base[..., 1].ravel() - k, size)
    pix8 = pix8.reshape(t, 4, size, size)
    if valid is not None:
        valid = valid.reshape(t, 4, size, size)
    offs = np.arange(-k, k + 1).astype(f32)
    off = (base - centroid).astype(f32)
    dx = off[..., 0, None, None] + offs[None, None, None, :]
    dy = off[..., 1, None, None] + offs[None, None, :, None]
    u = a[0] * dx + a[1] * dy
    v = a[2] * dx + a[3] * dy
    rho2 = u * u + v * v
    if white is None:
        ring = (rho2 >= f32(rf.REFINE_RING[0] ** 2)) & (rho2 <= f32(rf.REFINE_RING[1] ** 2))
        if valid is not None:
            ring &= valid
        white = _masked_median_u8(pix8.reshape(t * 4, -1), ring.reshape(t * 4, -1)).reshape(t, 4)
    pix = pix8.astype(f32)
    inner = rho2 <= f32(0.25)
    if valid is not None:
        inner &= valid
    black = (pix * inner).sum(axis=(2, 3)) / np.maximum(inner.sum(axis=(2, 3)), 1)
    taper = np.sqrt(rho2)
    np.subtract(f32(reach), taper, out=taper)
    taper *= f32(1.0 / rf.REFINE_TAPER)
    np.minimum(taper, f32(1.0), out=taper)
    np.maximum(taper, f32(0.0), out=taper)
    if valid is not None:
        taper *= valid
    weight = np.subtract(np.where(np.isfinite(white), white, 0.0).astype(f32)[..., None, None], pix, out=pix)
    np.maximum(weight, f32(0.0), out=weight)
    weight *= taper
    total = weight.sum(axis=(2, 3)).astype(np.float64)
    good = (total > 1e-6) & np.isfinite(white)
    safe = np.where(good, total, 1.0)
    mx = (weight.sum(axis=2) * dx[..., 0, :]).sum(axis=-1) / safe
    my = (weight.sum(axis=3) * dy[..., :, 0]).sum(axis=-1) / safe
    new = centroid.copy()
    new[..., 0] += np.where(good, mx, 0.0)
    new[..., 1] += np.where(good, my, 0.0)
    return new, np.where(good, total, 0.0), white - black, white


@pytest.mark.parametrize("n", [1, 5, 8, 9, 127, 128, 129, 256, 257, 1000, 1225, 5000])
def test_pairwise_sum_is_numpys_sum(n: int) -> None:
    rng = np.random.default_rng(n)
    a = (rng.standard_normal(n + 5) * 10 ** rng.uniform(-3, 3, n + 5)).astype(np.float32)
    assert np.float32(0.0) + pairwise_sum(a, 3, n) == a[3 : 3 + n].sum()


def test_centroid_step_matches_numpy(texture: Callable[[np.random.Generator, int, int], np.ndarray]) -> None:
    rng = np.random.default_rng(14)
    img = texture(rng, 160, 200)
    for trial in range(40):
        t = int(rng.integers(1, 6))
        centroid = np.stack([rng.uniform(-3, 203, (t, 4)), rng.uniform(-3, 163, (t, 4))], axis=-1)
        if trial % 2:  # well inside: the windows are views, no mask
            centroid = np.stack([rng.uniform(30, 170, (t, 4)), rng.uniform(30, 130, (t, 4))], axis=-1)
        scale = rng.uniform(5, 60)
        jac = scale * (np.eye(2) + rng.uniform(-0.4, 0.4, (t, 4, 2, 2)))
        white = None
        if trial % 3 == 0:
            white = rng.uniform(100, 255, (t, 4)).round() / 2
            white[0, 0] = np.nan
        got = rf._centroid_step(img, centroid, jac, rf.REFINE_WINDOW + rf.REFINE_TAPER, white)
        expected = _reference_centroid_step(img, centroid, jac, rf.REFINE_WINDOW + rf.REFINE_TAPER, white)
        for g, e in zip(got, expected, strict=True):
            np.testing.assert_array_equal(g, e)
