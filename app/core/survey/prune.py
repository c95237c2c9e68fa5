"""Judging the map by its views: outlier removal, and the robust noise level it judges by.

Whole views are judged (a misidentified target moves all its 4 discs), by their worst
disc, and every view counts, also those set aside: a frame or a target most of whose
views do not fit is taken out (a target is placed again only from more views), single
views that do not fit are set aside, and taken back once they fit. A view of a point
behind the camera or outside its field never fits (`Reconstruction.errors`).

The noise level is measured robustly, from the median 2D error (Rayleigh: the median of
a 2D Gaussian error's length is 1.1774 sigma), so that a few wild views do not move it.
"""

from __future__ import annotations

import numpy as np

from app.core.survey.features import feature_supported
from app.core.survey.state import SurveyState

#: The final bundle adjustment's robust loss and outlier test, on whitened errors (error
#: / expected error) in units of their robust spread (`whitened_spread`, re-measured
#: every round, so a noisier video than `DISC_ERROR_PX` assumes is judged by its own
#: noise): Huber's loss from HUBER_K spreads on; views with a disc beyond OUTLIER_K
#: spreads (and beyond MIN_OUTLIER_PX) are set aside, and taken back below half that.
#: Why: a fitted centre is good to ~0.01 px, but a few in a thousand are 0.3-0.9 px off
#: (glare or an occluder on one disc); with Huber's loss from ~100 expected errors and
#: outliers from 3 px they keep full weight and move a 300-frame map by up to 1 mm
#: (survey benchmark, 4 rooms, same detections: discs 0.36-0.96 mm with those
#: thresholds, 0.19-0.28 mm with these).
HUBER_K = 2.5
OUTLIER_K = 8.0
MIN_OUTLIER_PX = 0.05


