"""What the survey tells people to film: per-card warnings naming each weak or unconnected
card with what to film, and the pure pan's warning."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.detection import DetectedTarget
from app.core.survey.advice import (
    ADVISED_BASELINE_DEG,
    PAN_RADIUS_M,
    MapWarning,
    TargetViews,
    WarningKind,
    lens_warning,
    map_advice,
)
from app.core.survey.bundle import bundle_adjust
from app.core.survey.cards import max_angle_deg
from app.core.survey.place import MIN_BASELINE_DEG
from app.core.survey.result import (
    MIN_VIEWS,
    SurveyResult,
    map_advice_of,
    survey_result,
    surveyed_views,
)
from app.core.survey.scale import MetricScale
from app.core.survey.state import StageClock, SurveySettings, SurveyState
from app.core.survey.tracks import collect_tracks
from app.sim.examples import RoomWalk
from app.sim.scenes import frame_truth
from tests.core.survey.conftest import SURVEY_ROOM


def _advice(state: SurveyState) -> tuple[SurveyResult, list[MapWarning]]:
    _, info = bundle_adjust(state.reconstruction, state.tracks, state.usable.repeat(4), False, (0.2, 1e-5),
                            max_iterations=0, with_covariance=True)
    surveyed = surveyed_views(state)
    n = state.tracks.n_frames
    result = survey_result(state, info, surveyed, MetricScale(1.0, 0.0), list(range(n)), n)
    centres = np.array([p.position for p in result.trajectory if p is not None])
    return result, map_advice_of(result.targets, state.tracks, state.views, surveyed, centres)


def _keep_only(state: SurveyState, t: int, keep: np.ndarray) -> None:
    """Set aside every view of target index ``t`` but ``keep``."""
    views = state.views.of_target[t]
    state.usable[views[~np.isin(views, keep)]] = False


def _narrowest_window(state: SurveyState, walk: RoomWalk, t: int, size: int) -> tuple[np.ndarray, float]:
    """The ``size`` consecutive views of target index ``t`` seen over the narrowest range of
    directions, and that range (degrees, from the truth)."""
    views = state.views.of_target[t]
    X = walk.scene.targets[int(state.tracks.ids[t])].discs.mean(axis=0)
    assert walk.scene.targets[int(state.tracks.ids[t])].id == int(state.tracks.ids[t])
    centres = np.array([walk.poses[f].position for f in state.views.frame[views]])
    spans = [max_angle_deg(centres[j : j + size], X) for j in range(len(views) - size + 1)]
    j = int(np.argmin(spans))
    return views[j : j + size], spans[j]


def test_a_good_survey_gets_no_advice(true_state: SurveyState) -> None:
    result, advice = _advice(true_state)
    assert advice == []
    assert result.warnings == []
    assert all(np.isfinite(t.distance_m) and 1.0 < t.distance_m < 5.0 for t in result.targets)


def test_a_card_seen_from_one_direction_is_named_with_what_to_film(true_state: SurveyState,
                                                                   room_walk: RoomWalk) -> None:
    t = 7
    card = int(true_state.tracks.ids[t])
    keep, span = _narrowest_window(true_state, room_walk, t, 2)
    assert span < MIN_BASELINE_DEG
    _keep_only(true_state, t, keep)
    result, advice = _advice(true_state)
    assert [(w.kind, w.target_ids) for w in advice] == [(WarningKind.FEW_VIEWS, (card,))]
    text = advice[0].message
    distance = result.target(card).distance_m
    assert text.startswith(f"card {card}: seen in 2 registered frames only (fewer than {MIN_VIEWS})")
    assert f"from {distance:.1f} m" in text and f"within {result.target(card).baseline_deg:.2f} degrees" in text
    assert f"at least {ADVISED_BASELINE_DEG:g} degrees apart" in text and "walking past it" in text
    assert result.warnings == [text]  # the job's strings are the typed warnings' messages


def test_a_card_seen_often_but_over_a_narrow_range_is_named(true_state: SurveyState, room_walk: RoomWalk) -> None:
    t = 7
    card = int(true_state.tracks.ids[t])
    keep, span = _narrowest_window(true_state, room_walk, t, MIN_VIEWS)
    assert span < MIN_BASELINE_DEG
    _keep_only(true_state, t, keep)
    _, advice = _advice(true_state)
    assert [(w.kind, w.target_ids) for w in advice] == [(WarningKind.NARROW, (card,))]
    assert "too narrow a range" in advice[0].message and "fewer than" not in advice[0].message


def test_a_disconnected_card_is_named_with_its_nearest_mapped_neighbours(true_state: SurveyState,
                                                                         room_walk: RoomWalk) -> None:
    views, t = true_state.views, 0
    for f in set(views.frame[views.of_target[t]].tolist()):
        for v in views.of_frame[f]:
            if views.target[v] != t:
                true_state.usable[v] = False
    result, advice = _advice(true_state)
    card = int(true_state.tracks.ids[t])
    apart = [w for w in advice if w.kind is WarningKind.DISCONNECTED]
    assert [w.target_ids for w in apart] == [(card,)]
    centre = {c.id: c.discs.mean(axis=0) for c in room_walk.scene.targets}
    others = sorted((c.id for c in result.targets if c.id != card),
                    key=lambda i: np.linalg.norm(centre[i] - centre[card]))
    assert f"card {card}; film it in the same shot as card {others[0]} or {others[1]}" in apart[0].message
    assert "not seen together with the rest" in apart[0].message


def test_cards_detected_but_not_surveyed_are_named_with_the_cards_beside_them(true_state: SurveyState) -> None:
    views = true_state.views
    t = 15
    true_state.usable[views.of_target[t][:-1]] = False  # one view left: not surveyed
    _, advice = _advice(true_state)
    card = int(true_state.tracks.ids[t])
    missing = [w for w in advice if w.kind is WarningKind.NOT_SURVEYED]
    assert [w.target_ids for w in missing] == [(card,)]
    beside = sorted({int(true_state.tracks.ids[k]) for f in views.frame[views.of_target[t]]
                     for k in views.target[views.of_frame[f]]} - {card})
    assert f"card {card} could not be surveyed" in missing[0].message
    assert f"seen in the same frames: {', '.join(map(str, beside))}" in missing[0].message


@pytest.fixture
def pan_state() -> SurveyState:
    """The small room filmed turning on one spot: exact detections, every frame
    registered at its true pose, every target placed at its true discs."""
    walk = SURVEY_ROOM.walk(7, 80, "pan")
    frames = [[DetectedTarget(t.id, t.discs_px, 1.0) for t in frame_truth(SURVEY_ROOM.camera, p, walk.scene)
               .visible_targets()] for p in walk.poses]
    warnings: list[str] = []
    tracks = collect_tracks(frames, list(range(len(frames))), warnings)
    settings = SurveySettings(SURVEY_ROOM.marker_size_m, intrinsics_given=True)
    state = SurveyState.start(tracks, SURVEY_ROOM.camera, settings, StageClock(), warnings)
    truth = {t.id: t.discs for t in walk.scene.targets}
    for k, target_id in enumerate(tracks.ids):
        state.reconstruction.place(k, truth[int(target_id)])
    for f, pose in enumerate(walk.poses):
        if len(state.views.of_frame[f]):
            state.reconstruction.set_pose(f, pose)
    return state


def test_a_pure_pan_gets_the_pan_warning_instead_of_per_card_narrow_ones(pan_state: SurveyState) -> None:
    result, advice = _advice(pan_state)
    assert all(t.baseline_deg < 1e-3 for t in result.targets)  # no baseline at all
    pan = [w for w in advice if w.kind is WarningKind.PURE_PAN]
    assert len(pan) == 1 and advice[0] is pan[0]
    assert set(pan[0].target_ids) == {t.id for t in result.targets}
    assert "depths come only from their printed size" in pan[0].message and "walking" in pan[0].message
    assert not [w for w in advice if w.kind is WarningKind.NARROW]


def _target(i: int, centre: tuple[float, float, float], n_views: int = 10, baseline: float = 30.0) -> TargetViews:
    return TargetViews(i, np.array(centre, float), n_views, baseline, 2.0)


def test_camera_centres_apart_are_no_pan(true_state: SurveyState) -> None:
    """Only centres (nearly all of them) within ``PAN_RADIUS_M`` of one point make a pan; one
    frame registered out of place does not hide it."""
    tracks, views = true_state.tracks, true_state.views
    surveyed = surveyed_views(true_state)
    targets = [_target(int(tracks.ids[k]), (float(k), 0.0, 0.0)) for k in surveyed.targets]
    near = np.array([[0.0, 0, 0], [0.9 * PAN_RADIUS_M, 0, 0]])
    far = np.array([[0.0, 0, 0], [2.1 * PAN_RADIUS_M, 0, 0]])
    kinds = [w.kind for w in map_advice(targets, tracks, views, surveyed.used, surveyed.targets, near, 3, 2.0)]
    assert kinds == [WarningKind.PURE_PAN]
    assert map_advice(targets, tracks, views, surveyed.used, surveyed.targets, far, 3, 2.0) == []
    stray = np.vstack([np.zeros((19, 3)), [[1.0, 0.0, 0.0]]])
    kinds = [w.kind for w in map_advice(targets, tracks, views, surveyed.used, surveyed.targets, stray, 3, 2.0)]
    assert kinds == [WarningKind.PURE_PAN]


def test_cards_nearly_all_without_baseline_are_a_pan(true_state: SurveyState) -> None:
    """Centres scattered by depths from the card size alone still make a pan when nearly
    every card was seen from one direction; a few such cards are named one by one."""
    tracks, views = true_state.tracks, true_state.views
    surveyed = surveyed_views(true_state)
    apart = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    ids = [int(tracks.ids[k]) for k in surveyed.targets]
    narrow = [_target(i, (float(i), 0.0, 0.0), baseline=0.5 if k else 30.0) for k, i in enumerate(ids)]
    advice = map_advice(narrow, tracks, views, surveyed.used, surveyed.targets, apart, 3, 2.0)
    assert [w.kind for w in advice] == [WarningKind.PURE_PAN]
    assert f"{len(ids) - 1} of the {len(ids)} cards were each seen from within 2 degrees" in advice[0].message
    few = [_target(i, (float(i), 0.0, 0.0), baseline=0.5 if k < 2 else 30.0) for k, i in enumerate(ids)]
    advice = map_advice(few, tracks, views, surveyed.used, surveyed.targets, apart, 3, 2.0)
    assert [(w.kind, w.target_ids) for w in advice] == [(WarningKind.NARROW, (i,)) for i in ids[:2]]


def test_a_poorly_determined_principal_point_is_told() -> None:
    assert lens_warning(None) is None  # intrinsics given: nothing to tell
    assert lens_warning(np.array([0.5, 0.2, 0.3, 1e-3, 1e-3])) is None
    message = lens_warning(np.array([3.0, 0.4, 1.7, 1e-3, 1e-3]))
    assert message is not None and "+/- 1.7 px" in message and "intrinsics" in message

