"""Step 2 of the survey: the metric start from two frames."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from app.core.detection import DetectedTarget
from app.core.survey.seed import bootstrap, two_view_seed
from app.core.survey.state import Reconstruction, StageClock, SurveySettings, SurveyState
from app.core.survey.tracks import collect_tracks
from app.sim.examples import ExampleRoom, RoomWalk


def _empty(state: SurveyState) -> SurveyState:
    state.reconstruction = Reconstruction.empty(state.reconstruction.camera, state.tracks.n_frames,
                                                state.tracks.n_targets)
    state.seed_frame = -1
    return state


def test_two_view_seed_is_the_true_relative_pose_at_metric_scale(true_state: SurveyState,
                                                                 room_walk: RoomWalk) -> None:
    """On exact views the start is the truth in the first frame's camera frame, in metres
    (the printed card size gives the scale)."""
    truth = true_state.reconstruction
    start = two_view_seed(truth.camera, true_state.views, 0.2, tol_px=6.0)
    assert start is not None
    a, b, pose_b, discs = start
    assert a != b and len(discs) >= 3
    pa, pb = room_walk.poses[a], room_walk.poses[b]
    R = pb.R @ pa.R.T
    np.testing.assert_allclose(pose_b.R, R, atol=1e-9)
    np.testing.assert_allclose(pose_b.t, pb.t - R @ pa.t, atol=1e-9)
    for t, X in discs.items():
        np.testing.assert_allclose(X, pa.transform(truth.discs(t)), atol=1e-9)
        # Both frames see every target the start places.
        assert {a, b} <= set(true_state.views.frame[true_state.views.of_target[t]].tolist())


def test_bootstrap_fixes_the_map_frame(true_state: SurveyState) -> None:
    state = _empty(true_state)
    bootstrap(state)
    rec = state.reconstruction
    assert rec.n_registered == 2 and rec.registered()[state.seed_frame]
    np.testing.assert_array_equal(rec.rvec[state.seed_frame], 0.0)
    np.testing.assert_array_equal(rec.tvec[state.seed_frame], 0.0)
    assert rec.placed().sum() >= 12


def test_bootstrap_without_a_pair_starts_from_the_best_seen_frame(
        room: ExampleRoom, synthetic_frames: Callable[[float, int], list[list[DetectedTarget]]]) -> None:
    """When no two frames share 3 targets, the frame that sees most targets (then most
    card area) fixes the map frame alone, and nothing is placed yet."""
    frames = [f[:2] for f in synthetic_frames(0.0, 0)]
    warnings: list[str] = []
    tracks = collect_tracks(frames, list(range(len(frames))), warnings)
    state = SurveyState.start(tracks, room.camera, SurveySettings(0.2, intrinsics_given=True), StageClock(),
                              warnings)
    bootstrap(state)
    rec, views = state.reconstruction, state.views
    assert rec.n_registered == 1 and not rec.placed().any()
    seed = state.seed_frame
    n = np.array([len(v) for v in views.of_frame])
    area = np.array([views.area[v].sum() for v in views.of_frame])
    assert n[seed] == n.max() and area[seed] == area[n == n.max()].max()
