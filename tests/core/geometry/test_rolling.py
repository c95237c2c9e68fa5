"""Poses through a rolling shutter (app.core.geometry.rolling): the discs come from the
simulator's rolling-shutter truth (app.sim.shutter), never from the model under test."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.geometry import (
    CameraMotion,
    PoseHistory,
    PoseUndetermined,
    RollingShutter,
    TargetObservation,
    estimate_pose,
    extrapolate,
    rolling_shutter_pose,
    undo_rolling_shutter,
)
from app.core.geometry.rolling import MAX_GAP, STEADY_FRAMES
from app.sim import draw_walk, scenes
from app.sim.examples import BENCH_WALK
from app.sim.shutter import rolling_projection

READOUT_S = 0.020
NOISE_PX = 0.03


@pytest.fixture(scope="module")
def walk() -> tuple[list[list[TargetObservation]], list, object]:
    """A fast tracking walk in the bench room read out over 20 ms: each frame's whole
    cards as the rolling shutter shows them (plus a little noise), with the truth."""
    room = BENCH_WALK.walk(3, 60)
    camera = BENCH_WALK.room.camera
    rng = np.random.default_rng(5)
    drawn = draw_walk(np.random.default_rng([3, 1]), room.scene.room_size, 100, "tracking")
    readouts = drawn.readouts(READOUT_S)
    frames, truths = [], []
    discs_of = {t.id: t.discs for t in room.scene.targets}
    for pose, readout in zip(drawn.poses, readouts, strict=True):
        truth = scenes.frame_truth(camera, pose, room.scene)
        observed = []
        for target in truth.targets:
            if target.visible and not target.occluded and target.disc_diameter_px > 6:
                discs = rolling_projection(camera, readout, discs_of[target.id])
                if np.all((discs >= 0) & (discs < [camera.width, camera.height])):
                    observed.append(TargetObservation(target.id, discs + rng.normal(0, NOISE_PX, discs.shape),
                                                      discs_of[target.id]))
        frames.append(observed)
        truths.append(pose)
    return frames, truths, camera


def _error_mm(estimate_position: np.ndarray, truth) -> float:
    return 1000 * float(np.linalg.norm(estimate_position - truth.position))


def test_several_cards_pin_the_motion_down_without_a_track(walk) -> None:
    frames, truths, camera = walk
    shutter = RollingShutter.from_seconds(READOUT_S, 30.0)
    global_errors, rolling_errors = [], []
    for observed, truth in zip(frames, truths, strict=True):
        if len(observed) < 3:
            continue
        global_errors.append(_error_mm(estimate_pose(observed, camera).pose.position, truth))
        rolling_errors.append(_error_mm(rolling_shutter_pose(observed, camera, shutter).estimate.pose.position,
                                        truth))
    assert len(rolling_errors) >= 10
    # Read as a global shutter the pose is about a metre off (small cards, a fast turn);
    # with the motion fitted, a few centimetres.
    assert np.median(global_errors) > 500
    assert np.median(rolling_errors) < 0.05 * np.median(global_errors)


def test_a_track_carries_the_motion_through_frames_of_one_card(walk) -> None:
    frames, truths, camera = walk
    shutter = RollingShutter.from_seconds(READOUT_S, 30.0)
    history, posed = PoseHistory(), []
    global_errors, rolling_errors = [], []
    for k, (observed, truth) in enumerate(zip(frames, truths, strict=True)):
        prior = None
        if len(posed) >= 2 and posed[-1][0] == k - 1 and posed[-2][0] == k - 2:
            prior = extrapolate(posed[-2][1], posed[-1][1], 1.0)
        try:
            estimate = rolling_shutter_pose(observed, camera, shutter, history.motion_for(k), prior).estimate
        except PoseUndetermined:
            history.add(k, None)
            continue
        history.add(k, estimate.pose)
        posed.append((k, estimate.pose))
        if len(observed) == 1 and history.motion_for(k + 1) is not None and len(posed) > 5:
            rolling_errors.append(_error_mm(estimate.pose.position, truth))
            global_errors.append(_error_mm(estimate_pose(observed, camera, prior=prior).pose.position, truth))
    assert len(rolling_errors) >= 10
    assert np.median(global_errors) > 100
    assert np.median(rolling_errors) < 0.1 * np.median(global_errors)


def test_a_still_camera_or_a_global_shutter_changes_nothing(walk) -> None:
    frames, truths, camera = walk
    observed = next(o for o in frames if len(o) >= 2)
    pose = estimate_pose(observed, camera).pose
    moving = CameraMotion(np.array([0.0, 0.03, 0.0]), np.array([0.01, 0.0, 0.0]))
    for o, same in zip(observed, undo_rolling_shutter(observed, camera, RollingShutter(0.6), pose,
                                                      CameraMotion.still()), strict=True):
        np.testing.assert_array_equal(o.image, same.image)
    for o, same in zip(observed, undo_rolling_shutter(observed, camera, RollingShutter(0.0), pose, moving),
                       strict=True):
        np.testing.assert_allclose(o.image, same.image, atol=1e-12)
    plain = estimate_pose(observed, camera)
    rolled = rolling_shutter_pose(observed, camera, RollingShutter(0.0))
    np.testing.assert_allclose(rolled.estimate.pose.t, plain.pose.t, atol=1e-12)


def test_the_motion_between_two_poses_takes_one_to_the_other(walk) -> None:
    _, truths, _ = walk
    before, after = truths[10], truths[13]
    motion = CameraMotion.between(before, after, 3.0)
    points = np.array([[1.0, 2.0, 1.5], [3.0, 0.5, 1.0]])
    seen = motion.seen(before.transform(points), np.full(2, 3.0))
    np.testing.assert_allclose(seen, after.transform(points), atol=1e-9)


def test_the_history_forgets_across_a_gap_and_steadies_after_a_run() -> None:
    history = PoseHistory()
    poses = draw_walk(np.random.default_rng(1), (6.0, 5.0, 2.6), 40, "tracking").poses
    assert history.motion_for(0) is None
    history.add(0, poses[0])
    motion = history.motion_for(2)
    assert motion is not None and motion.frames_since == 2.0 and motion.earlier is None
    assert history.motion_for(1 + MAX_GAP) is None  # too long ago
    history.add(1 + MAX_GAP, poses[1])  # a gap too long: the track starts again
    for k in range(2 + MAX_GAP, 1 + MAX_GAP + STEADY_FRAMES):
        history.add(k, poses[k])
    motion = history.motion_for(1 + MAX_GAP + STEADY_FRAMES)
    assert motion is not None and motion.earlier is not None
    history.add(1 + MAX_GAP + STEADY_FRAMES, None)  # a frame without a pose
    assert history.motion_for(2 + MAX_GAP + STEADY_FRAMES) is None


def test_a_readout_longer_than_a_frame_is_refused() -> None:
    with pytest.raises(ValueError, match="frame intervals"):
        RollingShutter.from_seconds(0.05, 30.0)
