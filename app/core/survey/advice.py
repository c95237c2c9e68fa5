"""What to film to fix a weak map: one warning per weak or unconnected card, and one for
a pure pan, each saying what the user should film (docs/filming.md); and one per id taken
for a misread, which names its frames and asks for nothing."""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from app.core.survey.state import Misread, Tracks, Views

#: The range of viewing directions the advice asks for, degrees: well above the survey's
#: own threshold (`place.MIN_BASELINE_DEG`), so that a card filmed again is well placed.
ADVISED_BASELINE_DEG = 15.0
#: The distance range the advice asks cards to be filmed from, metres.
ADVISED_DISTANCE_M = (1.0, 2.0)
#: A pure pan: nearly every registered camera centre (``PAN_FRACTION`` of them) within this
#: distance of their median, metres; or nearly every surveyed target (``PAN_FRACTION`` of
#: them, 3 or more) seen over less than the survey's minimum baseline, since a pan's depths
#: from the card size can scatter the estimated centres wider than the pan itself. A
#: fraction rather than all, so that a frame or target placed out of place does not hide it.
PAN_RADIUS_M = 0.10
PAN_FRACTION = 0.9
#: How many mapped neighbours the advice names.
N_NEIGHBOURS = 2
#: A principal point more uncertain than this (1 sigma, px, either axis) gets a warning:
#: off by that much, every pose is tilted by it over the focal length (0.07 degrees for
#: 1 px at f 820 px: 4 mm sideways at 3 m).
PRINCIPAL_POINT_STD_PX = 0.5


class WarningKind(enum.Enum):
    """What is weak about a part of the map."""

    FEW_VIEWS = "few views"  # seen in too few registered frames (and maybe narrow too)
    NARROW = "narrow"  # seen over less than the survey's minimum baseline
    NOT_SURVEYED = "not surveyed"  # detected but not in the map
    DISCONNECTED = "disconnected"  # in the map, but never seen together with the rest
    PURE_PAN = "pure pan"  # the camera only turned: no baseline anywhere
    MISREAD = "probable misread"  # an id read a few times, weakly or on another card: not a card, not in the map
    PLAIN_WALLS = "plain walls"  # too little texture to track: the map rests on the cards alone
    UNCERTAIN = "uncertain"  # in the map, placed too uncertainly to trust (reached through card-less frames)


@dataclass(frozen=True)
class MapWarning:
    """One warning for the user: its kind, the printed ids of the cards it is about, and
    the text (what is weak, and what to film to fix it)."""

    kind: WarningKind
    target_ids: tuple[int, ...]
    message: str
    frames: tuple[int, ...] = ()  # the input frames it is about (a probable misread's reads), if any


@dataclass(frozen=True)
class TargetViews:
    """What the survey knows of one surveyed target's views, in the map's units (metres)."""

    id: int
    centre: np.ndarray  # (3,) the mean of its disc centres
    n_views: int  # registered frames in which it was used
    baseline_deg: float  # widest angle between two of those views, at the target
    distance_m: float  # median distance of those frames' camera centres to the target


def _ids(ids: list[int] | tuple[int, ...]) -> str:
    return ", ".join(str(i) for i in ids)


def _either(ids: list[int]) -> str:
    return str(ids[0]) if len(ids) == 1 else ", ".join(str(i) for i in ids[:-1]) + f" or {ids[-1]}"


def _card_advice(t: TargetViews, few: bool, narrow: bool, min_views: int, min_baseline_deg: float) -> str:
    lo, hi = ADVISED_DISTANCE_M
    side = np.tan(np.radians(ADVISED_BASELINE_DEG)) * hi
    facts = []
    if few:
        facts.append(f"seen in {t.n_views} registered frames only (fewer than {min_views})")
    facts.append(f"from {t.distance_m:.1f} m")
    if narrow:
        facts.append(f"all within {max(t.baseline_deg, 0.01):.2f} degrees of one direction (too narrow a range, "
                     f"under {min_baseline_deg:g} degrees)")
    else:
        facts.append(f"over {t.baseline_deg:.0f} degrees of viewing directions")
    return (f"card {t.id}: " + ", ".join(facts) + f": film it again from {lo:g}-{hi:g} m, walking past it so you "
            f"see it from at least {ADVISED_BASELINE_DEG:g} degrees apart (a step of {side:.1f} m sideways at "
            f"{hi:g} m), with other cards in the same shot")


def _nearest(centre: np.ndarray, among: list[TargetViews]) -> list[int]:
    if not among:
        return []
    d = [float(np.linalg.norm(t.centre - centre)) for t in among]
    return [among[k].id for k in np.argsort(d, kind="stable")[:N_NEIGHBOURS]]


