"""Placing targets in the map from registered frames (triangulation, survey step 3).

A target is triangulated by consensus over pairs of its registered views (DLT; views of
a misread card disagree and are left out; the card must come out with its printed
shape). While the baseline is narrow or the rays disagree, it is placed as the rigid
printed card fitted to its views instead (`place_card`), and triangulated later, once
the baseline allows.
"""

from __future__ import annotations

import numpy as np

from app.core.geometry import Camera, Pose
from app.core.survey.cards import (
    PAIR_UNITS,
    PAIRS,
    fit_card,
    max_angle_deg,
    normalised,
    planar_poses,
    triangulate_robust,
    view_error,
)
from app.core.survey.state import SurveyState

#: A target is triangulated only from views that see it from directions this far apart
#: (degrees); narrower, it is placed as the rigid printed card (and flagged in the result).
MIN_BASELINE_DEG = 2.0

#: A target triangulated with a disc-to-disc distance this far (relative) from the
#: printed card is not placed by triangulation (yet): its rays do not agree.
MAX_SHAPE_ERROR = 0.05


def _card_errors(camera: Camera, card: Pose, model: np.ndarray, poses: list[Pose], uvs: list[np.ndarray]
                 ) -> np.ndarray:
    """The worst disc error (px) of the card placed at ``card`` in each of its views."""
    X = card.transform(model)
    return np.array([view_error(camera, p, X, uv) for p, uv in zip(poses, uvs, strict=True)])


def _tilt_cost(R: np.ndarray, tilts: list[list[tuple[np.ndarray, float]]], among: np.ndarray) -> float:
    """Sum over the views ``among`` of the fit of that view's planar tilt nearest to the
    card orientation R (the nearest rotation has the largest trace of R @ R_tilt.T: 1 + 2 cos)."""
    return float(sum(max(fits, key=lambda fit: np.trace(R @ fit[0].T))[1]
                     for k, fits in enumerate(tilts) if among[k] and fits))


def place_card(state: SurveyState, views: list[int]) -> np.ndarray | None:
    """A card's discs from its views, as the printed card, rigid, fitted to them.

    Starts: its planar pose (both tilts) in its 3 largest images, each fitted to the
    views that agree with it (`cards.fit_card`). The start that most views agree with
    wins, then the tilt that the views' own planar fits favour. Not simply the largest
    view's planar pose: a broken detection or a folded projection from outside the field
    can be the largest (a card placed 6 m off drags the map with it); and not the
    closest joint fit: a card 17 px wide fits 3 views 1 degree apart within 0.1 px in
    both tilts, while those frames' poses are still ~0.2 px off each other (a wrong
    tilt, 80 degrees off, ends 80 mm off: a minimum the bundle does not leave). In each
    view alone the right tilt fits 4-10 times better, whatever that frame's position.

    Parameters
    ----------
    state : SurveyState
        The survey.
    views : list of int
        The card's views from registered frames (at most 30 are used, evenly).

    Returns
    -------
    (4, 3) ndarray or None
        The discs in the map; None when most views agree with no placement.
    """
    rec, model = state.reconstruction, state.settings.card_model
    view_frame, view_uv = state.views.frame, state.views.uv
    tol_px = state.tolerance_px
    if len(views) > 30:  # enough to tell the tilts apart, evenly over the track
        views = [views[k] for k in np.linspace(0, len(views) - 1, 30).round().astype(int)]
    poses = [rec.pose(view_frame[v]) for v in views]
    # Each view's two tilts: the card's orientation in the map, its fit in that view.
    tilts = [[(p.R.T @ plane.R, float(((rec.camera.project(plane.transform(model)) - view_uv[v]) ** 2).sum()))
              for plane in planar_poses(rec.camera, view_uv[v], model)]
             for p, v in zip(poses, views, strict=True)]
    uvs = [view_uv[v] for v in views]
    best: tuple[int, float] | None = None
    chosen: np.ndarray | None = None
    for c in sorted(views, key=lambda v: -state.views.area[v])[:3]:
        to_map = rec.pose(view_frame[c]).inverse()
        for plane in planar_poses(rec.camera, view_uv[c], model):
            card = to_map.compose(plane)
            for _ in range(2):  # fit to the views that agree, judge all
                agree = np.flatnonzero(_card_errors(rec.camera, card, model, poses, uvs) < tol_px)
                if len(agree) < 2:
                    break
                card, _ = fit_card(rec.camera, [poses[k] for k in agree], [uvs[k] for k in agree], model, card)
            fit = _card_errors(rec.camera, card, model, poses, uvs) < tol_px
            key = (int(fit.sum()), -_tilt_cost(card.R, tilts, fit))
            if best is None or key > best:
                best, chosen = key, card.transform(model)
    return chosen if best is not None and best[0] > len(views) / 2 else None


