"""The automatic survey end to end (structure from motion over a calibration video), and
alignment of its map."""

from __future__ import annotations

import json
from collections.abc import Callable

import cv2
import numpy as np
import pytest

from app.core.detection import DetectedTarget
from app.core.geometry import Camera, Pose
from app.core.geometry.alignment import (
    Similarity,
    alignment_residuals,
    similarity_from_points,
    target_origin_alignment,
)
from app.core.survey import SurveyError, SurveyResult, SurveyStage, survey
from app.sim.examples import BENCH_CAMERA, ExampleRoom, RoomWalk
from app.sim.scenes import Scene, camera_walk, render_walk, room_scene

Frames = list[list[DetectedTarget]]
SyntheticFrames = Callable[[float, int], Frames]


def _disc_rms(result: SurveyResult, scene: Scene, scale: bool = False) -> float:
    truth = {t.id: t.discs for t in scene.targets}
    src = np.concatenate([t.discs for t in result.targets])
    dst = np.concatenate([truth[t.id] for t in result.targets])
    similarity = similarity_from_points(src, dst, with_scale=scale)
    return float(np.sqrt(np.mean(alignment_residuals(similarity, src, dst) ** 2)))


# --- synthetic detections: fast and exact checks ----------------------------------------


def test_synthetic_survey_recovers_lens_and_map(room: ExampleRoom, room_walk: RoomWalk,
                                                synthetic_frames: SyntheticFrames) -> None:
    scene, poses, camera = room_walk.scene, room_walk.poses, room.camera
    # 0.03 px: about the real detector's error on such walks (0.023 px). The map error is
    # noise-limited and scales with it: at 0.1 px the 3 mm bound below is the median over
    # noise seeds (2.5-7.3 mm), at 0.03 px seeds 0-9 give 0.7-2.2 mm.
    frames = synthetic_frames(0.03, 0)
    stages: list[tuple[str, float]] = []
    result = survey(frames, 640, 480, room.marker_size_m, progress=lambda s, f: stages.append((s, f)))
    assert abs(result.camera.fx / camera.fx - 1) < 0.003, result.camera
    assert abs(result.camera.dist[0] - camera.dist[0]) < 0.02
    assert np.hypot(result.camera.cx - camera.cx, result.camera.cy - camera.cy) < 5.0
    # Each intrinsic comes with its standard deviation, which covers its error.
    std = result.intrinsics_std
    assert std is not None and (std > 0).all()
    errors = np.abs([result.camera.fx - camera.fx, result.camera.cx - camera.cx, result.camera.cy - camera.cy])
    assert (errors < 4 * std[:3]).all(), (errors, std)
    assert result.summary()["intrinsics_std"]["principal_point_px"] == [std[1], std[2]]
    # Independent noise in every frame: nothing to widen the uncertainties by.
    assert 1.0 <= result.correlation_time < 1.3 and result.summary()["correlation_time"] == result.correlation_time
    assert len(result.targets) == len({t.id for f in frames for t in f})
    # Metric without any scale fitting to the truth: the card layout fixes it.
    assert _disc_rms(result, scene) < 0.003
    assert result.rms_px < 0.2
    assert result.n_registered >= 0.9 * sum(bool(f) for f in frames)
    assert len(result.trajectory) == len(frames)
    # Registered poses are the true ones, in the survey frame: align and compare.
    truth = {t.id: t.discs for t in scene.targets}
    sim = similarity_from_points(np.concatenate([t.discs for t in result.targets]),
                                 np.concatenate([truth[t.id] for t in result.targets]))
    # (Frames that see 2+ targets: a pose from one small card is coarse, cm at 3 m.)
    errors = [np.linalg.norm(sim.apply_pose(p).position - q.position)
              for p, q, f in zip(result.trajectory, poses, frames, strict=True) if p is not None and len(f) >= 2]
    assert np.median(errors) < 0.01
    # Progress: the named stages in order, fractions in [0, 1], ending at 1.
    assert stages[-1] == ("done", 1.0) and all(0.0 <= f <= 1.0 for _, f in stages)
    assert all(a <= b for (_, a), (_, b) in zip(stages, stages[1:], strict=False))
    order = [list(SurveyStage).index(SurveyStage(s)) for s, _ in stages]
    assert order == sorted(order)
    assert set(result.timing_s) == {s.value for s in SurveyStage} - {"done"}
    # The discs' reported uncertainties are those of the map up to one rigid motion:
    # they match the errors left after a rigid alignment to the truth.
    std = np.concatenate([t.std_m for t in result.targets])
    src = np.concatenate([t.discs for t in result.targets])
    dst = np.concatenate([truth[t.id] for t in result.targets])
    rigid = similarity_from_points(src, dst, with_scale=False)
    error_rms = np.sqrt(np.mean(np.sum((rigid.apply(src) - dst) ** 2, axis=1)))
    assert np.isfinite(std).all() and 0.5 < error_rms / np.sqrt(np.mean(std**2)) < 2, (error_rms, std)