def map_advice(targets: list[TargetViews], tracks: Tracks, views: Views, used: np.ndarray,
               surveyed: np.ndarray, camera_centres: np.ndarray, min_views: int,
               min_baseline_deg: float, frame_groups: np.ndarray | None = None) -> list[MapWarning]:
    """The warnings about weak parts of a map, each naming its cards and what to film.

    Parameters
    ----------
    targets : list of TargetViews
        The surveyed targets, in the order of ``surveyed``.
    tracks : Tracks
        The observations.
    views : Views
        Every view.
    used : (V,) bool ndarray
        The views the map rests on.
    surveyed : (T',) int ndarray
        The target indices (into ``tracks.ids``) of the map.
    camera_centres : (F, 3) ndarray
        The centres of the registered cameras, in the map's units.
    min_views : int
        The fewest registered frames a target is to be used in.
    min_baseline_deg : float
        The survey's minimum baseline for a target, degrees.
    frame_groups : (F,) ndarray of int, optional
        A label per frame: frames with one label are linked by the scene's own points
        (`features.feature_groups`), so cards seen in any of them count as seen
        together. Default: each frame alone (cards only).

    Returns
    -------
    list of MapWarning
        In order: a pure pan (``PAN_FRACTION`` of the registered camera centres within
        ``PAN_RADIUS_M`` of their median, or of the targets under ``min_baseline_deg``; it
        takes the place of the per-card narrow warnings, which it explains); then per
        card, those seen in fewer than ``min_views`` frames or over less than
        ``min_baseline_deg``; then the cards detected but not surveyed, one warning per
        group of them seen together (each group named with the mapped cards seen in
        its frames); then the parts of the map never seen together with the rest, named
        with their nearest mapped neighbours.
    """
    group = np.arange(tracks.n_frames) if frame_groups is None else np.asarray(frame_groups)
    n_groups = int(group.max()) + 1 if len(group) else 0
    out: list[MapWarning] = []
    centres = np.asarray(camera_centres, float).reshape(-1, 3)
    if len(centres) >= 2:
        spread = float(np.quantile(np.linalg.norm(centres - np.median(centres, axis=0), axis=1), PAN_FRACTION))
    else:
        spread = np.inf
    n_narrow = sum(t.baseline_deg < min_baseline_deg for t in targets)
    pan = spread <= PAN_RADIUS_M or (len(targets) >= 3 and n_narrow >= PAN_FRACTION * len(targets))
    if pan:
        ids = tuple(t.id for t in targets)
        evidence = (f"{round(100 * PAN_FRACTION)} % of the registered camera centres are within "
                    f"{max(100 * spread, 1):.0f} cm of one point" if spread <= PAN_RADIUS_M else
                    f"{n_narrow} of the {len(targets)} cards were each seen from within {min_baseline_deg:g} degrees "
                    "of one direction")
        out.append(MapWarning(WarningKind.PURE_PAN, ids, (
            f"the camera only turned on one spot ({evidence}): the cards' depths come only from their printed "
            "size, so the map's scale and depths are only as good as the card size measurement; film again walking "
            f"through the room, not only turning, so each card is seen from at least {ADVISED_BASELINE_DEG:g} "
            "degrees apart")))
    for t in targets:
        few = t.n_views < min_views
        narrow = t.baseline_deg < min_baseline_deg
        if few or (narrow and not pan):
            kind = WarningKind.FEW_VIEWS if few else WarningKind.NARROW
            out.append(MapWarning(kind, (t.id,), _card_advice(t, few, narrow, min_views, min_baseline_deg)))
    mapped = {t.id for t in targets}
    index = {int(i): k for k, i in enumerate(tracks.ids)}
    missing = [index[i] for i in sorted(set(tracks.ids.tolist()) - mapped)]
    n = len(tracks.ids)
    if missing:
        # The missing cards in groups seen together (in one frame, or linked frames).
        inc_all = sp.csr_matrix((np.ones(len(views)), (views.target, group[views.frame])), shape=(n, n_groups))
        _, parts = connected_components((inc_all @ inc_all.T)[missing][:, missing], directed=False)
        for part in np.unique(parts):
            ids = sorted(int(tracks.ids[missing[k]]) for k in np.flatnonzero(parts == part))
            own = np.isin(views.target, [index[i] for i in ids])
            company = sorted(mapped & {int(tracks.ids[k]) for k in
                                       views.target[np.isin(group[views.frame], group[views.frame[own]])]})
            names = "cards " + _ids(ids) if len(ids) > 1 else f"card {ids[0]}"
            together = " (seen together, but not with the map)" if len(ids) > 1 and len(missing) > len(ids) else ""
            fix = (f"film {'them' if len(ids) > 1 else 'it'} again in the same shots as mapped cards "
                   f"(seen in the same frames: {_ids(company)}), from several positions" if company else
                   f"film {'them' if len(ids) > 1 else 'it'} in the same shots as cards already mapped, "
                   "from several positions")
            out.append(MapWarning(WarningKind.NOT_SURVEYED, tuple(ids), (
                f"{names}{together} could not be surveyed (detected, but not seen together with the rest of the "
                f"map from registered frames, or their views did not fit): {fix}")))
    # Co-visibility graph of the surveyed targets: an edge when two share a frame (or
    # frames linked by feature points).
    vf, vt = views.frame[used], views.target[used]
    inc = sp.csr_matrix((np.ones(len(vf)), (vt, group[vf])), shape=(n, n_groups))
    adj = (inc @ inc.T)[surveyed][:, surveyed]
    n_comp, labels = connected_components(adj, directed=False)
    if n_comp > 1:
        main = int(np.argmax(np.bincount(labels)))
        rest = [targets[k] for k in np.flatnonzero(labels == main)]
        for c in range(n_comp):
            if c == main:
                continue
            part = [targets[k] for k in np.flatnonzero(labels == c)]
            ids = sorted(t.id for t in part)
            near = _nearest(np.mean([t.centre for t in part], axis=0), rest)
            out.append(MapWarning(WarningKind.DISCONNECTED, tuple(ids), (
                f"parts of the map are not seen together with the rest (only linked through camera motion): "
                f"{'cards ' + _ids(ids) if len(ids) > 1 else f'card {ids[0]}'}; film "
                f"{'them' if len(ids) > 1 else 'it'} in the same shot as card {_either(near)} "
                f"(the nearest mapped {'neighbours' if len(near) > 1 else 'neighbour'})")))
    return out


