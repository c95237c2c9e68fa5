"""Disc candidates (app.core.detection.candidates): the shipped default classifier on simulator
frames, the stages on their own, serialisation, bad input, and the candidate stage's
compiled kernels against the numpy/OpenCV code they stand for, bit for bit."""

from __future__ import annotations

import json
from collections.abc import Callable

import cv2
import numpy as np
import pytest

from app.core.detection import _candidates_kernels as kernels
from app.core.detection import candidates as cand
from app.core.detection.candidates import DiscClassifier, find_candidates, load_default_classifier
from app.learning import training

#: The `texture` fixture: ``texture(rng, h, w)``, a random uint8 image with dark blobs.
Texture = Callable[[np.random.Generator, int, int], np.ndarray]


@pytest.fixture(scope="module")
def classifier() -> DiscClassifier:
    return load_default_classifier()


def _frames(name: str, n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        image, truth = training.safe_scenario_frame(name, rng)
        out.append((image, training.visible_discs(truth)))
    return out


@pytest.fixture(scope="module")
def clean_disc_frames() -> list[tuple[np.ndarray, np.ndarray]]:
    return _frames("clean", 4, seed=2024)


def test_finds_every_disc_in_clean_frames(classifier: DiscClassifier, clean_disc_frames: list) -> None:
    n_discs = 0
    for image, discs in clean_disc_frames:
        found = find_candidates(image, classifier)
        assert found.dtype == np.float32 and found.ndim == 2 and found.shape[1] == 4
        for u, v, diameter in discs:
            if diameter < 4.0:
                continue
            n_discs += 1
            dist = np.hypot(found[:, 0] - u, found[:, 1] - v)
            j = int(np.argmin(dist))
            assert dist[j] <= 1.5, f"disc at ({u:.1f}, {v:.1f}) d={diameter:.1f}: nearest candidate {dist[j]:.2f} px"
            ratio = found[j, 2] / (0.5 * diameter)
            assert 1 / 1.6 <= ratio <= 1.6, f"radius {found[j, 2]:.2f} for a disc of radius {diameter / 2:.2f}"
    assert n_discs >= 12


def test_one_candidate_per_disc(classifier: DiscClassifier, clean_disc_frames: list) -> None:
    for image, discs in clean_disc_frames:
        found = find_candidates(image, classifier)
        for u, v, diameter in discs:
            near = np.hypot(found[:, 0] - u, found[:, 1] - v) < 0.5 * diameter
            assert near.sum() == 1, f"{near.sum()} candidates on the disc at ({u:.1f}, {v:.1f})"


def test_candidates_sorted_by_score_and_inside_image(classifier: DiscClassifier, clean_disc_frames: list) -> None:
    image, _ = clean_disc_frames[0]
    found = find_candidates(image, classifier)
    assert np.all(np.diff(found[:, 3]) <= 0)
    assert np.all(found[:, 3] > classifier.nn_threshold)
    h, w = image.shape
    assert np.all((found[:, 0] > -2) & (found[:, 0] < w + 1) & (found[:, 1] > -2) & (found[:, 1] < h + 1))
    assert np.all(found[:, 2] > 0)


def test_few_candidates_on_marker_free_frames(classifier: DiscClassifier) -> None:
    counts = [len(find_candidates(image, classifier)) for image, _ in _frames("empty", 3, seed=7)]
    # The next stage (Delaunay grouping, verification) rejects these; the paper reports
    # "of the order of 100" per frame.
    assert max(counts) <= 400
    assert np.mean(counts) <= 300


def test_stage1_rejects_almost_every_window(classifier: DiscClassifier) -> None:
    image, _ = _frames("empty", 1, seed=11)[0]
    s1 = cand.stage1_windows(image, classifier)
    assert s1.total_windows == cand.pyramid_window_count(image.shape)
    assert s1.total_windows / max(len(s1), 1) > 500
    a = cand.stage1_windows(image, classifier, apply_screen=False)
    assert len(a) >= len(s1)
    assert a.windows.shape[1:] == (cand.WINDOW, cand.WINDOW) and a.windows.dtype == np.uint8


def test_stage1_alone_on_one_level(classifier: DiscClassifier) -> None:
    image, _ = _frames("default", 1, seed=3)[0]
    score = cand.stage1_scores(image)
    assert score.shape == (image.shape[0] + 1, image.shape[1] + 1) and score.dtype == np.float32
    assert np.all(np.isfinite(score)) and score.max() <= 1.0
    thr = float(classifier.blob_thresholds[0])
    mask = cand.stage1_mask(image, thr)
    a = cand.stage1_windows(image, classifier, apply_screen=False)
    assert mask.sum() == np.sum(a.level == 0)
    assert np.all(score[mask] > thr)


def _heldout_windows(classifier: DiscClassifier) -> tuple[np.ndarray, np.ndarray]:
    """Disc windows and non-disc windows as stage 2 sees them, from frames the shipped
    classifier never saw (its own seeds are elsewhere)."""
    pos, neg = [], []
    rng = np.random.default_rng(99)
    for name in ("default", "blur", "dark", "far"):
        for _ in range(2):
            image, truth = training.safe_scenario_frame(name, rng)
            s1 = cand.stage1_windows(image, classifier)
            centres = s1.full_resolution_centres()
            scale = 2.0 ** s1.level
            near = np.zeros(len(s1), bool)
            far = np.ones(len(s1), bool)
            for u, v, d in training.visible_discs(truth):
                dist = np.hypot(centres[:, 0] - u, centres[:, 1] - v)
                near |= np.isin(s1.level, training.disc_levels(d)) & (dist <= training.PEAK_REACH * scale)
            for u, v, d in training.all_discs(truth):
                far &= np.hypot(centres[:, 0] - u, centres[:, 1] - v) > 0.75 * d
            pos.append(s1.windows[near])
            neg.append(s1.windows[far])
    return np.concatenate(pos), np.concatenate(neg)


def test_stage2_scores_separate_heldout_windows(classifier: DiscClassifier) -> None:
    pos, neg = _heldout_windows(classifier)
    assert len(pos) >= 30 and len(neg) >= 100
    sp = cand.classify_windows(pos, classifier)
    sn = cand.classify_windows(neg, classifier)
    assert np.median(sp) > np.median(sn)
    # Area under the ROC curve of the stage-2 score on windows that passed stage 1.
    auc = np.mean(sp[:, None] > sn[None, :]) + 0.5 * np.mean(sp[:, None] == sn[None, :])
    assert auc > 0.7
    assert np.mean(sp > classifier.nn_threshold) > 0.95


def test_shipped_statistics(classifier: DiscClassifier) -> None:
    s = classifier.stats
    assert s["condensation_prototypes"] == classifier.prototypes.shape[0]
    assert s["condensation_prototypes"] < s["condensation_examples"]
    assert s["stage1_rejection_factor"] > 1000
    assert s["screen_fn_rate_heldout"] < 0.03
    assert 0.0 < s["heldout_agreement_condensed_vs_full"] <= 1.0
    json.dumps(s)


def test_round_trip_gives_identical_candidates(classifier: DiscClassifier, clean_disc_frames: list) -> None:
    arrays = classifier.to_arrays()
    for name, a in arrays.items():
        assert isinstance(a, np.ndarray) and a.dtype != object, name
    # As the service stores them: .npy bytes without pickle, stats as JSON.
    import io

    def npy(a: np.ndarray) -> np.ndarray:
        buffer = io.BytesIO()
        np.save(buffer, a, allow_pickle=False)
        return np.load(io.BytesIO(buffer.getvalue()), allow_pickle=False)

    again = DiscClassifier.from_arrays({k: npy(v) for k, v in arrays.items()}, json.loads(json.dumps(classifier.stats)))
    image, _ = clean_disc_frames[1]
    assert np.array_equal(find_candidates(image, classifier), find_candidates(image, again))
    assert again.stats == json.loads(json.dumps(classifier.stats))


def test_from_arrays_rejects_bad_arrays(classifier: DiscClassifier) -> None:
    arrays = classifier.to_arrays()
    with pytest.raises(ValueError):
        DiscClassifier.from_arrays({k: v for k, v in arrays.items() if k != "prototypes"}, {})
    bad = dict(arrays, labels=np.full(arrays["labels"].shape, 3, np.int8))
    with pytest.raises(ValueError):
        DiscClassifier.from_arrays(bad, {})
    bad = dict(arrays, screen_w1=arrays["screen_w1"][:10])
    with pytest.raises(ValueError):
        DiscClassifier.from_arrays(bad, {})


def test_bgr_input_matches_grey(classifier: DiscClassifier, clean_disc_frames: list) -> None:
    image, _ = clean_disc_frames[2]
    bgr = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    assert np.array_equal(find_candidates(bgr, classifier), find_candidates(image, classifier))


def test_small_and_odd_sized_images(classifier: DiscClassifier) -> None:
    rng = np.random.default_rng(0)
    for h, w in ((24, 24), (25, 61), (97, 33)):
        out = find_candidates(rng.integers(0, 256, (h, w), dtype=np.uint8), classifier)
        assert out.shape[1] == 4
    assert find_candidates(np.full((60, 80), 128, np.uint8), classifier).shape == (0, 4)


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((0, 0), np.uint8),
        np.zeros((10, 10), np.uint8),
        np.zeros((23, 100), np.uint8),
        np.zeros((40, 40, 2), np.uint8),
        np.zeros((2, 40, 40, 3), np.uint8),
        np.zeros(100, np.uint8),
        np.zeros((40, 40), np.float32),
    ],
)
def test_bad_input_raises(classifier: DiscClassifier, bad: np.ndarray) -> None:
    with pytest.raises(ValueError):
        find_candidates(bad, classifier)


