"""The feature tracker: frames in, one at a time, `FeatureTracks` out.

Per frame (see the package docstring for the whole design):

1. the points tracked so far are followed into the frame (KLT with the forward-backward
   check, each point starting from where its last motion predicts it), or, without
   optical flow, keypoints are detected and matched to the last frame's (ORB or SIFT,
   Lowe's ratio test);
2. the links to the last frame pass a geometric check (`matching.geometric_inliers`),
   all of them only if most agree; points that fail it, leave the image or enter an
   excluded region end their track;
3. new corners fill the image where tracks were lost, away from the live ones;
4. every ``keyframe_interval`` frames the live tracks are described and matched against
   the tracks of the earlier keyframes (`matching.KeyframeIndex`); a keyframe match
   counts when its group spans enough of the view and the optical flow from the earlier
   keyframe lands on it too; then the tracks merge, unless the two were seen in one
   frame (then they cannot be one point).

The tracker keeps each keyframe's image (as the flow reads it, one byte a pixel: 31 MB
for 1000 frames of 640x480 at the default interval) for that last check.
"""

from __future__ import annotations

from collections.abc import Iterable

import cv2
import numpy as np

from app.core.features import klt
from app.core.features.masks import allowed_mask, inside
from app.core.features.matching import (
    Describer,
    KeyframeIndex,
    geometric_inliers,
    ratio_matches,
)
from app.core.features.settings import FeatureSettings
from app.core.features.tracks import FeatureTracks, KeyframeLink
from app.core.geometry import Camera

__all__ = ["FeatureTracker", "track_features"]

#: The least part of a frame pair's links that must agree with one camera motion for any
#: to count: in a frame that follows on, nearly all do; after a cut in the video the few
#: points the flow still "follows" land anywhere, and a fundamental matrix (7 degrees of
#: freedom) fits about half of two dozen random matches within a pixel.
FRAME_AGREEMENT = 0.8
#: Features stay this far inside the image, px (the flow window's half and the lens's
#: worst corner pixels).
BORDER_PX = 8


