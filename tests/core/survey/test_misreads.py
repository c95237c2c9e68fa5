"""Misreads are not cards: an id read in a frame or two, weakly or where another card is,
is told as a probable misread with its frames, and stays out of the map and of the advice
on what to film; a card seen briefly with clear reads is still a card."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from app.core.detection import DetectedTarget
from app.core.survey import SurveyResult, WarningKind, survey
from app.core.survey import tracks as survey_tracks
from app.core.survey.advice import misread_advice
from app.core.survey.state import Misread
from tests.core.survey.conftest import SURVEY_ROOM

Frames = list[list[DetectedTarget]]

#: An id that no card of the room has.
MISREAD_ID = 40
#: A misread's code margin: just over the acceptance threshold (`CODE_GAP_MIN`).
WEAK_GAP = 0.17
#: A clear read's.
STRONG_GAP = 0.6


def _read(det: DetectedTarget, card: int, gap: float) -> DetectedTarget:
    """``det``'s discs read as ``card`` with a code gap of ``gap``."""
    return DetectedTarget(card, det.discs.copy(), det.score, code_gap=gap)


def _frames_of(frames: Frames, card: int) -> list[int]:
    return [f for f, detected in enumerate(frames) if any(t.id == card for t in detected)]


def _busiest_card(frames: Frames) -> tuple[int, int]:
    """A card and a frame in the middle of a run of 5 frames that see it."""
    for f in range(2, len(frames) - 2):
        for t in frames[f]:
            if all(any(u.id == t.id for u in frames[g]) for g in range(f - 2, f + 3)):
                return t.id, f
    raise AssertionError("no card seen in 5 frames running")