def test_classify_windows_checks_shape(classifier: DiscClassifier) -> None:
    with pytest.raises(ValueError):
        cand.classify_windows(np.zeros((3, 10, 10), np.uint8), classifier)
    assert cand.classify_windows(np.zeros((0, 12, 12), np.uint8), classifier).shape == (0,)


def test_suppress_collapses_duplicates_keeps_close_discs() -> None:
    # One disc seen at three positions/levels, and the four discs of a far card
    # (2.4 diameters apart): one candidate each, the best of the duplicates.
    rows = np.array([
        [100.0, 100.0, 4.0, 0.2], [100.8, 99.5, 4.3, 0.5], [99.4, 100.6, 8.0, 0.1],
        [200.0, 200.0, 2.5, 0.3], [212.0, 200.0, 2.5, 0.3], [212.0, 212.0, 2.5, 0.3], [200.0, 212.0, 2.5, 0.3],
    ], np.float32)
    kept = cand.suppress(rows)
    assert sorted(kept.tolist()) == [1, 3, 4, 5, 6]
    assert cand.suppress(rows[:0]).shape == (0,)


def test_normalise_windows_is_gain_and_offset_invariant() -> None:
    rng = np.random.default_rng(1)
    w = rng.uniform(0, 100, (5, 12, 12)).astype(np.float32)
    a = cand.normalise_windows(w)
    b = cand.normalise_windows(w * 2.5 + 40)
    assert np.allclose(a, b, atol=1e-5)
    assert np.allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-5)
    flat = cand.normalise_windows(np.full((1, 12, 12), 7.0))
    assert np.all(np.isfinite(flat)) and np.allclose(flat, 0.0)


