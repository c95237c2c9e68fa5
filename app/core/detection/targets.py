"""Targets from disc candidates (Claus & Fitzgibbon, WACV 2005, section 4, after the
learned disc stage): `assemble_targets` runs the stages, each in its own module.

1. Grouping (`grouping`): candidates joined into disc quadrilaterals, the 4-cycles of a
   graph of candidates that could be neighbouring discs of one card.
2. Verification (`verification`): each quadrilateral's card sampled through its
   homography and held to photometric checks, loosely before refinement.
3. Refinement (`refinement`): subpixel disc centres, then every check strictly.
4. Identification: the code read from the whole card (`code_reader`: every pixel against
   the rendered image of every code in all four rotations), checked against the quick
   nine-sample read (`identification`); the rotation gives the printed order of the discs.
5. Completion (`completion`): cards of which only three discs have candidates,
   proposed from those three and judged like the others.

Each id appears at most once and no candidate belongs to two targets (`_select`: the
best-scoring quadrilateral keeps them). Coordinates: full-resolution pixels, centre of
the top-left pixel at (0, 0). Discs of a target come in printed order: 0 top-left,
1 top-right, 2 bottom-right, 3 bottom-left, the card upright as its code defines.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.core.detection._frame import Pyramid, as_gray
from app.core.detection.completion import _MAX_SHIFT, _three_disc_cards
from app.core.detection.grouping import _Graph, _group
from app.core.detection.code_reader import MIN_MARGIN, SMEARED_MAX_READS, read_cards
from app.core.detection.identification import CLIPPED_WHITE_GREY, _PRINTED_ORDER, _decode
from app.core.detection.refinement import MAX_REFINE_SHIFT, refine_centres
from app.core.detection.verification import (
    MAX_DISC_LEVEL,
    MAX_DISC_SAMPLE,
    MAX_RADIUS_SPREAD,
    MAX_WHITE_SPREAD,
    MIN_GAP_LEVEL,
    MIN_WHITE_LOW,
    _measure,
    _Measures,
    _measures_from,
    _plan,
    _plan_and_quick,
    _predicted_radii,
    _quick_from,
    _radius_spread,
    _sample,
)
from app.core.geometry import homographies
from app.core.markers import DEFAULT_FAMILY, get_family

__all__ = ["DetectedTarget", "assemble_targets"]


@dataclass(frozen=True, eq=False)  # eq=False: ndarray fields make a generated __eq__ useless
class DetectedTarget:
    """One identified target in an image.

    Parameters
    ----------
    id : int
        The target's code id in its family.
    discs : ndarray, shape (4, 2)
        Subpixel disc centres (projections of the printed disc centres) in
        full-resolution pixels, in printed order.
    score : float
        Confidence 0..1: how clearly the weakest check passed.
    disc_radii : ndarray, shape (4,)
        Imaged disc radii in pixels (sqrt of the disc's dark area / pi).
    code_gap : float
        The nine-sample read's margin: how much worse the best other code (or rotation)
        fits the nine cell samples than this one (`identification.CodeMatch.gap`; below
        `CODE_GAP_MIN` when only the whole card was read); NaN when not known.
    read_margin : float
        The whole-card read's margin (`code_reader.CardReads.margin`): how much worse the
        best other printed pattern fits the card's pixels than this code, in units of the
        pixels' residual variance around a free fit of the card (twice the log-likelihood
        ratio); NaN when not known.
    """

    id: int
    discs: np.ndarray
    score: float
    disc_radii: np.ndarray = field(default_factory=lambda: np.zeros(4))
    code_gap: float = float("nan")
    read_margin: float = float("nan")

    def to_dict(self) -> dict[str, Any]:
        """The target as JSON-able values.

        Returns
        -------
        dict
            ``id``, ``discs`` (four ``[u, v]`` pairs), ``score`` and ``read_margin``
            (None when not known).
        """
        margin = float(self.read_margin)
        return {
            "id": int(self.id),
            "discs": [[float(u), float(v)] for u, v in np.asarray(self.discs, np.float64)],
            "score": float(self.score),
            "read_margin": round(margin, 1) if np.isfinite(margin) else None,
        }


def assemble_targets(gray: np.ndarray, candidates: np.ndarray, family: str = DEFAULT_FAMILY,
                     timing: dict[str, float] | None = None, counts: dict[str, int] | None = None,
                     pyramid: Sequence[np.ndarray] = ()) -> list[DetectedTarget]:
    """Identified targets in a frame from its disc candidates: group, verify, refine,
    identify, then complete cards of which only three discs have candidates.

    Parameters
    ----------
    gray : ndarray
        The frame: uint8 greyscale (other types and BGR are converted).
    candidates : ndarray, shape (N, 4)
        Disc candidates ``[u, v, radius, score]`` in full-resolution pixels.
    family : str
        The code family of the targets.
    timing : dict, optional
        Receives the milliseconds of each sub-stage: ``group``, ``verify``, ``refine``,
        ``identify``, ``complete``.
    counts : dict, optional
        Receives how many quadrilaterals each sub-stage kept: ``proposals``, ``quick``,
        ``verified``, ``identified``; ``completed``: targets found by completion,
        included in ``identified``.
    pyramid : sequence of ndarray
        The ``cv2.pyrDown`` levels of `gray` if already made (level 0 first), e.g. by
        the candidate stage.

    Returns
    -------
    list of DetectedTarget
        By id; each id at most once (the best-scoring quadrilateral keeps it) and no
        candidate in two targets. Degenerate input gives [].
    """
    fam = get_family(family)
    gray = as_gray(gray)
    cand = np.asarray(candidates, np.float64)
    clock = _Clock(timing, counts)
    if cand.ndim != 2 or cand.shape[0] < 3 or cand.shape[1] < 3:
        return []
    pyr = Pyramid(gray, built=pyramid)
    quads, graph = _group(cand, pyr.get(1), 0.5)
    clock.lap("group", proposals=quads.shape[0])
    out: list[DetectedTarget] = []
    used_ids: set[int] = set()
    used_cands: set[int] = set()
    judged: list[set[int]] = []
    smeared_left = SMEARED_MAX_READS
    if quads.shape[0]:
        res = _judge(gray, pyr, cand[quads, :2], fam.cells, family, smeared_left, clock)
        if res is not None:
            smeared_left -= res.smeared_reads
            judged = [set(q) for q in quads[res.keep].tolist()]
            out = _select(res, quads[res.keep], used_ids, used_cands)
    n_main = len(out)
    clock.lap("identify", identified=n_main)
    if graph is not None:
        out += _complete(gray, pyr, graph, out, used_ids, used_cands, judged, fam.cells, family, smeared_left)
    clock.lap("complete", identified=len(out), completed=len(out) - n_main)
    out.sort(key=lambda t: t.id)
    return out


class _Clock:
    """Sub-stage wall times (ms) and survivor counts of `assemble_targets`."""

    STAGES = ("group", "verify", "refine", "identify", "complete")
    COUNTS = ("proposals", "quick", "verified", "identified", "completed")

    def __init__(self, timing: dict[str, float] | None, counts: dict[str, int] | None) -> None:
        self.timing, self.counts = timing, counts
        if timing is not None:
            for k in self.STAGES:
                timing[k] = 0.0
        if counts is not None:
            for k in self.COUNTS:
                counts[k] = 0
        self.last = time.perf_counter()

    def lap(self, stage: str, **counts: int) -> None:
        now = time.perf_counter()
        if self.timing is not None:
            self.timing[stage] = (now - self.last) * 1e3
        if self.counts is not None:
            self.counts.update({k: int(v) for k, v in counts.items()})
        self.last = now


@dataclass(frozen=True, eq=False)
class _Judged:
    """What `_judge` found: the rows `keep` of the quadrilaterals that passed the coarse
    checks and were refined, and for those: whether each is a sound card (`ok`), its
    final measurements, whether its code was read (`decoded`) and as what (`ids`,
    `shifts`, the nine-sample read's `gap` and the whole card's `margin`), its refined
    disc centres and radii (layout orientation); and how many reads were tried against
    smeared cards."""

    keep: np.ndarray
    ok: np.ndarray
    measures: _Measures
    decoded: np.ndarray
    ids: np.ndarray
    shifts: np.ndarray
    gap: np.ndarray
    margin: np.ndarray
    refined: np.ndarray
    radii: np.ndarray
    smeared_reads: int


def _judge(gray: np.ndarray, pyr: Pyramid, pts: np.ndarray, n: int, family: str, smeared_reads: int,
           clock: _Clock | None = None, max_shift: np.ndarray | float = MAX_REFINE_SHIFT) -> _Judged | None:
    """Verify, refine and identify disc quadrilaterals `pts` (P, 4, 2) (layout
    orientation): None if none passes the coarse checks. `n`: the family's code has
    n x n cells; `smeared_reads`: at most this many cards get the whole-card fit with smears;
    `max_shift`: how far each disc may move in refinement, in predicted disc radii
    (scalar or (4,))."""
    hs = homographies(pts)
    # one sampling pass: the quick check's 16 points and the full plan
    plan = _plan(n)
    vals, inside = _sample(pyr, hs, _plan_and_quick(n))
    n_plan = plan.points.shape[0]
    quick = np.flatnonzero(_quick_from(vals[:, n_plan:], inside[:, n_plan:]))
    if quick.size == 0:
        if clock is not None:
            clock.lap("verify", quick=0)
        return None
    m = _measures_from(vals.take(quick, axis=0)[:, :n_plan], inside.take(quick, axis=0)[:, :n_plan], plan, cells=False)
    keep = quick[m.passed(coarse=True)]
    if clock is not None:
        clock.lap("verify", quick=quick.size, verified=keep.size)
    if keep.size == 0:
        return None
    pts = pts.take(keep, axis=0)
    refined, radii = refine_centres(gray, pts, _pyramid=pyr, _homographies=hs.take(keep, axis=0))
    if clock is not None:
        clock.lap("refine")
    hs = homographies(refined)
    m = _measure(pyr, hs, n)
    decoded, ids, shifts, _, gap = _decode(m.cells, family, m.white)
    ok = m.passed() & np.isfinite(refined).all(axis=(1, 2))
    # With the centres refined, every sample inside every disc must be dark (a disc
    # half hidden by another card, or a blob that is no disc, has light ones).
    ok &= m.disc_max <= MAX_DISC_SAMPLE
    # Refinement must stay on its candidate's disc (not be pulled to a neighbour):
    # within 80% of the disc radius the homography predicts (a candidate may sit ~0.6
    # radii off its disc).
    d = refined - pts
    moved = np.hypot(d[..., 0], d[..., 1])
    pred = _predicted_radii(hs)
    ok &= (moved <= np.maximum(2.0, np.asarray(max_shift) * pred)).all(axis=1)
    # Four points fix a homography exactly, so a disc of another card (an overlapping
    # one) or a half-hidden disc still gives a consistent-looking quadrilateral; its dark
    # area, though, disagrees with the size the homography predicts for it. Blur and
    # exposure scale all four alike, so only the spread of the ratios is tested.
    ok &= _radius_spread(pred, radii) <= MAX_RADIUS_SPREAD
    # Every sound card is read from its whole image (`code_reader.read_cards`), the
    # nine-sample read's code known to it: a read the nine samples contradict falls.
    sound = np.flatnonzero(ok)
    known = np.where(decoded[sound, None], np.stack([ids[sound], shifts[sound]], axis=1), -1)
    reads = read_cards(pyr, hs[sound], family, clipped=m.white[sound] >= CLIPPED_WHITE_GREY, known=known,
                       smeared=max(smeared_reads, 0))
    decoded = np.zeros_like(decoded)
    decoded[sound] = reads.ok
    ids[sound], shifts[sound] = reads.ids, reads.shifts
    margin = np.full(ok.shape, np.nan)
    margin[sound] = reads.margin
    return _Judged(keep=keep, ok=ok, measures=m, decoded=decoded, ids=ids, shifts=shifts, gap=gap, margin=margin,
                   refined=refined, radii=radii, smeared_reads=int(reads.smeared.sum()))


def _complete(gray: np.ndarray, pyr: Pyramid, g: _Graph, found: list[DetectedTarget], used_ids: set[int],
              used_cands: set[int], judged: list[set[int]], n: int, family: str, smeared_reads: int
              ) -> list[DetectedTarget]:
    """Targets completed from three discs (`completion`); `found`: the targets found
    already (no candidate on their cards is used); `used_ids`, `used_cands` (input
    rows) of those are honoured and updated; `judged`: the candidate sets of the
    quadrilaterals the main pass refined (a corner of one of them is not judged
    again)."""
    proposals = _three_disc_cards(gray, pyr, g, [t.discs for t in found], judged, n)
    if proposals is None:
        return []
    res = _judge(gray, pyr, proposals.discs, n, family, smeared_reads, max_shift=_MAX_SHIFT)
    if res is None:
        return []
    rows = proposals.rows[res.keep]
    # the predicted disc is no candidate: a distinct negative member per quadrilateral
    members = np.stack([rows[:, 0], rows[:, 1], -1 - np.arange(res.keep.size), rows[:, 2]], axis=1)
    return _select(res, members, used_ids, used_cands)


def _select(res: _Judged, quads: np.ndarray, used_ids: set[int], used_cands: set[int]) -> list[DetectedTarget]:
    """The sound, identified quadrilaterals of `res` (members `quads`: their rows of
    candidates), best score first, each id and candidate used once (`used_ids`,
    `used_cands`: taken already; updated)."""
    rows = np.flatnonzero(res.ok & res.decoded)
    if rows.size == 0:
        return []
    score = _score(res.measures, rows, res.margin)
    order = rows[np.argsort(-score, kind="stable")]
    score_of = dict(zip(rows.tolist(), score.tolist(), strict=True))
    out: list[DetectedTarget] = []
    for r in order.tolist():
        tid = int(res.ids[r])
        members = set(quads[r].tolist())
        if tid in used_ids or members & used_cands:
            continue
        used_ids.add(tid)
        used_cands |= members
        printed = _PRINTED_ORDER[res.shifts[r]]
        out.append(DetectedTarget(id=tid, discs=res.refined[r][printed], score=float(score_of[r]),
                                  disc_radii=res.radii[r][printed], code_gap=float(res.gap[r]),
                                  read_margin=float(res.margin[r])))
    return out


def _score(m: _Measures, rows: np.ndarray, margin: np.ndarray) -> np.ndarray:
    """Confidence 0..1 from how clearly each check passed (the weakest one)."""
    parts = np.array([
        margin[rows] / (4 * MIN_MARGIN) if margin.size else np.ones(rows.size),
        (MAX_DISC_LEVEL + 0.15 - m.disc_level[rows]) / (MAX_DISC_LEVEL + 0.15),
        (m.white_low[rows] - MIN_WHITE_LOW + 0.1) / (1.1 - MIN_WHITE_LOW),
        (m.gap_low[rows] - MIN_GAP_LEVEL + 0.1) / (1.1 - MIN_GAP_LEVEL),
        (MAX_WHITE_SPREAD + 0.1 - m.uniformity[rows]) / (MAX_WHITE_SPREAD + 0.1),
    ])
    return np.clip(parts, 0, 1).min(axis=0) ** 0.5
