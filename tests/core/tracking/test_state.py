"""A stream's memory without a server: where it searches the next frame and why, and
the pose it expects there, which decides a lone card's tilt."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from app.core.geometry import Camera, MapTargets, Pose
from app.core.tracking import TILT_OVERRULED_LIMIT, ScanReason, TrackState

CAMERA = Camera.pinhole(820.0, 640, 480)


def _pose(x: float, yaw_deg: float = 0.0) -> Pose:
    return Pose.from_rvec_tvec(np.array([0.0, np.radians(yaw_deg), 0.0]), np.array([x, 0.0, 3.0]))


def _seen(state: TrackState, seq: int, pose: Pose | None, overruled: bool = False) -> None:
    estimate = None if pose is None else SimpleNamespace(pose=pose, focal_px=CAMERA.fx, tilt_from_track=overruled)
    state.update(seq, CAMERA, estimate, full=True)  # type: ignore[arg-type]


def test_the_prior_goes_on_at_the_tracks_velocity_and_outlives_a_lost_frame() -> None:
    state = TrackState()
    assert state.prior(0) is None
    _seen(state, 0, _pose(0.00, 0.0))
    np.testing.assert_allclose(state.prior(1).t, _pose(0.0).t)  # one pose: itself
    _seen(state, 1, _pose(0.01, 1.0))
    expected = _pose(0.02, 2.0)
    np.testing.assert_allclose(state.prior(2).t, expected.t, atol=1e-3)
    _seen(state, 2, None)  # lost: regions are planned afresh, but the card is still expected
    prior = state.prior(3)
    assert prior is not None and np.degrees(np.arccos((np.trace(prior.R @ _pose(0.03, 3.0).R.T) - 1) / 2)) < 0.1
    assert state.prior(1 + state.params.max_steps + 1) is None  # too long ago


def test_a_jump_between_tilts_is_not_extrapolated() -> None:
    state = TrackState()
    _seen(state, 0, _pose(0.0, 0.0))
    _seen(state, 1, _pose(0.0, 40.0))  # 40 degrees in a frame: another tilt, not a motion
    np.testing.assert_allclose(state.prior(2).R, _pose(0.0, 40.0).R)


def test_a_track_that_keeps_overruling_the_residual_lets_it_decide() -> None:
    state = TrackState()
    for seq in range(TILT_OVERRULED_LIMIT):
        assert state.prior(seq) is not None or seq == 0
        _seen(state, seq, _pose(0.0), overruled=True)
    assert state.prior(TILT_OVERRULED_LIMIT) is None
    _seen(state, TILT_OVERRULED_LIMIT, _pose(0.0), overruled=False)
    assert state.prior(TILT_OVERRULED_LIMIT + 1) is not None


def test_the_plan_says_where_to_search_and_why() -> None:
    camera = Camera.pinhole(820.0, 640, 480)
    uv = np.array([[0.2, 0.2], [0.8, 0.2], [0.8, 0.8], [0.2, 0.8]]) - 0.5
    card = np.c_[0.2 * uv, np.full(4, 2.0)]  # 2 m ahead of the identity pose, facing it
    targets = MapTargets.from_discs({5: card})
    state = TrackState()

    def seen(pose: Pose, focal: float = 820.0) -> SimpleNamespace:
        return SimpleNamespace(pose=pose, focal_px=focal, tilt_from_track=False)

    assert state.plan(0, camera, targets) == (None, ScanReason.FIRST)
    state.update(0, camera, seen(Pose.identity()), full=True)
    regions, why = state.plan(1, camera, targets)
    assert why == ScanReason.REGIONS and [r.ids for r in regions] == [(5,)]
    state.update(1, camera, seen(Pose.identity()), full=False)
    assert state.plan(1 + 9, camera, targets) == (None, ScanReason.STALE)  # 9 frames on: too far ahead
    assert state.plan(2, camera.scaled_to(320, 240), targets) == (None, ScanReason.CAMERA)
    assert state.plan(2, camera, targets, regions=False) == (None, ScanReason.OFF)
    assert state.plan(2, camera, targets, full_scan_every=2) == (None, ScanReason.PERIODIC)
    # A zoom lens: the next prediction uses the focal length just measured.
    fixed = TrackState()
    for k in range(3):
        fixed.update(k, camera, seen(Pose.identity()), full=k == 0)
    state.update(2, camera, seen(Pose.identity(), focal=1640.0), full=False)
    zoomed, _ = state.plan(3, camera, targets)
    normal, _ = fixed.plan(3, camera, targets)
    assert zoomed[0].width > 1.5 * normal[0].width
    state.update(3, camera, None, full=False)
    assert state.plan(4, camera, targets) == (None, ScanReason.LOST)