def test_workspace_reuse_does_not_leak_between_frames(classifier: DiscClassifier) -> None:
    """The detector writes stage 1a into per-thread buffers: a frame's candidates do not
    depend on what was detected before (another frame, another size)."""
    (a, _), (b, _) = _frames("default", 2, seed=21)
    first = find_candidates(a, classifier)
    find_candidates(b, classifier)
    find_candidates(np.ascontiguousarray(b[:300, :400]), classifier)
    again = find_candidates(a, classifier)
    np.testing.assert_array_equal(first, again)
    # and the same as with a fresh workspace
    s1 = cand.stage1_windows(a, classifier, workspace=cand._Workspace())
    s2 = cand.stage1_windows(a, classifier)
    np.testing.assert_array_equal(s1.windows, s2.windows)


def _reference_blob_scores_by_box_filters(padded: np.ndarray) -> np.ndarray:
    """Stage 1a written plainly (two normalised float32 box filters): what `blob_scores`
    computes through an integral image and reused buffers."""
    se = np.ones((cand.WINDOW, cand.WINDOW), np.uint8)
    h, w = padded.shape
    dil = cv2.dilate(padded, se, anchor=(6, 6))
    ero = cv2.erode(padded, se, anchor=(6, 6))
    tophat = cv2.subtract(cv2.erode(dil, se, anchor=(5, 5)), padded)
    centre = cv2.boxFilter(tophat, cv2.CV_32F, (4, 4))[6 : h - 5, 6 : w - 5]
    window = cv2.boxFilter(tophat, cv2.CV_32F, (12, 12))[6 : h - 5, 6 : w - 5]
    den = cv2.subtract(dil, ero)[6 : h - 5, 6 : w - 5].astype(np.float32) + np.float32(2.0)
    return cv2.divide(centre - window, den)


