"""Shared fixtures of the survey's tests: a small room with a calibration walk and its
exact or noisy detections, the bench room's oblique views, and a survey state built on
the truth (every frame registered at its true pose, every target placed at its true
discs) for testing one stage at a time."""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
import pytest

from app.core.detection import DetectedTarget
from app.core.geometry import Camera
from app.core.survey.points import FeatureObservations
from app.core.survey.state import StageClock, SurveySettings, SurveyState
from app.core.survey.tracks import collect_tracks
from app.sim.examples import BENCH_ROOM, ExampleRoom, RoomWalk
from app.sim.scenes import Scene, TargetTruth, frame_truth

#: A small room for the survey's tests: 4 x 3 x 2.5 m, 16 cards of 0.2 m, 640x480 at
#: f 600 px with k1 -0.1; its walk is 80 frames from seed 7.
SURVEY_ROOM = ExampleRoom(
    "survey-test", (4.0, 3.0, 2.5), 16, 0.2,
    Camera(np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]]), np.array([-0.1, 0.0, 0.0, 0.0, 0.0]),
           640, 480))

Frames = list[list[DetectedTarget]]

#: Each wall feature track follows its point through at most this many consecutive frames.
RUN = 12


@functools.cache
def wall_walk() -> RoomWalk:
    """The small room's 80-frame calibration walk (seed 7)."""
    return SURVEY_ROOM.walk(7, 80)


def wall_points(rng: np.random.Generator, m: int, margin: tuple[float, float] = (0.05, 0.1),
                size: tuple[float, float, float] = SURVEY_ROOM.size) -> tuple[np.ndarray, np.ndarray]:
    """m points on the four walls of a room of ``size``, kept ``margin`` (along the wall as a
    fraction, from floor and ceiling in metres) off the edges, and each wall's inward normal."""
    w, d, h = size
    wall = rng.integers(4, size=m)
    along, z = rng.uniform(margin[0], 1 - margin[0], m), rng.uniform(margin[1], h - margin[1], m)
    X = np.select([wall[:, None] == k for k in range(3)],
                  [np.c_[along * w, 0 * z, z], np.c_[along * w, d + 0 * z, z], np.c_[0 * z, along * d, z]],
                  np.c_[w + 0 * z, along * d, z])
    inward = np.array([[0, 1, 0], [0, -1, 0], [1, 0, 0], [-1, 0, 0]], float)[wall]
    return X, inward


@functools.cache
def wall_features(sigma_px: float = 0.1, m: int = 6000, seed: int = 3, track_error_px: float = 0.0,
                  focal_px: float | None = None) -> FeatureObservations:
    """Tracks of wall points through `wall_walk`: each seen point followed through runs of
    up to ``RUN`` consecutive frames (a new track per run), with noise of ``sigma_px`` in
    every view, and with ``track_error_px`` a further error drawn once per track and kept
    through all its views (a tracker locked onto a patch a little off the point); with
    ``focal_px``, seen through a lens of that focal length instead of the room's."""
    walk, camera = wall_walk(), SURVEY_ROOM.camera
    if focal_px is not None:
        K = camera.K.copy()
        K[0, 0] = K[1, 1] = focal_px
        camera = Camera(K, camera.dist, camera.width, camera.height)
    rng = np.random.default_rng(seed)
    X, inward = wall_points(rng, m)
    rows: list[tuple[int, int, float, float]] = []
    live: dict[int, tuple[int, int]] = {}  # point -> (track, frames so far)
    offsets: list[np.ndarray] = []  # each track's own error
    for f, pose in enumerate(walk.poses):
        uv = camera.project_map(X, pose)
        ray = pose.position - X
        facing = (ray * inward).sum(axis=1) > 0.3 * np.linalg.norm(ray, axis=1)
        inside = ((uv >= 4) & (uv <= [camera.width - 5, camera.height - 5])).all(axis=1)
        seen = np.flatnonzero(camera.in_field(pose.transform(X)) & facing & inside)
        for j in set(live) - set(seen.tolist()):
            del live[j]
        for j in seen.tolist():
            track, count = live.get(j, (-1, RUN))
            if count >= RUN:
                track, count = len(offsets), 0
                offsets.append(rng.normal(0, track_error_px, 2) if track_error_px else np.zeros(2))
            live[j] = (track, count + 1)
            noisy = uv[j] + offsets[track] + rng.normal(0, sigma_px, 2)
            rows.append((f, track, float(noisy[0]), float(noisy[1])))
    a = np.array(rows)
    return FeatureObservations(a[:, 0].astype(np.int64), a[:, 1].astype(np.int64), a[:, 2:4], sigma_px=sigma_px)


