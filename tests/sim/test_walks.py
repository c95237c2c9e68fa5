"""Walks and rooms that look like real filming: what the survey benchmarks rely on."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from app.core.geometry import Pose, rotation_angle
from app.sim import scenes
from app.sim.examples import (
    CINE_LENS,
    BENCH_CAMERA,
    BENCH_ROOM,
    EXPOSURE_S,
    PAN_WALK,
    PLAIN_ROOM,
    SPARSE_ROOM,
    SPARSE_WALK,
    WALKS,
)
from app.sim.render import render
from app.sim.walks import FPS, TURN_DEG_S, Shake, ShakeMotion, draw_walk, exposure_average, walk_speeds

SIZE = BENCH_ROOM.size


def _gaze(poses: list[Pose]) -> np.ndarray:
    """Unit viewing direction (the optical axis) of each pose, map coordinates."""
    return np.array([p.R[2] for p in poses])


def _seen(camera, pose: Pose, scene: scenes.Scene) -> int:  # type: ignore[no-untyped-def]
    return sum(t.visible and t.facing_cos > 0.3 for t in scenes.frame_truth(camera, pose, scene).targets)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_pan_turns_round_one_fixed_point(seed: int) -> None:
    poses = draw_walk(np.random.default_rng(seed), SIZE, 300, "pan").poses
    centres = np.array([p.position for p in poses])
    assert np.ptp(centres, axis=0).max() < 1e-9  # no baseline at all
    assert 1.2 <= centres[0, 2] <= 1.8
    assert np.linalg.norm(centres[0, :2] - np.array(SIZE[:2]) / 2) < 0.75  # near the middle
    azimuth = np.unwrap(np.arctan2(_gaze(poses)[:, 1], _gaze(poses)[:, 0]))
    assert abs(azimuth[-1] - azimuth[0]) > math.radians(350)  # a full turn in 10 s: every wall
    _, turn = walk_speeds(poses)
    assert turn.max() <= 60.0
    # The named pan is hand-held but rotates only: still no baseline.
    shaken = PAN_WALK.walk(seed, 60).poses
    assert np.ptp([p.position for p in shaken], axis=0).max() < 1e-9


@pytest.mark.parametrize("seed", [0, 3])
def test_a_centre_loop_stays_near_the_middle_looking_out_at_the_walls(seed: int) -> None:
    poses = draw_walk(np.random.default_rng(seed), SIZE, 300, "centre_loop").poses
    centres = np.array([p.position for p in poses])
    middle = centres[:, :2].mean(axis=0)
    assert np.linalg.norm(middle - np.array(SIZE[:2]) / 2) < 0.75
    radius = np.linalg.norm(centres[:, :2] - middle, axis=1)
    assert 0.7 < radius.min() and radius.max() < 1.3  # a loop of about a metre
    assert ((centres[:, 2] >= 1.2) & (centres[:, 2] <= 1.8)).all()
    outward = (centres[:, :2] - middle) / radius[:, None]
    gaze = _gaze(poses)[:, :2] / np.linalg.norm(_gaze(poses)[:, :2], axis=1, keepdims=True)
    assert np.einsum("ij,ij->i", gaze, outward).min() > math.cos(math.radians(15))  # looking out
    angle = np.unwrap(np.arctan2(outward[:, 1], outward[:, 0]))
    assert abs(angle[-1] - angle[0]) > math.radians(350)  # round the whole room in 10 s
    speed, turn = walk_speeds(poses)
    assert 0.4 < np.median(speed) < 1.0 and turn.max() <= 60.0


@pytest.mark.parametrize("kind", ["centre_loop", "pan"])
def test_real_filming_keeps_a_persons_pace_whatever_the_length(kind: str) -> None:
    for n in (90, 600):
        _, turn = walk_speeds(draw_walk(np.random.default_rng(2), SIZE, n, kind).poses)  # type: ignore[arg-type]
        assert abs(np.median(turn) - TURN_DEG_S) < 5.0, (n, np.median(turn))


def test_survey_loops_are_the_same_path_denser_with_more_frames() -> None:
    """The calibration walk covers one path whatever its length: two loops round the room."""
    short = scenes.camera_walk(np.random.default_rng(4), SIZE, 101)
    long = scenes.camera_walk(np.random.default_rng(4), SIZE, 201)
    np.testing.assert_allclose([p.position for p in short], [p.position for p in long[::2]], atol=1e-9)
    calibration = np.array([p.position for p in scenes.camera_walk(np.random.default_rng(4), SIZE, 400)])
    round_room = np.unwrap(np.arctan2(calibration[:, 1] - SIZE[1] / 2, calibration[:, 0] - SIZE[0] / 2))
    assert abs(round_room[-1] - round_room[0]) == pytest.approx(4 * math.pi, abs=0.1)  # two loops


def test_shake_is_small_fast_jitter_on_top_of_the_same_walk() -> None:
    steady = draw_walk(np.random.default_rng(5), SIZE, 300, "centre_loop")
    shaken = draw_walk(np.random.default_rng(5), SIZE, 300, "centre_loop", Shake())
    assert shaken.base == steady.poses  # the shake is drawn after the walk: the walk is the same
    turn = np.array([np.linalg.norm((a.R @ b.R.T) - np.eye(3)) / math.sqrt(2)
                     for a, b in zip(shaken.poses, steady.poses, strict=True)])
    shift = np.linalg.norm([a.position - b.position for a, b in zip(shaken.poses, steady.poses, strict=True)], axis=1)
    # RMS 0.2 degrees and 1.5 mm per axis: about sqrt(3) times that in all.
    assert 0.15 < np.degrees(np.sqrt(np.mean(turn**2))) < 0.55
    assert 0.0015 < np.sqrt(np.mean(shift**2)) < 0.004
    # Several cycles a second: its spectrum sits in the 1.5-6 Hz band.
    assert shaken.shake is not None
    jitter, _ = shaken.shake.at(np.arange(3000) / FPS)
    spectrum = np.abs(np.fft.rfft(jitter[:, 0])) ** 2
    hz = np.fft.rfftfreq(3000, 1 / FPS)
    assert 1.5 < np.sum(hz * spectrum) / np.sum(spectrum) < 6.0
    with pytest.raises(ValueError):
        Shake(rotation_deg=-1.0)
    with pytest.raises(ValueError):
        Shake(band_hz=(0.0, 4.0))


def test_a_walk_between_frames_passes_through_its_frames() -> None:
    walk = draw_walk(np.random.default_rng(6), SIZE, 50, "centre_loop", Shake())
    again = walk.poses_at(np.arange(50.0))
    for a, b in zip(again, walk.poses, strict=True):
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.t, b.t, atol=1e-12)
    # Between frames the camera moves smoothly: half-way between two frames it is near
    # half-way between their centres, and its velocity does not jump at a frame.
    steady = draw_walk(np.random.default_rng(6), SIZE, 50, "centre_loop")
    mid = steady.poses_at(np.array([10.5]))[0]
    np.testing.assert_allclose(mid.position, (steady.poses[10].position + steady.poses[11].position) / 2, atol=1e-3)
    h = 1e-4
    before, at, after = (p.position for p in steady.poses_at(np.array([10.0 - h, 10.0, 10.0 + h])))
    np.testing.assert_allclose((at - before) / h, (after - at) / h, rtol=1e-3)
    turn_before = rotation_angle(steady.poses_at(np.array([10.0 - h]))[0], steady.poses[10]) / h
    turn_after = rotation_angle(steady.poses[10], steady.poses_at(np.array([10.0 + h]))[0]) / h
    assert turn_after == pytest.approx(turn_before, rel=1e-3)


def test_motion_blur_is_the_image_motion_during_the_exposure() -> None:
    pan = draw_walk(np.random.default_rng(7), SIZE, 120, "pan")
    blur = pan.exposure_blur(BENCH_CAMERA, EXPOSURE_S, SIZE)
    lengths = np.array([b.length_px for b in blur])
    # A pan turning 36 deg/s moves the image sideways by about f * omega * exposure.
    expected = BENCH_CAMERA.fx * math.radians(TURN_DEG_S) * EXPOSURE_S
    assert np.median(lengths) == pytest.approx(expected, rel=0.1)
    angles = np.array([b.angle_rad for b in blur])
    assert np.median(np.minimum(angles, math.pi - angles)) < math.radians(15)  # mostly horizontal
    # Twice the exposure, twice the smear; no exposure, no smear; a still camera, none either.
    double = [b.length_px for b in pan.exposure_blur(BENCH_CAMERA, 2 * EXPOSURE_S, SIZE)]
    np.testing.assert_allclose(double, 2 * lengths, rtol=0.02)
    assert all(b.length_px == 0 for b in pan.exposure_blur(BENCH_CAMERA, 0.0, SIZE))
    still = dataclasses.replace(pan, base=[pan.poses[0]] * 5)
    assert all(b.length_px < 1e-9 for b in still.exposure_blur(BENCH_CAMERA, EXPOSURE_S))
    with pytest.raises(ValueError):
        pan.exposure_blur(BENCH_CAMERA, 2.0 / FPS)


def test_rendered_walk_takes_its_blur_and_keeps_the_rest() -> None:
    room = SPARSE_WALK.walk(0, 3)
    assert room.blur is not None
    plain = SPARSE_ROOM.walk(0, 3, "centre_loop", SPARSE_WALK.shake)  # the same walk, the preset's blur
    assert plain.poses == room.poses
    blurred = [truth for _, truth in room.frames(BENCH_CAMERA)]
    preset = [truth for _, truth in plain.frames(BENCH_CAMERA)]
    for b, p, smear in zip(blurred, preset, room.blur, strict=True):
        assert b.degradation["blur_length"] == smear.length_px > 1.0
        assert b.degradation["blur_angle"] == smear.angle_rad
        assert b.pose == p.pose  # the truth is the pose at mid-exposure
    # The first frame's other degradations are drawn as without the walk's blur (later
    # frames differ: the sensor noise of a different image draws differently).
    rest = [{k: v for k, v in t.degradation.items() if not k.startswith("blur")} for t in (blurred[0], preset[0])]
    assert rest[0] == rest[1]


def test_a_frame_rendered_along_its_exposure_is_the_sensors_integral() -> None:
    room = SPARSE_WALK.walk(0, 3)
    assert room.blur is not None
    smear = room.blur[0]
    assert len(smear.path) >= max(3, math.ceil(smear.length_px))
    straight, straight_truth = next(iter(room.frames(BENCH_CAMERA, "none")))
    along, truth = next(iter(SPARSE_WALK.walk(0, 3).frames(BENCH_CAMERA, "none", follow_path=True)))
    # The truth is the pose averaged over the exposure: the mid-exposure pose here
    # (a smooth path), to a few micrometres.
    assert np.linalg.norm(truth.pose.position - straight_truth.pose.position) < 1e-4
    assert exposure_average(smear.path) == truth.pose
    # The mean of the renders along the path is the integral the straight smear
    # approximates: the same frame but for a few grey levels where the smear is not
    # straight (the shake turns the camera during the exposure).
    difference = np.abs(along.astype(float) - straight)
    sharp = scenes.render_frame(room.scene, BENCH_CAMERA, truth.pose, np.random.default_rng(0))[0]
    blurred = np.abs(along.astype(float) - sharp).mean()
    assert 0.1 < difference.mean() < 0.5 * blurred, (difference.mean(), blurred)


def test_a_lens_blurs_each_part_of_the_room_by_its_depth() -> None:
    lens = CINE_LENS
    room = BENCH_ROOM.walk(0, 300)
    depth = room.scene.surfaces(BENCH_CAMERA, room.poses[0]).depth
    # Depths are those of the walls the rays meet: inside the room, in front.
    assert 0.1 < depth.min() and depth.max() < math.hypot(*SIZE)
    sharp, truth = next(iter(room.frames(BENCH_CAMERA, "none")))
    soft, soft_truth = next(iter(BENCH_ROOM.walk(0, 300).frames(BENCH_CAMERA, "none", lens=lens)))
    assert soft_truth.pose == truth.pose  # the truth does not move
    radius = lens.blur_radius_px(depth, BENCH_CAMERA.fx)
    assert radius.max() > 0.5 and np.abs(soft.astype(float) - sharp).mean() > 0.5


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sparse_rooms_show_one_or_two_cards_at_a_time(seed: int) -> None:
    room = SPARSE_WALK.walk(seed, 300)
    centres = np.array([t.discs.mean(axis=0) for t in room.scene.targets])
    gaps = np.linalg.norm(centres[:, None] - centres[None], axis=2) + np.eye(len(centres)) * 99
    assert len(centres) == 10 and gaps.min() > 1.0  # spread out: bare wall between them
    counts = np.array([_seen(BENCH_CAMERA, p, room.scene) for p in room.poses])
    assert (counts <= 2).mean() > 0.95
    assert ((counts >= 1) & (counts <= 2)).mean() > 0.5
    dense = BENCH_ROOM.walk(seed, 300, "centre_loop")
    assert np.median([_seen(BENCH_CAMERA, p, dense.scene) for p in dense.poses]) >= 2


def test_plain_walls_carry_no_texture() -> None:
    camera = BENCH_CAMERA
    # From the middle of the room, square on to the 8 m wall 3 m away: the view holds that wall only.
    pose = Pose.look_at([SIZE[0] / 2, 3.0, 1.5], [SIZE[0] / 2, 0.0, 1.5])
    images = {}
    for room in (SPARSE_ROOM, PLAIN_ROOM):
        scene = room.scene(0)
        images[room.walls] = render(camera, pose, scene.background, background=0.5).astype(np.float64)
    fine = {walls: np.abs(np.diff(image, axis=1)).max() for walls, image in images.items()}
    assert fine["plain"] < 0.002 and fine["photo"] > 0.1
    assert 0.6 < images["plain"].mean() < 0.9 and np.ptp(images["plain"]) < 0.06  # one paint, slightly shaded
    # Same seed, same cards: only the walls differ between the two rooms.
    for a, b in zip(SPARSE_ROOM.scene(3).targets, PLAIN_ROOM.scene(3).targets, strict=True):
        np.testing.assert_array_equal(a.discs, b.discs)


def test_unknown_options_are_refused() -> None:
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError):
        draw_walk(rng, SIZE, 10, "sideways")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        scenes.room_scene(rng, SIZE, 4, walls="wallpaper")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        scenes.room_scene(rng, SIZE, 4, cards="grid")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        draw_walk(rng, (1.5, 1.5, 2.5), 10, "centre_loop")  # no room for a loop
    with pytest.raises(ValueError):
        scenes.room_scene(rng, SIZE, 200, cards="spread")  # cannot be spread apart


def test_every_example_walk_is_named_and_drawn_from_its_seed() -> None:
    assert set(WALKS) == {"bench", "centre_loop", "pan", "sparse", "plain", "furnished", "bare_wall"}
    for name, walk in WALKS.items():
        assert walk.name == name
        a, b = walk.walk(1, 20), walk.walk(1, 20)
        assert a.poses == b.poses and (a.blur == b.blur)
        assert (a.blur is None) == (walk.exposure_s is None)
    assert isinstance(ShakeMotion.draw(np.random.default_rng(0), Shake()), ShakeMotion)
