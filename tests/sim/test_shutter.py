"""A rolling shutter (app.sim.shutter): each row read from the camera's pose at its own
moment, and the truth that goes with it."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.detection import Detector, load_default_classifier
from app.sim import scenes
from app.sim.examples import BENCH_CAMERA, PAN_WALK
from app.sim.shutter import RollingReadout, rolling_projection


@pytest.fixture(scope="module")
def pan() -> list[tuple[np.ndarray, scenes.FrameTruth, scenes.FrameTruth]]:
    """Every 10th of 60 frames of the pan read out over 20 ms, each with its truth and
    the global shutter's truth of the same pose."""
    room = PAN_WALK.walk(0, 60)
    out = []
    for k, (image, truth) in enumerate(room.frames(BENCH_CAMERA, readout_s=0.020)):
        if k % 10 == 0:
            out.append((image, truth, scenes.frame_truth(BENCH_CAMERA, truth.pose, room.scene)))
    return out


def test_the_readout_is_centred_on_the_frames_pose() -> None:
    walk = PAN_WALK.walk(0, 30).walk
    assert walk is not None
    first, middle = walk.readouts(0.020)[3:5]
    assert middle.poses[len(middle.poses) // 2] == walk.poses[4]
    # Row by row the pose moves smoothly from the first row's to the last's.
    R, t = middle.at_rows(np.array([0.0, 239.5, 479.0]), 480)
    np.testing.assert_allclose(R[0], middle.poses[0].R, atol=1e-12)
    np.testing.assert_allclose(R[2], middle.poses[-1].R, atol=1e-12)
    np.testing.assert_allclose(R[1], walk.poses[4].R, atol=1e-9)
    assert first.poses[0] != middle.poses[0]
    with pytest.raises(ValueError):
        walk.readouts(0.05)  # longer than a frame


def test_a_still_camera_reads_as_a_global_shutter() -> None:
    pose = PAN_WALK.walk(0, 2).poses[0]
    points = np.array([[1.0, 0.5, 1.2], [2.0, 3.0, 1.5]])
    still = RollingReadout((pose,) * 5)
    np.testing.assert_allclose(rolling_projection(BENCH_CAMERA, still, points),
                               BENCH_CAMERA.project(pose.transform(points)), atol=1e-9)


def test_the_detector_finds_the_discs_where_the_rolling_shutter_truth_puts_them(pan: list) -> None:
    detector = Detector(load_default_classifier())
    rolled, global_ = [], []
    for image, truth, global_truth in pan:
        by_id = {t.id: t.discs_px for t in truth.targets if t.visible}
        at_pose = {t.id: t.discs_px for t in global_truth.targets}
        for found in detector.detect(image).targets:
            if found.id in by_id:
                rolled.append(np.linalg.norm(found.discs - by_id[found.id], axis=1))
                global_.append(np.linalg.norm(found.discs - at_pose[found.id], axis=1))
    rolled_error, global_error = np.median(np.concatenate(rolled)), np.median(np.concatenate(global_))
    assert len(rolled) >= 8
    # The frame and its truth agree as closely as a global shutter's do (0.03 px) ...
    assert rolled_error < 0.06, rolled_error
    # ... while a pan at a phone's readout puts the discs pixels away from where the
    # frame's own pose would.
    assert global_error > 0.5, global_error
