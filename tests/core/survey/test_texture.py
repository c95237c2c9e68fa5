"""Walls too plain to track: the survey's feature tracks find too little texture, and
the survey says that its map rests on the cards alone."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.features import FeatureTracker, exclusion_mask
from app.core.survey import FeatureObservations, WarningKind
from app.core.survey.features import MIN_FEATURE_INLIERS, texture_warning, textured_frames
from app.sim import WALKS


def _observations(frames: list[int], tracks: list[int]) -> FeatureObservations:
    return FeatureObservations(np.asarray(frames), np.asarray(tracks), np.zeros((len(frames), 2)))


def test_a_frame_is_textured_when_it_sees_enough_points_followed_through_several_frames() -> None:
    n = MIN_FEATURE_INLIERS
    # Frames 0-2 see the same n points (tracks of 3 frames); frame 3 sees n points seen only there.
    frames = [f for f in range(3) for _ in range(n)] + [3] * n
    tracks = [t for _ in range(3) for t in range(n)] + list(range(n, 2 * n))
    np.testing.assert_array_equal(textured_frames(_observations(frames, tracks), 5), [True, True, True, False, False])


def test_the_warning_comes_when_few_frames_are_textured() -> None:
    n = MIN_FEATURE_INLIERS
    frames = [f for f in range(3) for _ in range(n)]
    tracks = [t for _ in range(3) for t in range(n)]
    assert texture_warning(_observations(frames, tracks), 10) is None  # 3 of 10 frames
    warning = texture_warning(_observations(frames, tracks), 40)  # 3 of 40
    assert warning is not None and warning.kind is WarningKind.PLAIN_WALLS and warning.target_ids == ()
    assert "3 of the 40 frames" in warning.message
    for phrase in ("too little texture", "cards alone", "2 or more cards", "add texture"):
        assert phrase in warning.message
    assert texture_warning(FeatureObservations.empty(), 40) is not None
    assert texture_warning(FeatureObservations.empty(), 2) is None  # too short to tell


def _tracked(walk, seed: int, n_frames: int) -> FeatureObservations:  # type: ignore[no-untyped-def]
    """The feature tracks of a rendered walk, as the survey job makes them (cards left out
    by their true discs)."""
    room = walk.walk(seed, n_frames)
    tracker = FeatureTracker()
    for image, truth in room.frames(walk.room.camera):
        discs = np.array([t.discs_px for t in truth.targets if t.visible]).reshape(-1, 4, 2)
        tracker.add(image, exclusion_mask(image.shape[:2], discs))
    return FeatureObservations.from_tracks(tracker.tracks())


@pytest.mark.parametrize(("walk", "warned"), [(WALKS["plain"], True), (WALKS["sparse"], False)], ids=["plain", "photo"])
def test_plain_painted_walls_are_warned_about_and_photo_walls_are_not(walk, warned: bool) -> None:  # type: ignore[no-untyped-def]
    n_frames = 60
    warning = texture_warning(_tracked(walk, 0, n_frames), n_frames)
    assert (warning is not None) is warned, warning
