"""Feature points' observations and their robust losses."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from app.core.survey.points import FeatureObservations, RobustLoss


@pytest.mark.parametrize("loss", list(RobustLoss))
def test_each_loss_is_quadratic_near_zero_and_its_weight_is_its_slope(loss: RobustLoss) -> None:
    """cost(e) ~ e^2 / 2 for small errors, and weight(e) = cost'(e) / e: the weighted
    least squares of the bundle adjustment descend the loss itself."""
    e = np.array([1e-3, 0.5, 1.0, 2.5, 4.0, 30.0])
    np.testing.assert_allclose(loss.cost(e[:1], 2.5), 0.5 * e[:1] ** 2, rtol=1e-6)
    h = 1e-6
    slope = (loss.cost(e + h, 2.5) - loss.cost(e - h, 2.5)) / (2 * h)
    np.testing.assert_allclose(loss.weight(e, 2.5), slope / e, rtol=1e-6)


def test_a_wrong_match_weighs_little_and_cauchy_less_than_huber() -> None:
    """40 sigmas off: Huber's weight is scale / e, Cauchy's falls as 1 / e^2."""
    e = np.array([40.0])
    assert RobustLoss.HUBER.weight(e, 2.5)[0] == pytest.approx(2.5 / 40)
    assert RobustLoss.CAUCHY.weight(e, 2.5)[0] < 0.01 < RobustLoss.HUBER.weight(e, 2.5)[0]
    assert (RobustLoss.HUBER.weight(np.array([0.0, 2.5]), 2.5) == 1.0).all()


def test_observations_whiten_by_their_noise_level() -> None:
    features = FeatureObservations(np.array([0, 1]), np.array([0, 0]), np.zeros((2, 2)), sigma_px=0.5,
                                   loss=RobustLoss.HUBER, loss_scale=2.0)
    r = np.array([[0.3, 0.4], [6.0, 8.0]])  # 1 and 20 sigmas
    np.testing.assert_allclose(features.whitened(r), [1.0, 20.0])
    np.testing.assert_allclose(features.cost(r), [0.5, 2.0 * (20.0 - 1.0)])
    np.testing.assert_allclose(features.weights(r), np.array([1.0, 2.0 / 20.0]) / 0.25)


def test_a_trackers_arrays_map_to_observations() -> None:
    """Anything with flat frame, track and uv arrays (a feature tracker's tracks) maps to
    observations row for row."""

    @dataclass
    class Tracked:
        frame: np.ndarray
        track: np.ndarray
        uv: np.ndarray

    tracked = Tracked(np.array([0, 0, 3]), np.array([2, 5, 2]), np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]],
                                                                         np.float32))
    features = FeatureObservations.from_tracks(tracked, sigma_px=0.8, loss=RobustLoss.CAUCHY, loss_scale=3.0)
    np.testing.assert_array_equal(features.frame, tracked.frame)
    np.testing.assert_array_equal(features.track, tracked.track)
    np.testing.assert_array_equal(features.uv, tracked.uv)
    assert features.uv.dtype == np.float64 and len(features) == 3
    assert (features.sigma_px, features.loss, features.loss_scale) == (0.8, RobustLoss.CAUCHY, 3.0)
    assert len(FeatureObservations.empty()) == 0


def test_observations_are_checked() -> None:
    with pytest.raises(ValueError, match="one row per observation"):
        FeatureObservations(np.array([0, 1]), np.array([0]), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="one row per observation"):
        FeatureObservations(np.array([0, 1]), np.array([0, 1]), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="positive"):
        FeatureObservations(np.array([0]), np.array([0]), np.zeros((1, 2)), sigma_px=0.0)
