"""The survey's observations: the detections of the used frames, collected into tracks.

Every disc of every target id is one track (4 tracks per id); as in the paper (§5.1)
each disc gets its own 3D point, so cards that are not flat are surveyed as they are.
Detections that cannot be a view of a card are left out here, as are ids that are
probably misreads of another card's code (`probable_misreads`), and each observation gets
its weight (`disc_precision`) from the shape of its disc's image.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from app.core.detection import DetectedTarget
from app.core.geometry import disc_axes
from app.core.survey.state import Misread, SurveyError, Tracks

#: Expected error of a disc centre (px per axis) against the minor semi-axis b of the
#: disc's image: ``DISC_ERROR_PX[0] + DISC_ERROR_PX[1] / b**2``. A thin disc is measured
#: worse (fewer pixels across, the card's edge and code closer). Fitted to the robust
#: spread (median 2-D error / 1.1774) of `disc_fit`'s centres by bins of b, over 4 rooms
#: x 1000 frames of the survey benchmark's walk: 0.030 px at b 1-1.25, 0.016 at
#: 1.5-1.75, 0.011 at 2-2.5, 0.008 at 3-3.5, 0.0066 at 4-5.
DISC_ERROR_PX = (0.0048, 0.032)

#: A probable misread (`probable_misreads`): an id read in at most `MISREAD_MAX_FRAMES`
#: frames of the video, each read of it either where a card read in more frames is, or
#: weak (a code gap under `MISREAD_WEAK_GAP`) and alone (no read of the id within
#: `MISREAD_NEAR_FRAMES` frames of it). "Where a card is": within `MISREAD_SAME_PLACE`
#: times the read's image size (the mean of its diagonals) of that card's centre in the
#: same frame, or as predicted from the frames either side (f - 1, f + 1) or from the two
#: on one side. On the simulator's example walks (6 walk types x 6 rooms x 200 frames,
#: the survey's detector) a card's centre is within 0.33 diagonals of the mean of its
#: centres in the frames either side and within 0.67 of the line through two frames on
#: one side (max over 12000 and 24000 cases), while two cards in one frame are never
#: closer than 1.35 diagonals (22000 pairs). Of the 14600 true reads 3 % have a code gap
#: under 0.2, and of the 26 cards read in 3 frames or fewer only one (read once, gap
#: 0.15) is taken for a misread (at 0.3: 6); the wrong ids the code's acceptance rule
#: lets through have gaps just over its 0.15 (`CODE_GAP_MIN`; docs/benchmarks/detection.md:
#: one, at 0.176). Misreads put into those walks (a true read given another id) are all
#: found when weak (2160 of 2160), and 2098 of 2160 when read clearly (the others: the
#: true card not read in the frames around).
MISREAD_MAX_FRAMES = 3
MISREAD_WEAK_GAP = 0.2
MISREAD_NEAR_FRAMES = 2
MISREAD_SAME_PLACE = 0.9


def disc_precision(discs: np.ndarray) -> np.ndarray:
    """Weights of disc centres: the inverse of their expected variance (`DISC_ERROR_PX`).

    Parameters
    ----------
    discs : (T, 4, 2) ndarray
        The disc centres (px) of T views of a card.

    Returns
    -------
    (T, 4) ndarray
        The precision of each disc centre, px^-2: thin discs (a small minor semi-axis)
        weigh less.
    """
    b = np.maximum(disc_axes(discs)[..., 1], 0.5)
    sigma = DISC_ERROR_PX[0] + DISC_ERROR_PX[1] / b**2
    return 1.0 / sigma**2


def is_face(discs: np.ndarray) -> bool:
    """Whether 4 disc centres can be an image of a card's printed face.

    A convex quadrilateral turning the way the printed one does (perspective keeps
    both, a lens keeps them over a card's extent). A mirrored, folded or collinear quad
    is a broken detection, or a point beyond the edge of the lens's field that a
    distortion polynomial folds back into the image: either way no view of the card.

    Parameters
    ----------
    discs : (4, 2) ndarray
        Disc centres in the printed order.

    Returns
    -------
    bool
        True for a possible view of the card's face.
    """
    e = np.roll(discs, -1, axis=0) - discs
    turn = e[:, 0] * np.roll(e, -1, axis=0)[:, 1] - e[:, 1] * np.roll(e, -1, axis=0)[:, 0]
    return bool((turn > 0).all())


def subsample_frames(n: int, max_frames: int | None, step: int) -> list[int]:
    """The frames a survey uses: every ``step``-th, then at most ``max_frames``, evenly.

    Parameters
    ----------
    n : int
        Frames in the video.
    max_frames : int or None
        At most this many frames (None: no bound).
    step : int
        Take every ``step``-th frame first.

    Returns
    -------
    list of int
        Indices of the used frames, increasing.

    Raises
    ------
    SurveyError
        When ``max_frames`` is below 2.
    """
    used = list(range(0, n, max(1, int(step))))
    if max_frames is not None and len(used) > max_frames:
        if max_frames < 2:
            raise SurveyError("max_frames must be at least 2")
        pick = np.unique(np.linspace(0, len(used) - 1, int(max_frames)).round().astype(int))
        used = [used[i] for i in pick]
    return used


def _readable(detected: Sequence[DetectedTarget]) -> list[tuple[DetectedTarget, np.ndarray]]:
    """The detections of one frame a survey can use, with their discs: ids seen once in
    the frame, finite discs that can be a card's face (`is_face`)."""
    ids = [int(det.id) for det in detected]
    out = []
    for det in detected:
        discs = np.asarray(det.discs, np.float64).reshape(4, 2)
        if ids.count(int(det.id)) == 1 and np.isfinite(discs).all() and is_face(discs):
            out.append((det, discs))
    return out


def _predicted_centre(centres: dict[int, np.ndarray], f: int) -> np.ndarray | None:
    """A card's image centre in frame ``f`` from its centres by frame: its own, the mean
    of the frames either side, or the line through the two frames on one side."""
    if f in centres:
        return centres[f]
    if f - 1 in centres and f + 1 in centres:
        return 0.5 * (centres[f - 1] + centres[f + 1])
    for near, far in ((f - 1, f - 2), (f + 1, f + 2)):
        if near in centres and far in centres:
            return 2 * centres[near] - centres[far]
    return None


def _card_at(supported: dict[int, dict[int, np.ndarray]], f: int, discs: np.ndarray) -> int | None:
    """The card (of ``supported``: centres by frame, by id) whose image centre in frame
    ``f`` is that of ``discs`` (`MISREAD_SAME_PLACE`), the nearest; None when none is."""
    size = 0.5 * float(np.linalg.norm(discs[0] - discs[2]) + np.linalg.norm(discs[1] - discs[3]))
    near = sorted((float(np.linalg.norm(c - discs.mean(axis=0))), card) for card, centres in supported.items()
                  if (c := _predicted_centre(centres, f)) is not None)
    return near[0][1] if near and near[0][0] <= MISREAD_SAME_PLACE * size else None


def probable_misreads(frames: Sequence[Sequence[DetectedTarget]]) -> list[Misread]:
    """The ids that are probably misreads of another card's code, not cards.

    A misread puts a wrong id on a true card's image: the id turns up in a frame or two
    and no more, where another card is seen in the frames around, or with a weak code.
    An id read in at most `MISREAD_MAX_FRAMES` frames is taken for one when each read of
    it lies where a card read in more frames is (`MISREAD_SAME_PLACE`), or is weak (its
    code gap under `MISREAD_WEAK_GAP`) with no other read of the id within
    `MISREAD_NEAR_FRAMES` frames. An id read clearly where no other card is, or weakly
    but in frames running, is a card seen briefly, not a misread.

    Parameters
    ----------
    frames : sequence of sequences of DetectedTarget
        The detected targets of each frame of the video, in order.

    Returns
    -------
    list of Misread
        By id: its frames (indices into ``frames``), the card seen where it was read
        (None when its reads were weak but nowhere near another card) and whether every
        read was weak.
    """
    centres: dict[int, dict[int, np.ndarray]] = {}
    reads: dict[int, list[tuple[int, DetectedTarget, np.ndarray]]] = {}
    for f, detected in enumerate(frames):
        for det, discs in _readable(detected):
            centres.setdefault(int(det.id), {})[f] = discs.mean(axis=0)
            reads.setdefault(int(det.id), []).append((f, det, discs))
    supported = {i: c for i, c in centres.items() if len(c) > MISREAD_MAX_FRAMES}
    out: list[Misread] = []
    for card, its in sorted(reads.items()):
        if card in supported:
            continue
        seen_in = [f for f, _, _ in its]
        twins: list[int] = []
        for f, det, discs in its:
            twin = _card_at(supported, f, discs)
            weak = float(det.code_gap) < MISREAD_WEAK_GAP  # NaN (not known): not weak
            alone = all(g == f or abs(g - f) > MISREAD_NEAR_FRAMES for g in seen_in)
            if twin is None and not (weak and alone):
                break
            if twin is not None:
                twins.append(twin)
        else:
            of_id = max(sorted(set(twins)), key=twins.count) if twins else None
            weak_all = all(float(det.code_gap) < MISREAD_WEAK_GAP for _, det, _ in its)
            out.append(Misread(card, tuple(seen_in), of_id, weak_all))
    return out


def collect_tracks(frames: Sequence[Sequence[DetectedTarget]], used: list[int], warnings: list[str]) -> Tracks:
    """Flatten the detections of the used frames into tracks.

    An id found twice in one frame is ambiguous there: its detections are dropped, as
    are detections that cannot be a card's face (`is_face`); a warning says how many.
    The ids that are probably misreads (`probable_misreads`, judged over every frame of
    the video) are left out, and listed in the tracks' ``misreads``.

    Parameters
    ----------
    frames : sequence of sequences of DetectedTarget
        The detected targets of each frame of the video.
    used : list of int
        The frames to use (`subsample_frames`).
    warnings : list of str
        Warnings for the user; appended to.

    Returns
    -------
    Tracks
        The observations, frames numbered by their position in ``used``.

    Raises
    ------
    SurveyError
        When no target is left, or targets are seen in fewer than 2 frames.
    """
    misreads = probable_misreads(frames)
    misread_ids = {m.id for m in misreads}
    rows: list[tuple[int, int, np.ndarray]] = []
    duplicates = malformed = 0
    for fi, index in enumerate(used):
        seen: dict[int, int] = {}
        for det in frames[index]:
            seen[int(det.id)] = seen.get(int(det.id), 0) + 1
        for det in frames[index]:
            if int(det.id) in misread_ids:
                continue
            discs = np.asarray(det.discs, np.float64).reshape(4, 2)
            if seen[int(det.id)] > 1 or not np.isfinite(discs).all():
                duplicates += 1
                continue
            if not is_face(discs):
                malformed += 1
                continue
            rows.append((fi, int(det.id), discs))
    ids = np.array(sorted({r[1] for r in rows}), dtype=int)
    lookup = {int(i): k for k, i in enumerate(ids)}
    n = len(rows)
    tracks = Tracks(
        frame=np.repeat(np.array([r[0] for r in rows], int), 4) if n else np.zeros(0, int),
        target=np.repeat(np.array([lookup[r[1]] for r in rows], int), 4) if n else np.zeros(0, int),
        disc=np.tile(np.arange(4), n),
        uv=np.concatenate([r[2] for r in rows]) if n else np.zeros((0, 2)),
        ids=ids,
        n_frames=len(used),
        precision=disc_precision(np.array([r[2] for r in rows])).ravel() if n else np.zeros(0),
        misreads=tuple(misreads),
    )
    if duplicates:
        warnings.append(f"{duplicates} detections of an id seen twice in the same frame were ignored "
                        "(two cards with the same id?)")
    if malformed:
        warnings.append(f"{malformed} detections whose discs do not form the card's square (mirrored or "
                        "folded) were ignored")
    if len(tracks.ids) == 0:
        only = (f" (only ids taken for misreads of other cards' codes: {', '.join(str(m.id) for m in misreads)})"
                if misreads else "")
        raise SurveyError(f"no targets were detected in any frame of the video{only}")
    views_per_frame = np.bincount(tracks.frame[::4], minlength=tracks.n_frames)
    if (views_per_frame > 0).sum() < 2:
        raise SurveyError("targets were detected in fewer than 2 frames: nothing to triangulate from")
    return tracks
