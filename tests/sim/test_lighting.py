"""Lamps, glossy paper, furniture and what each pixel sees: the simulator's light falls off
and shades cards as the geometry says, boards stand in the room and hide what is behind
them from the truth."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.geometry.camera import Camera, Pose
from app.sim import scenes
from app.sim.examples import BENCH_CAMERA, FURNISHED_ROOM, GLOSSY_PAPER
from app.sim.lighting import Lamp, Lighting, irradiance
from app.sim.render import TexturedQuad

CAMERA = Camera.pinhole(800.0, 640, 480)
LOOKING_AT_WALL = Pose.identity()  # looking along +z at a wall 3 m away


def _wall(depth: float = 3.0, grey: float = 0.8) -> TexturedQuad:
    return TexturedQuad.from_frame([-4.0, -3.0, depth], [8.0, 0, 0], [0, 6.0, 0], np.full((4, 4), grey))


def _card(centre: tuple[float, float, float], marker_id: int = 3, size: float = 0.2) -> scenes.PlacedTarget:
    x, y = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    return scenes.PlacedTarget(marker_id, "fido3x3", size, np.asarray(centre) - size / 2 * (x + y), x, y)


def test_irradiance_falls_off_with_the_square_of_the_distance_and_the_cosine() -> None:
    lighting = Lighting((Lamp((0.0, 0.0, 1.0), 2.0),), ambient=0.0)
    points = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.0, 0, -1.0], [0.0, 0, 2.0]])
    normals = np.tile([0.0, 0, 1], (4, 1))
    got = irradiance(points, normals, lighting)
    # 2 / 1^2; 2 cos(45) / 2; 2 / 2^2; behind the lamp (facing away): only the ambient
    assert got == pytest.approx([2.0, 2 * np.sqrt(0.5) / 2, 0.5, 0.0])
    with pytest.raises(ValueError):
        Lighting((), ambient=0.0)


def test_a_lamp_beside_a_card_shades_it_across_its_face() -> None:
    # A card on a wall 3 m off, a lamp 0.6 m to its left, 0.5 m out from the wall: the
    # paper's brightness across the card follows the lamp's irradiance there.
    card = _card((0.0, 0.0, 2.998))
    scene = scenes.Scene([_wall()], [card])
    lamp = Lamp((-0.6, 0.0, 2.5), 1.0)
    lighting = Lighting((lamp,), ambient=0.0, key=0.1)  # exposed for the card: no white clips
    unlit = scenes.render_frame(scene, CAMERA, LOOKING_AT_WALL, np.random.default_rng(0))[0].astype(float)
    lit = scenes.render_frame(scene, CAMERA, LOOKING_AT_WALL, np.random.default_rng(0), lighting=lighting)[0]
    surfaces = scene.surfaces(CAMERA, LOOKING_AT_WALL)
    # white paper at the card's left and right edges, between its discs
    left, right = card.point(np.array([[0.08, 0.5]]))[0], card.point(np.array([[0.92, 0.5]]))[0]
    u = CAMERA.project_map(np.array([left, right]), LOOKING_AT_WALL).round().astype(int)
    assert 30 < lit[u[:, 1], u[:, 0]].min() and lit[u[:, 1], u[:, 0]].max() < 250
    ratio_image = (lit[u[0, 1], u[0, 0]] / unlit[u[0, 1], u[0, 0]]) / (lit[u[1, 1], u[1, 0]] / unlit[u[1, 1], u[1, 0]])
    e = irradiance(np.array([left, right]), np.tile([0.0, 0, -1], (2, 1)), lighting)
    assert ratio_image == pytest.approx(e[0] / e[1], rel=0.03)
    assert e[0] / e[1] > 1.3  # a shading gradient worth the name
    assert surfaces.card[u[0, 1], u[0, 0]] and surfaces.card[u[1, 1], u[1, 0]]
    assert surfaces.depth[u[0, 1], u[0, 0]] == pytest.approx(2.998, abs=1e-6)


def test_glossy_paper_washes_out_the_discs_under_the_highlight() -> None:
    # The lamp mirrored in the card straight towards the camera: glossy paper lifts the
    # black discs as much as the white, the matte one does not.
    card = _card((0.0, 0.0, 2.998))
    scene = scenes.Scene([_wall()], [card])
    lamps = (Lamp((0.0, 0.0, 0.3), 0.3),)  # between the camera and the card, on its axis
    disc = CAMERA.project_map(card.discs, LOOKING_AT_WALL).round().astype(int)
    levels = {}
    for gloss in (0.0, GLOSSY_PAPER):
        lighting = Lighting(lamps, ambient=0.05, gloss=gloss, shininess=10.0)
        image = scenes.render_frame(scene, CAMERA, LOOKING_AT_WALL, np.random.default_rng(0), lighting=lighting)[0]
        levels[gloss] = float(np.mean([image[v, u] for u, v in disc]))
    assert levels[0.0] < 20 and levels[GLOSSY_PAPER] > levels[0.0] + 40


def test_boards_stand_in_the_room_with_cards_on_them_and_hide_what_is_behind() -> None:
    scene = FURNISHED_ROOM.scene(0)
    w, d, _ = FURNISHED_ROOM.size
    assert len(scene.furniture) == FURNISHED_ROOM.furniture
    assert len(scene.targets) == FURNISHED_ROOM.n_targets + FURNISHED_ROOM.furniture
    assert [t.id for t in scene.targets] == list(range(len(scene.targets)))
    for board, card in zip(scene.furniture, scene.targets[FURNISHED_ROOM.n_targets:], strict=True):
        c = board.corners
        assert (c[:, 0] > 0).all() and (c[:, 0] < w).all() and (c[:, 1] > 0).all() and (c[:, 1] < d).all()
        assert scenes.BOARD_FOOT_M[0] <= c[:, 2].min() <= scenes.BOARD_FOOT_M[1]  # on a desk or lectern
        normal = np.cross(c[3] - c[0], c[1] - c[0])  # down x right: out of the face
        normal /= np.linalg.norm(normal)
        # the card lies on the board, facing the same way; leant back, both look up
        assert card.normal @ normal == pytest.approx(1.0)
        assert abs((card.discs - c[0]) @ normal - 0.002).max() < 0.005
        assert 0.15 < normal[2] < 0.95
    # Seen from the middle of the room, a wall card straight behind a board is hidden,
    # the board's own card is not.
    board, card = scene.furniture[0], scene.targets[FURNISHED_ROOM.n_targets]
    centre = board.corners.mean(axis=0)
    eye = centre + 2.0 * card.normal
    behind = scenes.PlacedTarget(59, card.family, card.size_m, card.origin - 0.3 * card.normal, card.x_axis,
                                 card.y_axis)  # the same card, 0.3 m behind the board
    forward = (centre - eye) / np.linalg.norm(centre - eye)
    pose = _look(eye, forward)
    hidden_scene = scenes.Scene(scene.background, [card, behind], room_size=scene.room_size,
                                furniture=scene.furniture)
    truth = {t.id: t for t in scenes.frame_truth(BENCH_CAMERA, pose, hidden_scene).targets}
    assert truth[card.id].visible
    assert not truth[59].disc_visible.any()
    bare = scenes.Scene(scene.background, [card, behind], room_size=scene.room_size)
    assert {t.id: t for t in scenes.frame_truth(BENCH_CAMERA, pose, bare).targets}[59].visible  # but for the board
    surfaces = hidden_scene.surfaces(BENCH_CAMERA, pose)
    middle = BENCH_CAMERA.project_map(card.discs.mean(axis=0)[None], pose)[0].round().astype(int)
    assert surfaces.card[middle[1], middle[0]]
    assert surfaces.normals[middle[1], middle[0]] @ card.normal == pytest.approx(1.0)


def _look(eye: np.ndarray, forward: np.ndarray) -> Pose:
    """The pose of a camera at `eye` looking along `forward`, the image's up towards +z."""
    z = forward / np.linalg.norm(forward)
    x = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return Pose(R, -R @ eye)


def test_a_lit_furnished_room_walk_renders_with_its_truth() -> None:
    walk = FURNISHED_ROOM.walk(1, 300, "centre_loop")
    lighting = FURNISHED_ROOM.lamps(GLOSSY_PAPER)
    frames = list(zip(range(2), walk.frames(BENCH_CAMERA, "none", lighting=lighting), strict=False))
    for _, (image, truth) in frames:
        assert image.shape == (480, 640) and image.dtype == np.uint8
        assert truth.targets
    lit = frames[0][1][0].astype(float)
    unlit = next(iter(FURNISHED_ROOM.walk(1, 300, "centre_loop").frames(BENCH_CAMERA, "none")))[0].astype(float)
    # the lamps change the brightness from place to place, not only its level
    ratio = (lit + 1) / (unlit + 1)
    assert np.percentile(ratio, 90) / np.percentile(ratio, 10) > 1.3
