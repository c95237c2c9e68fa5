"""Where feature points may lie: the image minus the regions a caller excludes.

The cards are tracked as discs already; a feature point on a card (a disc's rim, a code
cell's corner) would be a second, worse track of the same spot, so the caller excludes
the detected cards. `exclusion_mask` draws them from their disc centres.
"""

from __future__ import annotations

import cv2
import numpy as np

from app.core.geometry import apply_homographies, homographies

__all__ = ["allowed_mask", "exclusion_mask", "inside"]

#: The card's corners in card units (the discs sit at 0.2 and 0.8).
_CARD_CORNERS = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])


def exclusion_mask(shape: tuple[int, int], quads: np.ndarray, margin_px: float = 6.0) -> np.ndarray:
    """The image region covered by cards, from the image points of their disc centres.

    Each card's outline follows from its discs through the card homography (the discs
    sit at 0.2 and 0.8 of the card), grown by ``margin_px`` for the blur and the
    feature detector's window.

    Parameters
    ----------
    shape : tuple of int
        (height, width) of the image.
    quads : (N, 4, 2) array
        Each card's disc centres 0-3 in printed order, px (a detection's ``discs``).
    margin_px : float, optional
        How far beyond the card's edge the region reaches, px.

    Returns
    -------
    (height, width) ndarray of bool
        True on the cards.
    """
    h, w = int(shape[0]), int(shape[1])
    mask = np.zeros((h, w), np.uint8)
    q = np.asarray(quads, np.float64).reshape(-1, 4, 2)
    q = q[np.all(np.isfinite(q), axis=(1, 2))]
    if len(q) and h and w:
        corners = apply_homographies(homographies(q), _CARD_CORNERS)
        # Polygons far outside the image (a card half behind the camera) stay drawable.
        corners = np.clip(corners, -4.0 * max(h, w), 5.0 * max(h, w))
        cv2.fillPoly(mask, [np.round(c * 16).astype(np.int32) for c in corners], 255, cv2.LINE_8, shift=4)
        r = int(np.ceil(margin_px))
        if r > 0:
            mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    return mask > 0


def allowed_mask(shape: tuple[int, int], exclude: np.ndarray | None, border_px: int) -> np.ndarray:
    """Where feature points may lie: inside the image by ``border_px`` and outside the
    excluded regions.

    Parameters
    ----------
    shape : tuple of int
        (height, width) of the image.
    exclude : (height, width) array of bool or None
        True (non-zero) where no feature may lie.
    border_px : int
        Width of the image border left out (the tracker's window must fit).

    Returns
    -------
    (height, width) ndarray of uint8
        255 where a feature may lie, 0 elsewhere (OpenCV's mask convention).

    Raises
    ------
    ValueError
        If ``exclude`` does not have the image's shape.
    """
    h, w = int(shape[0]), int(shape[1])
    allowed = np.zeros((h, w), np.uint8)
    b = int(border_px)
    if h > 2 * b and w > 2 * b:
        allowed[b : h - b, b : w - b] = 255
    if exclude is not None:
        exclude = np.asarray(exclude)
        if exclude.shape != (h, w):
            raise ValueError(f"an exclusion mask must have the image's shape {(h, w)}, got {exclude.shape}")
        allowed[exclude != 0] = 0
    return allowed


def inside(allowed: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Which points lie where features may lie.

    Parameters
    ----------
    allowed : (height, width) ndarray of uint8
        `allowed_mask`.
    uv : (N, 2) ndarray
        Points, px.

    Returns
    -------
    (N,) ndarray of bool
        True where the nearest pixel is allowed (False outside the image or not finite).
    """
    h, w = allowed.shape
    ok = np.all(np.isfinite(uv), axis=1)
    x = np.full(len(uv), -1, np.int64)
    y = np.full(len(uv), -1, np.int64)
    x[ok] = np.round(uv[ok, 0]).astype(np.int64)
    y[ok] = np.round(uv[ok, 1]).astype(np.int64)
    ok &= (x >= 0) & (x < w) & (y >= 0) & (y < h)
    ok[ok] = allowed[y[ok], x[ok]] != 0
    return ok