def _frames(frames: tuple[int, ...]) -> str:
    if len(frames) == 1:
        return f"in frame {frames[0]} only"
    return f"in frames {', '.join(str(f) for f in frames[:-1])} and {frames[-1]} only"


def misread_advice(misreads: tuple[Misread, ...]) -> list[MapWarning]:
    """One warning per probable misread (`tracks.probable_misreads`): the id, the frames it
    was read in, and why it is not taken for a card; nothing to film for it.

    Parameters
    ----------
    misreads : tuple of Misread
        The ids left out of the survey as probable misreads.

    Returns
    -------
    list of MapWarning
        Of kind `WarningKind.MISREAD`, naming the id and its frames.
    """
    out = []
    for m in misreads:
        why = ", with a weak code" if m.weak else ""
        if m.of_id is not None:
            why += f", where card {m.of_id} is seen in the frames around it"
        of = f"card {m.of_id}" if m.of_id is not None else "another card"
        out.append(MapWarning(WarningKind.MISREAD, (m.id,), (
            f"id {m.id} was read {_frames(m.frames)}{why}: probably a misread of {of}, so it is not in the map "
            f"(a card {m.id}, if the room has one, was not seen clearly enough to map)"), m.frames))
    return out


def uncertainty_advice(uncertain: list[tuple[int, float]], mapped: list[TargetViews]) -> list[MapWarning]:
    """One warning per card placed too uncertainly: its uncertainty and what to film.

    Parameters
    ----------
    uncertain : list of (int, float)
        (id, largest disc std_m in metres) of each uncertain card (`verify.uncertain_cards`).
    mapped : list of TargetViews
        Every card of the map.

    Returns
    -------
    list of MapWarning
        Kind `WarningKind.UNCERTAIN`, one per card.
    """
    out = []
    weak = {card for card, _ in uncertain}
    rest = [t for t in mapped if t.id not in weak]
    centres = {t.id: t.centre for t in mapped}
    for card, std in uncertain:
        near = _nearest(centres[card], rest)
        amount = f"+/- {100 * std:.0f} cm" if np.isfinite(std) else "by an unknown amount"
        film = (f"film it in the same shot as card {_either(near)} (the nearest well-placed "
                f"{'neighbours' if len(near) > 1 else 'neighbour'})" if near else "film it together with other cards")
        out.append(MapWarning(WarningKind.UNCERTAIN, (card,), (
            f"card {card}: its position is uncertain ({amount}, 1 sigma): it was reached only through frames in which "
            f"no other card was in view, where the camera's path drifts; {film}")))
    return out


def lens_warning(intrinsics_std: np.ndarray | None) -> str | None:
    """The warning for a principal point the survey could not pin down, or None.

    Parameters
    ----------
    intrinsics_std : (5,) ndarray or None
        1 sigma of the adjusted ``[f, cx, cy, k1, k2]``; None when the intrinsics were
        given (nothing to warn about).

    Returns
    -------
    str or None
        What is weak and what to do: film with the camera rolled and the cards in the
        image's corners, or give the intrinsics.
    """
    if intrinsics_std is None:
        return None
    worst = float(max(intrinsics_std[1], intrinsics_std[2]))
    if not worst > PRINCIPAL_POINT_STD_PX:
        return None
    return (f"the lens's principal point is poorly determined (+/- {worst:.1f} px, 1 sigma): every pose is tilted by "
            f"as much; film again with the camera also rolled about its axis and cards in the corners of the image, "
            f"or give the camera's intrinsics")

