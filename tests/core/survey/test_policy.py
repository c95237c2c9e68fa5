"""When the survey bundle-adjusts again and when the lens moves."""

from __future__ import annotations

import numpy as np

from app.core.survey.policy import ShouldBundle, ShouldFitLens
from app.core.survey.state import SurveyState


def _keep_registered(state: SurveyState, n: int) -> None:
    for f in np.flatnonzero(state.reconstruction.registered())[n:]:
        state.reconstruction.unregister(int(f))
    assert state.reconstruction.n_registered == n


def test_should_bundle_after_a_change_once_enough_frames(true_state: SurveyState) -> None:
    should = ShouldBundle(min_frames=3)
    _keep_registered(true_state, 3)
    assert should(true_state, changed=True)
    assert not should(true_state, changed=False)
    _keep_registered(true_state, 2)
    assert not should(true_state, changed=True)


def test_the_lens_moves_only_when_enough_frames_and_not_given(true_state: SurveyState) -> None:
    should = ShouldFitLens(growing_min_frames=15, final_min_frames=10)
    assert true_state.lens_fixed  # given intrinsics are never fitted
    assert not should.while_growing(true_state) and not should.at_the_end(true_state)
    true_state.lens_fixed = False
    _keep_registered(true_state, 15)
    assert should.while_growing(true_state) and should.at_the_end(true_state)
    _keep_registered(true_state, 12)
    assert not should.while_growing(true_state) and should.at_the_end(true_state)
    _keep_registered(true_state, 9)
    assert not should.while_growing(true_state) and not should.at_the_end(true_state)