def test_misidentified_views_are_removed(room: ExampleRoom, room_walk: RoomWalk,
                                         synthetic_frames: SyntheticFrames) -> None:
    clean = synthetic_frames(0.1, 1)
    frames = [list(f) for f in clean]
    # Relabel one target as another in a few frames at the start of the video (a misread
    # code): same pixels, wrong id, so the views land on the wrong 3D points. Frame 3
    # sees only the relabelled card, frames 0-2 see it with cards not yet surveyed.
    ids_seen = sorted({t.id for f in frames for t in f})
    wrong_id = ids_seen[0]
    injected: list[int] = []  # frames holding a misread view
    for k, f in enumerate(frames):
        ids = {t.id for t in f}
        if wrong_id in ids or not f or len(injected) >= 4:
            continue
        victim = f[0]
        f[0] = DetectedTarget(wrong_id, victim.discs, 1.0)
        injected.append(k)
    assert len(injected) == 4
    result = survey(frames, 640, 480, room.marker_size_m)
    reference = survey(clean, 640, 480, room.marker_size_m)
    assert len(result.targets) == len(reference.targets) == len(ids_seen)
    # Every misread view is either rejected or left out with its whole frame (frame 3
    # sees nothing else: it cannot be registered).
    left_out = sum(result.trajectory[k] is None for k in injected)
    assert result.n_rejected_views + left_out >= len(injected)
    # The map is as good as without the misread codes (this walk's geometry allows
    # ~5 mm at 0.1 px noise; see the clean survey).
    scene = room_walk.scene
    assert _disc_rms(result, scene) < 1.1 * _disc_rms(reference, scene) + 0.0002
    assert _disc_rms(result, scene) < 0.006
    assert result.rms_px < 0.3


