"""The survey's observations: detections collected into tracks and views, their weights."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.detection import DetectedTarget
from app.core.geometry import disc_axes
from app.core.survey import SurveyError, disc_precision
from app.core.survey.state import Views
from app.core.survey.tracks import collect_tracks, is_face, subsample_frames

#: A card's discs in the printed order (0 top-left, then clockwise on the image).
SQUARE = np.array([[100.0, 100.0], [140.0, 100.0], [140.0, 140.0], [100.0, 140.0]])


def test_thin_discs_weigh_less_in_the_bundle_adjustment() -> None:
    """A card seen face-on with discs of 3 px radius, and the same card foreshortened
    to a third across: its discs' minor semi-axes are 1 px, their centres are measured
    worse, and the bundle adjustment weighs them less."""
    side = 0.6 * 3.0 / 0.125  # disc spacing for a 3 px disc radius
    face = np.array([[[0, 0], [side, 0], [side, side], [0, side]]], float) + 100.0
    thin = face.copy()
    thin[..., 0] = 100.0 + (face[..., 0] - 100.0) / 3.0
    np.testing.assert_allclose(disc_axes(face)[0], 3.0, atol=1e-9)
    np.testing.assert_allclose(disc_axes(thin)[0], [[3.0, 1.0]] * 4, atol=1e-9)
    w_face, w_thin = disc_precision(face)[0], disc_precision(thin)[0]
    assert np.allclose(w_face, w_face[0]) and np.allclose(w_thin, w_thin[0])
    assert w_thin[0] < 0.25 * w_face[0]


def test_a_face_turns_the_printed_way() -> None:
    assert is_face(SQUARE)
    assert not is_face(SQUARE[::-1])  # mirrored
    assert not is_face(SQUARE[[0, 2, 1, 3]])  # folded (a bow tie)
    assert not is_face(np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]]))  # collinear


def test_subsample_frames() -> None:
    assert subsample_frames(10, None, 1) == list(range(10))
    assert subsample_frames(10, None, 3) == [0, 3, 6, 9]
    used = subsample_frames(100, 7, 1)
    assert len(used) == 7 and used[0] == 0 and used[-1] == 99
    assert np.ptp(np.diff(used)) <= 1  # evenly
    assert subsample_frames(5, 10, 1) == list(range(5))
    with pytest.raises(SurveyError, match="max_frames"):
        subsample_frames(10, 1, 1)


def test_collect_tracks_keeps_what_can_be_a_card() -> None:
    card = SQUARE
    frames = [
        [DetectedTarget(4, card, 1.0), DetectedTarget(9, card + 60, 1.0)],
        [DetectedTarget(4, card + 1, 1.0), DetectedTarget(4, card + 80, 1.0)],  # id 4 twice: ambiguous
        [DetectedTarget(9, card[::-1] + 5, 1.0)],  # mirrored
        [DetectedTarget(9, card + 2, 1.0)],
    ]
    warnings: list[str] = []
    tracks = collect_tracks(frames, [0, 1, 2, 3], warnings)
    assert tracks.ids.tolist() == [4, 9] and tracks.n_frames == 4
    # Two views in frame 0, one in frame 3, 4 discs each, sorted by frame.
    assert tracks.frame.tolist() == [0] * 8 + [3] * 4
    assert tracks.disc.tolist() == [0, 1, 2, 3] * 3
    assert tracks.target[::4].tolist() == [0, 1, 1]
    np.testing.assert_array_equal(tracks.uv[8:], card + 2)
    assert tracks.point[8:].tolist() == [4, 5, 6, 7]
    np.testing.assert_allclose(tracks.expected_px, 1 / np.sqrt(tracks.precision))
    assert len(warnings) == 2
    assert warnings[0].startswith("2 detections of an id seen twice")
    assert warnings[1].startswith("1 detections whose discs do not form the card's square")
    views = Views.from_tracks(tracks)
    assert len(views) == 3
    assert [v.tolist() for v in views.of_frame] == [[0, 1], [], [], [2]]
    assert [v.tolist() for v in views.of_target] == [[0], [1, 2]]
    np.testing.assert_allclose(views.area, 1600.0)


def test_collect_tracks_refuses_what_cannot_be_surveyed() -> None:
    with pytest.raises(SurveyError, match="no targets"):
        collect_tracks([[], []], [0, 1], [])
    with pytest.raises(SurveyError, match="fewer than 2 frames"):
        collect_tracks([[DetectedTarget(1, SQUARE, 1.0)], []], [0, 1], [])
