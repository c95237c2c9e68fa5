"""Drawing what the detector found over the frame it found it in: each target's disc
quadrilateral, its discs (disc 0 marked, which fixes the card's orientation) and its id,
and every disc candidate, for a person checking a detection by eye."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from app.core.detection.targets import DetectedTarget
from app.core.markers import DISC_CENTRES, DISC_RADIUS

__all__ = ["CANDIDATE_COLOUR", "DISC_COLOUR", "QUAD_COLOUR", "TEXT_COLOUR", "draw_detections"]

#: Colours, BGR: candidates amber, a target's quadrilateral green, its discs red.
CANDIDATE_COLOUR = (0, 190, 255)
QUAD_COLOUR = (60, 220, 0)
DISC_COLOUR = (40, 40, 255)
TEXT_COLOUR = (255, 255, 255)

#: Drawing in 1/16 pixel (OpenCV's ``shift``): disc centres are subpixel.
_SHIFT = 4
_SCALE = 1 << _SHIFT
#: A disc's radius over the side of the disc quadrilateral on the printed card, for the
#: targets whose imaged radii are not known.
_RADIUS_OVER_SIDE = DISC_RADIUS / float(DISC_CENTRES[1, 0] - DISC_CENTRES[0, 0])


def _point(u: float, v: float) -> tuple[int, int]:
    return int(round(float(u) * _SCALE)), int(round(float(v) * _SCALE))


def _radius(r: float) -> int:
    return max(1, int(round(r * _SCALE)))


def draw_detections(gray: np.ndarray, targets: Sequence[DetectedTarget], candidates: np.ndarray) -> np.ndarray:
    """The frame in colour with the detections drawn over it.

    Candidates are drawn first (amber circles of their estimated radius), then each
    target: its disc quadrilateral (green), its four discs (red circles; disc 0, the
    card's top-left, also gets a filled dot) and its id at its centre. Coordinates
    follow the detector's convention: the centre of the top-left pixel is (0, 0).

    Parameters
    ----------
    gray : ndarray, shape (H, W) or (H, W, 3)
        The frame, uint8: greyscale, or BGR (drawn over as it is).
    targets : sequence of DetectedTarget
        The identified targets, their disc centres in the frame's pixels.
    candidates : ndarray, shape (N, 4)
        Disc candidates ``[u, v, radius, score]`` in the frame's pixels; (0, 4) for none.

    Returns
    -------
    ndarray, shape (H, W, 3)
        A new uint8 BGR image; `gray` is left unchanged.
    """
    frame = np.asarray(gray)
    if frame.dtype != np.uint8:
        raise ValueError(f"the frame must be uint8, not {frame.dtype}")
    if frame.ndim == 2:
        image = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
    elif frame.ndim == 3 and frame.shape[2] == 3:
        image = frame.copy()
    else:
        raise ValueError(f"the frame must be (H, W) or (H, W, 3), not {frame.shape}")
    height, width = image.shape[:2]
    # Lines and text grow with the frame so that they stay visible on a large photograph.
    thickness = max(1, int(round(min(height, width) / 480)))
    rows = np.asarray(candidates, np.float64).reshape(-1, 4)
    for u, v, r, _score in rows:
        cv2.circle(image, _point(u, v), _radius(max(r, 1.0)), CANDIDATE_COLOUR, thickness,
                   cv2.LINE_AA, _SHIFT)
    font_scale = 0.6 * thickness
    for target in targets:
        discs = np.asarray(target.discs, np.float64).reshape(4, 2)
        corners = np.array([_point(*d) for d in discs], np.int32).reshape(-1, 1, 2)
        cv2.polylines(image, [corners], True, QUAD_COLOUR, thickness, cv2.LINE_AA, _SHIFT)
        side = float(np.mean(np.linalg.norm(discs - np.roll(discs, -1, axis=0), axis=1)))
        radii = np.asarray(target.disc_radii, np.float64).reshape(-1)
        if radii.size != 4 or not np.all(radii > 0):
            radii = np.full(4, side * _RADIUS_OVER_SIDE)
        for disc, radius in zip(discs, radii, strict=True):
            cv2.circle(image, _point(*disc), _radius(radius), DISC_COLOUR, thickness, cv2.LINE_AA, _SHIFT)
        cv2.circle(image, _point(*discs[0]), _radius(max(1.5 * thickness, 0.25 * radii[0])), DISC_COLOUR,
                   cv2.FILLED, cv2.LINE_AA, _SHIFT)
        label = str(int(target.id))
        (text_w, text_h), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, font_scale, thickness)
        centre = discs.mean(axis=0)
        origin = (int(round(centre[0] - text_w / 2)), int(round(centre[1] + text_h / 2)))
        # A dark outline under the white text: readable on the white card and on any background.
        cv2.putText(image, label, origin, cv2.FONT_HERSHEY_SIMPLEX, font_scale, (0, 0, 0), thickness + 2,
                    cv2.LINE_AA)
        cv2.putText(image, label, origin, cv2.FONT_HERSHEY_SIMPLEX, font_scale, TEXT_COLOUR, thickness,
                    cv2.LINE_AA)
    return image