def test_a_disc_centre_far_off_is_set_aside(room: ExampleRoom, room_walk: RoomWalk,
                                            synthetic_frames: SyntheticFrames) -> None:
    """A fitted disc centre is good to ~0.01 px, but now and then one is 0.3-0.9 px off
    (glare or an occluder on one disc). Such a view is set aside and the map stays as
    it was: judged by the noise level, not by a fixed pixel tolerance (with a 3 px
    tolerance and Huber's loss from 1 px, these two views move this map from 0.28 to
    1.3 mm)."""
    clean = synthetic_frames(0.01, 2)
    frames = [list(f) for f in clean]
    rng = np.random.default_rng(2)
    views = [(i, j) for i, f in enumerate(frames) for j in range(len(f))]
    bad = rng.choice(len(views), size=len(views) // 100, replace=False)
    for k in bad:
        i, j = views[k]
        discs = frames[i][j].discs.copy()
        angle = rng.uniform(0, 2 * np.pi)
        discs[rng.integers(4)] += 0.5 * np.array([np.cos(angle), np.sin(angle)])
        frames[i][j] = DetectedTarget(frames[i][j].id, discs, 1.0)
    assert len(bad) == 2
    result = survey(frames, 640, 480, room.marker_size_m)
    reference = survey(clean, 640, 480, room.marker_size_m)
    assert reference.n_rejected_views == 0 and result.n_rejected_views == len(bad)
    assert _disc_rms(result, room_walk.scene) < 1.1 * _disc_rms(reference, room_walk.scene)


@pytest.mark.parametrize("seed", [5, 8])  # 5: a card that a plain refinement places 0.85 m off
def test_wrongly_identified_card_in_later_frames_is_removed(seed: int, room: ExampleRoom, room_walk: RoomWalk,
                                                            synthetic_frames: SyntheticFrames) -> None:
    """A misread code in the middle of the video, in frames with other targets."""
    frames = synthetic_frames(0.1, seed)
    ids_seen = sorted({t.id for f in frames for t in f})
    injected: list[int] = []  # frames holding a misread view
    for k in range(40, len(frames)):
        f = frames[k]
        ids = {t.id for t in f}
        spare = [i for i in ids_seen if i not in ids]
        if len(f) >= 3 and len(injected) < 3:
            f[0] = DetectedTarget(spare[0], f[0].discs, 1.0)
            injected.append(k)
    result = survey(frames, 640, 480, room.marker_size_m)
    # Every misread view is either rejected or left out with its whole frame.
    left_out = sum(result.trajectory[k] is None for k in injected)
    assert result.n_rejected_views + left_out >= len(injected)
    assert _disc_rms(result, room_walk.scene) < 0.006
    assert result.rms_px < 0.3


def test_oblique_cards_survey_to_the_noise(oblique_room: tuple[Scene, Frames]) -> None:
    """Strongly foreshortened cards are valid geometry: the map must reach the noise.

    The hard parts here: narrow-baseline cards (triangulated 1 m off), the wrong one of
    a card's two tilts, a folded projection of a card outside the field (the largest
    "view"); each, placed, is a wrong minimum the bundle adjustment stays in (13.6 mm and
    0.088 px here, 2x the noise). The bundle adjustment started from the truth gives
    2.3 mm on these frames (some cards are seen over 1.5 degrees only)."""
    scene, frames = oblique_room
    result = survey(frames, 640, 480, 0.2)
    assert result.rms_px < 0.05  # the noise: 0.03 px per coordinate, 0.042 px in 2D
    assert _disc_rms(result, scene, scale=True) < 0.004
    assert abs(result.camera.fx / BENCH_CAMERA.fx - 1) < 0.002
    # 26 of the 30 ids can be surveyed: 4 are seen in one frame, or only in frames that
    # see nothing else of the map.
    assert len(result.targets) >= 25
    assert any("mirrored or folded" in w for w in result.warnings)


def test_fixed_intrinsics_are_held(room: ExampleRoom, room_walk: RoomWalk,
                                   synthetic_frames: SyntheticFrames) -> None:
    result = survey(synthetic_frames(0.1, 2), 640, 480, room.marker_size_m, intrinsics=room.camera)
    assert result.intrinsics_fixed and result.intrinsics_std is None
    assert result.summary()["intrinsics_std"] is None
    assert result.camera == room.camera
    assert _disc_rms(result, room_walk.scene) < 0.005


def test_subsampling_and_trajectory_length(room: ExampleRoom, synthetic_frames: SyntheticFrames) -> None:
    frames = synthetic_frames(0.1, 3)
    result = survey(frames, 640, 480, room.marker_size_m, max_frames=40)
    assert len(result.frames_used) == 40
    assert len(result.trajectory) == len(frames)
    unused = set(range(len(frames))) - set(result.frames_used)
    assert all(result.trajectory[i] is None for i in unused)


def test_map_document_is_valid(room: ExampleRoom, synthetic_frames: SyntheticFrames) -> None:
    result = survey(synthetic_frames(0.1, 4), 640, 480, room.marker_size_m)
    doc = result.to_map_document(survey_job_id="job-1")
    assert doc["frame"] == "survey" and doc["units"] == "m" and doc["survey_job_id"] == "job-1"
    assert set(doc["camera"]) == {"width", "height", "K", "dist"}
    assert Camera.from_dict(doc["camera"]) == result.camera
    ids = [t["id"] for t in doc["targets"]]
    assert ids == sorted(ids) and len(ids) == len(result.targets)
    for t in doc["targets"]:
        assert np.asarray(t["discs"]).shape == (4, 3)
        assert len(t["std_m"]) == 4 and all(s > 0 for s in t["std_m"])
        assert t["n_views"] >= 2
    assert doc["rms_px"] == pytest.approx(result.rms_px, abs=1e-4)
    json.dumps(doc)  # plain JSON types only


def test_survey_refuses_what_cannot_be_surveyed(room: ExampleRoom, synthetic_frames: SyntheticFrames) -> None:
    size = room.marker_size_m
    with pytest.raises(SurveyError, match="no targets"):
        survey([[] for _ in range(10)], 640, 480, size)
    with pytest.raises(SurveyError, match="at least 2 frames"):
        survey([[]], 640, 480, size)
    one = synthetic_frames(0.1, 0)[10]
    assert one
    with pytest.raises(SurveyError, match="fewer than 2 frames"):
        survey([one] + [[] for _ in range(5)], 640, 480, size)
    with pytest.raises(SurveyError, match="marker_size_m"):
        survey(synthetic_frames(0.1, 0), 640, 480, 0.0)


# --- rendered frames, the real detector --------------------------------------------------


def test_rendered_room_survey(room: ExampleRoom) -> None:
    from app.core.detection import Detector, load_default_classifier

    rng = np.random.default_rng(11)
    scene = room_scene(rng, size=room.size, n_targets=14, marker_size_m=room.marker_size_m)
    poses = camera_walk(rng, room.size, 50, kind="calibration")
    detector = Detector(classifier=load_default_classifier())
    frames = [detector.detect(image).targets
              for image, _ in render_walk(scene, room.camera, poses, rng, supersample=1)]
    result = survey(frames, 640, 480, room.marker_size_m)
    assert abs(result.camera.fx / room.camera.fx - 1) < 0.01, result.camera
    assert len(result.targets) >= 5
    assert _disc_rms(result, scene) < 0.005
    doc = result.to_map_document()
    assert len(doc["targets"]) == len(result.targets)


# --- alignment ---------------------------------------------------------------------------


def test_umeyama_recovers_a_similarity() -> None:
    rng = np.random.default_rng(3)
    R, _ = cv2.Rodrigues(rng.normal(size=3))
    truth = Similarity(2.5, R, np.array([1.0, -2.0, 0.5]))
    src = rng.normal(size=(6, 3))
    dst = truth.apply(src)
    est = similarity_from_points(src, dst)
    assert est.scale == pytest.approx(2.5, rel=1e-9)
    np.testing.assert_allclose(est.R, R, atol=1e-9)
    np.testing.assert_allclose(est.t, truth.t, atol=1e-9)
    assert alignment_residuals(est, src, dst).max() < 1e-9
    # Noise shows in the residuals; the inverse undoes the transform.
    noisy = dst + rng.normal(0, 0.01, dst.shape)
    assert 0.001 < alignment_residuals(similarity_from_points(src, noisy), src, noisy).mean() < 0.05
    np.testing.assert_allclose(est.inverse().apply(dst), src, atol=1e-9)


def test_umeyama_refuses_degenerate_input() -> None:
    line = np.c_[np.linspace(0, 1, 5), 2 * np.linspace(0, 1, 5), np.zeros(5)]
    with pytest.raises(ValueError, match="collinear"):
        similarity_from_points(line, line + 1.0)
    with pytest.raises(ValueError, match="at least 3"):
        similarity_from_points(np.eye(3)[:2], np.eye(3)[:2])


def test_similarity_moves_poses_with_the_map() -> None:
    rng = np.random.default_rng(4)
    R, _ = cv2.Rodrigues(rng.normal(size=3))
    sim = Similarity(1.7, R, np.array([0.3, 0.1, -0.2]))
    camera = Camera.pinhole(700.0, 640, 480)
    pose = Pose.look_at([0.0, 0.0, 0.0], [0.0, 3.0, 0.2])
    X = rng.uniform(-1, 1, (10, 3)) + np.array([0.0, 3.0, 0.0])
    np.testing.assert_allclose(camera.project_map(sim.apply(X), sim.apply_pose(pose)),
                               camera.project_map(X, pose), atol=1e-9)
    np.testing.assert_allclose(sim.apply_pose(pose).position, sim.apply(pose.position), atol=1e-9)


def test_target_origin_alignment(room: ExampleRoom, room_walk: RoomWalk) -> None:
    target = room_walk.scene.targets[3]
    sim = target_origin_alignment(target.discs)
    moved = sim.apply(target.discs)
    np.testing.assert_allclose(moved[:, 2], 0.0, atol=1e-3)  # the card bends by a few mm at most
    np.testing.assert_allclose(moved.mean(axis=0)[:2], 0.0, atol=1e-9)
    x = moved[1] - moved[0]
    assert x[0] > 0 and abs(x[1]) < 1e-3
    assert moved[0, 1] > moved[3, 1]  # disc 0 (top) above disc 3 (bottom): y up the card
    # z points out of the printed face, i.e. into the room, towards a viewer.
    assert (sim.R @ target.normal)[2] == pytest.approx(1.0, abs=1e-6)
    assert sim.scale == 1.0
    doc = sim.apply_map_document(room_walk.scene.map_document(room.camera))
    assert doc["frame"] == "world"
    np.testing.assert_allclose(np.asarray(doc["targets"][3]["discs"])[:, 2], 0.0, atol=1e-3)
