"""Judging the map by its views: outlier removal and the robust noise level."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.survey.prune import drop_unsupported, noise_variance, prune, view_errors, whitened_spread
from app.core.survey.state import SurveyState


def test_a_corrupted_view_is_set_aside_and_taken_back(true_state: SurveyState) -> None:
    views, usable = true_state.views, true_state.usable
    v = views.of_target[4][3]
    views.uv[v, 2] += (1.0, 0.5)
    errors = view_errors(true_state, np.ones(len(views), bool))
    assert errors[v] == pytest.approx(np.hypot(1.0, 0.5), abs=1e-9) and np.delete(errors, v).max() < 1e-9
    assert prune(true_state, 0.5)
    assert not usable[v] and usable.sum() == len(views) - 1
    assert true_state.reconstruction.n_registered == sum(len(f) > 0 for f in views.of_frame)
    assert not prune(true_state, 0.5)  # nothing more to do
    views.uv[v, 2] -= (1.0, 0.5)  # it fits again
    assert prune(true_state, 0.5) and usable[v]


def test_views_set_aside_come_back_only_below_the_readmission_threshold(true_state: SurveyState) -> None:
    views, usable = true_state.views, true_state.usable
    v = views.of_target[4][3]
    views.uv[v, 2] += (0.3, 0.0)
    usable[v] = False
    assert not prune(true_state, 0.5, readmit_below=0.25) and not usable[v]
    assert prune(true_state, 0.5) and usable[v]


def test_thresholds_in_units_of_each_observation(true_state: SurveyState) -> None:
    views, usable = true_state.views, true_state.usable
    v = views.of_target[4][3]
    views.uv[v, 2] += (0.3, 0.0)
    unit = np.full(len(true_state.tracks.frame), 0.1)  # px: the view is 3 units off
    assert not prune(true_state, 5.0, unit) and usable[v]
    assert prune(true_state, 2.0, unit) and not usable[v]


def test_a_frame_whose_views_do_not_fit_is_unregistered(true_state: SurveyState) -> None:
    rec, views = true_state.reconstruction, true_state.views
    f = 20
    views.uv[views.of_frame[f]] += 3.0
    assert prune(true_state, 0.5)
    assert not rec.registered()[f]
    assert rec.n_registered == sum(len(v) > 0 for v in views.of_frame) - 1
    assert true_state.usable.all()  # the frame is out; its views are not judged


def test_the_seed_frame_stays(true_state: SurveyState) -> None:
    rec, views = true_state.reconstruction, true_state.views
    f = true_state.seed_frame
    views.uv[views.of_frame[f]] += 3.0
    assert prune(true_state, 0.5)
    assert rec.registered()[f] and not true_state.usable[views.of_frame[f]].any()


def test_a_target_most_views_disagree_with_is_unplaced(true_state: SurveyState) -> None:
    """Judged by every view, also those set aside: a target placed wrong fits none, is
    taken out, and its views get a new chance (it is placed again only from more)."""
    rec, views = true_state.reconstruction, true_state.views
    t = 4
    rec.place(t, rec.discs(t) + 0.05)
    true_state.usable[views.of_target[t][:3]] = False
    assert prune(true_state, 0.5)
    assert not rec.placed()[4 * t : 4 * t + 4].any()
    assert true_state.usable[views.of_target[t]].all()
    assert true_state.unplaced_at[t] == len(views.of_target[t])


def test_drop_unsupported(true_state: SurveyState) -> None:
    rec, views = true_state.reconstruction, true_state.views
    n = rec.n_registered
    true_state.usable[views.of_frame[20]] = False
    true_state.usable[views.of_target[15]] = False
    drop_unsupported(true_state)
    assert not rec.registered()[20] and not rec.placed()[60:64].any()
    # Frames that saw only target 15 are out too; the rest stay.
    alone = [f for f, v in enumerate(views.of_frame) if len(v) and set(views.target[v]) == {15}]
    assert rec.n_registered == n - 1 - len(alone)
    assert rec.placed().sum() == 4 * (true_state.tracks.n_targets - 1)


def test_the_noise_level_is_measured_robustly(true_state: SurveyState) -> None:
    rng = np.random.default_rng(3)
    tracks = true_state.tracks
    exact = tracks.uv.copy()
    tracks.uv[:] = exact + rng.normal(0, 0.2, exact.shape)
    assert noise_variance(true_state) == pytest.approx(0.2**2, rel=0.15)
    # A few wild views do not move it.
    tracks.uv[::50] += 30.0
    assert noise_variance(true_state) == pytest.approx(0.2**2, rel=0.2)
    # Whitened: errors as `DISC_ERROR_PX` expects them have a spread of 1.
    tracks.uv[:] = exact + rng.normal(size=exact.shape) * tracks.expected_px[:, None]
    assert whitened_spread(true_state) == pytest.approx(1.0, rel=0.1)
    # No noise: floored, so that Huber's loss keeps a scale.
    tracks.uv[:] = exact
    assert whitened_spread(true_state) == 0.01 and noise_variance(true_state) == 0.01**2


def test_setting_views_aside_does_not_lower_the_noise_level_that_judges_them(true_state: SurveyState) -> None:
    """The refinement's outlier threshold is a multiple of the spread: were the views set
    aside left out of it, each round would cut the threshold and set aside more, until
    whole cards whose errors are a little larger than the rest are lost."""
    rng = np.random.default_rng(4)
    tracks = true_state.tracks
    tracks.uv += rng.normal(size=tracks.uv.shape) * tracks.expected_px[:, None]
    before = whitened_spread(true_state)
    worst = np.argsort(view_errors(true_state, true_state.usable))[-len(true_state.usable) // 5:]
    true_state.usable[worst] = False
    assert whitened_spread(true_state) == before
