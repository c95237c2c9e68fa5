"""The pose a /track connection expects next, which decides a lone card's tilt."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from app.core.geometry import Camera, Pose
from app.services.tracking import TILT_OVERRULED_LIMIT, TrackState

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
