"""`FeatureTracks`: observations sorted by frame, tracks numbered by first appearance, and
the selections a reconstruction makes of them."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.features import FeatureTracks, KeyframeLink


def _tracks() -> FeatureTracks:
    # Labels 7, 3 and 5 as a tracker might leave them; 7 is seen first, then 3, then 5.
    frame = np.array([2, 0, 1, 1, 2, 3, 0])
    track = np.array([7, 7, 7, 3, 3, 3, 5])
    uv = np.arange(14, dtype=float).reshape(7, 2)
    return FeatureTracks.from_observations(frame, track, uv, n_frames=5)


def test_observations_are_sorted_by_frame_and_tracks_numbered_by_first_appearance() -> None:
    t = _tracks()
    assert t.frame.tolist() == [0, 0, 1, 1, 2, 2, 3]
    # Frame 0 sees labels 5 and 7 (ties go by label): 5 -> 0, 7 -> 1; then 3 -> 2.
    label_of_row = {0.0: 7, 2.0: 7, 4.0: 7, 6.0: 3, 8.0: 3, 10.0: 3, 12.0: 5}
    renumbered = {5: 0, 7: 1, 3: 2}
    assert all(t.track[i] == renumbered[label_of_row[t.uv[i, 0]]] for i in range(len(t)))
    assert t.n_tracks == 3
    assert t.lengths().tolist() == [1, 3, 3]
    assert t.per_frame().tolist() == [2, 2, 2, 1, 0]
    assert np.array_equal(t.point, t.track)


def test_of_frame_and_of_track_index_the_observations() -> None:
    t = _tracks()
    assert t.frame[t.of_frame(1)].tolist() == [1, 1]
    assert len(t.of_frame(4)) == 0
    for k in range(t.n_tracks):
        rows = t.of_track(k)
        assert np.all(t.track[rows] == k) and np.all(np.diff(t.frame[rows]) > 0)


def test_seen_in_keeps_the_tracks_seen_often_enough_renumbered() -> None:
    t = _tracks()
    long = t.seen_in(3)
    assert long.n_tracks == 2 and len(long) == 6 and long.n_frames == 5
    assert sorted(long.lengths().tolist()) == [3, 3]
    assert t.seen_in(4).n_tracks == 0 and len(t.seen_in(4)) == 0


def test_a_track_seen_twice_in_one_frame_is_refused() -> None:
    with pytest.raises(ValueError, match="twice"):
        FeatureTracks.from_observations(np.array([0, 0]), np.array([1, 1]), np.zeros((2, 2)), 1)
    with pytest.raises(ValueError, match="frames"):
        FeatureTracks.from_observations(np.array([3]), np.array([1]), np.zeros((1, 2)), 2)


def test_empty_tracks() -> None:
    t = FeatureTracks.empty(4)
    assert t.n_tracks == 0 and len(t) == 0 and t.per_frame().tolist() == [0, 0, 0, 0]
    assert t.seen_in(2).n_tracks == 0


def test_links_name_the_tracks_in_the_new_numbering() -> None:
    frame = np.array([0, 1, 5, 6, 0, 6])
    track = np.array([40, 40, 40, 40, 9, 9])  # 40 merged across the gap; 9 as well
    link = KeyframeLink(frame=5, earlier_frame=0, tracks=(40, 9, 77))  # 77: no such track
    t = FeatureTracks.from_observations(frame, track, np.zeros((6, 2)), 7, (link,))
    assert t.links[0].tracks == (0, 1) and t.links[0].merged == 2
    # Label 9 comes first in frame 0 (ties go by label), so it is track 0; keep only track 1 (label 40).
    kept = t.select(np.array([False, True]))
    assert kept.n_tracks == 1 and kept.links[0].tracks == (0,) and kept.links[0].frame == 5
