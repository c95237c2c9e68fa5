"""The result of feature tracking: every observation of the scene's own points, one track
per physical point, flat and sorted by frame as the survey's disc `Tracks` are.

A disc track's 3D point is known by construction (target and disc); a feature track's
point is whatever textured spot of a wall the track follows, so its index *is* its point
(`FeatureTracks.point`). Keyframe matches that joined tracks across the video are kept as
`KeyframeLink`, so a caller can tell which frames the features connect.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["FeatureTracks", "KeyframeLink"]


@dataclass(frozen=True)
class KeyframeLink:
    """Two keyframes whose features matched, were verified by geometry and optical flow
    and merged their tracks (a loop closure when the frames lie far apart in the video).

    A link is strong evidence, not proof: a pattern repeated in the room (a poster hung
    twice) looks the same from both places, and only the reconstruction can tell. It
    names its tracks so that the reconstruction can split one whose observations before
    and after the link do not meet in one point.

    Attributes
    ----------
    frame : int
        The later keyframe.
    earlier_frame : int
        The earlier keyframe it matched.
    tracks : tuple of int
        The merged tracks (each seen in ``earlier_frame``'s part of the video and again
        from ``frame`` on).
    """

    frame: int
    earlier_frame: int
    tracks: tuple[int, ...]

    @property
    def merged(self) -> int:
        """How many tracks the link merged."""
        return len(self.tracks)


@dataclass(eq=False)
class FeatureTracks:
    """Every feature observation, flat, sorted by frame then track.

    Attributes
    ----------
    frame : (M,) ndarray of int
        Index of each observation's frame among the frames tracked.
    track : (M,) ndarray of int
        Its track, ``0 .. n_tracks - 1``, numbered in order of first appearance; one
        track is one physical point, seen at most once per frame.
    uv : (M, 2) ndarray of float
        Where it was seen, px (the image as given: lens distortion included; centre of
        the top-left pixel at (0, 0)).
    n_frames : int
        Frames tracked, including those without observations.
    links : tuple of KeyframeLink
        The keyframe matches that merged tracks, in the order found.
    """

    frame: np.ndarray
    track: np.ndarray
    uv: np.ndarray
    n_frames: int
    links: tuple[KeyframeLink, ...] = field(default=())

    @classmethod
    def empty(cls, n_frames: int = 0) -> FeatureTracks:
        """No observations.

        Parameters
        ----------
        n_frames : int, optional
            Frames tracked.

        Returns
        -------
        FeatureTracks
            With no track.
        """
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), n_frames)

    @classmethod
    def from_observations(cls, frame: np.ndarray, track: np.ndarray, uv: np.ndarray, n_frames: int,
                          links: tuple[KeyframeLink, ...] = ()) -> FeatureTracks:
        """Observations in any order and with any track labels, sorted by frame and
        their tracks renumbered ``0 ..`` in order of first appearance.

        Parameters
        ----------
        frame : (M,) array of int
            Frame of each observation.
        track : (M,) array of int
            Any label per physical point (e.g. the tracker's raw ids after merging).
        uv : (M, 2) array
            Image points, px.
        n_frames : int
            Frames tracked.
        links : tuple of KeyframeLink, optional
            Keyframe matches that merged tracks, naming them by the same labels (tracks
            not among the observations are left out of them).

        Returns
        -------
        FeatureTracks
            The same observations in the canonical order and numbering.

        Raises
        ------
        ValueError
            If the arrays disagree in length, a frame lies outside ``0 .. n_frames - 1``
            or a track is seen twice in one frame.
        """
        frame = np.asarray(frame, np.int64).reshape(-1)
        track = np.asarray(track, np.int64).reshape(-1)
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        if not len(frame) == len(track) == len(uv):
            raise ValueError("frame, track and uv must have one row per observation")
        if len(frame) and (frame.min() < 0 or frame.max() >= n_frames):
            raise ValueError(f"frames must lie in 0 .. {n_frames - 1}")
        order = np.lexsort((track, frame))
        frame, track, uv = frame[order], track[order], uv[order]
        if np.any((np.diff(frame) == 0) & (np.diff(track) == 0)):
            raise ValueError("a track is seen twice in one frame")
        # Number tracks by first appearance: the first row of each label in frame order.
        labels, first = np.unique(track, return_index=True)
        rank = np.empty(len(labels), np.int64)
        rank[np.argsort(first, kind="stable")] = np.arange(len(labels))
        renumbered = rank[np.searchsorted(labels, track)]
        order = np.lexsort((renumbered, frame))
        return cls(frame[order], renumbered[order], uv[order], int(n_frames),
                   tuple(_relabelled(link, labels, rank) for link in links))

    def __len__(self) -> int:
        return len(self.frame)

    @property
    def n_tracks(self) -> int:
        """The number of tracks (physical points)."""
        return int(self.track.max()) + 1 if len(self.track) else 0

    @property
    def point(self) -> np.ndarray:
        """(M,) index of each observation's 3D point: the track itself (the disc tracks'
        ``Tracks.point`` is target and disc)."""
        return self.track

    def lengths(self) -> np.ndarray:
        """How many frames each track is seen in.

        Returns
        -------
        (n_tracks,) ndarray of int
            Observations per track.
        """
        return np.bincount(self.track, minlength=self.n_tracks)

    def per_frame(self) -> np.ndarray:
        """How many tracks each frame sees.

        Returns
        -------
        (n_frames,) ndarray of int
            Observations per frame.
        """
        return np.bincount(self.frame, minlength=self.n_frames)

    def of_frame(self, f: int) -> np.ndarray:
        """The observations of one frame.

        Parameters
        ----------
        f : int
            The frame's index.

        Returns
        -------
        ndarray of int
            Indices of its observations (rows of `frame`, `track`, `uv`).
        """
        lo, hi = np.searchsorted(self.frame, [f, f + 1])
        return np.arange(lo, hi)

    def of_track(self, t: int) -> np.ndarray:
        """The observations of one track, in frame order.

        Parameters
        ----------
        t : int
            The track.

        Returns
        -------
        ndarray of int
            Indices of its observations.
        """
        return np.flatnonzero(self.track == t)

    def select(self, keep: np.ndarray) -> FeatureTracks:
        """Some of the tracks, renumbered in order of first appearance.

        Parameters
        ----------
        keep : (n_tracks,) array of bool
            Which tracks to keep.

        Returns
        -------
        FeatureTracks
            Their observations; the frames stay as they are, the links name the kept
            tracks only.
        """
        keep = np.asarray(keep, bool)
        if len(keep) != self.n_tracks:
            raise ValueError(f"keep must have one entry per track ({self.n_tracks})")
        rows = keep[self.track] if len(self.track) else np.zeros(0, bool)
        return FeatureTracks.from_observations(self.frame[rows], self.track[rows], self.uv[rows], self.n_frames,
                                               self.links)

    def seen_in(self, k: int) -> FeatureTracks:
        """The tracks seen in at least ``k`` frames (the ones that can be triangulated
        from ``k`` views).

        Parameters
        ----------
        k : int
            The fewest frames a track must be seen in.

        Returns
        -------
        FeatureTracks
            Those tracks, renumbered.
        """
        return self.select(self.lengths() >= k)


def _relabelled(link: KeyframeLink, labels: np.ndarray, rank: np.ndarray) -> KeyframeLink:
    """A link with its tracks' labels turned into the new numbers (labels not in `labels` dropped)."""
    tracks = np.asarray(link.tracks, np.int64)
    at = np.clip(np.searchsorted(labels, tracks), 0, max(len(labels) - 1, 0))
    known = (at < len(labels)) & (labels[at] == tracks) if len(labels) else np.zeros(len(tracks), bool)
    return KeyframeLink(link.frame, link.earlier_frame, tuple(sorted(rank[at[known]].tolist())))
