"""The metric scale of the map, from the printed card size."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.survey.scale import apply_metric_scale
from app.core.survey.state import SurveyState


def test_the_map_takes_the_printed_card_size(true_state: SurveyState) -> None:
    rec = true_state.reconstruction
    truth_X, truth_t = rec.X.copy(), rec.tvec.copy()
    rec.X *= 2.5
    rec.tvec *= 2.5  # the same views, a map 2.5 times too large
    scale = apply_metric_scale(rec, np.arange(true_state.tracks.n_targets), 0.2)
    assert scale.factor == pytest.approx(0.4, rel=1e-9) and scale.residual_m < 1e-12
    np.testing.assert_allclose(rec.X, truth_X, atol=1e-12)
    np.testing.assert_allclose(rec.tvec, truth_t, atol=1e-12, equal_nan=True)
    # The poses' rotations do not change: every view fits as before.
    assert np.nanmax(rec.errors(true_state.tracks, np.arange(len(true_state.tracks.frame)))) < 1e-9


def test_the_residual_says_how_far_the_cards_are_from_their_printed_size(true_state: SurveyState) -> None:
    rec = true_state.reconstruction
    rec.X[0] += (0.01, 0.0, 0.0)  # one disc 1 cm off: that card is not the printed square
    scale = apply_metric_scale(rec, np.arange(true_state.tracks.n_targets), 0.2)
    assert scale.factor == pytest.approx(1.0, abs=1e-3)
    assert 1e-4 < scale.residual_m < 0.01
