"""The feature tracker end to end on videos of known motion: tracks follow the motion,
wrong links and excluded regions are kept out, a wall seen again closes the loop, and
frames with nothing to track give nothing."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.features import (
    FeatureSettings,
    FeatureTracker,
    FeatureTracks,
    Method,
    track_features,
)
from tests.core.features.conftest import film, texture, transfer, view


def _errors(tracks: FeatureTracks, views: list[np.ndarray]) -> np.ndarray:
    """Each observation's distance (px) from where its track's first observation's point lies."""
    errors = []
    for t in range(tracks.n_tracks):
        rows = tracks.of_track(t)
        first = rows[0]
        for r in rows[1:]:
            truth = transfer(views, int(tracks.frame[first]), int(tracks.frame[r]), tracks.uv[first][None])[0]
            errors.append(np.linalg.norm(truth - tracks.uv[r]))
    return np.array(errors)


def _link_errors(tracks: FeatureTracks, views: list[np.ndarray]) -> np.ndarray:
    """Each link's distance (px) from the truth: a track's observation against where its
    previous observation's point lies."""
    order = np.lexsort((tracks.frame, tracks.track))
    f, t, uv = tracks.frame[order], tracks.track[order], tracks.uv[order]
    link = np.flatnonzero(t[1:] == t[:-1])
    return np.array([np.linalg.norm(transfer(views, int(f[i]), int(f[i + 1]), uv[i][None])[0] - uv[i + 1])
                     for i in link])


