"""Completion: cards of which only three discs have usable candidates.

A card whose fourth disc has no candidate (blur merged it with its surroundings, a
highlight, the candidate stage's miss) or a candidate the grouping cannot use (radius
off by more than `grouping.RADIUS_RATIO_MAX`) is proposed from the other three: every
corner of card sides (apex i with neighbours j, l; the grouping's corner checks) among
the candidates no found target uses, its fourth disc predicted by the parallelogram
j + l - i (`_three_disc_cards`). A corner must pass a cheap look at pyramid level 1 and
an affine read of the card (`_corner_triples`); the driver (`targets.assemble_targets`)
then judges the proposal exactly like the grouping's (coarse verification, refinement,
which pulls the predicted disc onto the dark disc, the strict checks, identification):
the predicted disc is held to the same photometric checks as a candidate's, and may
move further in refinement (`COMPLETE_REFINE_SHIFT`). The affine points are computed
in one compiled loop (`_completion_kernels.affine_points`).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from app.core.detection import _completion_kernels as kernels
from app.core.detection._frame import Pyramid
from app.core.detection.grouping import SIDE_WHITE_MIN, _NEXT, _Graph
from app.core.detection.refinement import MAX_REFINE_SHIFT
from app.core.detection.verification import (
    MIN_CONTRAST_GREY,
    NOISE_SPREAD_GREY,
    QUICK_DISC,
    _mean,
    _measures_from,
    _plan,
)
from app.core.markers import DISC_CENTRES, DISC_RADIUS

__all__ = [
    "COMPLETE_MAX",
    "COMPLETE_REFINE_SHIFT",
    "CORNER_FOURTH_LEVEL",
    "CORNER_GAP_LEVEL",
    "CORNER_RING",
    "CORNER_WHITE_LOW",
    "CORNER_WHITE_SPREAD",
]

#: At most this many corners per frame are proposed (the first in the grouping's
#: corner order: apex by apex).
COMPLETE_MAX = 8
#: A completed disc may move this far in refinement (predicted disc radii; the
#: parallelogram prediction is off by perspective).
COMPLETE_REFINE_SHIFT = 1.5
#: How far each disc of a completed card may move in refinement, in predicted disc
#: radii: the predicted disc (vertex 2) further than a candidate's.
_MAX_SHIFT = np.array([MAX_REFINE_SHIFT, MAX_REFINE_SHIFT, COMPLETE_REFINE_SHIFT, MAX_REFINE_SHIFT])
#: The predicted fourth disc: at most this far above the mean of the three discs, in
#: the contrast between them and the white of the card's sides (the parallelogram
#: prediction may sit off the disc).
CORNER_FOURTH_LEVEL = 0.5
#: `_corner_look`: looser than the coarse verification (an affine guess of a card).
CORNER_WHITE_SPREAD = 0.5
CORNER_GAP_LEVEL = 0.45
CORNER_WHITE_LOW = 0.35
#: Ring points of `_corner_look` around the three discs that have candidates: 1.45 disc
#: radii out, towards the inside of the card only (the affine guess is off by
#: perspective; outwards the card edge is near).
CORNER_RING = 1.45


@dataclass(frozen=True, eq=False)
class _Proposals:
    """Cards proposed from three discs: their disc points (T, 4, 2) in the layout's
    orientation, a parallelogram whose vertex 2 is the predicted disc, and the input
    rows (T, 3) of the candidates at vertices 0, 1 and 3."""

    discs: np.ndarray
    rows: np.ndarray


def _three_disc_cards(gray: np.ndarray, pyr: Pyramid, g: _Graph, found: Sequence[np.ndarray],
                      judged: list[set[int]], n: int) -> _Proposals | None:
    """Cards to complete from three discs (None if there are none): the corners
    (`_corner_triples`, at most `COMPLETE_MAX`) of candidates free of the cards found
    already (`found`: their disc centres (4, 2), clockwise on screen) that are no
    corner of a quadrilateral the grouping's proposals refined (`judged`: their sets of
    input rows); `n`: the family's code has n x n cells."""
    free = np.ones(g.idx.size, bool)
    if found:
        # nothing on a card found already (its discs, its code cells) is free: inside the
        # card outline, approximated by the disc quadrilateral scaled about its centre by
        # 0.5 / 0.3 (a little more)
        q = np.array(found)  # (F, 4, 2), clockwise on screen
        cen = _mean(q, 1)[:, None]
        c = cen + 1.7 * (q - cen)
        e = c[:, _NEXT] - c  # (F, 4, 2) outline edges
        d = g.pts[None, None, :, :] - c[:, :, None, :]  # (F, 4, N, 2)
        inside = (e[:, :, None, 0] * d[..., 1] - e[:, :, None, 1] * d[..., 0] >= 0).all(axis=1).any(axis=0)
        free &= ~inside
    i, j, l_, pred = _corner_triples(g, free, pyr.get(1), 0.5, gray, n)
    if i.size and judged:
        trip = zip(g.idx[i].tolist(), g.idx[j].tolist(), g.idx[l_].tolist(), strict=True)
        fresh = np.array([not any(a in q and b in q and c in q for q in judged) for a, b, c in trip])
        i, j, l_, pred = i[fresh], j[fresh], l_[fresh], pred[fresh]
    if i.size == 0:
        return None
    if i.size > COMPLETE_MAX:
        i, j, l_, pred = i[:COMPLETE_MAX], j[:COMPLETE_MAX], l_[:COMPLETE_MAX], pred[:COMPLETE_MAX]
    p = g.pts
    discs = np.stack([p[i], p[j], pred, p[l_]], axis=1)  # (T, 4, 2) layout orientation: a parallelogram
    return _Proposals(discs=discs, rows=np.stack([g.idx[i], g.idx[j], g.idx[l_]], axis=1))