class FeatureTracker:
    """Tracks the scene's own points through a video, frame by frame.

    Parameters
    ----------
    settings : FeatureSettings, optional
        The method and its settings (the defaults are the benchmark's choice).
    camera : Camera, optional
        The lens, when known: the geometric checks then work on lens-corrected points.
        The tracks keep the points as seen.
    """

    def __init__(self, settings: FeatureSettings | None = None, camera: Camera | None = None) -> None:
        self.settings = settings if settings is not None else FeatureSettings()
        self.camera = camera
        method = self.settings.method
        self._describer = Describer(method.descriptor) if method.descriptor is not None else None
        self._index = (KeyframeIndex(self._describer, self.settings.ratio, self.settings.loop_geometric_px,
                                     self.settings.loop_min_inliers, camera)
                       if self._describer is not None else None)
        self._n_frames = 0
        self._shape: tuple[int, ...] | None = None
        self._frames: list[np.ndarray] = []
        self._tracks: list[np.ndarray] = []
        self._uv: list[np.ndarray] = []
        self._links: list[KeyframeLink] = []
        self._keyframe_images: dict[int, np.ndarray] = {}  # each keyframe as the flow reads it
        # The live tracks: their ids, where they are now, and (without flow) their descriptors.
        self._live = np.zeros(0, np.int64)
        self._live_uv = np.zeros((0, 2))
        self._live_desc: np.ndarray | None = None
        self._velocity = np.zeros((0, 2))  # the live points' last motion, px per frame (optical flow)
        self._previous: np.ndarray | None = None  # the last frame (optical flow)
        # Every track ever started: its first and last frame, and the union-find of merged tracks.
        self._next = 0
        self._parent = np.zeros(0, np.int64)
        self._first = np.zeros(0, np.int64)
        self._last = np.zeros(0, np.int64)
        self._members: dict[int, list[int]] = {}

    @property
    def n_frames(self) -> int:
        """Frames added so far."""
        return self._n_frames

    def add(self, image: np.ndarray, exclude: np.ndarray | None = None) -> int:
        """Track the features into the next frame.

        Parameters
        ----------
        image : (h, w) ndarray of uint8
            The frame, greyscale (or BGR, converted). An empty image is a frame without
            features; a frame of another size than the last starts every track afresh.
        exclude : (h, w) array of bool, optional
            True where no feature may lie (the detected cards, `exclusion_mask`).

        Returns
        -------
        int
            The frame's index among the frames added.

        Raises
        ------
        ValueError
            If the image is not 8-bit greyscale or BGR, or ``exclude`` has another shape.
        """
        image = _greyscale(image)
        allowed = allowed_mask(image.shape, exclude, BORDER_PX) if image.size else None
        f = self._n_frames
        self._n_frames += 1
        if allowed is None:
            self._drop_live()
            self._shape = None
            return f
        if image.shape != self._shape:
            self._drop_live()
            self._shape = image.shape
        if self.settings.method.flow:
            ids, uv, desc = self._flow_step(image, allowed)
        else:
            ids, uv, desc = self._descriptor_step(image, allowed)
        self._last[ids] = f
        self._frames.append(np.full(len(ids), f, np.int64))
        self._tracks.append(ids)
        self._uv.append(uv)
        if self._index is not None and f % self.settings.keyframe_interval == 0:
            self._keyframe(f, image, ids, uv, desc)
        return f

    def tracks(self) -> FeatureTracks:
        """The tracks so far, merged tracks as one.

        Returns
        -------
        FeatureTracks
            Every observation of the frames added.
        """
        if not self._tracks:
            return FeatureTracks.empty(self._n_frames)
        raw = np.concatenate(self._tracks)
        links = tuple(KeyframeLink(link.frame, link.earlier_frame, tuple(self._roots(np.array(link.tracks)).tolist()))
                      for link in self._links)
        return FeatureTracks.from_observations(np.concatenate(self._frames), self._roots(raw),
                                               np.concatenate(self._uv), self._n_frames, links)

    # ---- one frame ------------------------------------------------------------------

    def _flow_step(self, image: np.ndarray, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray, None]:
        s = self.settings
        ids, uv = np.zeros(0, np.int64), np.zeros((0, 2))
        current = klt.flow_image(image, s.shading_px)
        if len(self._live) and self._previous is not None:
            moved, ok = klt.flow(self._previous, current, self._live_uv, s, self._live_uv + self._velocity)
            ok &= inside(allowed, moved)
            idx = np.flatnonzero(ok)
            keep = idx[geometric_inliers(self._live_uv[idx], moved[idx], s.geometric_px, self.camera,
                                         min_fraction=FRAME_AGREEMENT)]
            ids, uv, velocity = self._live[keep], moved[keep], moved[keep] - self._live_uv[keep]
        else:
            velocity = np.zeros((0, 2))
        if len(ids) < s.max_features:
            seeds = klt.seed_points(image, allowed, uv, s.max_features - len(ids), s)
            ids = np.r_[ids, self._start(len(seeds))]
            uv = np.vstack([uv, seeds])
            # A new point is expected to move as the image does.
            typical = np.median(velocity, axis=0) if len(velocity) else np.zeros(2)
            velocity = np.vstack([velocity, np.tile(typical, (len(seeds), 1))])
        self._previous = current
        self._live, self._live_uv, self._velocity = ids, uv, velocity
        return ids, uv, None

    def _descriptor_step(self, image: np.ndarray, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        assert self._describer is not None
        s = self.settings
        uv, desc = self._describer.detect(image, allowed, s.max_features)
        ids = np.full(len(uv), -1, np.int64)
        if len(self._live) and self._live_desc is not None:
            q, t = ratio_matches(desc, self._live_desc, s.ratio, self._describer.norm)
            ok = geometric_inliers(self._live_uv[t], uv[q], s.geometric_px, self.camera, min_fraction=FRAME_AGREEMENT)
            ids[q[ok]] = self._live[t[ok]]
        new = ids < 0
        ids[new] = self._start(int(new.sum()))
        self._live, self._live_uv, self._live_desc = ids, uv, desc
        return ids, uv, desc

    def _keyframe(self, f: int, image: np.ndarray, ids: np.ndarray, uv: np.ndarray, desc: np.ndarray | None) -> None:
        assert self._index is not None and self._describer is not None
        s = self.settings
        if desc is None:
            desc, rows = self._describer.describe(image, uv)
            ids, uv = ids[rows], uv[rows]
        current = self._previous if s.method.flow else klt.flow_image(image, s.shading_px)
        assert current is not None
        self._keyframe_images[f] = current
        for match in self._index.match(ids, uv, desc, self._roots):
            # A repeated pattern (a poster hung twice, one photograph in two places) matches
            # as well as a wall seen again, but only over its own patch of the view.
            earlier = self._keyframe_images[match.earlier_frame]
            hull = cv2.contourArea(cv2.convexHull(match.later_uv.astype(np.float32)))
            if hull < s.loop_min_spread * image.shape[0] * image.shape[1] or earlier.shape != current.shape:
                continue
            # The descriptors found the spot; the flow from the earlier keyframe says whether
            # it is the very point (a neighbouring corner of like look lies pixels away).
            found, ok = klt.flow(earlier, current, match.earlier_uv, s, match.later_uv)
            ok &= np.linalg.norm(found - match.later_uv, axis=1) <= s.loop_same_px
            # Only where the flow's window lies whole in both frames can it tell.
            ok &= _away_from_border(match.earlier_uv, image.shape, s.window_px)
            ok &= _away_from_border(match.later_uv, image.shape, s.window_px)
            pairs = [(a, b) for a, b in zip(match.earlier[ok].tolist(), match.later[ok].tolist(), strict=True)
                     if self._mergeable(a, b)]
            if len(pairs) < s.loop_min_confirmed:
                continue
            merged = [b for a, b in pairs if self._merge(a, b)]
            self._links.append(KeyframeLink(f, match.earlier_frame, tuple(merged)))
            self._index.forget(np.array([a for a, _ in pairs]))
        self._index.add(f, ids, uv, desc)

    def _drop_live(self) -> None:
        self._live, self._live_uv, self._live_desc, self._previous = np.zeros(0, np.int64), np.zeros((0, 2)), None, None
        self._velocity = np.zeros((0, 2))

    # ---- track bookkeeping ------------------------------------------------------------

    def _start(self, n: int) -> np.ndarray:
        """Ids for n new tracks, each its own root, first seen in the current frame."""
        ids = np.arange(self._next, self._next + n, dtype=np.int64)
        self._next += n
        if self._next > len(self._parent):
            grow = max(self._next, 2 * len(self._parent), 1024) - len(self._parent)
            self._parent = np.r_[self._parent, np.zeros(grow, np.int64)]
            self._first = np.r_[self._first, np.zeros(grow, np.int64)]
            self._last = np.r_[self._last, np.zeros(grow, np.int64)]
        self._parent[ids] = ids
        self._first[ids] = self._n_frames - 1
        return ids

    def _roots(self, ids: np.ndarray) -> np.ndarray:
        """The point each track is part of: its root in the union-find of merged tracks."""
        roots = self._parent[ids]
        while True:
            up = self._parent[roots]
            if np.array_equal(up, roots):
                return roots
            roots = up

    def _mergeable(self, a: int, b: int) -> bool:
        """Whether tracks a and b may be one point: not one already, never seen in one frame."""
        ra, rb = int(self._roots(np.array([a]))[0]), int(self._roots(np.array([b]))[0])
        if ra == rb:
            return False
        ma, mb = self._members.get(ra, [ra]), self._members.get(rb, [rb])
        fa, la = self._first[ma], self._last[ma]
        fb, lb = self._first[mb], self._last[mb]
        return not np.any((fa[:, None] <= lb[None, :]) & (fb[None, :] <= la[:, None]))

    def _merge(self, a: int, b: int) -> bool:
        """Merge the points of tracks a and b if they may be one."""
        if not self._mergeable(a, b):
            return False
        ra, rb = int(self._roots(np.array([a]))[0]), int(self._roots(np.array([b]))[0])
        self._members[rb] = self._members.get(ra, [ra]) + self._members.get(rb, [rb])
        self._members.pop(ra, None)
        self._parent[ra] = rb
        return True


def track_features(frames: Iterable[np.ndarray], exclude: Iterable[np.ndarray | None] | None = None,
                   camera: Camera | None = None, settings: FeatureSettings | None = None) -> FeatureTracks:
    """Feature tracks through a video.

    Parameters
    ----------
    frames : iterable of (h, w) ndarray of uint8
        The frames in order, greyscale.
    exclude : iterable of (h, w) array of bool or None, optional
        Per frame, True where no feature may lie (the detected cards); None: nothing
        excluded.
    camera : Camera, optional
        The lens, for the geometric checks.
    settings : FeatureSettings, optional
        The method and its settings.

    Returns
    -------
    FeatureTracks
        Every observation, one track per point.
    """
    tracker = FeatureTracker(settings, camera)
    masks = iter(exclude) if exclude is not None else None
    for image in frames:
        tracker.add(image, next(masks, None) if masks is not None else None)
    return tracker.tracks()


def _away_from_border(uv: np.ndarray, shape: tuple[int, ...], margin: float) -> np.ndarray:
    return np.all((uv >= margin) & (uv <= np.array([shape[1], shape[0]]) - 1 - margin), axis=1)


def _greyscale(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.dtype != np.uint8:
        raise ValueError(f"a frame must be 8-bit, got {a.dtype}")
    if a.ndim == 3 and a.shape[2] in (3, 4) and a.size:
        a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if a.ndim != 2 and a.size:
        raise ValueError(f"a frame must be greyscale or BGR, got shape {a.shape}")
    return np.ascontiguousarray(a) if a.ndim == 2 else a.reshape(0, 0)
