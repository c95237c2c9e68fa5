"""Checks of the finished map against what it could have got wrong unseen (survey step 6).

A survey with feature tracks links frames that see no card through the walls between
them. Through a long stretch of such frames the trajectory drifts, and what is placed at
the far end of it (a card, or the lens that fits best) inherits the drift while still
fitting its own views: the reprojection error does not show it. Two checks find it from
evidence the drift does not bend:

* `lens_agreement`: the lens the map settled on against the one the cards' own
  perspective gives (`lens.lens_from_cards`, every card view on its own, no trajectory
  involved). A chain of frames that drifted bends the map, and the focal length takes up
  part of the bend.
* `uncertain_cards`: each card's uncertainty (`std_m`, with each feature track's views
  counted as one observation's worth: `bundle`'s covariance) against what a map is for.
  A card reached only through seconds of card-less frames is uncertain by centimetres,
  and is named, not silently kept.

And one that needs no drift: a lens fitted from fewer than `MIN_LENS_FRAMES` registered
frames is warned about whatever its reported uncertainty (`few_frames_lens_message`).

numpy only; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The map's focal length may differ from the cards' own estimate by this fraction
#: before the lens is judged wrong. The cards' estimate alone is within 1.4 % of the
#: truth on the example walks (sparse and centre-loop rooms, 150-670 card views), 3.2 %
#: with a few misread cards among them; a drifted map moves the focal length by tens
#: of percent.
LENS_AGREEMENT = 0.05
#: A focal length more uncertain than this fraction (1 sigma) gets a warning: a focal
#: length off by 0.5 % moves a camera 15 mm along its axis at 3 m.
FOCAL_STD_FRACTION = 0.0015
#: A card more uncertain than this (the largest of its discs' std_m, metres) is named.
UNCERTAIN_CARD_M = 0.01
#: A lens fitted from fewer registered frames than this gets a warning whatever its
#: reported uncertainty: on the example walks every such lens (11-18 frames of one to
#: three cards) was 2.6-5 % off, and the covariance, which holds the disc centres' noise
#: but not their bias, said 0.15 % or less for some of them.
MIN_LENS_FRAMES = 20


@dataclass(frozen=True)
class LensAgreement:
    """The map's focal length against the cards' own."""

    map_focal_px: float
    card_focal_px: float

    @property
    def difference(self) -> float:
        """The relative difference, map over cards minus one."""
        return self.map_focal_px / self.card_focal_px - 1.0

    @property
    def agrees(self) -> bool:
        """Whether the two agree within `LENS_AGREEMENT`."""
        return bool(abs(self.difference) <= LENS_AGREEMENT)

    def message(self) -> str:
        """Why a survey whose lens disagrees is refused, and what to film.

        Returns
        -------
        str
            The sentence for the user: both focal lengths, the difference, what to film.
        """
        return (f"the lens could not be calibrated reliably: the map's focal length ({self.map_focal_px:.0f} px) and "
                f"the one the cards' own shapes give ({self.card_focal_px:.0f} px) differ by "
                f"{100 * abs(self.difference):.0f} %, so the camera drifted through stretches of the video where no "
                f"card was in view; film again with two or more cards in view in most frames and no long stretch "
                f"without a card, or give the camera's intrinsics")


def focal_std_message(focal_px: float, focal_std_px: float) -> str | None:
    """The warning for a focal length the survey could not pin down, or None.

    Parameters
    ----------
    focal_px, focal_std_px : float
        The focal length and its standard deviation, px.

    Returns
    -------
    str or None
        What is weak and what to do.
    """
    if not focal_std_px > FOCAL_STD_FRACTION * focal_px:
        return None
    return (f"the lens's focal length is poorly determined (+/- {100 * focal_std_px / focal_px:.1f} %, 1 sigma): "
            f"distances along the camera's axis are off by as much; film the cards from more directions and "
            f"distances, with two or more cards in view, or give the camera's intrinsics")


def few_frames_lens_message(n_frames: int) -> str | None:
    """The warning for a lens fitted from too few frames to trust, or None.

    Parameters
    ----------
    n_frames : int
        The registered frames the lens was fitted from.

    Returns
    -------
    str or None
        What is weak and what to do, below `MIN_LENS_FRAMES` frames.
    """
    if n_frames >= MIN_LENS_FRAMES:
        return None
    return (f"the lens was calibrated from only {n_frames} registered frames (fewer than {MIN_LENS_FRAMES}): its focal "
            f"length can be several percent off, and distances along the camera's axis with it; film again with two "
            f"or more cards in view in most frames, or give the camera's intrinsics")


def uncertain_cards(ids: list[int], std_m: list[np.ndarray]) -> list[tuple[int, float]]:
    """The cards more uncertain than `UNCERTAIN_CARD_M`, with their largest disc std_m.

    Parameters
    ----------
    ids : list of int
        The cards' printed ids.
    std_m : list of (4,) ndarray
        Each card's discs' std_m (metres).

    Returns
    -------
    list of (int, float)
        (id, the largest std_m) of each uncertain card, in the order given.
    """
    out = []
    for card, std in zip(ids, std_m, strict=True):
        worst = float(np.nanmax(std)) if np.isfinite(std).any() else float("inf")
        if not worst <= UNCERTAIN_CARD_M:
            out.append((card, worst))
    return out
