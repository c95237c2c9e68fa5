"""Descriptor matching with geometric verification, and the keyframe index that closes
loops.

Every link between two frames passes a geometric check (`geometric_inliers`): a
homography or a fundamental matrix fitted by RANSAC to the matches, on lens-corrected
pixels when a camera is given; a match that the camera's motion does not explain within
the tolerance is dropped.

The keyframe index holds one descriptor per track: the one of the latest keyframe the
track was seen in. A new keyframe's tracks are matched against the tracks not seen in
it (Lowe's ratio test between distinct tracks), the matches are grouped by an earlier
keyframe in which the matched tracks were seen, and each group is verified by its own
geometric check (the tracker then confirms each match by optical flow, `tracker`).
Returning to a wall thus joins the tracks of its first visit, however long ago, and a
track lost for a few frames (blur, a passing occlusion) is joined to its own
continuation.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from app.core.features.settings import Descriptor
from app.core.geometry import Camera

__all__ = ["Describer", "KeyframeIndex", "KeyframeMatch", "geometric_inliers", "ratio_matches"]

#: Fewest matches for a fundamental matrix by RANSAC; below, a homography.
MIN_FUNDAMENTAL = 15
#: Fewest matches checked by a homography (it fits four exactly, so four prove nothing).
MIN_HOMOGRAPHY = 8
#: A homography that explains this share of what a fundamental matrix explains decides.
PLANAR_SHARE = 0.95
#: Fewest agreeing matches for any of them to count, by default.
MIN_AGREEING = 8
#: The least part of a keyframe pair's descriptor matches that must agree with one camera
#: motion (random matches agree by chance with a fundamental matrix fitted to them).
LOOP_AGREEMENT = 0.5
# RANSAC's confidence and its most iterations.
_CONFIDENCE = 0.999
_MAX_ITERS = 2000
# ORB descriptors are taken at this patch size at the image's own scale.
_ORB_PATCH = 31
# The size (px) given to a tracked point's SIFT keypoint: its descriptor's 4 x 4 cells are
# then 1.5 times that wide, 48 px across in all (the ORB patch: 31 px).
_SIFT_SIZE = 8.0


def geometric_inliers(uv_a: np.ndarray, uv_b: np.ndarray, threshold_px: float, camera: Camera | None = None,
                      min_agreeing: int = MIN_AGREEING, min_fraction: float = 0.0) -> np.ndarray:
    """Which matches between two frames agree with one camera motion.

    From 15 matches up, a fundamental matrix and a homography are both fitted (RANSAC):
    when the homography explains nearly as many matches as the fundamental matrix (a
    single wall in view, a camera that turns more than it moves) its stricter two-sided
    test decides, else the fundamental matrix's distance from the epipolar line (a wrong
    match that happens to lie along its epipolar line is then let through). From 8 to 14
    matches, a homography alone; fewer cannot be checked (four random matches fit a
    homography exactly) and are all refused, as are all when too few or too small a part
    of them agree (after a cut in the video, the few points the flow still "follows"
    agree with nothing).

    Parameters
    ----------
    uv_a, uv_b : (N, 2) ndarray
        The matched points in the two frames, px.
    threshold_px : float
        How far from its epipolar line (or from the homography's transfer) a match may
        lie, px.
    camera : Camera, optional
        The lens, to correct its distortion first (epipolar lines are straight only in
        an undistorted image).
    min_agreeing : int, optional
        Fewest agreeing matches for any to count.
    min_fraction : float, optional
        Least fraction of the matches that must agree for any to count.

    Returns
    -------
    (N,) ndarray of bool
        The matches that agree.
    """
    n = len(uv_a)
    none = np.zeros(n, bool)
    if n < max(MIN_HOMOGRAPHY, min_agreeing):
        return none
    if camera is not None and camera.has_distortion:
        uv_a, uv_b = camera.undistort_pixels(uv_a), camera.undistort_pixels(uv_b)
    a, b = uv_a.astype(np.float64), uv_b.astype(np.float64)
    _, h_mask = cv2.findHomography(a, b, cv2.RANSAC, threshold_px, maxIters=_MAX_ITERS, confidence=_CONFIDENCE)
    ok = none if h_mask is None or h_mask.size != n else h_mask.ravel() != 0
    if n >= MIN_FUNDAMENTAL:
        try:
            _, f_mask = cv2.findFundamentalMat(a, b, cv2.USAC_MAGSAC, threshold_px, _CONFIDENCE, _MAX_ITERS)
        except cv2.error:
            # MAGSAC++ asserts on some degenerate sets (repeated points); plain RANSAC copes.
            _, f_mask = cv2.findFundamentalMat(a, b, cv2.FM_RANSAC, threshold_px, _CONFIDENCE, _MAX_ITERS)
        if f_mask is not None and f_mask.size == n and ok.sum() < PLANAR_SHARE * np.count_nonzero(f_mask):
            ok = f_mask.ravel() != 0
    if ok.sum() < min_agreeing or ok.sum() < min_fraction * n:
        return none
    return ok


def ratio_matches(query: np.ndarray, train: np.ndarray, ratio: float, norm: int,
                  train_groups: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-neighbour descriptor matches that pass Lowe's ratio test, each train row
    used at most once (its closest query).

    Parameters
    ----------
    query, train : ndarray
        Descriptors, one per row (uint8 for ORB, float32 for SIFT).
    ratio : float
        The best distance must be below ``ratio`` times the second best.
    norm : int
        OpenCV's norm (``cv2.NORM_HAMMING`` or ``cv2.NORM_L2``).
    train_groups : (len(train),) ndarray of int, optional
        Rows of one group are one point: the second best is the best of another group.

    Returns
    -------
    query_rows, train_rows : ndarray of int
        The matched pairs.
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if len(query) == 0 or len(train) < 2:
        return empty
    k = 2 if train_groups is None else min(4, len(train))
    knn = cv2.BFMatcher(norm).knnMatch(query, train, k=k)
    q_rows, t_rows, dist = [], [], []
    for ms in knn:
        if len(ms) < 2:
            continue
        best = ms[0]
        second = ms[1] if train_groups is None else next(
            (m for m in ms[1:] if train_groups[m.trainIdx] != train_groups[best.trainIdx]), None)
        if second is not None and best.distance >= ratio * second.distance:
            continue
        q_rows.append(best.queryIdx)
        t_rows.append(best.trainIdx)
        dist.append(best.distance)
    if not q_rows:
        return empty
    q, t, d = np.array(q_rows), np.array(t_rows), np.array(dist)
    order = np.lexsort((d, t))
    first = np.r_[True, np.diff(t[order]) != 0]
    keep = np.sort(order[first])
    return q[keep], t[keep]


@dataclass(eq=False)
class Describer:
    """OpenCV's ORB or SIFT: descriptors of given points, or keypoints detected and described.

    Attributes
    ----------
    descriptor : Descriptor
        Which descriptor.
    """

    descriptor: Descriptor
    _extractor: cv2.Feature2D = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.descriptor is Descriptor.ORB:
            self._extractor = cv2.ORB_create(edgeThreshold=_ORB_PATCH, patchSize=_ORB_PATCH)
        else:
            self._extractor = cv2.SIFT_create()

    @property
    def norm(self) -> int:
        """The distance between two descriptors (OpenCV's norm type)."""
        return cv2.NORM_HAMMING if self.descriptor is Descriptor.ORB else cv2.NORM_L2

    def describe(self, image: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Descriptors of given points at the image's own scale.

        Parameters
        ----------
        image : (h, w) ndarray of uint8
            The frame.
        uv : (N, 2) ndarray
            The points, px.

        Returns
        -------
        descriptors : (K, D) ndarray
            One row per point described.
        rows : (K,) ndarray of int
            Which of the points they describe (points too near the border have none).
        """
        size = float(_ORB_PATCH if self.descriptor is Descriptor.ORB else _SIFT_SIZE)
        keypoints = [cv2.KeyPoint(float(x), float(y), size, -1.0, 0.0, 0, i) for i, (x, y) in enumerate(uv)]
        if not keypoints:
            return self._no_descriptors(), np.zeros(0, np.int64)
        kept, desc = self._extractor.compute(image, keypoints)
        if desc is None or not kept:
            return self._no_descriptors(), np.zeros(0, np.int64)
        return desc, np.array([k.class_id for k in kept], np.int64)

    def detect(self, image: np.ndarray, allowed: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints detected where features may lie, and their descriptors.

        Parameters
        ----------
        image : (h, w) ndarray of uint8
            The frame.
        allowed : (h, w) ndarray of uint8
            Non-zero where a feature may lie.
        count : int
            Most keypoints (the strongest).

        Returns
        -------
        uv : (K, 2) ndarray
            The keypoints, px.
        descriptors : (K, D) ndarray
            Their descriptors.
        """
        if self.descriptor is Descriptor.ORB:
            self._extractor.setMaxFeatures(int(count))
        keypoints, desc = self._extractor.detectAndCompute(image, allowed)
        if desc is None or not keypoints:
            return np.zeros((0, 2)), self._no_descriptors()
        if len(keypoints) > count:  # SIFT keeps every keypoint of its last octave's cut-off
            best = np.argsort([-k.response for k in keypoints], kind="stable")[:count]
            keypoints, desc = [keypoints[i] for i in best], desc[best]
        return np.array([k.pt for k in keypoints], np.float64), desc

    def _no_descriptors(self) -> np.ndarray:
        return np.zeros((0, 32), np.uint8) if self.descriptor is Descriptor.ORB else np.zeros((0, 128), np.float32)


@dataclass(frozen=True)
class KeyframeMatch:
    """Tracks of a new keyframe verified to be tracks seen in an earlier one.

    Attributes
    ----------
    earlier_frame : int
        The earlier keyframe.
    earlier : (K,) ndarray of int
        The earlier tracks (the tracker's ids).
    later : (K,) ndarray of int
        The new keyframe's tracks, one per earlier track.
    earlier_uv, later_uv : (K, 2) ndarray
        Where they were seen in the earlier keyframe and in the new one, px.
    """

    earlier_frame: int
    earlier: np.ndarray
    later: np.ndarray
    earlier_uv: np.ndarray
    later_uv: np.ndarray


class KeyframeIndex:
    """The descriptors of every track at its latest keyframe, and where each track was
    seen in every keyframe (see the module docstring).

    Parameters
    ----------
    describer : Describer
        Whose descriptors are stored.
    ratio : float
        Lowe's ratio test.
    threshold_px : float
        The geometric tolerance of a keyframe match, px.
    min_inliers : int
        Fewest verified matches that join two keyframes.
    camera : Camera, optional
        The lens, for the geometric check.
    """

    def __init__(self, describer: Describer, ratio: float, threshold_px: float, min_inliers: int,
                 camera: Camera | None = None) -> None:
        self.describer = describer
        self.ratio = ratio
        self.threshold_px = threshold_px
        self.min_inliers = min_inliers
        self.camera = camera
        self._desc: np.ndarray | None = None  # (capacity, D)
        self._track = np.zeros(0, np.int64)  # (capacity,) the track of each row
        self._active = np.zeros(0, bool)  # rows still matched against (one per track)
        self._n = 0
        self._row_of: dict[int, int] = {}
        self._keyframes: list[tuple[int, np.ndarray, np.ndarray]] = []  # (frame, sorted tracks, their uv)

    def __len__(self) -> int:
        return int(self._active[: self._n].sum())

    def add(self, frame: int, tracks: np.ndarray, uv: np.ndarray, descriptors: np.ndarray) -> None:
        """Store a keyframe: its tracks' descriptors replace their older ones.

        Parameters
        ----------
        frame : int
            The keyframe's index.
        tracks : (K,) ndarray of int
            The tracks described in it.
        uv : (K, 2) ndarray
            Where they were seen, px.
        descriptors : (K, D) ndarray
            Their descriptors.
        """
        order = np.argsort(tracks, kind="stable")
        self._keyframes.append((frame, tracks[order].copy(), uv[order].copy()))
        if len(tracks) == 0:
            return
        self._grow(len(tracks), descriptors)
        assert self._desc is not None
        for track, desc in zip(tracks.tolist(), descriptors, strict=True):
            row = self._row_of.get(track)
            if row is None:
                row = self._n
                self._n += 1
                self._row_of[track] = row
                self._track[row] = track
            self._desc[row] = desc
            self._active[row] = True

    def forget(self, tracks: np.ndarray) -> None:
        """Stop matching against some tracks (merged into others, which carry on).

        Parameters
        ----------
        tracks : ndarray of int
            The tracks.
        """
        for track in np.asarray(tracks).tolist():
            row = self._row_of.get(track)
            if row is not None:
                self._active[row] = False

    def match(self, tracks: np.ndarray, uv: np.ndarray, descriptors: np.ndarray,
              roots: Callable[[np.ndarray], np.ndarray]) -> list[KeyframeMatch]:
        """The earlier tracks that a new keyframe's tracks are, verified by geometry.

        Parameters
        ----------
        tracks : (K,) ndarray of int
            The new keyframe's tracks.
        uv : (K, 2) ndarray
            Where they are, px.
        descriptors : (K, D) ndarray
            Their descriptors.
        roots : callable
            Maps tracks to the point each is part of (tracks already merged share one):
            tracks of a point seen in the new keyframe are not matched again.

        Returns
        -------
        list of KeyframeMatch
            One per earlier keyframe whose matches passed, best supported first.
        """
        if self._desc is None or len(tracks) < self.min_inliers:
            return []
        rows = np.flatnonzero(self._active[: self._n])
        rows = rows[~np.isin(roots(self._track[rows]), roots(tracks))]
        if len(rows) < self.min_inliers:
            return []
        q, t = ratio_matches(descriptors, self._desc[rows], self.ratio, self.describer.norm,
                             train_groups=roots(self._track[rows]))
        earlier, later, later_uv = self._track[rows[t]], tracks[q], uv[q]
        found: list[KeyframeMatch] = []
        pool = np.ones(len(earlier), bool)
        while pool.sum() >= self.min_inliers:
            # The earlier keyframe that saw most of the matched tracks still unverified.
            seen = [np.isin(earlier, kf_tracks) & pool for _, kf_tracks, _ in self._keyframes]
            counts = np.array([s.sum() for s in seen])
            best = int(np.argmax(counts))
            if counts[best] < self.min_inliers:
                break
            sel = np.flatnonzero(seen[best])
            kf_frame, kf_tracks, kf_uv = self._keyframes[best]
            uv_then = kf_uv[np.searchsorted(kf_tracks, earlier[sel])]
            ok = geometric_inliers(uv_then, later_uv[sel], self.threshold_px, self.camera, self.min_inliers,
                                   LOOP_AGREEMENT)
            pool[sel] = False
            if ok.any():
                found.append(KeyframeMatch(kf_frame, earlier[sel[ok]], later[sel[ok]], uv_then[ok], later_uv[sel[ok]]))
        return found

    def _grow(self, extra: int, descriptors: np.ndarray) -> None:
        need = self._n + extra
        if self._desc is not None and need <= len(self._desc):
            return
        capacity = max(need, 2 * (0 if self._desc is None else len(self._desc)), 1024)
        desc = np.zeros((capacity, descriptors.shape[1]), descriptors.dtype)
        track = np.zeros(capacity, np.int64)
        active = np.zeros(capacity, bool)
        if self._desc is not None:
            desc[: self._n], track[: self._n], active[: self._n] = (self._desc[: self._n], self._track[: self._n],
                                                                    self._active[: self._n])
        self._desc, self._track, self._active = desc, track, active
