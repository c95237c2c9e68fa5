"""Disc candidates (app.core.detection.candidates): the shipped default classifier on simulator
frames, the stages on their own, serialisation, and bad input. Fast (a few seconds)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from app.core.detection import candidates as cand
from app.learning import training
from app.core.detection.candidates import DiscClassifier, find_candidates, load_default_classifier


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
def clean_frames() -> list[tuple[np.ndarray, np.ndarray]]:
    return _frames("clean", 4, seed=2024)


def test_finds_every_disc_in_clean_frames(classifier: DiscClassifier, clean_frames: list) -> None:
    n_discs = 0
    for image, discs in clean_frames:
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


def test_one_candidate_per_disc(classifier: DiscClassifier, clean_frames: list) -> None:
    for image, discs in clean_frames:
        found = find_candidates(image, classifier)
        for u, v, diameter in discs:
            near = np.hypot(found[:, 0] - u, found[:, 1] - v) < 0.5 * diameter
            assert near.sum() == 1, f"{near.sum()} candidates on the disc at ({u:.1f}, {v:.1f})"


def test_candidates_sorted_by_score_and_inside_image(classifier: DiscClassifier, clean_frames: list) -> None:
    image, _ = clean_frames[0]
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


def test_hart_condensing_is_consistent_and_agrees_with_full_1nn() -> None:
    """Hart's rule on real windows: the condensed set classifies every training window
    as the full training set does (by construction) and mostly agrees on held-out ones;
    Gates' reduction keeps the training consistency."""
    rng = np.random.default_rng(5)
    image, truth = training.safe_scenario_frame("default", rng)
    blob = (0.25, 0.16, 0.16, 0.16)
    fw = training.frame_windows(image, training.visible_discs(truth), training.all_discs(truth), blob, None, rng)
    photo = training.degrade.to_uint8(training.scenes.builtin_photos()[0])
    fw2 = training.frame_windows(photo, np.zeros((0, 3)), np.zeros((0, 3)), blob, None, rng)
    pos = cand.normalise_windows(cand.dihedral(np.concatenate(fw.positives)))
    neg = cand.normalise_windows(np.concatenate(fw.negatives + fw2.negatives))
    x = np.concatenate([pos, neg])
    y = np.concatenate([np.ones(len(pos), np.int8), np.zeros(len(neg), np.int8)])
    perm = rng.permutation(len(x))
    test, train = perm[: len(x) // 5], perm[len(x) // 5 :]
    store, passes = cand.condense(x[train], y[train], rng)
    assert 1 <= passes < 50 and 0 < store.size < train.size
    full = cand.nn_predict(x[train], x[train], y[train])
    assert np.array_equal(full, y[train])
    assert np.array_equal(cand.nn_predict(x[train], x[train][store], y[train][store]), y[train])
    reduced = cand.reduce_store(x[train], y[train], store)
    assert reduced.size <= store.size
    assert np.array_equal(cand.nn_predict(x[train], x[train][reduced], y[train][reduced]), y[train])
    full_test = cand.nn_predict(x[test], x[train], y[train])
    agree = np.mean(full_test == cand.nn_predict(x[test], x[train][store], y[train][store]))
    assert agree > 0.85


def test_shipped_statistics(classifier: DiscClassifier) -> None:
    s = classifier.stats
    assert s["condensation_prototypes"] == classifier.prototypes.shape[0]
    assert s["condensation_prototypes"] < s["condensation_examples"]
    assert s["stage1_rejection_factor"] > 1000
    assert s["screen_fn_rate_heldout"] < 0.03
    assert 0.0 < s["heldout_agreement_condensed_vs_full"] <= 1.0
    json.dumps(s)


def test_round_trip_gives_identical_candidates(classifier: DiscClassifier, clean_frames: list) -> None:
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
    image, _ = clean_frames[1]
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


def test_bgr_input_matches_grey(classifier: DiscClassifier, clean_frames: list) -> None:
    image, _ = clean_frames[2]
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


def _reference_blob_scores(padded: np.ndarray) -> np.ndarray:
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
            expected = _reference_blob_scores(padded)
            np.testing.assert_array_equal(cand.blob_scores(padded, ws), expected)
            np.testing.assert_array_equal(cand.blob_scores(padded), expected)
            got = cand.local_maxima(cand.blob_scores(padded, ws).copy(), 0.16, ws)
            mask = cv2.compare(expected, cv2.max(cv2.dilate(expected, None), 0.16 + 1e-6), cv2.CMP_GE)
            ys, xs = np.nonzero(mask)
            np.testing.assert_array_equal(got[0], ys)
            np.testing.assert_array_equal(got[1], xs)
