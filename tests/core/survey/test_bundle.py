"""Bundle adjustment: the lens, every pose and every disc at once."""

from __future__ import annotations

import copy

import numpy as np

from app.core.survey.bundle import bundle_adjust, camera_from_intrinsics
from app.core.survey.cards import PAIR_UNITS, PAIRS
from app.core.survey.state import SurveyState

PRIOR = (0.2, 1e-5)  # the printed card, 10 um


def _held(state: SurveyState) -> int:
    """The frame the bundle adjustment holds (the gauge)."""
    _, info = bundle_adjust(state.reconstruction, state.tracks, state.usable.repeat(4), False, PRIOR,
                            max_iterations=0)
    return info.held_frame


def _disturb(state: SurveyState, rng: np.random.Generator) -> None:
    """Every point by ~5 mm, every pose but the held one by ~0.3 degree and ~1 cm."""
    rec = state.reconstruction
    held = _held(state)
    moved = rec.registered()
    moved[held] = False
    rec.X += rng.normal(0, 0.005, rec.X.shape)
    rec.rvec[moved] += rng.normal(0, 0.005, (int(moved.sum()), 3))
    rec.tvec[moved] += rng.normal(0, 0.01, (int(moved.sum()), 3))


def test_bundle_adjustment_recovers_disturbed_poses_and_points(true_state: SurveyState) -> None:
    truth = copy.deepcopy(true_state.reconstruction)
    _disturb(true_state, np.random.default_rng(1))
    start = true_state.reconstruction
    out, info = bundle_adjust(start, true_state.tracks, true_state.usable.repeat(4), False, PRIOR)
    # The held frame and the card prior fix the gauge: the optimum is the truth.
    np.testing.assert_allclose(out.X, truth.X, atol=1e-9)
    np.testing.assert_allclose(out.rvec, truth.rvec, atol=1e-9)
    np.testing.assert_allclose(out.tvec, truth.tvec, atol=1e-9)
    assert info.rms_px < 1e-9 and 0 < info.iterations < 100
    assert info.n_intr == 0 and out.camera is start.camera
    assert start.X is not out.X  # the start is left as it was


def test_bundle_adjustment_finds_the_lens(true_state: SurveyState) -> None:
    camera = true_state.reconstruction.camera
    _disturb(true_state, np.random.default_rng(2))
    true_state.reconstruction.camera = camera_from_intrinsics(np.array([612.0, 324.0, 236.0, -0.08, 0.01]), 640, 480)
    out, info = bundle_adjust(true_state.reconstruction, true_state.tracks, true_state.usable.repeat(4), True, PRIOR)
    assert info.n_intr == 5 and info.rms_px < 1e-9
    np.testing.assert_allclose(out.camera.K, camera.K, atol=1e-6)
    np.testing.assert_allclose(out.camera.dist, camera.dist, atol=1e-9)


def test_the_card_prior_makes_the_map_metric(true_state: SurveyState) -> None:
    """Reprojection alone leaves the scale free; the card prior gives every card its
    printed size."""
    rec = true_state.reconstruction
    rec.X *= 1.1
    rec.tvec *= 1.1
    use = true_state.usable.repeat(4)
    free, _ = bundle_adjust(rec, true_state.tracks, use, False, None)
    metric, info = bundle_adjust(rec, true_state.tracks, use, False, PRIOR)
    assert info.rms_px < 1e-9

    def sides(X: np.ndarray) -> np.ndarray:
        cards = X.reshape(-1, 4, 3)
        return np.linalg.norm(cards[:, PAIRS[:, 0]] - cards[:, PAIRS[:, 1]], axis=2) / (PAIR_UNITS * 0.2)

    np.testing.assert_allclose(sides(free.X), 1.1, rtol=1e-9)
    np.testing.assert_allclose(sides(metric.X), 1.0, rtol=1e-7)


def test_huber_loss_lowers_the_pull_of_a_wild_observation(true_state: SurveyState) -> None:
    """A disc 1 px off (glare) weighs by its precision times Huber's weight: with the
    loss from 2.5 expected errors it moves the map far less than in least squares."""
    truth = true_state.reconstruction.X.copy()
    views = true_state.views
    v = views.of_target[4][5]
    views.uv[v, 0] += (0.8, -0.6)
    use = true_state.usable.repeat(4)
    robust, info = bundle_adjust(true_state.reconstruction, true_state.tracks, use, False, PRIOR, loss_scale=2.5)
    plain, _ = bundle_adjust(true_state.reconstruction, true_state.tracks, use, False, PRIOR, loss_scale=1e6)
    k = int(np.flatnonzero(info.obs == 4 * v)[0])
    assert info.weights[k] < 0.1 * true_state.tracks.precision[4 * v]
    others = np.delete(np.arange(len(info.obs)), k)
    np.testing.assert_allclose(info.weights[others], true_state.tracks.precision[info.obs[others]])
    error = np.nanmax(np.abs(robust.X - truth)), np.nanmax(np.abs(plain.X - truth))
    assert error[0] < 0.5 * error[1]


def test_only_used_observations_take_part(true_state: SurveyState) -> None:
    rec, views = true_state.reconstruction, true_state.views
    use = true_state.usable.copy()
    use[views.of_target[3]] = False  # target 3 left out: its points do not move
    rec.X[12:16] += 0.01
    out, info = bundle_adjust(rec, true_state.tracks, use.repeat(4), False, PRIOR, max_iterations=3)
    np.testing.assert_array_equal(out.X[12:16], rec.X[12:16])
    assert 12 not in info.points and len(info.obs) == 4 * int(use.sum())


def test_covariance_gives_each_disc_an_uncertainty(true_state: SurveyState) -> None:
    rng = np.random.default_rng(4)
    true_state.tracks.uv += rng.normal(0, 0.1, true_state.tracks.uv.shape)
    use = true_state.usable.repeat(4)
    rec, _ = bundle_adjust(true_state.reconstruction, true_state.tracks, use, False, PRIOR)
    again, info = bundle_adjust(rec, true_state.tracks, use, False, PRIOR, max_iterations=0, with_covariance=True)
    np.testing.assert_array_equal(again.X, rec.X)  # no iterations: the map stays
    assert info.covariance is not None and info.covariance.shape == (3 * len(info.points),) * 2
    std = info.disc_std(len(rec.X))
    assert np.isfinite(std).all() and 1e-4 < np.median(std) < 0.02  # 0.1 px at 1-3 m: mm
    # Without the covariance: no uncertainty.
    _, plain = bundle_adjust(rec, true_state.tracks, use, False, PRIOR, max_iterations=0)
    assert plain.covariance is None and np.isnan(plain.disc_std(len(rec.X))).all()
