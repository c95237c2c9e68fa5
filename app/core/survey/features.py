"""Feature points in the growing map: triangulation, resection and pruning (survey step 3).

The scene's own points (`points.FeatureObservations`, from a feature tracker) are the
survey's second kind of track. They do what the cards cannot: a frame that sees one card
or none registers through the feature points it shares with registered frames, and two
groups of cards never filmed together join through the walls between them. The cards
still give the map its scale and its content: feature points are never part of the map
document.

Three stages, each a function over the `SurveyState`:

* `triangulate_features`: every feature track seen from registered frames over a wide
  enough angle gets a 3D point, if all but a few of its views agree on one;
* `register_by_features`: every unregistered frame that sees enough of those points gets
  its pose by RANSAC over them (and the discs of placed cards it sees);
* `prune_features`: views that do not fit the adjusted map are set aside, those that fit
  again are taken back, and a point left with fewer than two views is taken out, to be
  triangulated again. A wrong match (a repeated pattern merged by a loop closure) is
  thus set aside where it disagrees with the rest of its track.
"""

from __future__ import annotations

import cv2
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from app.core.geometry import Camera, Pose
from app.core.survey.advice import MapWarning, WarningKind
from app.core.survey.cards import normalised
from app.core.survey.points import FeatureObservations
from app.core.survey.state import FIELD_MARGIN, SurveyState

#: A feature point is triangulated only from views that see it from directions this far
#: apart (degrees): narrower, its depth is mostly noise.
MIN_FEATURE_ANGLE_DEG = 1.5
#: Views of a track more than this many frames apart belong to different runs: the
#: track was joined by a keyframe match (`triangulate_features` checks that the runs agree).
RUN_GAP = 3
#: A frame registers through feature points only when this many agree on its pose.
MIN_FEATURE_INLIERS = 20
#: ... and at least this fraction of the points it sees.
MIN_INLIER_FRACTION = 0.5
#: ... and when they pin its position to this fraction of their distance (standard
#: deviation): points bunched in one corner of the image leave a pose that trades
#: position against turn, and each frame registered on it passes its error on.
MAX_POSITION_STD = 0.002
#: A frame holds on to the walls' texture when it sees ``MIN_FEATURE_INLIERS`` points of
#: tracks followed through this many frames or more (a point seen once cannot be
#: triangulated).
TEXTURED_TRACK_VIEWS = 3
#: Fewer textured frames than this fraction: the walls had too little texture to track.
#: On the example walks (300 frames) photo walls give 100 % in every room (the pan and the
#: bare wall included), plain paint 0-4 %.
MIN_TEXTURED_SHARE = 0.25


def feature_tolerance_px(state: SurveyState) -> float:
    """How far (px) a feature view may be off and still agree with its point while the map
    grows: the survey's own tolerance until the lens is fitted (the initial focal length
    may be some percent off), then four of the features' standard deviations, at least
    1 px. Tighter than the cards': a pose resting on feature points passes its error on to
    every point triangulated from it, and on the centre-loop example walk the cards' 3 px
    left maps about three times worse.

    Parameters
    ----------
    state : SurveyState
        The survey.

    Returns
    -------
    float
        The tolerance, px.
    """
    if not state.lens_refined:
        return state.tolerance_px
    return max(1.0, 4 * state.features.sigma_px)


def _rotations(state: SurveyState, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, 3, 3) rotations and (F, 3) translations of frames (map to camera)."""
    rec = state.reconstruction
    R = np.stack([cv2.Rodrigues(rec.rvec[f])[0] for f in frames]) if len(frames) else np.zeros((0, 3, 3))
    return R, rec.tvec[frames]


def feature_errors(state: SurveyState, obs: np.ndarray) -> np.ndarray:
    """Reprojection errors of feature observations.

    Parameters
    ----------
    state : SurveyState
        The survey.
    obs : (N,) ndarray of int
        Feature observations to judge.

    Returns
    -------
    (N,) ndarray
        2D error (px); inf where the point lies behind the camera or outside its field,
        nan where the frame is not registered or the point not triangulated.
    """
    features = state.features
    return _errors(state, features.frame[obs], state.feature_X[features.track[obs]], features.uv[obs])


def _errors(state: SurveyState, frame: np.ndarray, X: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N,) errors (px) of points X (N, 3) seen at uv (N, 2) in frames (N,): see `feature_errors`."""
    rec = state.reconstruction
    err = np.full(len(frame), np.nan)
    ok = rec.registered()[frame] & np.isfinite(X[:, 0])
    if not ok.any():
        return err
    frames, inverse = np.unique(frame[ok], return_inverse=True)
    R, t = _rotations(state, frames)
    cam = np.einsum("nij,nj->ni", R[inverse], X[ok]) + t[inverse]
    seen = rec.camera.in_field(cam, FIELD_MARGIN)
    err[ok] = np.where(seen, np.linalg.norm(rec.camera.project(cam) - uv[ok], axis=1), np.inf)
    return err