def _only_once(frames: Frames, card: int) -> int:
    """Leave ``card`` in the middle one of its frames only, read clearly there; that frame."""
    seen = _frames_of(frames, card)
    keep = seen[len(seen) // 2]
    for f in seen:
        frames[f] = [_read(t, card, STRONG_GAP) if t.id == card else t for t in frames[f] if t.id != card or f == keep]
    return keep


def _place_of(frames: Frames, f: int, card: int) -> DetectedTarget:
    return next(t for t in frames[f] if t.id == card)


def test_a_weak_read_on_another_cards_place_is_a_misread(synthetic_frames: Callable[[float, int], Frames]) -> None:
    """The usual misread: a true card's image read as another id in one frame (the true
    card is not read there, but is in the frames around)."""
    frames = synthetic_frames(0.05, 0)
    card, f = _busiest_card(frames)
    frames[f] = [_read(t, MISREAD_ID, WEAK_GAP) if t.id == card else t for t in frames[f]]
    assert survey_tracks.probable_misreads(frames) == [Misread(MISREAD_ID, (f,), card, True)]


def test_a_clear_read_on_another_cards_place_is_a_misread(synthetic_frames: Callable[[float, int], Frames]) -> None:
    """Where it was read says enough: its discs coincide with a card seen in many frames
    (here in the same frame), whatever its code's margin."""
    frames = synthetic_frames(0.05, 0)
    card, f = _busiest_card(frames)
    frames[f].append(_read(_place_of(frames, f, card), MISREAD_ID, STRONG_GAP))
    assert survey_tracks.probable_misreads(frames) == [Misread(MISREAD_ID, (f,), card, False)]


def _nowhere(frames: Frames, f: int) -> np.ndarray:
    """Discs of a small card in a corner of frame ``f`` far from every card read in the
    frames around it."""
    square = np.array([[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]])
    near = np.array([t.discs.mean(axis=0) for g in range(f - 2, f + 3) for t in frames[g]]).reshape(-1, 2)
    grid = np.stack(np.meshgrid(np.arange(20.0, 620.0, 20.0), np.arange(20.0, 460.0, 20.0)), axis=-1).reshape(-1, 2)
    clearance = np.linalg.norm(grid[:, None] - near[None], axis=2).min(axis=1, initial=np.inf)
    assert clearance.max() > 100, f"no empty place in frame {f}"
    return square + grid[np.argmax(clearance)]


def test_weak_reads_nowhere_near_a_card_are_misreads(synthetic_frames: Callable[[float, int], Frames]) -> None:
    """Two weak reads of an id where no card is read: misreads of something the detector
    did not otherwise see (none of the other cards' places)."""
    frames = synthetic_frames(0.05, 0)
    at = (20, 50)
    for f in at:
        frames[f].append(DetectedTarget(MISREAD_ID, _nowhere(frames, f), 0.5, code_gap=WEAK_GAP))
    assert survey_tracks.probable_misreads(frames) == [Misread(MISREAD_ID, at, None, True)]
    # Read clearly there, it is a card seen briefly.
    for f in at:
        frames[f][-1] = DetectedTarget(MISREAD_ID, frames[f][-1].discs, 0.5, code_gap=STRONG_GAP)
    assert survey_tracks.probable_misreads(frames) == []


def test_a_card_read_clearly_in_one_frame_is_a_card(synthetic_frames: Callable[[float, int], Frames]) -> None:
    """Seen once, with a clear code, where no other card is: a card seen briefly."""
    frames = synthetic_frames(0.05, 0)
    _only_once(frames, 15)
    assert survey_tracks.probable_misreads(frames) == []
    # Known or not, a margin that is no evidence of a misread keeps it a card.
    frames = [[DetectedTarget(t.id, t.discs, t.score) for t in detected] for detected in frames]
    assert survey_tracks.probable_misreads(frames) == []


def test_weak_reads_in_frames_running_are_a_card(synthetic_frames: Callable[[float, int], Frames]) -> None:
    """Every read weak: the cards read in many frames are cards, and so is card 11, read
    in 3 frames running only (a card whose code reads poorly, seen briefly)."""
    frames = synthetic_frames(0.05, 0)
    frames = [[_read(t, t.id, WEAK_GAP) for t in detected] for detected in frames]
    assert len(_frames_of(frames, 11)) <= survey_tracks.MISREAD_MAX_FRAMES
    assert survey_tracks.probable_misreads(frames) == []
    # Left with one of those frames, it is a weak read alone: a misread.
    for f in _frames_of(frames, 11)[1:]:
        frames[f] = [t for t in frames[f] if t.id != 11]
    assert [(m.id, m.of_id, m.weak) for m in survey_tracks.probable_misreads(frames)] == [(11, None, True)]


def test_the_misread_warning_names_the_id_and_its_frames() -> None:
    weak, placed = misread_advice((Misread(40, (112,), None, True), Misread(41, (7, 8), 12, False)))
    assert (weak.kind, weak.target_ids, weak.frames) == (WarningKind.MISREAD, (40,), (112,))
    assert weak.message.startswith("id 40 was read in frame 112 only, with a weak code: probably a misread of "
                                   "another card, so it is not in the map")
    assert (placed.target_ids, placed.frames) == ((41,), (7, 8))
    assert "in frames 7 and 8 only, where card 12 is seen in the frames around it: probably a misread of card 12" \
        in placed.message
    assert "film it again" not in weak.message + placed.message


@pytest.fixture(scope="module")
def misread_survey(synthetic_frames: Callable[[float, int], Frames]
                   ) -> tuple[Frames, Frames, int, int, SurveyResult]:
    """The small room's walk with card 15 read clearly in one frame only, and the same
    with an id no card has read weakly, once, on a card's place (its discs on that
    card's): the frames without and with the misread, the misread's frame, the card it
    was read on, and the survey of the frames with it."""
    clean = synthetic_frames(0.05, 0)
    _only_once(clean, 15)
    card, f = _busiest_card(clean)
    frames = [list(detected) for detected in clean]
    frames[f].append(_read(_place_of(frames, f, card), MISREAD_ID, WEAK_GAP))
    cam = SURVEY_ROOM.camera
    return clean, frames, f, card, survey(frames, cam.width, cam.height, SURVEY_ROOM.marker_size_m)


def test_a_misread_is_no_card_and_nothing_to_film(misread_survey: tuple[Frames, Frames, int, int, SurveyResult]
                                                  ) -> None:
    _, _, f, card, result = misread_survey
    assert MISREAD_ID not in {t.id for t in result.targets}
    about = [w for w in result.map_warnings if MISREAD_ID in w.target_ids]
    assert [(w.kind, w.target_ids, w.frames) for w in about] == [(WarningKind.MISREAD, (MISREAD_ID,), (f,))]
    assert about[0].message.startswith(f"id {MISREAD_ID} was read in frame {f} only, with a weak code, where card "
                                       f"{card} is seen in the frames around it: probably a misread of card {card}")
    assert not any(f"card {MISREAD_ID} could not" in text or f"card {MISREAD_ID}:" in text for text in result.warnings)
    assert about[0].message in result.warnings
    summary = result.summary()["card_warnings"]
    assert {"kind": "probable misread", "target_ids": [MISREAD_ID], "message": about[0].message,
            "frames": [f]} in summary


def test_a_card_seen_briefly_is_still_advised(misread_survey: tuple[Frames, Frames, int, int, SurveyResult]) -> None:
    _, _, _, _, result = misread_survey
    not_surveyed = [w for w in result.map_warnings if w.kind is WarningKind.NOT_SURVEYED]
    assert [w.target_ids for w in not_surveyed] == [(15,)]
    assert "card 15 could not be surveyed" in not_surveyed[0].message
    assert [w.target_ids for w in result.map_warnings if w.kind is WarningKind.MISREAD] == [(MISREAD_ID,)]


def test_the_map_is_what_it_is_without_the_misread(misread_survey: tuple[Frames, Frames, int, int, SurveyResult]
                                                   ) -> None:
    """The misread's detections are left out: the observations the map is made of are
    those of the walk without it, and every card of that walk is mapped but the one
    seen once."""
    clean, frames, _, card, result = misread_survey
    used = list(range(len(frames)))
    with_misread, without = survey_tracks.collect_tracks(frames, used, []), survey_tracks.collect_tracks(clean, used, [])
    for name in ("frame", "target", "disc", "uv", "ids", "precision"):
        np.testing.assert_array_equal(getattr(with_misread, name), getattr(without, name))
    assert [m.id for m in with_misread.misreads] == [MISREAD_ID] and without.misreads == ()
    assert {t.id for t in result.targets} == set(without.ids.tolist()) - {15}
    assert card in {t.id for t in result.targets}
