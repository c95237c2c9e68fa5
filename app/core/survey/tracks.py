"""The survey's observations: the detections of the used frames, collected into tracks.

Every disc of every target id is one track (4 tracks per id); as in the paper (§5.1)
each disc gets its own 3D point, so cards that are not flat are surveyed as they are.
Detections that cannot be a view of a card are left out here, and each observation gets
its weight (`disc_precision`) from the shape of its disc's image.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from app.core.detection import DetectedTarget
from app.core.geometry import disc_axes
from app.core.survey.state import SurveyError, Tracks

#: Expected error of a disc centre (px per axis) against the minor semi-axis b of the
#: disc's image: ``DISC_ERROR_PX[0] + DISC_ERROR_PX[1] / b**2``. A thin disc is measured
#: worse (fewer pixels across, the card's edge and code closer). Fitted to the robust
#: spread (median 2-D error / 1.1774) of `disc_fit`'s centres by bins of b, over 4 rooms
#: x 1000 frames of the survey benchmark's walk: 0.030 px at b 1-1.25, 0.016 at
#: 1.5-1.75, 0.011 at 2-2.5, 0.008 at 3-3.5, 0.0066 at 4-5.
DISC_ERROR_PX = (0.0048, 0.032)


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


def collect_tracks(frames: Sequence[Sequence[DetectedTarget]], used: list[int], warnings: list[str]) -> Tracks:
    """Flatten the detections of the used frames into tracks.

    An id found twice in one frame is ambiguous there: its detections are dropped, as
    are detections that cannot be a card's face (`is_face`); a warning says how many.

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
    rows: list[tuple[int, int, np.ndarray]] = []
    duplicates = malformed = 0
    for fi, index in enumerate(used):
        seen: dict[int, int] = {}
        for det in frames[index]:
            seen[int(det.id)] = seen.get(int(det.id), 0) + 1
        for det in frames[index]:
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
    )
    if duplicates:
        warnings.append(f"{duplicates} detections of an id seen twice in the same frame were ignored "
                        "(two cards with the same id?)")
    if malformed:
        warnings.append(f"{malformed} detections whose discs do not form the card's square (mirrored or "
                        "folded) were ignored")
    if len(tracks.ids) == 0:
        raise SurveyError("no targets were detected in any frame of the video")
    views_per_frame = np.bincount(tracks.frame[::4], minlength=tracks.n_frames)
    if (views_per_frame > 0).sum() < 2:
        raise SurveyError("targets were detected in fewer than 2 frames: nothing to triangulate from")
    return tracks