def test_blob_scores_match_the_plain_formula_bit_for_bit() -> None:
    rng = np.random.default_rng(5)
    ws = cand._Workspace()
    for _ in range(12):
        h, w = (int(s) for s in rng.integers(24, 260, 2))
        image = cv2.GaussianBlur(rng.integers(0, 256, (h, w)).astype(np.uint8), (0, 0), float(rng.uniform(0.3, 3)))
        for level in cand.pyramid(image):
            padded = cand.pad_level(level)
            expected = _reference_blob_scores_by_box_filters(padded)
            np.testing.assert_array_equal(cand.blob_scores(padded, ws), expected)
            np.testing.assert_array_equal(cand.blob_scores(padded), expected)
            got = cand.local_maxima(cand.blob_scores(padded, ws).copy(), 0.16, ws)
            mask = cv2.compare(expected, cv2.max(cv2.dilate(expected, None), 0.16 + 1e-6), cv2.CMP_GE)
            ys, xs = np.nonzero(mask)
            np.testing.assert_array_equal(got[0], ys)
            np.testing.assert_array_equal(got[1], xs)


# --------------------------------------------------------------------------------------
# The compiled kernels (`_candidates_kernels`) against the numpy/OpenCV code they stand
# for, bit for bit, on random inputs
# --------------------------------------------------------------------------------------


def _reference_blob_scores_by_integral(padded: np.ndarray) -> np.ndarray:
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


