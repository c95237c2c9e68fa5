"""One frame without a server: its plan from the size alone, its targets and pose, a
frame decoded smaller brought back to its own pixels, and the whole-frame fallback."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from app.core.detection import Detector, load_default_classifier
from app.core.geometry import Camera, Pose
from app.core.tracking import ScanReason, TrackingMap, TrackOptions, TrackState, plan_frame, track_frame
from app.sim import degrade, scenes

#: An HD camera: large enough for its frames to be decoded smaller.
CAMERA = Camera.pinhole(1000.0, 1280, 720)


@pytest.fixture(scope="module")
def room() -> tuple[TrackingMap, np.ndarray, Detector]:
    """Three cards about a metre ahead of a camera at the identity pose, its frame, and
    the map of the cards."""
    rng = np.random.default_rng(7)
    scene = scenes.single_frame_scene(rng, CAMERA, n_targets=3, distance_m=(0.9, 1.2), tilt_deg=(0.0, 30.0))
    image, _ = scenes.render_frame(scene, CAMERA, Pose.identity(), rng, degrade.Degradation(read_sigma=0.005))
    track_map = TrackingMap(CAMERA, {t.id: t.discs for t in scene.targets})
    return track_map, image, Detector(load_default_classifier())


def _seen(pose: Pose) -> SimpleNamespace:
    """A pose as `TrackState.update` reads an estimate."""
    return SimpleNamespace(pose=pose, focal_px=CAMERA.fx, tilt_from_track=False)


def test_a_lone_image_is_scanned_whole_and_posed(room) -> None:
    track_map, image, detector = room
    plan = plan_frame(track_map, TrackOptions(), 1280, 720)
    assert (plan.regions, plan.reason, plan.reduction) == (None, ScanReason.SINGLE, 1)
    assert plan.camera == CAMERA
    tracked = track_frame(detector, image, 1, plan, track_map, TrackOptions())
    assert not tracked.regions and tracked.reason == ScanReason.SINGLE
    assert sorted(t.id for t in tracked.targets) == sorted(track_map.discs)
    assert tracked.estimate is not None and np.linalg.norm(tracked.estimate.pose.position) < 0.005
    # The options' intrinsics take the map camera's place, scaled to the frame's size.
    other = Camera.pinhole(500.0, 640, 360)
    assert plan_frame(track_map, TrackOptions(intrinsics=other), 1280, 720).camera.fx == pytest.approx(1000.0)


def test_a_stream_decodes_large_discs_smaller_in_its_own_pixels(room) -> None:
    track_map, image, detector = room
    state = TrackState()
    first = plan_frame(track_map, TrackOptions(), 1280, 720, state, 0)
    assert (first.reason, first.reduction) == (ScanReason.FIRST, 1)  # nothing says how large the discs are
    whole = track_frame(detector, image, 1, first, track_map, TrackOptions(), state, 0)
    assert whole.estimate is not None
    second = plan_frame(track_map, TrackOptions(), 1280, 720, state, 1)
    # Predicted from the track (in regions, or whole where they would cover most of the
    # frame), and decoded at half: 1/4 would be under 360 rows.
    predicted = (ScanReason.REGIONS, ScanReason.WIDE)
    assert second.reason in predicted and second.reduction == 2
    half = cv2.resize(image, (640, 360), interpolation=cv2.INTER_AREA)  # as the decoder's DCT scaling
    reduced = track_frame(detector, half, 2, second, track_map, TrackOptions(), state, 1)
    assert reduced.regions == (second.regions is not None) and reduced.timing_ms["reduction"] == 2.0
    found = {t.id: t.discs for t in whole.targets}
    for target in reduced.targets:  # the frame's own pixels, not the decoded ones
        assert np.abs(target.discs - found[target.id]).max() < 0.5
    assert reduced.estimate is not None
    assert np.linalg.norm(reduced.estimate.pose.position - whole.estimate.pose.position) < 0.005
    assert reduced.estimate.focal_px == pytest.approx(CAMERA.fx)
    # The state holds the frame's own camera: the next frame is predicted again.
    assert plan_frame(track_map, TrackOptions(), 1280, 720, state, 2).reason in predicted


def test_regions_that_find_no_pose_fall_back_to_the_whole_frame(room) -> None:
    track_map, image, detector = room
    state = TrackState()
    # A track that believes the camera turned away: its regions hold no card.
    turned = Pose.from_rvec_tvec(np.array([0.0, 0.35, 0.0]), np.zeros(3))
    small_camera = CAMERA.scaled_to(640, 360)  # a frame too small to be decoded smaller
    state.update(0, small_camera, _seen(turned), full=True)  # type: ignore[arg-type]
    state.update(1, small_camera, _seen(turned), full=False)  # type: ignore[arg-type]
    plan = plan_frame(track_map, TrackOptions(), 640, 360, state, 2)
    assert plan.reason == ScanReason.REGIONS
    small = cv2.resize(image, (640, 360), interpolation=cv2.INTER_AREA)
    tracked = track_frame(detector, small, 1, plan, track_map, TrackOptions(), state, 2)
    assert tracked.reason == ScanReason.FALLBACK and not tracked.regions
    assert tracked.estimate is not None and np.linalg.norm(tracked.estimate.pose.position) < 0.01
    # Without regions asked for, the frame is scanned whole from the start.
    off = plan_frame(track_map, TrackOptions(regions=False), 640, 360, state, 3)
    assert (off.regions, off.reason) == (None, ScanReason.OFF)
