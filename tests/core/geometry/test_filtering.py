"""Smoothing and prediction of a stream of poses (One Euro filter)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from app.core.geometry.camera import Pose
from app.core.geometry.filtering import OneEuroParams, PoseFilter

FPS = 30.0


def _pose(centre: np.ndarray, yaw: float) -> Pose:
    """A camera at `centre` turned `yaw` about the map's z."""
    R_wc = cv2.Rodrigues(np.array([0.0, 0.0, yaw]))[0] @ np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
    R = R_wc.T
    return Pose(R, -R @ centre)


def _yaw(pose: Pose) -> float:
    return float(np.arctan2(pose.R.T[1, 0], pose.R.T[0, 0]))


def test_a_still_camera_is_smoothed() -> None:
    rng = np.random.default_rng(0)
    f = PoseFilter()
    raw, out = [], []
    for k in range(300):
        pose = _pose(np.array([1.0, 2.0, 1.5]) + rng.normal(0, 0.001, 3), rng.normal(0, 0.002))
        raw.append(pose)
        out.append(f.update(k / FPS, pose))
    raw_std = np.array([p.position for p in raw[30:]]).std(axis=0).sum()
    out_std = np.array([p.position for p in out[30:]]).std(axis=0).sum()
    assert out_std < 0.4 * raw_std, (out_std, raw_std)  # a first-order low-pass at 1 Hz, 30 fps: 0.31
    assert np.std([_yaw(p) for p in out[30:]]) < 0.4 * np.std([_yaw(p) for p in raw[30:]])


def test_motion_is_followed_and_predicted() -> None:
    """At a constant 1 m/s and 0.5 rad/s the smoothed pose trails a little (its cut-off
    rises with the speed); the pose predicted 100 ms ahead is where the camera is 100 ms
    later, give or take that trail."""
    f = PoseFilter()
    for k in range(90):
        t = k / FPS
        out = f.update(t, _pose(np.array([t, 0.0, 1.5]), 0.5 * t))
    t_last = 89 / FPS
    assert 0 < t_last - out.position[0] < 0.05  # behind, by less than 50 ms of motion
    ahead = f.predict(0.1)
    np.testing.assert_allclose(ahead.position, [t_last + 0.1, 0.0, 1.5], atol=0.01)
    assert 0 < 0.5 * (t_last + 0.1) - _yaw(ahead) < 0.5 * 0.05


def test_prediction_without_smoothing_starts_from_the_pose_given() -> None:
    f = PoseFilter(smooth=False)
    for k in range(30):
        pose = _pose(np.array([k / FPS, 0.0, 1.5]), 0.0)
        assert f.update(k / FPS, pose) is pose
    np.testing.assert_allclose(f.predict(0.0).position, pose.position, atol=1e-12)
    assert f.predict(0.1).position[0] == pytest.approx(29 / FPS + 0.1, abs=0.01)


def test_a_gap_starts_afresh() -> None:
    f = PoseFilter(OneEuroParams(reset_after_s=0.5))
    for k in range(30):
        f.update(k / FPS, _pose(np.zeros(3), 0.0))
    jumped = _pose(np.array([5.0, 0.0, 0.0]), 1.0)
    assert f.update(29 / FPS + 1.0, jumped) is jumped  # after a second without a pose: taken as it is
    np.testing.assert_allclose(f.predict(0.2).position, [5.0, 0.0, 0.0], atol=1e-12)


def test_predict_needs_a_pose() -> None:
    with pytest.raises(ValueError, match="no pose"):
        PoseFilter().predict(0.1)