def triangulate_features(state: SurveyState, min_angle_deg: float = MIN_FEATURE_ANGLE_DEG) -> int:
    """Triangulate every feature track with new views from registered frames.

    Each track not yet triangulated whose usable views from registered frames grew since
    it was last tried: the point nearest the rays of its longest run of consecutive views
    (least squares), then nearest the rays of all its views that fit that point within
    `feature_tolerance_px` (in front of the camera), twice. It is kept when two views and
    a third of them fit it and the fitting rays span ``min_angle_deg``; the views that do
    not fit are set aside (``feature_usable``).

    Parameters
    ----------
    state : SurveyState
        The survey; ``feature_X`` gains the points, ``feature_usable`` loses the views
        that disagree.

    Returns
    -------
    int
        The number of feature points triangulated.
    """
    features, rec = state.features, state.reconstruction
    if not len(features):
        return 0
    registered = rec.registered()
    todo = ~np.isfinite(state.feature_X[:, 0])
    obs = np.flatnonzero(state.feature_usable & registered[features.frame] & todo[features.track])
    count = np.bincount(features.track[obs], minlength=len(state.feature_X))
    fresh = (count >= 2) & (count > state.feature_attempted)
    obs = obs[fresh[features.track[obs]]]
    if not len(obs):
        return 0
    state.feature_attempted[fresh] = count[fresh]
    camera = rec.camera
    frames, inverse = np.unique(features.frame[obs], return_inverse=True)
    R, t = _rotations(state, frames)
    centres = -np.einsum("nji,nj->ni", R, t)
    x = np.c_[normalised(camera, features.uv[obs]), np.ones(len(obs))]
    rays = np.einsum("nji,nj->ni", R[inverse], x)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    track = features.track[obs]
    X = _from_longest_run(rays, centres[inverse], track, features.frame[obs], len(state.feature_X))
    for _ in range(2):  # the longest run's point, then all the views that fit it
        err = _errors(state, features.frame[obs], X[track], features.uv[obs])
        keep = err <= feature_tolerance_px(state)  # inf behind the camera
        X = _nearest_points(rays[keep], centres[inverse[keep]], track[keep], len(state.feature_X))
    err = _errors(state, features.frame[obs], X[track], features.uv[obs])
    keep = err <= feature_tolerance_px(state)
    n_views = np.bincount(track, minlength=len(X))
    n_fit = np.bincount(track[keep], minlength=len(X))
    angle = _widest_angle(rays, track, keep, len(X))
    good = todo & (n_fit >= 2) & (3 * n_fit >= n_views) & (angle >= min_angle_deg) & np.isfinite(X[:, 0])
    state.feature_X[good] = X[good]
    state.feature_usable[obs[good[track] & ~keep]] = False
    return int(good.sum())


def _from_longest_run(rays: np.ndarray, centres: np.ndarray, track: np.ndarray, frame: np.ndarray, n: int
                      ) -> np.ndarray:
    """(n, 3) each track's point from its longest run of views (frames at most
    ``RUN_GAP`` apart). A feature tracker follows a point frame to frame; a track
    with a gap was joined across the video by a keyframe match, which may be wrong (a
    pattern repeated in the room): its runs are judged against the longest one."""
    order = np.lexsort((frame, track))
    t, f = track[order], frame[order]
    new_run = np.r_[True, (t[1:] != t[:-1]) | (np.diff(f) > RUN_GAP)]
    run = np.empty(len(order), np.int64)
    run[order] = np.cumsum(new_run) - 1
    run_track = np.zeros(int(run.max()) + 1 if len(run) else 0, np.int64)
    run_track[run] = track
    size = np.bincount(run, minlength=len(run_track))
    points = _nearest_points(rays, centres, run, len(run_track))
    size = np.where(np.isfinite(points[:, 0]), size, 0)
    # The largest run of each track (ties: the first).
    best = np.full(n, -1)
    by_size = np.lexsort((-np.arange(len(run_track)), size))
    best[run_track[by_size]] = by_size
    X = np.full((n, 3), np.nan)
    ok = best >= 0
    X[ok] = points[best[ok]]
    return X


