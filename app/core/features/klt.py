"""KLT: corners followed by pyramidal Lucas-Kanade optical flow between consecutive frames.

Optical flow assumes that a point keeps its brightness, which a camera's exposure, gain,
tone curve and uneven light break from frame to frame; the flow therefore reads each
frame with its shading removed and its contrast normalised (`flow_image`: on the
simulator's frames the tracks grow longer and their links more precise; where nothing
changes it costs a little precision within the shading's box of the image's border;
docs/benchmarks/features.md). Each point starts its search where its last motion would
put it (a camera turns smoothly), so the pyramid only has to find the change of motion.
A point is kept only when tracking it back from the new frame lands where it started
(the forward-backward check: occlusions, blur and repeated texture make the two
directions disagree); new corners (`cv2.goodFeaturesToTrack`, refined to subpixel) fill
the image where tracks were lost, at least the minimum distance from the live ones.
"""

from __future__ import annotations

import cv2
import numpy as np

from app.core.features.settings import FeatureSettings

__all__ = ["flow", "flow_image", "seed_points"]

# `flow_image` scales the remaining texture to this standard deviation (grey levels),
# amplifying by at most _FLOW_STD / _MIN_STD (a plain wall's noise stays noise).
_FLOW_STD = 40.0
_MIN_STD = 5.0
# Lucas-Kanade stops after 30 iterations or a step of 0.01 px.
_LK_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
# Subpixel corners: a 5x5 half-window, stops at 0.01 px.
_SUBPIX_HALF = 5
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.01)
# The smaller eigenvalue of the corners is measured over this block, px.
_BLOCK = 7


def flow_image(image: np.ndarray, shading_px: int | None = 20) -> np.ndarray:
    """The frame as the optical flow reads it: its shading (the mean over a box
    ``2 shading_px + 1`` px wide, of the pixels inside the image) removed and the rest
    scaled to a standard contrast, so that exposure, gain, tone and light changing from
    frame to frame do not move the points.

    Parameters
    ----------
    image : (h, w) ndarray of uint8
        A greyscale frame.
    shading_px : int or None, optional
        Half the width of the shading's box; None: the frame as it is.

    Returns
    -------
    (h, w) ndarray of uint8
        Texture around grey 128 (or the frame itself).
    """
    if shading_px is None:
        return image
    a = image.astype(np.float32)
    size = (2 * int(shading_px) + 1,) * 2
    # Only the pixels inside the image count: mirrored content near the border would
    # move against the scene and drag the points there along.
    inside = cv2.blur(np.ones_like(a), size, borderType=cv2.BORDER_CONSTANT)
    texture = a - cv2.blur(a, size, borderType=cv2.BORDER_CONSTANT) / inside
    gain = _FLOW_STD / max(float(texture.std()), _MIN_STD)
    return np.clip(np.rint(128.0 + gain * texture), 0, 255).astype(np.uint8)


