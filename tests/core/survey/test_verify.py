"""The survey checks its map against what could have gone wrong unseen: a lens the cards'
own shapes disagree with is refused, a card placed too uncertainly is named, and std_m
follows the error when the feature tracks' errors are correlated within a track (the
bundle adjustment's covariance counts each track once).

The feature tracks are exact images of points on the small room's walls (from the room's
geometry and the walk's true poses) with noise (`conftest.wall_features`)."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.detection import DetectedTarget
from app.core.geometry import similarity_from_points
from app.core.survey import FeatureObservations, SurveyError, SurveyResult, survey
from app.core.survey.advice import TargetViews, WarningKind, uncertainty_advice
from app.core.survey.verify import (
    MIN_LENS_FRAMES,
    UNCERTAIN_CARD_M,
    LensAgreement,
    few_frames_lens_message,
    uncertain_cards,
)

from .conftest import SURVEY_ROOM, wall_features, wall_walk


def _one_card_a_frame(frames: list[list[DetectedTarget]]) -> list[list[DetectedTarget]]:
    """Each frame with only its first card: how a room with few cards is filmed."""
    return [[f[0]] if f else [] for f in frames]


def _survey(frames: list[list[DetectedTarget]], features: FeatureObservations | None) -> SurveyResult:
    camera = SURVEY_ROOM.camera
    return survey(frames, camera.width, camera.height, SURVEY_ROOM.marker_size_m, features=features)


def _errors_m(result: SurveyResult) -> dict[int, np.ndarray]:
    """Each card's disc errors (m) after the best rigid motion onto the truth (std_m is
    relative to one rigid motion of the whole metric map)."""
    truth = {t.id: t.discs for t in wall_walk().scene.targets}
    src = np.concatenate([t.discs for t in result.targets])
    dst = np.concatenate([truth[t.id] for t in result.targets])
    rigid = similarity_from_points(src, dst, with_scale=False)
    return {t.id: np.linalg.norm(rigid.apply(t.discs) - truth[t.id], axis=1) for t in result.targets}


def test_lens_agreement() -> None:
    assert LensAgreement(824.0, 820.0).agrees
    wrong = LensAgreement(1035.0, 820.0)
    assert not wrong.agrees
    assert abs(wrong.difference - 0.262) < 0.001
    assert "26 %" in wrong.message() and "intrinsics" in wrong.message() and "film again" in wrong.message()


def test_a_lens_fitted_from_few_frames_is_warned_about_whatever_its_reported_std() -> None:
    assert few_frames_lens_message(MIN_LENS_FRAMES) is None
    message = few_frames_lens_message(12)
    assert message is not None and "only 12 registered frames" in message and "intrinsics" in message


def test_a_survey_of_a_few_frames_warns_about_its_lens(synthetic_frames) -> None:  # type: ignore[no-untyped-def]
    frames = synthetic_frames(0.05, 1)
    short = [f if k < 16 else [] for k, f in enumerate(frames)]
    result = _survey(short, None)
    assert 10 <= result.n_registered < MIN_LENS_FRAMES and result.intrinsics_std is not None
    assert any("the lens was calibrated from only" in w for w in result.warnings)
    assert not any("the lens was calibrated from only" in w for w in _survey(frames, None).warnings)


def test_an_uncertain_card_is_named_with_what_to_film() -> None:
    std = [np.full(4, 0.002), np.full(4, 3 * UNCERTAIN_CARD_M), np.full(4, 0.001)]
    uncertain = uncertain_cards([4, 7, 9], std)
    assert [card for card, _ in uncertain] == [7]
    cards = [TargetViews(i, np.array([x, 0.0, 1.0]), 20, 10.0, 2.0) for i, x in ((4, 0.0), (7, 1.0), (9, 3.0))]
    [warning] = uncertainty_advice(uncertain, cards)
    assert warning.kind is WarningKind.UNCERTAIN and warning.target_ids == (7,)
    assert "card 7" in warning.message and "+/- 3 cm" in warning.message and "card 4 or 9" in warning.message


@pytest.fixture(scope="module")
def sparse_frames(synthetic_frames) -> list[list[DetectedTarget]]:  # type: ignore[no-untyped-def]
    return _one_card_a_frame(synthetic_frames(0.05, 1))


def test_a_lens_the_cards_disagree_with_is_refused(sparse_frames: list[list[DetectedTarget]]) -> None:
    # The walls' points seen through a lens 30 % longer than the cards': the map's focal
    # length follows the thousands of points, the cards' own shapes say otherwise.
    features = wall_features(focal_px=1.3 * SURVEY_ROOM.camera.fx)
    with pytest.raises(SurveyError, match="the lens could not be calibrated reliably"):
        _survey(sparse_frames, features)


def test_std_m_covers_the_error_when_a_track_errs_as_one(sparse_frames: list[list[DetectedTarget]]) -> None:
    # Each track off by its own 0.3 px through all its views, as a tracker locked onto a
    # patch beside the point is: independent noise of 0.05 px on top.
    result = _survey(sparse_frames, wall_features(sigma_px=0.05, track_error_px=0.3))
    errors = _errors_m(result)
    ratio = np.concatenate([errors[t.id] / t.std_m for t in result.targets])
    # Honest, |error| / std_m would be sqrt(chi-square(3) / 3), median 0.89. Each track
    # counted once brings it to about 2.4 here (the part of a track's error its point
    # absorbs does not show in the residuals that set the noise level); counted as
    # independent, the tracks' views make std_m several times smaller still.
    assert 0.4 < np.median(ratio) < 3.0


def test_a_long_stretch_without_cards_never_leaves_a_card_5_cm_off_unnamed(
        sparse_frames: list[list[DetectedTarget]]) -> None:
    # No card in a third of the walk: the frames there register through the walls alone.
    frames = [[] if 25 <= k < 55 else f for k, f in enumerate(sparse_frames)]
    try:
        result = _survey(frames, wall_features(sigma_px=0.05, track_error_px=0.3))
    except SurveyError:
        return  # a refusal that says why is an answer too
    errors = _errors_m(result)
    named = {card for w in result.map_warnings for card in w.target_ids}
    for t in result.targets:
        wrong = errors[t.id].max() > 0.05
        assert not wrong or t.id in named, f"card {t.id} is {1000 * errors[t.id].max():.0f} mm off, unnamed"


def _cards_near_the_middle(frames: list[list[DetectedTarget]], radius_px: float) -> list[list[DetectedTarget]]:
    """Each frame with only the cards whose discs are all within ``radius_px`` of the
    image's centre: a room filmed with the cards always in the middle of the picture."""
    centre = np.array([SURVEY_ROOM.camera.width - 1, SURVEY_ROOM.camera.height - 1]) / 2
    return [[t for t in f if (np.linalg.norm(t.discs - centre, axis=1) < radius_px).all()] for f in frames]


def test_a_principal_point_the_footage_cannot_pin_down_is_warned_about(synthetic_frames) -> None:  # type: ignore[no-untyped-def]
    frames = synthetic_frames(0.05, 0)
    camera = SURVEY_ROOM.camera
    weak = _survey(_cards_near_the_middle(frames, 200.0), None)
    assert weak.n_registered >= MIN_LENS_FRAMES and weak.intrinsics_std is not None
    # Cards only near the middle of the picture leave the principal point loose: the
    # survey says so, by how much, and what to film ...
    warnings = [w for w in weak.warnings if "principal point is poorly determined" in w]
    assert len(warnings) == 1 and "rolled" in warnings[0], weak.warnings
    std = weak.intrinsics_std[1:3]
    error = np.abs([weak.camera.cx - camera.cx, weak.camera.cy - camera.cy])
    assert (std > 0.5).all() and (error < 3 * std).all(), (error, std)
    # ... while the same walk with the cards all over the picture pins it down.
    whole = _survey(frames, None)
    assert whole.intrinsics_std is not None and not any("principal point" in w for w in whole.warnings)
    assert np.hypot(whole.camera.cx - camera.cx, whole.camera.cy - camera.cy) < 1.0
