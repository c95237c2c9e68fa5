"""Registering frames against the map (resection)."""

from __future__ import annotations

import numpy as np

from app.core.geometry import Pose, TargetObservation
from app.core.survey.register import continuity, register_frames, single_target_pose
from app.core.survey.state import SurveyState
from app.sim.examples import RoomWalk


def _frame_seeing(state: SurveyState, n_targets: int) -> int:
    return int(next(f for f, v in enumerate(state.views.of_frame) if len(v) == n_targets and f > 2))


def test_a_frame_seeing_several_targets_is_registered_at_its_pose(true_state: SurveyState,
                                                                  room_walk: RoomWalk) -> None:
    rec = true_state.reconstruction
    f = _frame_seeing(true_state, 5)
    rec.unregister(f)
    assert register_frames(true_state, 2) == 1
    np.testing.assert_allclose(rec.pose(f).R, room_walk.poses[f].R, atol=1e-9)
    np.testing.assert_allclose(rec.pose(f).t, room_walk.poses[f].t, atol=1e-9)
    assert not true_state.weak[f] and true_state.attempted[f] == 5
    # Tried once with 5 targets: not again until it sees more.
    rec.unregister(f)
    assert register_frames(true_state, 2) == 0


def test_a_frame_seeing_one_target_waits_for_single_target_poses(true_state: SurveyState,
                                                                 room_walk: RoomWalk) -> None:
    """A frame that sees one placed target is registered only when single-target poses
    are allowed, at the tilt that fits the camera's motion, and marked weak."""
    rec = true_state.reconstruction
    f = _frame_seeing(true_state, 1)
    rec.unregister(f)
    assert register_frames(true_state, 2) == 0 and not rec.registered()[f]
    assert register_frames(true_state, 1) == 1
    assert true_state.weak[f]
    np.testing.assert_allclose(rec.pose(f).position, room_walk.poses[f].position, atol=1e-5)


def test_a_misread_target_is_set_aside_in_its_frame(true_state: SurveyState, room_walk: RoomWalk) -> None:
    """A view whose card is not where the map has it (a misread code) does not move the
    frame's pose and is not used in that frame."""
    rec, views = true_state.reconstruction, true_state.views
    f = _frame_seeing(true_state, 5)
    wrong = views.of_frame[f][0]
    views.uv[wrong] = views.uv[wrong] + (60.0, 40.0)
    rec.unregister(f)
    assert register_frames(true_state, 2) == 1
    np.testing.assert_allclose(rec.pose(f).t, room_walk.poses[f].t, atol=1e-6)
    assert not true_state.usable[wrong] and true_state.usable[views.of_frame[f][1:]].all()


def test_continuity_refuses_a_pose_far_from_the_neighbours(true_state: SurveyState, room_walk: RoomWalk) -> None:
    f = _frame_seeing(true_state, 1)
    true_pose = room_walk.poses[f]
    near = continuity(true_state, f, true_pose)
    assert np.isfinite(near)
    assert continuity(true_state, f, Pose(true_pose.R, true_pose.t + np.array([1.0, 0.0, 0.0]))) == np.inf
    # No frame registered on 2+ targets within 10 frames: no judgement possible.
    for g in np.flatnonzero(true_state.reconstruction.registered()):
        if abs(g - f) <= 10 and g != f:
            true_state.reconstruction.unregister(int(g))
    assert continuity(true_state, f, true_pose) == np.inf


def test_single_target_pose_picks_the_true_tilt(true_state: SurveyState, room_walk: RoomWalk) -> None:
    """Where the image refutes the other tilt (exact views, a tiny noise level) the pose
    from one card is the true one, for every card of every frame."""
    rec, views = true_state.reconstruction, true_state.views
    for f in range(3, true_state.tracks.n_frames):
        for v in views.of_frame[f]:
            t = int(views.target[v])
            ob = TargetObservation(t, views.uv[v], rec.discs(t))
            pose = single_target_pose(true_state, f, ob, noise_px2=1e-6)
            assert pose is not None
            np.testing.assert_allclose(pose.position, room_walk.poses[f].position, atol=1e-5)
