"""The survey's result: the map, its uncertainty, the trajectory, warnings."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.survey.advice import WarningKind
from app.core.survey.bundle import bundle_adjust
from app.core.survey.result import (
    MIN_VIEWS,
    SurveyedViews,
    SurveyResult,
    map_advice_of,
    survey_result,
    surveyed_views,
)
from app.core.survey.scale import MetricScale
from app.core.survey.state import SurveyError, SurveyState
from app.sim.examples import RoomWalk


def _result(state: SurveyState, used: list[int], n_input: int) -> tuple[SurveyResult, SurveyedViews]:
    _, info = bundle_adjust(state.reconstruction, state.tracks, state.usable.repeat(4), False, (0.2, 1e-5),
                            max_iterations=0, with_covariance=True)
    surveyed = surveyed_views(state)
    return survey_result(state, info, surveyed, MetricScale(1.0, 0.0), used, n_input), surveyed


def test_survey_result_of_the_true_state(true_state: SurveyState, room_walk: RoomWalk) -> None:
    n = true_state.tracks.n_frames
    used = list(range(0, 2 * n, 2))  # as if every other frame of a video twice as long
    result, surveyed = _result(true_state, used, 2 * n)
    assert result.rms_px < 1e-9 and result.n_rejected_views == 0
    assert len(result.targets) == true_state.tracks.n_targets == len(surveyed.targets)
    truth = {t.id: t.discs for t in room_walk.scene.targets}
    for target in result.targets:
        np.testing.assert_allclose(target.discs, truth[target.id], atol=1e-12)
        assert target.n_views == len(true_state.views.of_target[list(true_state.tracks.ids).index(target.id)])
        assert np.isfinite(target.std_m).all()
    # The discs' joint covariance, by target in the result's order: each disc's block
    # gives its std_m.
    assert result.disc_covariance is not None and result.disc_covariance.shape == (12 * len(result.targets),) * 2
    blocks = np.diag(result.disc_covariance).reshape(-1, 3).sum(axis=1)
    np.testing.assert_allclose(np.sqrt(blocks), np.concatenate([t.std_m for t in result.targets]))
    assert len(result.trajectory) == 2 * n
    assert all(p is None for p in result.trajectory[1::2])
    for f, pose in enumerate(result.trajectory[::2]):
        if pose is None:
            assert not len(true_state.views.of_frame[f])
        else:
            np.testing.assert_allclose(pose.t, room_walk.poses[f].t, atol=1e-12)
    assert result.n_observations == len(true_state.tracks.frame)
    assert result.frames_used == used and result.intrinsics_fixed
    assert result.warnings is true_state.warnings


def test_rejected_views_and_weak_targets(true_state: SurveyState) -> None:
    views = true_state.views
    t = 11  # seen 3 times
    assert len(views.of_target[t]) == MIN_VIEWS
    true_state.usable[views.of_target[t][0]] = False
    true_state.usable[views.of_target[15][:-1]] = False  # target 15: one view left, not surveyed
    result, surveyed = _result(true_state, list(range(true_state.tracks.n_frames)), true_state.tracks.n_frames)
    assert result.n_rejected_views == 1 + len(views.of_target[15]) - 1 == surveyed.n_rejected
    ids = true_state.tracks.ids
    assert int(ids[15]) not in {r.id for r in result.targets}
    assert result.target(int(ids[t])).n_views == MIN_VIEWS - 1
    with pytest.raises(KeyError):
        result.target(int(ids[15]))
    assert any(w.startswith(f"card {int(ids[t])}: seen in {MIN_VIEWS - 1} registered frames only (fewer than "
                            f"{MIN_VIEWS})") for w in result.warnings)
    assert any(w.startswith(f"card {int(ids[15])} could not be surveyed") for w in result.warnings)


def test_parts_of_the_map_seen_apart_are_flagged(true_state: SurveyState) -> None:
    """Targets never seen together with the rest are linked only through the camera's
    motion: a warning names them."""
    views = true_state.views
    t = 0
    frames_t = set(views.frame[views.of_target[t]].tolist())
    # Keep target 0's views, drop every other view in its frames.
    for f in frames_t:
        for v in views.of_frame[f]:
            if views.target[v] != t:
                true_state.usable[v] = False
    result, surveyed = _result(true_state, list(range(true_state.tracks.n_frames)), true_state.tracks.n_frames)
    card = int(true_state.tracks.ids[t])
    assert any("not seen together with the rest" in w.message and f": card {card};" in w.message
               and w.kind is WarningKind.DISCONNECTED and card in w.target_ids
               for w in map_advice_of(result.targets, true_state.tracks, views, surveyed))


def test_nothing_seen_twice_cannot_be_surveyed(true_state: SurveyState) -> None:
    for v in true_state.views.of_target:
        true_state.usable[v[1:]] = False
    with pytest.raises(SurveyError, match="2 or more registered frames"):
        surveyed_views(true_state)
