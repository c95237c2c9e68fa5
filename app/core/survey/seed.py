"""The metric start of the map (survey step 2): two frames, their shared targets
triangulated, the scale from the printed card.

No card is placed from its own planar pose here: for small cards the two tilts fit
alike, and a wrong one misleads everything registered against it. When no pair of
frames qualifies, the frame that sees most targets fixes the map frame alone and the
growth places its cards as rigid printed cards.
"""

from __future__ import annotations

import cv2
import numpy as np

from app.core.geometry import Camera, Pose
from app.core.survey.cards import PAIR_UNITS, PAIRS, normalised, project_norm
from app.core.survey.state import SurveyState, Views


def two_view_seed(camera: Camera, views: Views, marker_size_m: float, tol_px: float
                  ) -> tuple[int, int, Pose, dict[int, np.ndarray]] | None:
    """The start of the map from two frames by the essential matrix (no card planarity).

    Two frames that share several targets, seen from directions some degrees apart,
    give the relative pose (5-point RANSAC over all shared disc centres: a misidentified
    target is an outlier) and the discs by triangulation, with no tilt to choose. The
    printed card size gives the scale. Of the pairs among the 6 frames that see most
    targets (30 partners each at most), the one with the most cards of their printed
    shape, seen from the widest angle, wins.

    Parameters
    ----------
    camera : Camera
        The initial camera.
    views : Views
        Every view of the video.
    marker_size_m : float
        The printed card's side, metres.
    tol_px : float
        How far (px) a disc may be off its triangulated point in either frame.

    Returns
    -------
    tuple or None
        (frame a, frame b, pose of b (a is at the identity), {target index: (4, 3)
        discs, metres}); None when no pair gives a start.
    """
    view_target, view_uv, views_of_frame = views.target, views.uv, views.of_frame
    n_frames = len(views_of_frame)
    counts = np.array([len(v) for v in views_of_frame])
    x_all = normalised(camera, view_uv.reshape(-1, 2)).reshape(-1, 4, 2)
    frame_views = [dict(zip(view_target[v].tolist(), v.tolist(), strict=True)) for v in views_of_frame]
    tol = tol_px / camera.fx
    best: tuple[float, int, int, Pose, dict[int, np.ndarray]] | None = None
    for a in np.argsort(-counts, kind="stable")[:6]:
        a = int(a)
        if counts[a] < 3:
            break
        ta = frame_views[a]
        partners = [b for b in range(n_frames) if b != a and sum(t in ta for t in frame_views[b]) >= 3]
        if len(partners) > 30:
            partners = [partners[k] for k in np.linspace(0, len(partners) - 1, 30).round().astype(int)]
        for b in partners:
            shared = [t for t in frame_views[b] if t in ta]
            x1 = np.concatenate([x_all[ta[t]] for t in shared])
            x2 = np.concatenate([x_all[frame_views[b][t]] for t in shared])
            try:
                E, mask = cv2.findEssentialMat(x1, x2, np.eye(3), cv2.RANSAC, 0.999, tol)
            except cv2.error:
                continue
            if E is None or E.shape[0] < 3 or mask is None:
                continue
            candidates = [E[3 * k : 3 * k + 3] for k in range(E.shape[0] // 3)]
            for E in candidates:
                try:
                    _, R, t, _ = cv2.recoverPose(E, x1, x2, np.eye(3), mask=mask.copy())
                except cv2.error:
                    continue
                pb = Pose(R, t.ravel())
                pa = Pose.identity()
                X = cv2.triangulatePoints(np.c_[np.eye(3), np.zeros(3)], np.c_[R, t], x1.T, x2.T)
                if (np.abs(X[3]) < 1e-12).any():
                    continue
                X = (X[:3] / X[3]).T
                err = np.maximum(np.abs(project_norm(pa, X) - x1).max(axis=1),
                                 np.abs(project_norm(pb, X) - x2).max(axis=1))
                ok = (err < tol) & (X[:, 2] > 0) & (pb.transform(X)[:, 2] > 0)
                ok_t = ok.reshape(-1, 4).all(axis=1)
                if ok_t.sum() < 3:
                    continue
                Xg = X.reshape(-1, 4, 3)[ok_t]
                ray_a = Xg.mean(axis=1)
                ray_b = ray_a - pb.position
                cos = (ray_a * ray_b).sum(axis=1) / (np.linalg.norm(ray_a, axis=1) * np.linalg.norm(ray_b, axis=1))
                angle = float(np.degrees(np.median(np.arccos(np.clip(cos, -1, 1)))))
                if angle < 3.0:
                    continue
                d = np.linalg.norm(Xg[:, PAIRS[:, 0]] - Xg[:, PAIRS[:, 1]], axis=2).ravel()
                L = np.tile(PAIR_UNITS * marker_size_m, len(Xg))
                scale = float((d * L).sum() / (d * d).sum())
                # Cards whose triangulated shape is far from the printed one are not kept.
                shape = np.abs(scale * d - L).reshape(-1, 6).max(axis=1) < 0.25 * marker_size_m
                if shape.sum() < 3:
                    continue
                # Quality: the printed shape of the kept cards. A wrong relative pose (a
                # narrow pair whose 5-point fit is loose within the lens's unmodelled
                # distortion) still places every card within tolerance, but bent: cards
                # 5-12 % off their shape, against ~1 % for a right one. Scored by the
                # angle alone, a wrong pair with a wide (wrong) angle ties a right one.
                rel = float(np.median(np.abs(scale * d - L).reshape(-1, 6)[shape].max(axis=1))) / marker_size_m
                score = float(shape.sum()) * min(angle, 10.0) / (1.0 + (rel / 0.02) ** 2)
                if best is None or score > best[0]:
                    kept = [tg for tg, k in zip(np.array(shared)[ok_t], shape, strict=True) if k]
                    discs = {int(tg): scale * Xg[i] for i, tg in enumerate(np.array(shared)[ok_t]) if shape[i]}
                    assert len(discs) == len(kept)
                    best = (score, a, b, Pose(pb.R, scale * pb.t), discs)
    if best is None:
        return None
    return best[1], best[2], best[3], best[4]


def bootstrap(state: SurveyState) -> None:
    """Fix the map frame and place the first targets (step 2).

    From `two_view_seed` (judged loosely: the lens is not fitted yet) when a pair of
    frames gives a start. Otherwise (too few targets shared, too little motion) the
    frame that sees most targets, then most card area, is the seed alone: its cards are
    placed by the growth, as rigid printed cards.

    Parameters
    ----------
    state : SurveyState
        The state from `SurveyState.start`; its seed frame is set and registered at
        the identity, and the seed pair's targets placed.
    """
    rec, views = state.reconstruction, state.views
    start = two_view_seed(rec.camera, views, state.settings.marker_size_m, state.settings.loose_px)
    if start is not None:
        seed, partner, partner_pose, discs = start
        rec.set_pose(seed, Pose.identity())
        rec.set_pose(partner, partner_pose)
        for t, X in discs.items():
            rec.place(t, X)
    else:
        n_frames = state.tracks.n_frames
        views_per_frame = np.bincount(views.frame, minlength=n_frames)
        score = views_per_frame * 1e9 + np.bincount(views.frame, weights=views.area, minlength=n_frames)
        seed = int(np.argmax(score))
        rec.set_pose(seed, Pose.identity())
    state.seed_frame = seed
