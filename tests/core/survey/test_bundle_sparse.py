"""The bundle adjustment's sparse factorisation of the reduced camera system: the same
optimum, steps and covariance as the dense Cholesky, and the survey's growth schedule."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import scipy.sparse

from app.core.survey.bundle import (
    ReducedSolver,
    _camera_of,
    _feature_problem,
    _feature_structure,
    _joint,
    _problem,
    _sparse_factor,
    _sparse_pattern,
    _sparse_reduced,
    _sparse_system,
    bundle_adjust,
)
from app.core.survey.points import FeatureObservations
from app.core.survey.policy import FeatureKeyframes
from app.core.survey.state import SurveyState
from app.sim.examples import ExampleRoom
from tests.core.survey.test_bundle import PRIOR, _disturb, _wall_features


def _problem_with_loops(state: SurveyState, room: ExampleRoom, seed: int) -> tuple[FeatureObservations, np.ndarray]:
    """Feature points on the walls, each seen in a run of frames, plus some seen again
    much later (a loop closure: cameras far apart in the video share a point), disturbed
    by noise and a few wrong matches; the state disturbed too."""
    rng = np.random.default_rng(seed)
    features, points = _wall_features(state, room, rng, 120)
    uv = features.uv + rng.normal(0, 0.5, features.uv.shape)
    wrong = rng.choice(len(uv), 4, replace=False)
    uv[wrong] += rng.uniform(10, 30, (4, 2))
    features = FeatureObservations(features.frame, features.track, uv, sigma_px=0.5, loss=features.loss)
    _disturb(state, rng)
    return features, points + rng.normal(0, 0.02, points.shape)


@pytest.mark.parametrize("free_intrinsics", [False, True])
def test_the_sparse_solver_finds_the_dense_optimum(true_state: SurveyState, room: ExampleRoom,
                                                   free_intrinsics: bool) -> None:
    features, start = _problem_with_loops(true_state, room, 21)
    rec, tracks, use = true_state.reconstruction, true_state.tracks, true_state.usable.repeat(4)
    results = {
        solver: bundle_adjust(rec, tracks, use, free_intrinsics, PRIOR, features=features, feature_X=start,
                              with_covariance=True, tolerance=1e-14, solver=solver)
        for solver in ReducedSolver
    }
    (dense, d_info), (sparse, s_info) = results[ReducedSolver.DENSE], results[ReducedSolver.SPARSE]
    assert 0 < s_info.iterations < 100 and len(s_info.feature_obs) > 0

    # The same optimum: the cost to 1e-9. The parameters stop apart by more than rounding
    # along the flat directions of the optimum (a disc seen from few directions; with
    # the lens free, the focal length against the depths).
    assert s_info.cost == pytest.approx(d_info.cost, rel=1e-9)
    rtol = 1e-6 if free_intrinsics else 1e-7

    def close(a: np.ndarray, b: np.ndarray) -> None:
        np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol * np.nanmax(np.abs(b)))

    close(sparse.X, dense.X)
    close(sparse.rvec, dense.rvec)
    close(sparse.tvec, dense.tvec)
    close(sparse.camera.K, dense.camera.K)
    close(sparse.camera.dist, dense.camera.dist)
    assert s_info.feature_X is not None and d_info.feature_X is not None
    close(s_info.feature_X, d_info.feature_X)
    assert s_info.covariance is not None and d_info.covariance is not None
    # The marginal covariance of [intrinsics, discs]: the same to rounding (the inverse
    # of a system of condition ~1e8: rounding weighs more than in the optimum).
    C = d_info.covariance
    np.testing.assert_allclose(s_info.covariance, C, rtol=0, atol=1e-7 * np.abs(C).max())
    np.testing.assert_allclose(s_info.disc_std(sparse.X)[s_info.points], d_info.disc_std(dense.X)[d_info.points],
                               rtol=1e-7)
    if free_intrinsics:
        np.testing.assert_allclose(s_info.intrinsics_std(), d_info.intrinsics_std(), rtol=1e-7)


def test_one_sparse_step_is_the_dense_step(true_state: SurveyState, room: ExampleRoom) -> None:
    """One damped iteration from the same start: the same step to rounding (the system the
    sparse pattern holds is the dense one, entry for entry)."""
    features, start = _problem_with_loops(true_state, room, 22)
    rec, tracks, use = true_state.reconstruction, true_state.tracks, true_state.usable.repeat(4)
    steps = [bundle_adjust(rec, tracks, use, True, PRIOR, features=features, feature_X=start, max_iterations=1,
                           solver=solver) for solver in ReducedSolver]
    (dense, d_info), (sparse, s_info) = steps
    assert d_info.iterations == s_info.iterations == 1
    np.testing.assert_allclose(sparse.X, dense.X, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sparse.tvec, dense.tvec, rtol=0, atol=1e-12)
    assert s_info.feature_X is not None and d_info.feature_X is not None
    np.testing.assert_allclose(s_info.feature_X, d_info.feature_X, rtol=0, atol=1e-11)


def test_the_pattern_holds_the_whole_reduced_system(true_state: SurveyState, room: ExampleRoom) -> None:
    """Every entry of the dense reduced system lies in the sparse pattern, with the same
    value; the loop closures make blocks between cameras far apart in the video."""
    from app.core.survey.bundle import _feature_reduced, _feature_system

    features, start = _problem_with_loops(true_state, room, 23)
    rec, tracks = true_state.reconstruction, true_state.tracks
    p = _problem(rec, tracks, true_state.usable.repeat(4), True, PRIOR, 100.0)
    obs, points = _feature_problem(rec, features, start, None)
    joint = _joint(p, features, obs)
    fp = _feature_structure(features, obs, points, joint)
    sp = _sparse_pattern(p, fp, joint)
    intr = np.array([rec.camera.fx, rec.camera.cx, rec.camera.cy, rec.camera.dist[0], rec.camera.dist[1]])
    cams = np.c_[rec.rvec[joint.frames], rec.tvec[joint.frames]]
    X, Xf = rec.X[p.points], start[points]
    from app.core.survey.bundle import _feature_residuals, _residuals

    cam = _camera_of(p, intr)
    r, rf = _residuals(p, cam, cams[joint.dmap], X), _feature_residuals(fp, cam, cams, Xf)
    dense, g_dense, _ = _feature_reduced(p, fp, joint, _feature_system(p, fp, joint, intr, cams, X, Xf, r, rf), 1e-3)
    H, g, _ = _sparse_reduced(fp, sp, _sparse_system(p, fp, joint, sp, intr, cams, X, Xf, r, rf), 1e-3)
    assert isinstance(H, scipy.sparse.csc_matrix)
    scale = np.abs(dense).max()
    np.testing.assert_allclose(H.toarray(), dense, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(g, g_dense, rtol=0, atol=1e-12 * np.abs(g_dense).max())
    assert H.nnz < 0.5 * H.shape[0] ** 2  # sparse indeed
    # A loop closure: some camera block couples frames 50+ apart in the video.
    free = joint.frames[joint.ccol >= 0]
    rows = np.repeat(np.arange(len(sp.indptr) - 1), np.diff(sp.indptr))
    assert (np.abs(free[rows] - free[sp.indices]) > 0).any()
    # Positive definite: it factorises, and the factor solves it.
    x = _sparse_factor(H).solve(g)
    np.testing.assert_allclose(dense @ x, g, rtol=0, atol=1e-8 * np.abs(g).max())


def test_a_system_that_is_not_positive_definite_is_refused() -> None:
    H = scipy.sparse.csc_matrix(np.array([[2.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 3.0]]))
    with pytest.raises(np.linalg.LinAlgError):
        _sparse_factor(H)
    with pytest.raises(np.linalg.LinAlgError):
        _sparse_factor(scipy.sparse.csc_matrix(np.zeros((3, 3))))


def test_without_feature_points_the_solver_changes_nothing(true_state: SurveyState) -> None:
    rec, tracks, use = true_state.reconstruction, true_state.tracks, true_state.usable.repeat(4)
    _disturb(true_state, np.random.default_rng(24))
    a, a_info = bundle_adjust(rec, tracks, use, True, PRIOR, with_covariance=True, solver=ReducedSolver.DENSE)
    b, b_info = bundle_adjust(copy.deepcopy(rec), tracks, use, True, PRIOR, with_covariance=True)
    np.testing.assert_array_equal(a.X, b.X)
    np.testing.assert_array_equal(a.rvec, b.rvec)
    assert a_info.covariance is not None and b_info.covariance is not None
    np.testing.assert_array_equal(a_info.covariance, b_info.covariance)


# --- keyframes: the feature observations of every k-th frame adjusted jointly -------------


def test_keyframes_are_every_kth_frame_within_the_bound() -> None:
    frames = np.arange(3, 1003)
    assert FeatureKeyframes(250)(frames[:250]).all()
    assert FeatureKeyframes(None)(frames).all()
    key = FeatureKeyframes(250)(frames)
    assert key.sum() == 250 and key[0]
    np.testing.assert_array_equal(np.flatnonzero(key), np.arange(0, 1000, 4))
    key = FeatureKeyframes(300)(frames)  # k = 4: the least stride that keeps within 300
    assert key.sum() <= 300 and np.diff(np.flatnonzero(key)).tolist() == [4] * (int(key.sum()) - 1)


def test_over_keyframes_the_adjustment_still_finds_the_truth(true_state: SurveyState, room: ExampleRoom) -> None:
    """Noise-free: the keyframes' joint adjustment, then the other frames' poses fitted
    to it and the points seen in fewer than two keyframes to those, end at the truth;
    every observation is reported."""
    truth = copy.deepcopy(true_state.reconstruction)
    rng = np.random.default_rng(25)
    features, points = _wall_features(true_state, room, rng, 150)
    _disturb(true_state, rng)
    start = points + rng.normal(0, 0.02, points.shape)
    rec, tracks, use = true_state.reconstruction, true_state.tracks, true_state.usable.repeat(4)
    n_seen = len(np.unique(features.frame))
    out, info = bundle_adjust(rec, tracks, use, False, PRIOR, features=features, feature_X=start,
                              keyframes=FeatureKeyframes(n_seen // 3))
    _, full_info = bundle_adjust(rec, tracks, use, False, PRIOR, features=features, feature_X=start,
                              keyframes=FeatureKeyframes(None))
    assert info.feature_X is not None and full_info.feature_X is not None
    # Fewer observations jointly, every one reported:
    np.testing.assert_array_equal(np.sort(info.feature_obs), np.sort(full_info.feature_obs))
    np.testing.assert_array_equal(info.feature_points, full_info.feature_points)
    np.testing.assert_allclose(out.X, truth.X, atol=1e-8)
    np.testing.assert_allclose(out.rvec, truth.rvec, atol=1e-8)
    np.testing.assert_allclose(out.tvec, truth.tvec, atol=1e-8)
    np.testing.assert_allclose(info.feature_X, points, atol=1e-6)
    assert info.feature_rms_px < 1e-6 and info.held_frame == full_info.held_frame