@pytest.fixture(scope="session")
def room() -> ExampleRoom:
    """The small test room (its camera, card size, walls)."""
    return SURVEY_ROOM


@pytest.fixture(scope="session")
def room_walk() -> RoomWalk:
    """The small room and its 80-frame calibration walk."""
    return SURVEY_ROOM.walk(7, 80)


@functools.cache
def _synthetic_frames(sigma: float, seed: int) -> tuple[tuple[DetectedTarget, ...], ...]:
    walk = SURVEY_ROOM.walk(7, 80)
    rng = np.random.default_rng(seed)
    frames = []
    for pose in walk.poses:
        truth = frame_truth(SURVEY_ROOM.camera, pose, walk.scene)
        frames.append(tuple(DetectedTarget(t.id, t.discs_px + rng.normal(0, sigma, (4, 2)), 1.0)
                            for t in truth.visible_targets()))
    return tuple(frames)


@pytest.fixture(scope="session")
def synthetic_frames() -> Callable[[float, int], Frames]:
    """Detections of the small room's walk: the projections of the true discs of every
    visible target, plus Gaussian noise of ``sigma`` px drawn from ``seed`` (a fresh
    list every call, to alter at will)."""

    def frames(sigma: float, seed: int = 0) -> Frames:
        return [list(f) for f in _synthetic_frames(sigma, seed)]

    return frames


def _in_image(t: TargetTruth) -> bool:
    """Every disc projects into the image (2 px in) and the card faces the camera: the
    visible cards, and also those outside the lens's field that the distortion polynomial
    folds back into the image (target_truth calls them not visible). Kept on purpose where
    the survey must not be misled by such detections."""
    uv = t.discs_px
    return bool(np.isfinite(uv).all() and ((uv >= 2) & (uv <= [637, 477])).all() and t.facing_cos > 0.05)


@pytest.fixture(scope="session")
def oblique_room() -> tuple[Scene, Frames]:
    """The bench room's first 100 calibration frames (`BENCH_ROOM`, seed 0) with
    ground-truth detections of every card facing the camera by more than 0.3 (up to 72
    degrees off its normal), plus 0.03 px of Gaussian noise. As visible, the truth also
    counts some projections of cards outside the field that the distortion polynomial
    folds back into the image: the survey must not be misled by them."""
    walk = BENCH_ROOM.walk(0, 300)
    noise = np.random.default_rng(5)
    frames = []
    for pose in walk.poses[:100]:
        truth = frame_truth(BENCH_ROOM.camera, pose, walk.scene)
        frames.append([DetectedTarget(t.id, t.discs_px + noise.normal(0, 0.03, (4, 2)), 1.0)
                       for t in truth.targets if _in_image(t) and t.facing_cos > 0.3])
    return walk.scene, frames


@pytest.fixture
def true_state(room_walk: RoomWalk, synthetic_frames: Callable[[float, int], Frames]) -> SurveyState:
    """A survey state on the small room's exact detections (no noise), the camera given,
    every frame registered at its true pose and every target placed at its true discs:
    the optimum. Tests take out or disturb what their stage is to find."""
    frames = synthetic_frames(0.0, 0)
    warnings: list[str] = []
    tracks = collect_tracks(frames, list(range(len(frames))), warnings)
    settings = SurveySettings(SURVEY_ROOM.marker_size_m, intrinsics_given=True)
    state = SurveyState.start(tracks, SURVEY_ROOM.camera, settings, StageClock(), warnings)
    truth = {t.id: t.discs for t in room_walk.scene.targets}
    for k, target_id in enumerate(tracks.ids):
        state.reconstruction.place(k, truth[int(target_id)])
    for f, pose in enumerate(room_walk.poses):
        if len(state.views.of_frame[f]):
            state.reconstruction.set_pose(f, pose)
    state.seed_frame = int(np.flatnonzero(state.reconstruction.registered())[0])
    return state
