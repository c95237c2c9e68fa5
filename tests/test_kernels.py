"""The compiled kernels (app.core.kernels) against the numpy/OpenCV code they replaced,
bit for bit, on random inputs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from app.core import candidates as cand
from app.core import kernels
from app.core import targets as tg

# --------------------------------------------------------------------------------------
# References: the numpy/OpenCV code each kernel replaced
# --------------------------------------------------------------------------------------


def _reference_blob_scores(padded: np.ndarray) -> np.ndarray:
    """Stage 1a through OpenCV calls: integral image, shifted differences, addWeighted."""
    se = np.ones((12, 12), np.uint8)
    h, w = padded.shape
    dil = cv2.dilate(padded, se, anchor=(6, 6))
    ero = cv2.erode(padded, se, anchor=(6, 6))
    tophat = cv2.subtract(cv2.erode(dil, se, anchor=(5, 5)), padded)
    integral = cv2.integral(tophat, sdepth=cv2.CV_32S)
    oh, ow = h - 11, w - 11
    strip = cv2.subtract(integral[12:], integral[:oh])
    sum12 = cv2.subtract(strip[:, 12:], strip[:, :ow])
    rows4 = cv2.subtract(integral[8 : h - 3], integral[4 : h - 7])
    sum4 = cv2.subtract(rows4[:, 8 : w - 3], rows4[:, 4 : w - 7])
    num = cv2.addWeighted(sum4, 1.0 / 16.0, sum12, -1.0 / 144.0, 0.0, dtype=cv2.CV_32F)
    den = cv2.add(cv2.subtract(dil, ero)[6 : h - 5, 6 : w - 5], 2.0, dtype=cv2.CV_32F)
    return cv2.divide(num, den)


def _reference_maxima(score: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    mask = cv2.compare(score, cv2.max(cv2.dilate(score, None), float(threshold) + 1e-6), cv2.CMP_GE)
    return np.nonzero(mask)


def _reference_screen_raw(raw: np.ndarray, classifier: cand.DiscClassifier) -> np.ndarray:
    w = raw.reshape(-1, 144).astype(np.float32)
    product = w @ classifier._w1_ext
    hidden = product[:, :-1]
    mean = product[:, -1] / np.float32(144)
    sq = np.einsum("ij,ij->i", w, w) - np.float32(144) * mean * mean
    inv = 1.0 / np.maximum(np.sqrt(np.maximum(sq, 0.0)), np.float32(1e-3))
    hidden -= mean[:, None] * classifier._w1_sum[None, :]
    hidden *= inv[:, None]
    hidden += classifier.screen_b1
    np.maximum(hidden, 0.0, out=hidden)
    return hidden @ classifier.screen_w2 + np.float32(classifier.screen_b2)


def _reference_clash_pairs(rows: np.ndarray, claims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = rows.shape[0]
    x = rows[:, 0]
    order = np.argsort(x, kind="stable")
    xs = x[order]
    r = rows[order, 2]
    lo = np.searchsorted(xs, xs - r, side="left")
    hi = np.searchsorted(xs, xs + r, side="right")
    cnt = hi - lo
    total = int(cnt.sum())
    a = order[np.repeat(np.arange(n), cnt)]
    b = order[np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt) + np.repeat(lo, cnt)]
    ahead = a < b
    a, b = a[ahead], b[ahead]
    d = rows[a, :2] - rows[b, :2]
    reach = np.where(claims[a], rows[a, 2], np.minimum(rows[a, 2], rows[b, 2]))
    close = np.einsum("ij,ij->i", d, d) < reach * reach
    return a[close], b[close]


def _reference_greedy(n: int, first: np.ndarray, second: np.ndarray, active: np.ndarray | None) -> np.ndarray:
    keep = np.ones(n, bool) if active is None else active.copy()
    if first.size == 0:
        return keep
    if active is not None:
        both = active[first] & active[second]
        first, second = first[both], second[both]
    for _ in range(n):
        hits = np.bincount(second, weights=keep[first], minlength=n)
        new = (hits == 0) if active is None else (hits == 0) & active
        if np.array_equal(new, keep):
            break
        keep = new
    return keep


def _reference_centroid_step(img: np.ndarray, centroid: np.ndarray, jac: np.ndarray, reach: float,
                             white: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    t = centroid.shape[0]
    f32 = np.float32
    j00, j01, j10, j11 = jac[..., 0, 0], jac[..., 0, 1], jac[..., 1, 0], jac[..., 1, 1]
    det = j00 * j11 - j01 * j10
    s = 1.0 / (det * tg.DISC_RADIUS)
    a = (np.array([j11, -j01, -j10, j00]) * s).astype(f32)[..., None, None]
    ext = reach * tg.DISC_RADIUS * np.sqrt((jac * jac).sum(axis=-1).max(axis=-1))
    k = int(np.ceil(ext.max())) + 1
    size = 2 * k + 1
    base = np.rint(centroid).astype(np.intp)
    pix8, valid = tg._windows_u8(img, base[..., 0].ravel() - k, base[..., 1].ravel() - k, size)
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
        ring = (rho2 >= f32(tg.REFINE_RING[0] ** 2)) & (rho2 <= f32(tg.REFINE_RING[1] ** 2))
        if valid is not None:
            ring &= valid
        white = tg._masked_median_u8(pix8.reshape(t * 4, -1), ring.reshape(t * 4, -1)).reshape(t, 4)
    pix = pix8.astype(f32)
    inner = rho2 <= f32(0.25)
    if valid is not None:
        inner &= valid
    black = (pix * inner).sum(axis=(2, 3)) / np.maximum(inner.sum(axis=(2, 3)), 1)
    taper = np.sqrt(rho2)
    np.subtract(f32(reach), taper, out=taper)
    taper *= f32(1.0 / tg.REFINE_TAPER)
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


def _texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A random image with dark blobs of every size (plenty of maxima and ties)."""
    img = cv2.GaussianBlur(rng.integers(0, 256, (h, w)).astype(np.uint8), (0, 0), float(rng.uniform(0.3, 3)))
    for _ in range(int(rng.integers(0, 12))):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        cv2.circle(img, c, int(rng.integers(1, 20)), int(rng.integers(0, 60)), -1)
    if rng.random() < 0.3:
        img[: h // 3] = 128  # flat: equal scores, plateaus of maxima
    return img


# --------------------------------------------------------------------------------------
# Stage 1
# --------------------------------------------------------------------------------------


def test_blob_kernels_match_opencv_bit_for_bit() -> None:
    rng = np.random.default_rng(11)
    ws = cand._Workspace()
    for _ in range(15):
        h, w = (int(s) for s in rng.integers(24, 300, 2))
        for level in cand.pyramid(_texture(rng, h, w)):
            padded = cand.pad_level(level)
            expected = _reference_blob_scores(padded)
            np.testing.assert_array_equal(cand.blob_scores(padded, ws), expected)
            for threshold in (0.25, 0.16, -2.0):
                ys, xs = _reference_maxima(expected, threshold)
                got = cand.local_maxima(expected, threshold, ws)
                np.testing.assert_array_equal(got[0], ys)
                np.testing.assert_array_equal(got[1], xs)
                score, gy, gx = cand._blob_maxima(padded, threshold, ws)
                np.testing.assert_array_equal(score, expected)
                np.testing.assert_array_equal(gy, ys)
                np.testing.assert_array_equal(gx, xs)


def test_gathered_screen_matches_the_numpy_screen() -> None:
    rng = np.random.default_rng(12)
    classifier = cand.load_default_classifier()
    for n in (1, 7, 300):
        padded = cand.pad_level(_texture(rng, 120, 160))
        ys = rng.integers(0, padded.shape[0] - 11, n)
        xs = rng.integers(0, padded.shape[1] - 11, n)
        raw = np.empty((n, 12, 12), np.uint8)
        flat = np.empty((n, 144), np.float32)
        sums, sums_sq = np.empty(n, np.int64), np.empty(n, np.int64)
        kernels.gather_windows(padded, ys, xs, raw, flat, sums, sums_sq)
        expected_raw = cand.extract_windows(padded, ys, xs)
        np.testing.assert_array_equal(raw, expected_raw)
        np.testing.assert_array_equal(flat, expected_raw.reshape(n, 144).astype(np.float32))
        np.testing.assert_array_equal(sums, expected_raw.reshape(n, -1).sum(axis=1))
        np.testing.assert_array_equal(sums_sq, (expected_raw.reshape(n, -1).astype(np.int64) ** 2).sum(axis=1))
        np.testing.assert_array_equal(cand._screen_gathered(flat, sums, sums_sq, classifier),
                                      _reference_screen_raw(raw, classifier))


def test_stage1_windows_unchanged_without_the_screen() -> None:
    rng = np.random.default_rng(13)
    classifier = cand.load_default_classifier()
    image = _texture(rng, 240, 320)
    s1 = cand.stage1_windows(image, classifier, apply_screen=False)
    np.testing.assert_array_equal(s1.screen, _reference_screen_raw(s1.windows, classifier))
    for lv, padded, pad, ys, xs, blob in cand.scan_levels(image, classifier.blob_thresholds):
        at = s1.level == lv
        np.testing.assert_array_equal(s1.windows[at], cand.extract_windows(padded, ys, xs))
        np.testing.assert_array_equal(s1.blob[at], blob)


@pytest.mark.parametrize("n", [0, 1, 2, 50, 400])
def test_suppression_kernels_match_numpy(n: int) -> None:
    rng = np.random.default_rng(n)
    for _ in range(10):
        rows = np.zeros((n, 4), np.float32)
        rows[:, :2] = rng.uniform(0, 100, (n, 2))
        if n > 4:  # ties along x, and coincident centres
            rows[: n // 4, 0] = np.round(rows[: n // 4, 0])
            rows[n // 2 : n // 2 + 2, :2] = rows[0, :2]
        rows[:, 2] = rng.uniform(0.5, 12, n)
        claims = rng.random(n) < 0.5
        first, second = cand._clash_pairs(rows, claims)
        if n >= 2:
            ef, es = _reference_clash_pairs(rows, claims)
            np.testing.assert_array_equal(first, ef)
            np.testing.assert_array_equal(second, es)
            assert first.dtype == np.intp and second.dtype == np.intp
        else:
            assert first.size == 0 and second.size == 0
        np.testing.assert_array_equal(cand._greedy(n, first, second), _reference_greedy(n, first, second, None))
        active = rng.random(n) < 0.6
        np.testing.assert_array_equal(cand._greedy(n, first, second, active),
                                      _reference_greedy(n, first, second, active))


# --------------------------------------------------------------------------------------
# Targets
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [1, 5, 8, 9, 127, 128, 129, 256, 257, 1000, 1225, 5000])
def test_pairwise_sum_is_numpys_sum(n: int) -> None:
    rng = np.random.default_rng(n)
    a = (rng.standard_normal(n + 5) * 10 ** rng.uniform(-3, 3, n + 5)).astype(np.float32)
    assert np.float32(0.0) + kernels.pairwise_sum(a, 3, n) == a[3 : 3 + n].sum()


def test_centroid_step_matches_numpy() -> None:
    rng = np.random.default_rng(14)
    img = _texture(rng, 160, 200)
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
        got = tg._centroid_step(img, centroid, jac, tg.REFINE_WINDOW + tg.REFINE_TAPER, white)
        expected = _reference_centroid_step(img, centroid, jac, tg.REFINE_WINDOW + tg.REFINE_TAPER, white)
        for g, e in zip(got, expected, strict=True):
            np.testing.assert_array_equal(g, e)


def test_warm_up_compiles_what_the_detector_calls() -> None:
    """After `warm_up` a detection compiles nothing more (its argument types, read-only
    and non-contiguous arrays included, were all seen)."""
    from app.core.detector import Detector

    kernels.warm_up()
    dispatchers = {name: getattr(kernels, name) for name in dir(kernels)
                   if hasattr(getattr(kernels, name), "signatures") and not name.startswith("_")}
    dispatchers.pop("pairwise_sum")  # called from the kernels only (compiled into them)
    before = {name: set(d.signatures) for name, d in dispatchers.items()}
    rng = np.random.default_rng(15)
    Detector(cand.load_default_classifier()).detect(_texture(rng, 240, 320))
    assert {name: set(d.signatures) for name, d in dispatchers.items()} == before