def _corner_triples(g: _Graph, free: np.ndarray, img: np.ndarray, scale: float, full: np.ndarray | None = None,
                    n_cells: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Corners of a possible card among the free candidates (local indices): apex
    triples (i, j, l), j following i clockwise on screen and l preceding it, that pass
    the grouping's corner checks and a cheap look at `img` (a pyramid level, `scale`
    its pixels per full-resolution pixel): both apex sides look like card sides (white
    between two dark discs, `SIDE_WHITE_MIN`) and the predicted fourth disc j + l - i is
    dark (`CORNER_FOURTH_LEVEL`) with white halfway to it from j and from l; then, if
    `full` (the full-resolution image) is given, the card the parallelogram i, j,
    j + l - i, l spans (the layout mapped affinely) is read there: `_corner_look`, then
    the coarse verification (`_Measures.passed`; codes of `n_cells` x `n_cells`).
    Returns i, j, l and the predictions (T, 2)."""
    z = np.zeros(0, np.intp)
    none = z, z, z, np.zeros((0, 2))
    if g.corners is None or g.corner_white is None or g.dark is None:
        return none
    # the grouping's corners (`_Graph.corners`) of free candidates only
    sel = np.flatnonzero(free.take(g.corners).all(axis=0))
    if sel.size == 0:
        return none
    tri = g.corners.take(sel, axis=1)  # (3, T): i, j, l
    i, j, l_ = tri
    pi, pj, pl = g.pts.take(tri, axis=0)  # (T, 2) each
    pred = pj + pl - pi
    dark = g.dark.take(tri)
    black = (dark[0] + dark[1] + dark[2]) * (1.0 / 3.0)
    con = g.corner_white.take(sel) - black
    # the fourth disc, and halfway to it from j and from l (the other two sides)
    q = (np.concatenate([pred, 0.5 * (pj + pred), 0.5 * (pl + pred)]) * scale).astype(np.float32).reshape(1, -1, 2)
    look4 = cv2.remap(img, q, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(3, -1).astype(np.float32)
    ok = look4[0] - black <= CORNER_FOURTH_LEVEL * con
    ok &= np.minimum(look4[1], look4[2]) - black >= SIDE_WHITE_MIN * con
    sel = np.flatnonzero(ok)
    if sel.size == 0:
        return none
    if full is not None:
        # a first look at the card (a parallelogram: the layout maps affinely) on `full`
        pi, pj, pl = pi.take(sel, axis=0), pj.take(sel, axis=0), pl.take(sel, axis=0)
        hf, wf = full.shape
        xy, _ = kernels.affine_points(pi, pj, pl, _corner_look_points(), wf, hf)
        vals = cv2.remap(full, xy, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        look = np.flatnonzero(_corner_look(vals.astype(np.float32)))
        sel = sel.take(look)
        if sel.size:
            # then the coarse verification, on the same affine guess
            pi, pj, pl = pi.take(look, axis=0), pj.take(look, axis=0), pl.take(look, axis=0)
            xy, inside = kernels.affine_points(pi, pj, pl, _plan_affine(n_cells), wf, hf)
            vals = cv2.remap(full, xy, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            coarse = _measures_from(vals.astype(np.float32), inside, _plan(n_cells), cells=False).passed(coarse=True)
            sel = sel.compress(coarse)
    return i.take(sel), j.take(sel), l_.take(sel), pred.take(sel, axis=0)


@functools.cache
def _plan_affine(n: int) -> np.ndarray:
    """The points of `_plan(n)` as affine coefficients along the sides from disc 0 to
    discs 1 and 3."""
    return (_plan(n).points - DISC_CENTRES[0]) / (DISC_CENTRES[2] - DISC_CENTRES[0])


@functools.cache
def _corner_look_points() -> np.ndarray:
    """(37, 2) affine coefficients (along the sides from disc 0 to discs 1 and 3) of
    the points `_corner_look` reads: the 4 disc centres, 12 between discs, 12 in the
    gap around the code, 9 on rings around discs 0, 1 and 3."""
    plan = _plan(3)
    ring = []
    for k in (0, 1, 3):
        inward = np.sign(0.5 - DISC_CENTRES[k])  # towards the card centre
        for d in ([inward[0], 0.0], [0.0, inward[1]], inward / np.sqrt(2.0)):
            ring.append(DISC_CENTRES[k] + CORNER_RING * DISC_RADIUS * np.asarray(d))
    pts = np.concatenate([DISC_CENTRES, plan.points[plan.between], plan.points[plan.gap], np.array(ring)])
    return (pts - DISC_CENTRES[0]) / (DISC_CENTRES[2] - DISC_CENTRES[0])


def _corner_look(vals: np.ndarray) -> np.ndarray:
    """bool (T,): samples (T, 37) of `_corner_look_points`: dark discs, and white
    between them, around the code and around the discs, uniform (the coarse checks of
    `_Measures`, looser)."""
    disc = vals[:, :4]
    black = _mean(disc, 1)
    w = np.sort(vals[:, 4:28], axis=1)  # 24 between and in the gap
    white = 0.5 * (w[:, 11] + w[:, 12])
    c = white - black
    cn = np.maximum(c, 1e-3)
    ok = (c >= MIN_CONTRAST_GREY) & (disc.max(axis=1) - black <= QUICK_DISC * cn)
    spread = _quantile_sorted(w, 0.9) - _quantile_sorted(w, 0.1)
    ok &= spread <= np.maximum(CORNER_WHITE_SPREAD * cn, NOISE_SPREAD_GREY)
    ok &= np.sort(vals[:, 16:28], axis=1)[:, 1] - black >= CORNER_GAP_LEVEL * cn
    allw = np.sort(vals[:, 4:], axis=1)  # 33
    ok &= _quantile_sorted(allw, 0.1) - black >= CORNER_WHITE_LOW * cn
    return ok


def _quantile_sorted(v: np.ndarray, q: float) -> np.ndarray:
    """Quantile q of each row of the row-sorted array v (linear interpolation)."""
    pos = q * (v.shape[1] - 1)
    lo = int(np.floor(pos))
    hi = min(lo + 1, v.shape[1] - 1)
    return v[:, lo] + (pos - lo) * (v[:, hi] - v[:, lo])
