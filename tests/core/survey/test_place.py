"""Placing targets in the map from registered frames (triangulation)."""

from __future__ import annotations

import numpy as np

from app.core.survey.cards import normalised, triangulate_robust
from app.core.survey.place import place_card, place_targets
from app.core.survey.state import SurveyState


def _consecutive_pair(state: SurveyState, t: int) -> list[int]:
    """Two views of target ``t`` from consecutive frames: a narrow baseline."""
    v = state.views.of_target[t]
    f = state.views.frame[v]
    k = int(np.flatnonzero(np.diff(f) == 1)[0])
    return [int(v[k]), int(v[k + 1])]


def test_a_target_is_triangulated_from_known_poses(true_state: SurveyState) -> None:
    rec = true_state.reconstruction
    truth = rec.X.copy()
    for t in (0, 4, 11):
        rec.unplace(t)
    assert place_targets(true_state) == 3
    np.testing.assert_allclose(rec.X, truth, atol=1e-9)
    assert not true_state.placed_by_plane.any()
    assert place_targets(true_state) == 0  # nothing left to place


def test_a_narrow_baseline_places_the_rigid_card_then_triangulates(true_state: SurveyState) -> None:
    """From two frames 1.8 degrees apart the card is placed as the printed card fitted to
    its views; once wider views come in it is triangulated."""
    rec = true_state.reconstruction
    t = 2
    truth = rec.discs(t).copy()
    pair = _consecutive_pair(true_state, t)
    rec.unplace(t)
    true_state.usable[true_state.views.of_target[t]] = False
    true_state.usable[pair] = True
    assert place_targets(true_state) == 1
    assert true_state.placed_by_plane[t]
    np.testing.assert_allclose(rec.discs(t), truth, atol=1e-9)
    true_state.usable[true_state.views.of_target[t]] = True
    assert place_targets(true_state) == 1  # the upgrade counts: the map changed
    assert not true_state.placed_by_plane[t]
    np.testing.assert_allclose(rec.discs(t), truth, atol=1e-9)


def test_place_card_fits_the_printed_card(true_state: SurveyState) -> None:
    rec = true_state.reconstruction
    for t in range(true_state.tracks.n_targets):
        if np.any(np.diff(true_state.views.frame[true_state.views.of_target[t]]) == 1):
            card = place_card(true_state, _consecutive_pair(true_state, t))
            assert card is not None
            np.testing.assert_allclose(card, rec.discs(t), atol=1e-9)


def test_views_of_another_card_are_outvoted(true_state: SurveyState) -> None:
    """Views that show another card (a misread code) do not move the triangulated target."""
    rec, views = true_state.reconstruction, true_state.views
    t, other = 1, 2
    truth = rec.discs(t).copy()
    # In the frames that see both, t's view shows the other card's discs.
    frames_t = views.frame[views.of_target[t]]
    frames_o = set(views.frame[views.of_target[other]].tolist())
    wrong = [int(v) for v, f in zip(views.of_target[t], frames_t, strict=True) if f in frames_o]
    assert 2 <= len(wrong) < len(frames_t) / 3
    for v in wrong:
        f = views.frame[v]
        views.uv[v] = views.uv[next(w for w in views.of_target[other] if views.frame[w] == f)]
    rec.unplace(t)
    assert place_targets(true_state) == 1
    np.testing.assert_allclose(rec.discs(t), truth, atol=1e-9)
    # The consensus says which views agree.
    seen = list(views.of_target[t])
    poses = [rec.pose(views.frame[v]) for v in seen]
    x = np.stack([normalised(rec.camera, views.uv[v]) for v in seen])
    found = triangulate_robust(poses, x, 1e-3, np.random.default_rng(0))
    assert found is not None
    assert [seen[k] for k in np.flatnonzero(~found[1])] == wrong


def test_a_target_found_wrong_waits_for_more_views(true_state: SurveyState) -> None:
    rec = true_state.reconstruction
    t = 4
    rec.unplace(t)
    true_state.unplaced_at[t] = len(true_state.views.of_target[t])  # found wrong with every view it has
    assert place_targets(true_state) == 0 and not rec.placed()[4 * t]
    true_state.unplaced_at[t] -= 1
    assert place_targets(true_state) == 1