def flow(before: np.ndarray, after: np.ndarray, uv: np.ndarray, settings: FeatureSettings,
         guess: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Points of one frame followed into the next, with the forward-backward check.

    Parameters
    ----------
    before, after : (h, w) ndarray of uint8
        The two frames as `flow_image` gives them.
    uv : (N, 2) ndarray
        Points in the first frame, px.
    settings : FeatureSettings
        The window, the levels and the forward-backward tolerance.
    guess : (N, 2) ndarray, optional
        Where to start looking for each point in the second frame (its predicted place);
        by default where it was.

    Returns
    -------
    uv_after : (N, 2) ndarray
        Where the points are in the second frame, px (meaningless where not ``ok``).
    ok : (N,) ndarray of bool
        Tracked both ways, back within ``forward_backward_px`` of the start.
    """
    if len(uv) == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    win = (settings.window_px, settings.window_px)
    p0 = uv.astype(np.float32).reshape(-1, 1, 2)
    start = p0.copy() if guess is None else guess.astype(np.float32).reshape(-1, 1, 2)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(before, after, p0, start, winSize=win, maxLevel=settings.pyramid_levels,
                                          criteria=_LK_CRITERIA, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(after, before, p1, p0.copy(), winSize=win,
                                            maxLevel=settings.pyramid_levels, criteria=_LK_CRITERIA,
                                            flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    p1, back = p1.reshape(-1, 2).astype(np.float64), back.reshape(-1, 2).astype(np.float64)
    with np.errstate(invalid="ignore"):
        returned = np.linalg.norm(back - uv, axis=1) <= settings.forward_backward_px
        ok = (st1.ravel() == 1) & (st2.ravel() == 1) & returned
    return p1, ok & np.all(np.isfinite(p1), axis=1)


def seed_points(image: np.ndarray, allowed: np.ndarray, live: np.ndarray, count: int,
                settings: FeatureSettings) -> np.ndarray:
    """New corners where features may lie, away from the live ones.

    Parameters
    ----------
    image : (h, w) ndarray of uint8
        The frame.
    allowed : (h, w) ndarray of uint8
        Non-zero where a feature may lie (`masks.allowed_mask`).
    live : (K, 2) ndarray
        The points already tracked in this frame, px.
    count : int
        Most new corners.
    settings : FeatureSettings
        The minimum distance, the quality level and the least eigenvalue.

    Returns
    -------
    (N, 2) ndarray
        New corners, N <= count, strongest first; subpixel where the refinement finds
        the corner within a pixel.
    """
    if count <= 0 or not allowed.any():
        return np.zeros((0, 2))
    mask = allowed
    if len(live):
        near = np.zeros_like(allowed)
        xy = np.round(live).astype(np.int64)
        h, w = allowed.shape
        inside = (xy[:, 0] >= 0) & (xy[:, 0] < w) & (xy[:, 1] >= 0) & (xy[:, 1] < h)
        near[xy[inside, 1], xy[inside, 0]] = 255
        r = max(int(np.ceil(settings.min_distance_px)), 1)
        near = cv2.dilate(near, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
        mask = np.where(near != 0, np.uint8(0), allowed)
    corners = cv2.goodFeaturesToTrack(image, int(count), settings.quality_level, settings.min_distance_px,
                                      mask=mask, blockSize=_BLOCK)
    if corners is None:
        return np.zeros((0, 2))
    corners = corners.reshape(-1, 2)
    # goodFeaturesToTrack's quality is relative to the frame's best corner: on a plain
    # wall the best is noise, so an absolute floor keeps noise out.
    eig = _min_eigenvalues(image, corners)
    corners = corners[eig >= settings.min_eigenvalue]
    if len(corners) == 0:
        return np.zeros((0, 2))
    refined = cv2.cornerSubPix(image, corners.reshape(-1, 1, 2).astype(np.float32).copy(),
                               (_SUBPIX_HALF, _SUBPIX_HALF), (-1, -1), _SUBPIX_CRITERIA).reshape(-1, 2)
    # The refinement finds the corner's saddle; on a blob it wanders off to the blob's
    # middle, and the corner stays where the detector put it.
    near = np.linalg.norm(refined - corners, axis=1) <= 1.0
    return np.where(near[:, None], refined, corners).astype(np.float64)


def _min_eigenvalues(image: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """The smaller structure-tensor eigenvalue at each corner, on cornerMinEigenVal's
    scale, from the patch around it alone."""
    h, w = image.shape
    half = _BLOCK // 2 + 2
    out = np.zeros(len(corners))
    for i, (x, y) in enumerate(np.round(corners).astype(np.int64)):
        x0, y0, x1, y1 = max(x - half, 0), max(y - half, 0), min(x + half + 1, w), min(y + half + 1, h)
        patch = image[y0:y1, x0:x1]
        if patch.shape[0] < _BLOCK or patch.shape[1] < _BLOCK:
            continue
        eig = cv2.cornerMinEigenVal(patch, _BLOCK)
        out[i] = eig[y - y0, x - x0]
    return out