def test_klt_tracks_follow_the_known_motion(gliding: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    views, frames = gliding
    tracks = track_features(frames, settings=FeatureSettings(method=Method.KLT))
    assert tracks.n_frames == 20
    assert tracks.per_frame().min() >= 250
    assert np.median(tracks.lengths()) >= 10
    # Each link lands within a few hundredths of a pixel of where the homography puts it
    # (points near the border, where the shading's box is cut, a little farther) ...
    links = _link_errors(tracks, views)
    assert np.median(links) < 0.03 and np.percentile(links, 95) < 0.1 and links.max() < 1.0
    # ... and a whole track, its links' errors added up over up to 19 frames of turning
    # and zooming, stays within a fraction of a pixel of its point.
    err = _errors(tracks, views)
    assert np.median(err) < 0.2 and np.percentile(err, 95) < 0.6


def test_klt_on_the_frames_as_they_are_is_more_precise_still(
        gliding: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    # Without the shading removed (no exposure changes here to remove) the border points
    # are as good as the others.
    views, frames = gliding
    tracks = track_features(frames, settings=FeatureSettings(method=Method.KLT, shading_px=None))
    links = _link_errors(tracks, views)
    assert np.percentile(links, 95) < 0.05 and links.max() < 0.5
    err = _errors(tracks, views)
    assert np.median(err) < 0.15 and np.percentile(err, 95) < 0.45


@pytest.mark.parametrize("method", [Method.ORB, Method.SIFT])
def test_descriptor_tracks_follow_the_known_motion(gliding: tuple[list[np.ndarray], list[np.ndarray]],
                                                   method: Method) -> None:
    views, frames = gliding
    tracks = track_features(frames, settings=FeatureSettings(method=method))
    err = _errors(tracks, views)
    assert len(err) > 1000
    assert np.median(err) < 1.0 and np.mean(err > 3.0) < 0.02


def test_a_patch_that_changes_in_one_frame_ends_its_tracks(plane: np.ndarray) -> None:
    views = [view(300 + 3.0 * k, 200 + 2.0 * k, k) for k in range(12)]
    frames = film(plane, views)
    # Something passes in front of a part of frame 6 only.
    frames[6][150:300, 200:380] = texture(9, 480, 640)[150:300, 200:380]
    tracks = track_features(frames, settings=FeatureSettings(method=Method.KLT))
    in_six = tracks.of_frame(6)
    uv = tracks.uv[in_six]
    inside = (uv[:, 0] > 200 + 12) & (uv[:, 0] < 380 - 12) & (uv[:, 1] > 150 + 12) & (uv[:, 1] < 300 - 12)
    # The covered points are not seen in frame 6 (new corners there would be of the
    # cover, and a cover's corner seen once makes no link).
    covered_tracks = set(tracks.track[in_six][inside].tolist())
    assert all(len(tracks.of_track(t)) == 1 for t in covered_tracks)
    # And no track of the wall jumps across the cover: every link lands where it should.
    order = np.lexsort((tracks.frame, tracks.track))
    f, t, p = tracks.frame[order], tracks.track[order], tracks.uv[order]
    link = np.flatnonzero(t[1:] == t[:-1])
    truth = np.array([transfer(views, int(f[i]), int(f[i + 1]), p[i][None])[0] for i in link])
    assert np.max(np.linalg.norm(truth - p[link + 1], axis=1)) < 1.0


def test_excluded_regions_get_no_features(gliding: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    _, frames = gliding
    exclude = []
    for k in range(len(frames)):
        mask = np.zeros((480, 640), bool)
        mask[100 + 3 * k : 260 + 3 * k, 150:330] = True  # a card's region, moving down the frames
        exclude.append(mask)
    tracks = track_features(frames, exclude, settings=FeatureSettings(method=Method.KLT))
    assert tracks.per_frame().min() >= 200
    for k in range(len(frames)):
        xy = np.round(tracks.uv[tracks.of_frame(k)]).astype(int)
        assert not exclude[k][xy[:, 1], xy[:, 0]].any()


@pytest.mark.parametrize("method", [Method.KLT_ORB, Method.KLT_SIFT])
def test_returning_to_a_wall_closes_the_loop(plane: np.ndarray, method: Method) -> None:
    # Frames 0-11 film one part of the plane, 12-23 another far from it, 24-35 the first
    # part again: the same points must carry their first visit's tracks.
    views = ([view(100 + 4.0 * k, 150 + 2.0 * k, 0) for k in range(12)]
             + [view(1500 + 4.0 * k, 150 + 2.0 * k, 0) for k in range(12)]
             + [view(112 + 4.0 * k, 160 + 2.0 * k, 0) for k in range(12)])
    frames = film(plane, views)
    tracks = track_features(frames, settings=FeatureSettings(method=method, keyframe_interval=6))
    first = set(tracks.track[tracks.frame < 12].tolist())
    middle = set(tracks.track[(tracks.frame >= 12) & (tracks.frame < 24)].tolist())
    last = set(tracks.track[tracks.frame >= 24].tolist())
    closed = first & last
    assert len(closed) >= 20
    assert not first & middle and not middle & last
    loops = [link for link in tracks.links if link.earlier_frame < 12 and link.frame >= 24]
    assert loops and all(set(link.tracks) <= closed for link in loops)
    # Each closed track's point: its observations of the return agree with its first visit
    # (within the two visits' drift and the matched corners' own distance, < 1 px).
    for t in closed:
        rows = tracks.of_track(t)
        a = rows[tracks.frame[rows] < 12][-1]
        b = rows[tracks.frame[rows] >= 24][0]
        truth = transfer(views, int(tracks.frame[a]), int(tracks.frame[b]), tracks.uv[a][None])[0]
        assert np.linalg.norm(truth - tracks.uv[b]) < 2.0


def test_without_keyframe_matching_the_return_starts_new_tracks(plane: np.ndarray) -> None:
    views = [view(100 + 4.0 * k, 150, 0) for k in range(6)] + [view(1500, 150, 0)] + [view(100, 150, 0)]
    tracks = track_features(film(plane, views), settings=FeatureSettings(method=Method.KLT))
    assert not set(tracks.track[tracks.frame < 6].tolist()) & set(tracks.track[tracks.frame == 7].tolist())
    assert tracks.links == ()


@pytest.mark.parametrize("method", list(Method))
def test_blank_and_empty_frames_give_no_tracks_and_no_error(method: Method) -> None:
    rng = np.random.default_rng(0)
    frames = [np.zeros((480, 640), np.uint8), np.full((480, 640), 180, np.uint8),
              np.clip(np.rint(120 + rng.normal(0, 2.0, (480, 640))), 0, 255).astype(np.uint8),
              np.zeros((0, 0), np.uint8), np.full((240, 320, 3), 90, np.uint8)]
    tracker = FeatureTracker(FeatureSettings(method=method))
    assert [tracker.add(f) for f in frames] == [0, 1, 2, 3, 4]
    tracks = tracker.tracks()
    assert tracks.n_frames == 5 and tracks.n_tracks == 0 and len(tracks) == 0


def test_a_blank_frame_breaks_the_tracks_and_tracking_goes_on(
        gliding: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    _, frames = gliding
    video = frames[:5] + [np.zeros((480, 640), np.uint8)] + frames[5:10]
    tracks = track_features(video, settings=FeatureSettings(method=Method.KLT))
    assert tracks.per_frame()[5] == 0 and tracks.per_frame()[6:].min() >= 250
    assert not set(tracks.track[tracks.frame < 5].tolist()) & set(tracks.track[tracks.frame > 5].tolist())


def test_tracking_is_deterministic(gliding: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    _, frames = gliding
    a = track_features(frames[:12], settings=FeatureSettings(keyframe_interval=4))
    b = track_features(frames[:12], settings=FeatureSettings(keyframe_interval=4))
    assert np.array_equal(a.frame, b.frame) and np.array_equal(a.track, b.track) and np.array_equal(a.uv, b.uv)


def test_bad_input_is_refused() -> None:
    tracker = FeatureTracker()
    with pytest.raises(ValueError, match="8-bit"):
        tracker.add(np.zeros((48, 64), np.float32))
    with pytest.raises(ValueError, match="shape"):
        tracker.add(np.zeros((48, 64), np.uint8), np.zeros((10, 10), bool))
    with pytest.raises(ValueError):
        FeatureSettings(loop_min_inliers=5)