def _nearest_points(rays: np.ndarray, centres: np.ndarray, track: np.ndarray, n: int) -> np.ndarray:
    """(n, 3) the point nearest each track's rays in the least-squares sense; nan for a
    track with fewer than two rays or rays nearly parallel."""
    P = np.eye(3) - rays[:, :, None] * rays[:, None, :]  # projects onto the plane normal to the ray
    A = np.zeros((n, 3, 3))
    b = np.zeros((n, 3))
    np.add.at(A, track, P)
    np.add.at(b, track, np.einsum("nij,nj->ni", P, centres))
    X = np.full((n, 3), np.nan)
    ok = np.bincount(track, minlength=n) >= 2
    ok[ok] = np.linalg.eigvalsh(A[ok])[:, 0] > 1e-6  # rays not all parallel
    X[ok] = np.linalg.solve(A[ok], b[ok][:, :, None])[:, :, 0]
    return X


def _widest_angle(rays: np.ndarray, track: np.ndarray, keep: np.ndarray, n: int) -> np.ndarray:
    """(n,) the angle (degrees) between the mean ray and the ray farthest from it, twice:
    about the widest angle between two of each track's kept rays."""
    mean = np.zeros((n, 3))
    np.add.at(mean, track[keep], rays[keep])
    norm = np.linalg.norm(mean, axis=1, keepdims=True)
    mean = np.divide(mean, norm, out=np.zeros_like(mean), where=norm > 0)
    cos = np.full(n, 1.0)
    np.minimum.at(cos, track[keep], np.einsum("ni,ni->n", rays[keep], mean[track[keep]]))
    return 2 * np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def register_by_features(state: SurveyState, min_inliers: int = MIN_FEATURE_INLIERS) -> int:
    """Register every unregistered frame that sees enough triangulated feature points.

    The pose is found by RANSAC (P3P) over the frame's feature points and the discs of
    the placed cards it sees, then refined over the points that agree. It is kept when
    ``min_inliers`` feature points and ``MIN_INLIER_FRACTION`` of them agree within
    `feature_tolerance_px` (the cards' discs within the survey's own tolerance) and they
    pin the camera's position to ``MAX_POSITION_STD`` of their distance (`position_std`).
    The feature views and card views that do not agree are set aside in that frame.

    Parameters
    ----------
    state : SurveyState
        The survey: frames are registered in its reconstruction.
    min_inliers : int
        The fewest feature points that must agree on a pose.

    Returns
    -------
    int
        The number of frames registered.
    """
    features, rec, views = state.features, state.reconstruction, state.views
    if not len(features):
        return 0
    registered, placed = rec.registered(), rec.placed()[0::4]
    usable = state.feature_usable & np.isfinite(state.feature_X[features.track, 0]) & ~registered[features.frame]
    obs = np.flatnonzero(usable)
    per_frame = np.bincount(features.frame[obs], minlength=state.tracks.n_frames)
    added = 0
    tol = feature_tolerance_px(state)
    for f in np.argsort(-per_frame, kind="stable"):
        if per_frame[f] < min_inliers:
            break
        if state.feature_tried.get(int(f), -1) >= per_frame[f]:
            continue
        state.feature_tried[int(f)] = int(per_frame[f])
        mine = obs[features.frame[obs] == f]
        card_views = [v for v in views.of_frame[f] if placed[views.target[v]] and state.usable[v]]
        X = np.concatenate([state.feature_X[features.track[mine]]] + [rec.discs(views.target[v]) for v in card_views])
        uv = np.concatenate([features.uv[mine]] + [views.uv[v] for v in card_views])
        try:
            ok, rvec, tvec, inliers = cv2.solvePnPRansac(
                X, uv, rec.camera.K, rec.camera.dist, iterationsCount=200, reprojectionError=tol,
                confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
        except cv2.error:
            continue
        if not ok or inliers is None:
            continue
        inl = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(X[inl], uv[inl], rec.camera.K, rec.camera.dist, rvec, tvec)
        pose = Pose.from_rvec_tvec(rvec, tvec)
        err = np.linalg.norm(rec.camera.project_map(X, pose) - uv, axis=1)
        in_front = pose.transform(X)[:, 2] > 0
        # The cards are judged by their own tolerance (their discs are surveyed by now).
        fit = (err <= np.where(np.arange(len(X)) < len(mine), tol, state.tolerance_px)) & in_front
        n_fit = int(fit[: len(mine)].sum())
        if n_fit < min_inliers or n_fit < MIN_INLIER_FRACTION * len(mine):
            continue
        depth = float(np.median(pose.transform(X[fit])[:, 2]))
        std = position_std(rec.camera, pose, X[fit], features.sigma_px)
        if not std <= MAX_POSITION_STD * depth:
            continue
        rec.set_pose(int(f), pose)
        state.weak[f] = False
        state.feature_usable[mine[~fit[: len(mine)]]] = False
        for k, v in enumerate(card_views):
            if not fit[len(mine) + 4 * k : len(mine) + 4 * k + 4].all():
                state.usable[v] = False
        added += 1
    return added


def position_std(camera: Camera, pose: Pose, X: np.ndarray, sigma_px: float) -> float:
    """How well points pin a camera's position: the RMS standard deviation (per axis) of
    its centre fitted to their images, each off by ``sigma_px``.

    Parameters
    ----------
    camera : Camera
        The camera.
    pose : Pose
        The camera's pose (map to camera).
    X : (N, 3) ndarray
        The points it sees, in the map.
    sigma_px : float
        The error of each image point, px per axis.

    Returns
    -------
    float
        In the map's units; inf when the points do not determine the pose.
    """
    _, jac = cv2.projectPoints(X.reshape(-1, 1, 3), pose.rvec, pose.t, camera.K, camera.dist)
    J = jac[:, :6]
    # The centre C = -R^T t as a function of (rvec, t): its Jacobian, numerically over rvec.
    dC = np.empty((3, 6))
    dC[:, 3:] = -pose.R.T
    for k in range(3):
        step = np.zeros(3)
        step[k] = 1e-6
        dC[:, k] = (Pose.from_rvec_tvec(pose.rvec + step, pose.t).position - pose.position) / 1e-6
    try:
        cov = np.linalg.inv(J.T @ J) * sigma_px**2
    except np.linalg.LinAlgError:
        return float("inf")
    return float(np.sqrt(max(np.trace(dC @ cov @ dC.T), 0.0) / 3))


def prune_features(state: SurveyState, threshold_px: float, readmit_px: float | None = None) -> bool:
    """Set aside the feature views that do not fit the map, take back those that do.

    A frame registered through feature points most of whose feature views do not fit
    (and that sees no card) is unregistered; a point left with fewer than two usable
    views is taken out (`triangulate_features` may find it again).

    Parameters
    ----------
    state : SurveyState
        The survey.
    threshold_px : float
        A view further off than this (px) does not fit.
    readmit_px : float, optional
        A view set aside is taken back within this (default: ``threshold_px``).

    Returns
    -------
    bool
        True if anything changed.
    """
    features, rec = state.features, state.reconstruction
    if not len(features):
        return False
    obs = np.arange(len(features))
    err = feature_errors(state, obs)
    judged = ~np.isnan(err)
    misfit = judged & (err > threshold_px)
    changed = False
    frame = features.frame
    n_judged = np.bincount(frame[judged], minlength=state.tracks.n_frames)
    n_misfit = np.bincount(frame[misfit], minlength=state.tracks.n_frames)
    for f in np.flatnonzero(rec.registered() & (n_judged > 0) & (2 * n_misfit > n_judged)):
        if f != state.seed_frame and not len(state.views.of_frame[f]):
            rec.unregister(int(f))
            changed = True
    readmit = judged & ~state.feature_usable & (err <= (threshold_px if readmit_px is None else readmit_px))
    bad = misfit & state.feature_usable
    state.feature_usable[bad] = False
    state.feature_usable[readmit] = True
    alive = state.feature_usable & rec.registered()[frame]
    support = np.bincount(features.track[alive], minlength=len(state.feature_X))
    lost = np.isfinite(state.feature_X[:, 0]) & (support < 2)
    state.feature_X[lost] = np.nan
    state.feature_attempted[lost] = 0
    return changed or bool(bad.any() or readmit.any() or lost.any())


def feature_supported(state: SurveyState, min_inliers: int = MIN_FEATURE_INLIERS) -> np.ndarray:
    """Which frames rest on feature points: ``min_inliers`` usable views of triangulated points.

    Parameters
    ----------
    state : SurveyState
        The survey.
    min_inliers : int
        The fewest usable feature views.

    Returns
    -------
    (F,) bool ndarray
        True where the frame has that many.
    """
    features = state.features
    alive = state.feature_usable & np.isfinite(state.feature_X[features.track, 0])
    return np.bincount(features.frame[alive], minlength=state.tracks.n_frames) >= min_inliers


def feature_groups(state: SurveyState) -> np.ndarray:
    """Which registered frames the feature points link: a label per frame.

    Two registered frames are linked when both see one triangulated feature point in a
    usable view; the labels are the connected parts of that graph.

    Parameters
    ----------
    state : SurveyState
        The survey.

    Returns
    -------
    (F,) ndarray of int
        Equal labels for linked frames; a frame linked to none (or not registered) has a
        label of its own.
    """
    features, n_frames = state.features, state.tracks.n_frames
    alive = (state.feature_usable & state.reconstruction.registered()[features.frame]
             & np.isfinite(state.feature_X[features.track, 0]))
    obs = np.flatnonzero(alive)
    obs = obs[np.lexsort((features.frame[obs], features.track[obs]))]
    same = features.track[obs][1:] == features.track[obs][:-1]
    a, b = features.frame[obs][:-1][same], features.frame[obs][1:][same]
    graph = sp.csr_matrix((np.ones(len(a)), (a, b)), shape=(n_frames, n_frames))
    _, labels = connected_components(graph, directed=False)
    return labels


def textured_frames(features: FeatureObservations, n_frames: int, min_points: int = MIN_FEATURE_INLIERS,
                    min_views: int = TEXTURED_TRACK_VIEWS) -> np.ndarray:
    """Which frames see enough of the walls' texture to rest on it.

    Parameters
    ----------
    features : FeatureObservations
        The feature tracks of the video.
    n_frames : int
        The video's frames (those the tracks number).
    min_points : int
        The fewest tracked points a frame must see.
    min_views : int
        The fewest frames a point's track must span to count.

    Returns
    -------
    (n_frames,) bool ndarray
        True where the frame sees ``min_points`` points of tracks of ``min_views`` frames or more.
    """
    frame, track = np.asarray(features.frame, np.int64), np.asarray(features.track, np.int64)
    long = np.bincount(track)[track] >= min_views if len(track) else np.zeros(0, bool)
    return np.bincount(frame[long], minlength=n_frames)[:n_frames] >= min_points


def texture_warning(features: FeatureObservations, n_frames: int) -> MapWarning | None:
    """The warning for walls with too little texture to track, or None.

    The feature tracks then add nothing to the cards: every frame registers through its
    cards alone, as without feature tracks, and a frame with one card or none stays out.

    Parameters
    ----------
    features : FeatureObservations
        The feature tracks of the video.
    n_frames : int
        The video's frames.

    Returns
    -------
    MapWarning or None
        Of kind ``PLAIN_WALLS`` (naming no card) when fewer than ``MIN_TEXTURED_SHARE``
        of the frames are `textured_frames`; None otherwise, or for fewer than
        ``TEXTURED_TRACK_VIEWS`` frames (too short to tell).
    """
    if n_frames < TEXTURED_TRACK_VIEWS:
        return None
    n_textured = int(textured_frames(features, n_frames).sum())
    if n_textured >= MIN_TEXTURED_SHARE * n_frames:
        return None
    return MapWarning(WarningKind.PLAIN_WALLS, (), (
        f"the walls had too little texture to track (only {n_textured} of the {n_frames} frames saw "
        f"{MIN_FEATURE_INLIERS} or more points that could be followed): the map rests on the cards alone, as without "
        "feature tracks; film again with 2 or more cards in most frames, or add "
        "texture to the walls (posters, pictures, patterned cloth)"))