def place_targets(state: SurveyState) -> int:
    """Place every unplaced target seen by a registered frame.

    A target is triangulated (`cards.triangulate_robust`) when its agreeing views span
    ``MIN_BASELINE_DEG`` and come out with the printed shape (``MAX_SHAPE_ERROR``); a
    target placed as a rigid card is upgraded so when its views allow. Otherwise it is
    placed by `place_card`, from frames whose pose rests on 2+ targets when there are
    any. A target found wrong (`prune.prune`) is placed again only from more registered
    views than it had then.

    Parameters
    ----------
    state : SurveyState
        The survey: targets are placed in its reconstruction (``placed_by_plane`` marks
        those placed as rigid cards).

    Returns
    -------
    int
        The number of targets placed or upgraded.
    """
    rec, views, usable, marker_size_m = state.reconstruction, state.views, state.usable, state.settings.marker_size_m
    view_frame = views.frame
    registered = rec.registered()
    added = 0
    for t in range(state.tracks.n_targets):
        if np.isfinite(rec.X[4 * t, 0]) and not state.placed_by_plane[t]:
            continue
        # A target found wrong is placed again only from more evidence than it had.
        if int(registered[view_frame[views.of_target[t]]].sum()) <= state.unplaced_at[t]:
            continue
        # Only frames whose pose rests on 2+ targets place new targets: a chain of
        # single-card poses (each with its two-tilt ambiguity) drifts and flips.
        # Frames registered from one card may still triangulate (2+ views, a real
        # baseline), but never place a card from its own planar pose alone.
        seen = [v for v in views.of_target[t] if registered[view_frame[v]] and usable[v]]
        strong = [v for v in seen if not state.weak[view_frame[v]]]
        if not seen:
            continue
        poses = [rec.pose(view_frame[v]) for v in seen]
        if len(seen) >= 2:
            centres = np.array([p.position for p in poses])
            x = np.stack([normalised(rec.camera, views.uv[v]) for v in seen])  # (V, 4, 2)
            tol = state.tolerance_px / rec.camera.fx
            found = triangulate_robust(poses, x, tol, state.rng)
            if found is not None:
                X, inl = found
                wide = max_angle_deg(centres[inl], X.mean(axis=0)) >= MIN_BASELINE_DEG
                # The card must come out with its printed shape: rays from poses that
                # are still a little off cross metres away from the card when the
                # baseline is narrow (3 views 3.6 degrees apart can place a card 1.2 m off,
                # 15-27 % off its size: a wrong minimum the bundle does not leave).
                d = np.linalg.norm(X[PAIRS[:, 0]] - X[PAIRS[:, 1]], axis=1)
                printed = bool(np.abs(d / (PAIR_UNITS * marker_size_m) - 1).max() < MAX_SHAPE_ERROR)
                if wide and printed and (inl.sum() >= 3 or inl.sum() == len(seen)):
                    rec.place(t, X)
                    # An upgrade from a planar placement also counts: the map changed.
                    state.placed_by_plane[t] = False
                    added += 1
                    continue
        if np.isfinite(rec.X[4 * t, 0]):
            continue  # keep the planar placement until the baseline allows better
        # From frames whose pose rests on 2+ targets if any; a frame posed from one card
        # is the last resort (the only link to a part of the room seen apart).
        seen = strong or seen
        if not seen:
            continue
        # Narrow baseline so far: the printed card, rigid, fitted to its views.
        chosen = place_card(state, seen)
        if chosen is None:
            continue  # the views disagree: wait for more
        rec.place(t, chosen)
        state.placed_by_plane[t] = True
        added += 1
    return added