def _reference_window_geometry(windows: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """`candidates.window_radius` then `window_centroid` as numpy chains on (N, 144) rows."""
    w = np.asarray(windows, dtype=np.float32).reshape(-1, 144)
    n = w.shape[0]
    prof = w @ cand._RINGS
    dark = prof[:, :2].min(axis=1)
    half = 0.5 * (dark + prof[:, 2:].max(axis=1))
    below = prof < half[:, None]
    first = np.where(below.all(axis=1), prof.shape[1], np.argmin(below, axis=1))
    k = np.minimum(np.maximum(first, 1), prof.shape[1] - 1)
    flat = prof.reshape(-1)
    p1_index = np.arange(0, n * prof.shape[1], prof.shape[1]) + k
    p0, p1 = flat[p1_index - 1], flat[p1_index]
    step = np.where(np.abs(p1 - p0) > 1e-6, p1 - p0, np.float32(1e-6))
    radius = cand._RING_MID[k - 1] + np.minimum(np.maximum((half - p0) / step, 0.0), 1.0)
    radius = (np.where(first == 0, 0.5, radius) * cand._RADIUS_GAIN).astype(np.float32)
    dark = half[:, None] - w
    np.maximum(dark, 0.0, out=dark)
    reach2 = ((radius + 1.0) ** 2)[:, None]
    offset = np.zeros((n, 2), np.float32)
    for it in range(iterations):
        if it == 0:
            d2 = cand._DIST2[None, :]
        else:
            d2 = (cand._DX[None, :] - offset[:, :1]) ** 2 + (cand._DY[None, :] - offset[:, 1:]) ** 2
        weight = dark * (d2 <= reach2)
        total = weight.sum(axis=1)
        ok = total > 1e-6
        new = (weight @ cand._DXY) / np.where(ok, total, 1.0)[:, None]
        offset = np.where(ok[:, None], np.minimum(np.maximum(new, -2.0), 2.0), offset).astype(np.float32)
    return offset, radius


def test_blob_kernels_match_opencv_bit_for_bit(texture: Texture) -> None:
    rng = np.random.default_rng(11)
    ws = cand._Workspace()
    for _ in range(15):
        h, w = (int(s) for s in rng.integers(24, 300, 2))
        for level in cand.pyramid(texture(rng, h, w)):
            padded = cand.pad_level(level)
            expected = _reference_blob_scores_by_integral(padded)
            np.testing.assert_array_equal(cand.blob_scores(padded, ws), expected)
            for threshold in (0.25, 0.16, -2.0):
                ys, xs = _reference_maxima(expected, threshold)
                got = cand.local_maxima(expected, threshold, ws)
                np.testing.assert_array_equal(got[0], ys)
                np.testing.assert_array_equal(got[1], xs)
                gy, gx, blob = cand._blob_maxima(padded, threshold, ws)
                np.testing.assert_array_equal(blob, expected[ys, xs])
                np.testing.assert_array_equal(gy, ys)
                np.testing.assert_array_equal(gx, xs)


def test_gathered_screen_matches_the_numpy_screen(texture: Texture) -> None:
    rng = np.random.default_rng(12)
    classifier = cand.load_default_classifier()
    for n in (1, 7, 300):
        padded = cand.pad_level(texture(rng, 120, 160))
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


def test_stage1_windows_unchanged_without_the_screen(texture: Texture) -> None:
    rng = np.random.default_rng(13)
    classifier = cand.load_default_classifier()
    image = texture(rng, 240, 320)
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


@pytest.mark.parametrize("iterations", [1, 2, 3])
def test_window_geometry_kernels_match_numpy(iterations: int) -> None:
    """`ring_radius`, `centroid_weights`, `centroid_offset` (through `window_geometry`)
    against the numpy chains, on noise, noisy discs and flat windows."""
    rng = np.random.default_rng(iterations)
    for trial in range(60):
        n = int(rng.integers(0, 50))
        if trial % 3 == 0:
            w = rng.integers(0, 256, (n, 12, 12)).astype(np.uint8)
        elif trial % 3 == 1:
            yy, xx = np.mgrid[:12, :12] - 5.5 - rng.normal(0, 1, (2, 1, 1))
            r = rng.uniform(0.5, 6.0, (n, 1, 1))
            disc = np.where(np.hypot(yy, xx)[None] < r, 30.0, 200.0) + rng.normal(0, 8, (n, 12, 12))
            w = np.clip(disc, 0, 255).astype(np.uint8)
        else:
            w = np.full((n, 12, 12), rng.integers(0, 256), np.uint8)
        got = cand.window_geometry(w, iterations)
        expected = _reference_window_geometry(w, iterations) if n else got
        for g, e in zip(got, expected):
            assert g.dtype == e.dtype and g.shape == e.shape
            np.testing.assert_array_equal(g, e)


def test_a_coarse_window_holding_a_whole_small_card_leaves_its_discs(monkeypatch: pytest.MonkeyPatch) -> None:
    # A brightly lit card with 4 px discs, its white clipped into a white wall: two
    # levels up the whole card is one dark blob, whose window passes both stages and would
    # suppress the card's four discs. They are kept beside it, and the card is found.
    import zlib

    from app.core.detection import Detector
    from app.sim import scenes

    image, truth = scenes.scenario_frame("bright", np.random.default_rng([0, zlib.crc32(b"bright"), 47, 0]))
    card = next(t for t in truth.targets if t.id == 53)
    assert card.visible and card.disc_diameter_px < 5
    detector = Detector(load_default_classifier())
    assert 53 in [t.id for t in detector.detect(image).targets]
    monkeypatch.setattr(cand, "_claimed_discs", lambda *args: np.zeros(args[2].size, bool))
    assert 53 not in [t.id for t in detector.detect(image).targets]