def view_errors(state: SurveyState, views: np.ndarray, px_unit: np.ndarray | None = None) -> np.ndarray:
    """The worst disc error of each view.

    Parameters
    ----------
    state : SurveyState
        The survey.
    views : (V,) ndarray of bool
        The views to judge.
    px_unit : (M,) ndarray, optional
        Measure each observation's error in multiples of this (px); default: px.

    Returns
    -------
    (V,) ndarray
        The worst disc error of each view in ``views`` (0 elsewhere; inf for a view of
        a point behind the camera, outside its field, or not placed).
    """
    obs = np.flatnonzero(views.repeat(4))
    err = state.reconstruction.errors(state.tracks, obs)
    if px_unit is not None:
        err = err / px_unit[obs]
    view_err = np.zeros(len(views))
    np.maximum.at(view_err, obs // 4, np.nan_to_num(err, nan=np.inf))
    return view_err


def judged_views(state: SurveyState) -> np.ndarray:
    """The views the map can be judged by.

    Parameters
    ----------
    state : SurveyState
        The survey.

    Returns
    -------
    (V,) ndarray of bool
        The views of a registered frame and a placed target (usable or not).
    """
    rec, views = state.reconstruction, state.views
    return rec.registered()[views.frame] & rec.placed()[views.target * 4]


def prune(state: SurveyState, threshold: float, px_unit: np.ndarray | None = None,
          readmit_below: float | None = None) -> bool:
    """Remove what does not fit the map, and take back what fits again.

    Judges the map by every view of a registered frame and a placed target, also those
    set aside: a frame or a target most of whose views do not fit is wrong (unregistered
    / unplaced; the target's views get a new chance), a single view that does not fit is
    set aside (a misread card, a point outside the field), one set aside earlier that
    fits now is taken back. Why all views: judged by the views it kept, a target placed
    from a few wrong views (a folded projection from outside the field, placed from its
    planar pose) fits them perfectly, while the 60 right ones would be set aside as
    outliers against it, one frame at a time. The seed frame is never taken out.

    Parameters
    ----------
    state : SurveyState
        The survey: its reconstruction and ``usable`` views are updated.
    threshold : float
        A view whose worst disc is off by more than this does not fit.
    px_unit : (M,) ndarray, optional
        The unit of ``threshold`` for each observation, px; default: px.
    readmit_below : float, optional
        A view set aside is taken back below this (default: ``threshold``).

    Returns
    -------
    bool
        True if anything changed.
    """
    rec, views, usable = state.reconstruction, state.views, state.usable
    changed = False
    judged = judged_views(state)
    errors = view_errors(state, judged, px_unit)
    misfit = judged & (errors > threshold)
    # A frame that rests on feature points is judged by them (`prune_features`): cards
    # that do not fit it are set aside there.
    on_features = feature_supported(state)
    for f in np.flatnonzero(rec.registered() & ~on_features):
        v = views.of_frame[f][judged[views.of_frame[f]]]
        if f != state.seed_frame and len(v) and misfit[v].mean() > 0.5:
            rec.unregister(f)
            changed = True
    judged &= rec.registered()[views.frame]
    for t in np.flatnonzero(rec.placed()[0::4]):
        v = views.of_target[t][judged[views.of_target[t]]]
        if len(v) and misfit[v].mean() > 0.5:
            rec.unplace(t)
            state.placed_by_plane[t] = False
            usable[views.of_target[t]] = True
            state.unplaced_at[t] = len(v)
            changed = True
    judged &= rec.placed()[views.target * 4]
    bad = judged & misfit & usable
    readmit = judged & ~usable & (errors <= (threshold if readmit_below is None else readmit_below))
    usable[bad] = False
    usable[readmit] = True
    return changed or bool(bad.any() or readmit.any())


def drop_unsupported(state: SurveyState) -> None:
    """Unregister every frame, and unplace every target, left with no usable view (for a
    frame: neither a card's nor enough feature points', `features.feature_supported`).

    Parameters
    ----------
    state : SurveyState
        The survey; its reconstruction is updated.
    """
    rec, views, usable = state.reconstruction, state.views, state.usable
    on_features = feature_supported(state)
    for f in np.flatnonzero(rec.registered() & ~on_features):
        if not usable[views.of_frame[f]].any():
            rec.unregister(f)
    for t in range(state.tracks.n_targets):
        if not usable[views.of_target[t]].any():
            rec.unplace(t)


def noise_variance(state: SurveyState) -> float:
    """The variance of the map's residuals now, robust.

    Parameters
    ----------
    state : SurveyState
        The survey.

    Returns
    -------
    float
        px^2 per coordinate, from the median 2D error of the usable views; at least
        (0.01 px)^2, and 1 when there is nothing to judge.
    """
    judged = state.usable & judged_views(state)
    err = state.reconstruction.errors(state.tracks, np.flatnonzero(judged.repeat(4)))
    err = err[np.isfinite(err)]
    return max(float(np.median(err)) / 1.1774 if len(err) else 1.0, 0.01) ** 2


def whitened_spread(state: SurveyState) -> float:
    """The robust spread of the judged observations' whitened errors (error / expected
    error, `Tracks.expected_px`), those set aside included.

    Set-aside views count so that setting views aside does not lower the spread, and
    with it the outlier threshold, round after round: judged by the kept views alone, the
    threshold shrank until whole cards with slightly larger errors were taken out (sparse
    room 1 of the walks benchmark kept 6 of its 8 cards that way, 7 this way).

    Parameters
    ----------
    state : SurveyState
        The survey.

    Returns
    -------
    float
        1 when the errors are as `DISC_ERROR_PX` expects; at least 0.01 (on noise-free
        input a zero spread would make every residual an outlier of Huber's loss), and
        1 when there is nothing to judge.
    """
    obs = np.flatnonzero(judged_views(state).repeat(4))
    z = state.reconstruction.errors(state.tracks, obs) / state.tracks.expected_px[obs]
    z = z[np.isfinite(z)]
    return max(float(np.median(z)) / 1.1774, 0.01) if len(z) else 1.0
