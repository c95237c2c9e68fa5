"""Step 1 of the survey: the initial lens from the cards alone."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from app.core.detection import DetectedTarget
from app.core.geometry import Camera, Pose
from app.core.markers import DISC_CENTRES
from app.core.survey.lens import focal_from_cards, initial_camera, lens_from_cards
from app.core.survey.tracks import collect_tracks
from app.sim.examples import ExampleRoom
from app.sim.scenes import Scene

Frames = list[list[DetectedTarget]]


def _cards(frames: Frames) -> list[np.ndarray]:
    return [t.discs for f in frames for t in f]


def _tilted_cards(camera: Camera, n: int, rng: np.random.Generator, noise_px: float) -> list[np.ndarray]:
    """Images of a 0.2 m card tilted 20-60 degrees, 1-2.5 m in front of ``camera``."""
    model = np.c_[DISC_CENTRES * 0.2, np.zeros(4)]
    quads = []
    for _ in range(n):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R, _ = cv2.Rodrigues(axis * np.radians(rng.uniform(20, 60)))
        pose = Pose(R, np.r_[rng.uniform(-0.5, 0.5, 2), rng.uniform(1.0, 2.5)] - R @ model.mean(axis=0))
        quads.append(camera.project_map(model, pose) + rng.normal(0, noise_px, (4, 2)))
    return quads


def test_focal_from_cards() -> None:
    camera = Camera.pinhole(750.0, 640, 480)
    quads = _tilted_cards(camera, 40, np.random.default_rng(5), 0.1)
    f = focal_from_cards(quads, 640, 480)
    assert f is not None and abs(f / 750.0 - 1) < 0.03
    # Head-on cards carry no information about f.
    model = np.c_[DISC_CENTRES * 0.2, np.zeros(4)]
    flat = [camera.project_map(model, Pose(np.eye(3), np.array([0.0, 0.0, 2.0]))) for _ in range(10)]
    assert focal_from_cards(flat, 640, 480) is None


def test_lens_from_cards_is_unbiased(oblique_room: tuple[Scene, Frames]) -> None:
    """The closed form is biased by detector noise (+4 % here at 0.03 px); the maximum
    likelihood fit over every card (each its own pose) is not, and finds k1 too."""
    _, frames = oblique_room
    cards = _cards(frames)
    closed = focal_from_cards(cards, 640, 480)
    assert closed is not None and closed / 820.0 - 1 > 0.03
    lens = lens_from_cards(cards, 640, 480, closed)
    assert lens is not None
    f, k1 = lens
    assert abs(f / 820.0 - 1) < 0.01
    assert abs(k1 - -0.12) < 0.02


def test_lens_from_cards_is_exact_on_exact_cards(room: ExampleRoom,
                                                 synthetic_frames: Callable[[float, int], Frames]) -> None:
    """On the exact images of the cards the maximum-likelihood lens is the true one,
    from a closed-form start several percent off (it ignores the distortion)."""
    cards = _cards(synthetic_frames(0.0, 0))
    closed = focal_from_cards(cards, 640, 480)
    assert closed is not None and abs(closed / room.camera.fx - 1) > 0.01
    lens = lens_from_cards(cards, 640, 480, closed)
    assert lens is not None
    assert abs(lens[0] - room.camera.fx) < 1e-6 * room.camera.fx
    assert abs(lens[1] - room.camera.dist[0]) < 1e-6


def test_lens_from_cards_refuses_too_few_cards(synthetic_frames: Callable[[float, int], Frames]) -> None:
    cards = _cards(synthetic_frames(0.0, 0))
    assert lens_from_cards(cards[:3], 640, 480, 600.0) is None


def test_lens_from_cards_trims_misread_cards(room: ExampleRoom,
                                            synthetic_frames: Callable[[float, int], Frames]) -> None:
    """A few cards that are no image of a square (a wrong disc) do not move the lens."""
    cards = _cards(synthetic_frames(0.0, 0))
    broken = [c.copy() for c in cards]
    for c in broken[::25]:
        c[2] += (6.0, -4.0)
    closed = focal_from_cards(broken, 640, 480)
    assert closed is not None
    lens = lens_from_cards(broken, 640, 480, closed)
    assert lens is not None
    assert abs(lens[0] / room.camera.fx - 1) < 1e-3 and abs(lens[1] - room.camera.dist[0]) < 1e-3


def test_initial_camera(room: ExampleRoom, synthetic_frames: Callable[[float, int], Frames]) -> None:
    frames = synthetic_frames(0.0, 0)
    warnings: list[str] = []
    tracks = collect_tracks(frames, list(range(len(frames))), warnings)
    # A given camera is kept as it is.
    assert initial_camera(tracks, 640, 480, room.camera, warnings) is room.camera
    # Else the lens from the cards: principal point at the image centre, k1 only.
    camera = initial_camera(tracks, 640, 480, None, warnings)
    assert abs(camera.fx / room.camera.fx - 1) < 1e-6 and camera.fx == camera.fy
    assert (camera.cx, camera.cy) == (319.5, 239.5)
    np.testing.assert_allclose(camera.dist, [room.camera.dist[0], 0, 0, 0, 0], atol=1e-6)
    assert warnings == []


def test_initial_camera_from_head_on_cards_is_a_typical_lens() -> None:
    """Cards all seen head-on do not determine the focal length: a typical lens (~60
    degrees), with a warning."""
    camera = Camera.pinhole(750.0, 640, 480)
    model = np.c_[DISC_CENTRES * 0.2, np.zeros(4)]
    frames = [[DetectedTarget(1, camera.project_map(model, Pose(np.eye(3), np.array([0.1 * k, 0.0, 2.0]))), 1.0)]
              for k in range(3)]
    warnings: list[str] = []
    tracks = collect_tracks(frames, [0, 1, 2], warnings)
    start = initial_camera(tracks, 640, 480, None, warnings)
    assert start.fx == 0.85 * 640 and np.all(start.dist == 0)
    assert len(warnings) == 1 and "initial focal length" in warnings[0]
