"""Which targets of a rendered frame count: the truth a detector is scored against.

The simulator's `TargetTruth.visible` looks at each card alone (in front, inside the
image, facing the camera, not occluded by a drawn occluder); a card can still hide
behind a nearer one. `truth_cards` recovers each card's outline from its reference
points and counts a target only when its footprint lies in the image and no nearer
card overlaps it. The test is the same whatever is printed on the card (our discs or a
peer's tag, `CardArtwork`), so every detector is counted on the same targets.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from app.core.markers import DEFAULT_FAMILY, marker_layout
from app.sim.scenes import CardArtwork, FrameTruth

__all__ = ["BORDER_PX", "FOOTPRINT_HI", "FOOTPRINT_LO", "FOOTPRINT_UV", "TruthCard", "truth_cards"]

#: A counted card's footprint lies at least this far inside the image (px), as the
#: simulator's visibility test.
BORDER_PX = 2.0
#: The footprint: the square 0.075..0.925 of the card, the outer extent of our discs
#: (0.2 - 0.125 .. 0.8 + 0.125); a peer's tag prints its black square over exactly this.
FOOTPRINT_LO, FOOTPRINT_HI = 0.075, 0.925
FOOTPRINT_UV = np.array([[FOOTPRINT_LO, FOOTPRINT_LO], [FOOTPRINT_HI, FOOTPRINT_LO], [FOOTPRINT_HI, FOOTPRINT_HI],
                         [FOOTPRINT_LO, FOOTPRINT_HI]], np.float64)
FOOTPRINT_UV.setflags(write=False)
_UNIT_SQUARE = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64)


@dataclass(frozen=True)
class TruthCard:
    """The truth of one card in one frame.

    Parameters
    ----------
    id : int
        The card's marker id.
    points : ndarray, shape (4, 2)
        True image points of the card's four reference points (px): our disc centres,
        or a tag's corners, in printed order.
    counted : bool
        Visible, its footprint inside the image, and not covered by a nearer card.
    centre : ndarray, shape (2,)
        The card's centre in the image (px; NaN when its points are not finite).
    side_px : float
        Mean side of the imaged card (px).
    disc_px : float
        Approximate imaged disc diameter (px).
    """

    id: int
    points: np.ndarray
    counted: bool
    centre: np.ndarray
    side_px: float
    disc_px: float


def _points_uv(artwork: Callable[[int], CardArtwork] | None, marker_id: int) -> np.ndarray:
    """The card's reference points in card units: our disc centres, or the artwork's."""
    if artwork is None:
        return np.asarray(marker_layout(DEFAULT_FAMILY, marker_id).discs, np.float64)
    return np.asarray(artwork(marker_id).points_uv, np.float64)


def truth_cards(truth: FrameTruth, artwork: Callable[[int], CardArtwork] | None) -> list[TruthCard]:
    """The frame's true targets, each with whether it counts.

    A target is counted when the simulator calls it visible, its footprint
    (`FOOTPRINT_UV`) lies inside the image (`BORDER_PX`), and no nearer card overlaps
    the footprint. The card outline comes from the reference points (the cards of these
    scenes are flat).

    Parameters
    ----------
    truth : FrameTruth
        The frame's ground truth.
    artwork : callable or None
        ``id -> CardArtwork`` when another marker is printed on the cards (its
        ``points_uv`` are the reference points); None for our own cards.

    Returns
    -------
    list of TruthCard
        One per target of `truth`, in its order.
    """
    size = np.array([truth.camera.width, truth.camera.height], np.float64)
    geo = []
    for t in truth.targets:
        if not np.isfinite(t.discs_px).all():
            geo.append(None)
            continue
        h = cv2.getPerspectiveTransform(_points_uv(artwork, t.id).astype(np.float32), t.discs_px.astype(np.float32))
        card = cv2.perspectiveTransform(_UNIT_SQUARE[None], h)[0]
        inner = cv2.perspectiveTransform(FOOTPRINT_UV[None], h)[0]
        geo.append((card, inner))
    cards = []
    for i, t in enumerate(truth.targets):
        g = geo[i]
        if g is None:
            cards.append(TruthCard(t.id, t.discs_px, False, np.array([np.nan, np.nan]), 0.0, t.disc_diameter_px))
            continue
        card, inner = g
        covered = False
        for j, other in enumerate(truth.targets):
            if j == i or geo[j] is None or other.distance_m >= t.distance_m:
                continue
            area, _ = cv2.intersectConvexConvex(inner.astype(np.float32), geo[j][0].astype(np.float32))
            covered |= area > 0
        side = float(np.mean(np.linalg.norm(card - np.roll(card, -1, axis=0), axis=1)))
        inside = bool(((inner >= BORDER_PX) & (inner <= size - 1 - BORDER_PX)).all())
        cards.append(TruthCard(t.id, t.discs_px, bool(t.visible and inside and not covered), card.mean(axis=0), side,
                               t.disc_diameter_px))
    return cards
