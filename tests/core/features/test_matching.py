"""The checks that keep wrong matches out: the epipolar check drops matches that no
single camera motion explains, Lowe's ratio test drops ambiguous descriptors."""

from __future__ import annotations

import cv2
import numpy as np

from app.core.features.matching import geometric_inliers, ratio_matches
from app.core.geometry import Camera, Pose


def _two_views(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, Camera]:
    """Points on two walls at 2-5 m seen by a camera before and after a step and a turn;
    also the true fundamental matrix (ideal pixels) and the camera."""
    rng = np.random.default_rng(seed)
    camera = Camera.pinhole(800.0, 640, 480, dist=[-0.1, 0.0, 0.0, 0.0, 0.0])
    X = np.c_[rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), np.where(rng.random(n) < 0.5, 3.0, 4.5)]
    X[:, 2] += 0.3 * X[:, 0]
    a = Pose.identity()
    b = Pose.from_rvec_tvec([0.02, 0.08, 0.01], [-0.25, 0.03, 0.05])
    uv_a, uv_b = camera.project_map(X, a), camera.project_map(X, b)
    tx = np.array([[0, -b.t[2], b.t[1]], [b.t[2], 0, -b.t[0]], [-b.t[1], b.t[0], 0]])
    Kinv = np.linalg.inv(camera.K)
    F = Kinv.T @ tx @ b.R @ Kinv
    return uv_a, uv_b, F, camera


def _epipolar_distance(F: np.ndarray, camera: Camera, uv_a: np.ndarray, uv_b: np.ndarray) -> np.ndarray:
    a, b = camera.undistort_pixels(uv_a), camera.undistort_pixels(uv_b)
    lines = np.c_[a, np.ones(len(a))] @ F.T
    return np.abs(np.sum(lines * np.c_[b, np.ones(len(b))], axis=1)) / np.hypot(lines[:, 0], lines[:, 1])


def test_the_epipolar_check_drops_injected_wrong_matches_and_keeps_the_right_ones() -> None:
    uv_a, uv_b, F, camera = _two_views(300, 0)
    rng = np.random.default_rng(1)
    uv_b = uv_b + rng.normal(0.0, 0.2, uv_b.shape)
    wrong = rng.random(len(uv_b)) < 0.25
    shift = rng.uniform(3.0, 40.0, wrong.sum())
    angle = rng.uniform(0, 2 * np.pi, wrong.sum())
    uv_b[wrong] += np.c_[shift * np.cos(angle), shift * np.sin(angle)]
    ok = geometric_inliers(uv_a, uv_b, 1.0, camera)
    off_line = _epipolar_distance(F, camera, uv_a, uv_b)
    assert np.median(off_line[~wrong]) < 0.3 and (off_line[wrong] > 2.0).mean() > 0.8  # the truth itself
    # Every wrong match off its epipolar line goes; a wrong match that happens to lie on
    # its line cannot be told from a right one by two views.
    assert not np.any(ok & wrong & (off_line > 2.0))
    assert ok[~wrong].mean() >= 0.97


def test_too_few_matches_to_check_are_refused() -> None:
    uv_a, uv_b, _, camera = _two_views(3, 2)
    assert not geometric_inliers(uv_a, uv_b, 1.0, camera).any()
    assert len(geometric_inliers(np.zeros((0, 2)), np.zeros((0, 2)), 1.0)) == 0


def test_a_few_matches_are_checked_by_a_homography() -> None:
    # Ten matches of a frame shifted by (3, -2) px, one of them 10 px off.
    rng = np.random.default_rng(3)
    uv_a = rng.uniform(50, 600, (10, 2))
    uv_b = uv_a + [3.0, -2.0]
    uv_b[4] += [10.0, 0.0]
    ok = geometric_inliers(uv_a, uv_b, 1.0)
    assert ok.tolist() == [True, True, True, True, False, True, True, True, True, True]


def test_the_ratio_test_drops_ambiguous_descriptors() -> None:
    rng = np.random.default_rng(4)
    train = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    query = train[:10].copy()
    query[:, 0] ^= 1  # one bit off: still far nearer its own row than any other
    # Row 10 duplicates row 0: a query of row 0 now has two equally good matches.
    ambiguous = np.vstack([train, train[0]])
    q, t = ratio_matches(query, train, 0.8, cv2.NORM_HAMMING)
    assert q.tolist() == list(range(10)) and t.tolist() == list(range(10))
    q, t = ratio_matches(query, ambiguous, 0.8, cv2.NORM_HAMMING)
    assert 0 not in q.tolist() and q.tolist() == list(range(1, 10))
    # The same duplicate as one group (one point seen twice) is no ambiguity.
    groups = np.r_[np.arange(50), 0]
    q, t = ratio_matches(query, ambiguous, 0.8, cv2.NORM_HAMMING, train_groups=groups)
    assert q.tolist() == list(range(10))


def test_matches_that_agree_with_nothing_are_all_refused() -> None:
    # After a cut in the video the few points the flow still "follows" land anywhere.
    rng = np.random.default_rng(5)
    for n in (6, 12, 40):
        uv_a, uv_b = rng.uniform(0, 640, (n, 2)), rng.uniform(0, 480, (n, 2))
        assert not geometric_inliers(uv_a, uv_b, 1.0, min_fraction=0.5).any()
