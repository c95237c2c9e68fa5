"""The simulator's scenes and ground truth: what every benchmark and test measures against."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from app.cli import main as cli
from app.core.geometry.camera import Camera, Pose
from app.schemas import MapDocument
from app.sim import scenes
from app.sim.examples import BENCH_CAMERA, BENCH_ROOM, SMALL_ROOM
from app.sim.render import render


def _card_facing_camera(distance: float, size: float = 0.2, bend: float = 0.0, marker_id: int = 5) -> scenes.PlacedTarget:
    origin = np.array([-size / 2, -size / 2, distance])
    return scenes.PlacedTarget(id=marker_id, family="fido3x3", size_m=size, origin=origin,
                               x_axis=np.array([1.0, 0, 0]), y_axis=np.array([0, 1.0, 0]), bend_m=bend)


def _white_scene(target: scenes.PlacedTarget) -> scenes.Scene:
    return scenes.Scene(background=[], targets=[target])


def _disc_centroids(image: np.ndarray, truth: np.ndarray, radius_px: float) -> np.ndarray:
    """Intensity-weighted centroid of darkness in a window around each true centre."""
    dark = 1.0 - image.astype(np.float64)
    centroids = []
    for x, y in truth:
        r = int(np.ceil(radius_px + 1.5))
        x0, y0 = int(round(x)) - r, int(round(y)) - r
        window = dark[y0 : y0 + 2 * r + 1, x0 : x0 + 2 * r + 1]
        ys, xs = np.mgrid[y0 : y0 + 2 * r + 1, x0 : x0 + 2 * r + 1]
        centroids.append([(window * xs).sum() / window.sum(), (window * ys).sum() / window.sum()])
    return np.array(centroids)


def test_clean_fronto_parallel_disc_centroids_match_truth() -> None:
    camera = Camera.pinhole(800.0, 640, 480)
    target = _card_facing_camera(1.0)
    image = render(camera, Pose.identity(), _white_scene(target).quads(), background=1.0)
    truth = scenes.target_truth(camera, Pose.identity(), target)
    assert truth is not None and truth.visible
    radius_px = 0.125 * 0.2 * 800 / 1.0
    error = np.linalg.norm(_disc_centroids(image, truth.discs_px, radius_px) - truth.discs_px, axis=1)
    assert error.max() < 0.05, error


def test_bent_card_truth_follows_the_bend() -> None:
    camera = Camera.pinhole(800.0, 640, 480)
    bent = _card_facing_camera(0.8, bend=0.01)
    flat = _card_facing_camera(0.8)
    truth_bent = scenes.target_truth(camera, Pose.identity(), bent)
    truth_flat = scenes.target_truth(camera, Pose.identity(), flat)
    assert truth_bent is not None and truth_flat is not None
    # Discs sit on the outer panels, which tilt: the bent truth differs from the flat one,
    # and it, not the flat one, is where the discs are rendered.
    assert np.abs(truth_bent.discs_px - truth_flat.discs_px).max() > 0.3
    image = render(camera, Pose.identity(), _white_scene(bent).quads(), background=1.0)
    radius_px = 0.125 * 0.2 * 800 / 0.8
    centroids = _disc_centroids(image, truth_bent.discs_px, radius_px)
    error = np.linalg.norm(centroids - truth_bent.discs_px, axis=1)
    error_flat = np.linalg.norm(centroids - truth_flat.discs_px, axis=1)
    # The outer panels tilt by ~8 degrees, so the imaged ellipse's centroid is off the
    # projected centre by the perspective bias (~0.1 px here), far less than the bend moves it.
    assert error.max() < 0.15 and error.max() < error_flat.min() / 3, (error, error_flat)


def test_distorted_truth_undistorts_onto_the_pinhole_projection() -> None:
    camera = Camera.pinhole(820.0, 640, 480, dist=[-0.25, 0.08, 0.001, -0.001, 0.0])
    rng = np.random.default_rng(3)
    scene = scenes.room_scene(rng, (6.0, 5.0, 3.0), n_targets=12)
    pose = scenes.camera_walk(rng, (6.0, 5.0, 3.0), 20, "calibration")[5]
    truth = scenes.frame_truth(camera, pose, scene)
    visible = truth.visible_targets()
    assert visible
    for target in visible:
        placed = next(t for t in scene.targets if t.id == target.id)
        ideal = Camera.pinhole(820.0, 640, 480).project(pose.transform(placed.discs))
        undistorted = cv2.undistortPoints(target.discs_px.reshape(-1, 1, 2), camera.K, camera.dist, P=camera.K)
        np.testing.assert_allclose(undistorted.reshape(-1, 2), ideal, atol=1e-3)


def test_card_seen_from_behind_is_invisible_in_image_and_truth() -> None:
    camera = Camera.pinhole(800.0, 640, 480)
    # Printed face pointing away from the camera: normal +z.
    target = scenes.PlacedTarget(id=3, family="fido3x3", size_m=0.2, origin=np.array([0.1, -0.1, 1.0]),
                                 x_axis=np.array([-1.0, 0, 0]), y_axis=np.array([0, 1.0, 0]))
    assert target.normal[2] > 0
    image = render(camera, Pose.identity(), _white_scene(target).quads(), background=0.5)
    assert np.all(image == np.float32(0.5))
    truth = scenes.target_truth(camera, Pose.identity(), target)
    assert truth is not None and not truth.disc_visible.any()


def _card_off_axis(degrees: float, distance: float = 1.5, size: float = 0.2) -> scenes.PlacedTarget:
    """A card `degrees` to the right of the optical axis (identity pose), facing the camera."""
    a = np.radians(degrees)
    x_axis, y_axis = np.array([np.cos(a), 0.0, -np.sin(a)]), np.array([0.0, 1.0, 0.0])
    centre = distance * np.array([np.sin(a), 0.0, np.cos(a)])
    return scenes.PlacedTarget(id=5, family="fido3x3", size_m=size, origin=centre - size / 2 * (x_axis + y_axis),
                               x_axis=x_axis, y_axis=y_axis)


def test_card_folded_into_the_image_by_the_distortion_is_not_visible() -> None:
    """71 degrees off axis, beyond the lens's fold (59 degrees for k1 = -0.12), the
    distortion polynomial turns back and projects the card into the image; the lens
    does not see it there (nor does the renderer draw it), so neither may the truth."""
    camera = BENCH_CAMERA
    # (r - 0.12 r^3 vanishes at r = tan 71 degrees: the card lands mid-image.)
    folded, near_axis = _card_off_axis(71.0, distance=4.0), _card_off_axis(15.0)
    cam = Pose.identity().transform(folded.discs)
    uv = camera.project(cam)
    assert ((uv >= 10) & (uv <= [629, 469])).all(), uv  # well inside the image ...
    assert (np.hypot(cam[:, 0], cam[:, 1]) / cam[:, 2] > camera.fold_radius).all()  # ... from beyond the fold
    truth = scenes.target_truth(camera, Pose.identity(), folded)
    assert truth is not None and truth.facing_cos > 0.9  # in front, facing the camera
    assert not truth.disc_visible.any()
    image = render(camera, Pose.identity(), _white_scene(folded).quads(), background=0.5)
    assert np.all(image == np.float32(0.5))  # the renderer draws nothing either
    control = scenes.target_truth(camera, Pose.identity(), near_axis)
    assert control is not None and control.visible


def test_room_targets_lie_on_the_walls_and_make_a_valid_map() -> None:
    size = BENCH_ROOM.size
    scene = BENCH_ROOM.scene(0)
    discs = np.array([t.discs for t in scene.targets])
    assert discs.shape == (30, 4, 3)
    assert (discs >= -0.02).all() and (discs <= np.array(size) + 0.02).all()
    # Each card is on one wall: within a few mm of it (bend and offset).
    distance_to_wall = np.minimum.reduce([discs[..., 0], size[0] - discs[..., 0], discs[..., 1], size[1] - discs[..., 1]])
    assert distance_to_wall.max() < 0.01
    centres = discs.mean(axis=1)
    gaps = np.linalg.norm(centres[:, None] - centres[None], axis=2) + np.eye(30) * 99
    assert gaps.min() > 0.2
    document = MapDocument.model_validate(scene.map_document(BENCH_CAMERA))
    assert sorted(t.id for t in document.targets) == list(range(30))


def test_walks_are_smooth_inside_the_room_and_see_targets() -> None:
    size = BENCH_ROOM.size
    walk = BENCH_ROOM.walk(1, 300, "calibration")
    scene, camera, rng = walk.scene, BENCH_ROOM.camera, walk.rng
    walks = {"calibration": walk.poses, "tracking": scenes.camera_walk(rng, size, 300, "tracking")}
    for kind, poses in walks.items():
        positions = np.array([p.position for p in poses])
        assert (positions > 0.3).all() and (positions < np.array(size) - 0.3).all()
        assert np.linalg.norm(np.diff(positions, axis=0), axis=1).max() < 0.15
        visible = [len(scenes.frame_truth(camera, p, scene).visible_targets()) for p in poses]
        assert np.median(visible) >= 3, kind
    with pytest.raises(ValueError):
        scenes.camera_walk(rng, size, 10, "sideways")


@pytest.mark.parametrize("name", sorted(scenes.SCENARIOS))
def test_every_scenario_renders_with_truth(name: str) -> None:
    image, truth = scenes.scenario_frame(name, np.random.default_rng(7))
    again, _ = scenes.scenario_frame(name, np.random.default_rng(7))
    assert image.shape == (480, 640) and image.dtype == np.uint8
    np.testing.assert_array_equal(image, again)  # deterministic for a seed
    if name == "empty":
        assert truth.targets == []
    else:
        assert truth.targets and all(t.discs_px.shape == (4, 2) for t in truth.targets)
    if name == "occluded":
        assert any(t.occluded for t in truth.targets)
    json.dumps(truth.to_dict())


def test_far_scenario_is_far() -> None:
    _, truth = scenes.scenario_frame("far", np.random.default_rng(2))
    assert all(4.0 <= t.distance_m <= 8.5 for t in truth.targets)


def test_cli_writes_frames_and_room_walks(tmp_path: Path) -> None:
    assert cli(["synth", "frames", "--scenario", "blur", "--count", "3", "--out", str(tmp_path / "f"), "-q"]) == 0
    truth = json.loads((tmp_path / "f" / "truth.json").read_text())
    assert len(truth["frames"]) == 3 and (tmp_path / "f" / truth["frames"][0]["file"]).exists()

    args = ["synth", "room", "--room", "5x4x2.5", "--markers", "8", "--frames", "6", "-q"]
    assert cli([*args, "--out", str(tmp_path / "r")]) == 0
    video = cv2.VideoCapture(str(tmp_path / "r" / "calibration.mp4"))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == 6
    ok, frame = video.read()
    assert ok and frame.shape[:2] == (480, 640)
    document = json.loads((tmp_path / "r" / "truth.json").read_text())
    assert len(document["calibration"]) == 6 and len(document["tracking"]) == 6
    MapDocument.model_validate(document["map"])

    assert cli([*args, "--format", "jpeg", "--out", str(tmp_path / "j")]) == 0
    assert len(list((tmp_path / "j" / "tracking").glob("*.jpg"))) == 6


def test_room_cards_lie_wholly_in_front_of_their_walls() -> None:
    """A card bent into its wall would have a panel hidden by the wall while its truth
    still called every disc visible."""
    scene = SMALL_ROOM.scene(11)
    walls = scenes.room_walls(SMALL_ROOM.size)[:4]
    grid = np.stack(np.meshgrid(np.linspace(0, 1, 21), np.linspace(0, 1, 21)), -1).reshape(-1, 2)
    for target in scene.targets:
        wall = min(walls, key=lambda w: abs(np.dot(target.corners[0] - w.centre, w.inward)))
        height = (target.point(grid) - wall.centre) @ wall.inward
        assert height.min() > 0.001, (target.id, height.min())
