"""Feature points in the survey: frames that see one card register through the walls'
own points, cards never seen together join, and wrong matches do not move the map.

The feature tracks here are exact images of points on the small room's walls (from the
room's geometry and the walk's true poses, never from the survey) with Gaussian noise."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.detection import DetectedTarget
from app.core.geometry import similarity_from_points
from app.core.survey import FeatureObservations, SurveyResult, survey
from app.core.survey.features import feature_groups, position_std, triangulate_features
from app.core.survey.state import StageClock, SurveySettings, SurveyState
from app.core.survey.tracks import collect_tracks

from .conftest import SURVEY_ROOM, wall_features, wall_walk


def _one_card_a_frame(frames: list[list[DetectedTarget]]) -> list[list[DetectedTarget]]:
    """Each frame with only its largest card: how a room with few cards is filmed."""
    def area(t: DetectedTarget) -> float:
        x, y = t.discs[:, 0], t.discs[:, 1]
        return 0.5 * abs(float(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1))))
    return [[max(f, key=area)] if f else [] for f in frames]


def _disc_rms_mm(result: SurveyResult) -> float:
    truth = {t.id: t.discs for t in wall_walk().scene.targets}
    src = np.concatenate([t.discs for t in result.targets])
    dst = np.concatenate([truth[t.id] for t in result.targets])
    similar = similarity_from_points(src, dst)
    return 1000 * float(np.sqrt(np.mean(np.sum((similar.apply(src) - dst) ** 2, axis=1))))


def _survey(frames: list[list[DetectedTarget]], features: FeatureObservations | None) -> SurveyResult:
    camera = SURVEY_ROOM.camera
    return survey(frames, camera.width, camera.height, SURVEY_ROOM.marker_size_m, features=features)


@pytest.fixture(scope="module")
def sparse_frames(synthetic_frames) -> list[list[DetectedTarget]]:  # type: ignore[no-untyped-def]
    return _one_card_a_frame(synthetic_frames(0.05, 1))


@pytest.fixture(scope="module")
def with_features(sparse_frames: list[list[DetectedTarget]]) -> SurveyResult:
    return _survey(sparse_frames, wall_features())


def test_a_walk_with_one_card_a_frame_is_surveyed_whole_through_feature_tracks(
        sparse_frames: list[list[DetectedTarget]], with_features: SurveyResult) -> None:
    seen = {t.id for f in sparse_frames for t in f}
    often = {i for i in seen if sum(any(t.id == i for t in f) for f in sparse_frames) >= 5}
    cards_only = _survey(sparse_frames, None)
    mapped = {t.id for t in with_features.targets}
    # The cards alone leave most of it out; with the walls' points every card seen in 5
    # frames is mapped, from nearly every frame.
    assert len({t.id for t in cards_only.targets}) < len(often) - 2
    assert often <= mapped
    assert with_features.n_registered >= 0.95 * len(sparse_frames) > 1.5 * cards_only.n_registered
    assert _disc_rms_mm(with_features) < 3.0
    assert abs(with_features.camera.fx / SURVEY_ROOM.camera.fx - 1) < 0.005
    # The cards are linked through the walls: no warning calls a part of the map disconnected.
    assert not [w for w in with_features.warnings if w.startswith("parts of the map are not seen together")]


def test_wrong_feature_matches_do_not_move_the_map(sparse_frames: list[list[DetectedTarget]],
                                                    with_features: SurveyResult) -> None:
    clean = wall_features()
    rng = np.random.default_rng(5)
    track = clean.track.copy()
    uv = clean.uv.copy()
    # A tenth of the tracks merged with another point's track seen in other frames (what
    # a wrong keyframe match does), and 2 % of all observations matched anywhere.
    n = int(track.max()) + 1
    for a in rng.choice(n, n // 10, replace=False):
        b = int(rng.integers(n))
        if b != a and not set(clean.frame[track == a].tolist()) & set(clean.frame[track == b].tolist()):
            track[track == b] = a
    thrown = rng.random(len(uv)) < 0.02
    uv[thrown] = rng.uniform([0, 0], [SURVEY_ROOM.camera.width, SURVEY_ROOM.camera.height], (int(thrown.sum()), 2))
    wrong = FeatureObservations(clean.frame, track, uv, sigma_px=clean.sigma_px)
    result = _survey(sparse_frames, wrong)
    assert {t.id for t in result.targets} == {t.id for t in with_features.targets}
    moved = max(float(np.abs(result.target(t.id).discs - t.discs).max()) for t in with_features.targets)
    # Both maps are in the survey's own frame (the seed frame's camera): compare directly.
    assert moved < 2e-3
    assert _disc_rms_mm(result) < 3.0


def test_feature_points_are_triangulated_only_from_views_wide_enough_apart(
        sparse_frames: list[list[DetectedTarget]]) -> None:
    walk, camera = wall_walk(), SURVEY_ROOM.camera
    features = wall_features()
    frames = sparse_frames
    tracks = collect_tracks(frames, np.arange(len(frames)), [])
    state = SurveyState.start(tracks, camera, SurveySettings(SURVEY_ROOM.marker_size_m), StageClock(), [], features)
    state.lens_refined = True
    for f, pose in enumerate(walk.poses[:30]):
        state.reconstruction.set_pose(f, pose)
    assert triangulate_features(state) > 100
    placed = np.isfinite(state.feature_X[:, 0])
    # Every point triangulated from the true poses lies on a wall (within noise).
    w, d, _ = SURVEY_ROOM.size
    X = state.feature_X[placed]
    off_wall = np.min(np.abs(np.c_[X[:, 0], X[:, 0] - w, X[:, 1], X[:, 1] - d]), axis=1)
    assert np.median(off_wall) < 0.01
    # A point seen only from frames under 1.5 degrees apart stays out.
    assert not placed[np.bincount(features.track[features.frame < 30], minlength=len(placed)) == 0].any()
    # Frames linked through shared points form one group.
    assert len(set(feature_groups(state)[:30].tolist())) == 1


def test_a_pose_on_points_bunched_together_is_known_to_be_weak() -> None:
    camera = SURVEY_ROOM.camera
    pose = wall_walk().poses[0]
    rng = np.random.default_rng(0)
    ahead = pose.inverse().transform(np.c_[rng.uniform(-1, 1, (40, 2)), np.full(40, 3.0)])
    bunched = pose.inverse().transform(np.c_[rng.uniform(-0.05, 0.05, (40, 2)), np.full(40, 3.0)])
    assert position_std(camera, pose, bunched, 0.1) > 10 * position_std(camera, pose, ahead, 0.1)
