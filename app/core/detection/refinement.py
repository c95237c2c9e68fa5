"""Refinement: subpixel disc centres of verified cards.

Each disc's centre is the background-corrected, intensity-weighted centroid of its
darkness in a window that is the image of a circle around the disc (through the
homography of the card's four current centres), minus the perspective bias of the
ellipse centroid (exact, from the image conic of the disc), iterated (`refine_centres`).
One centroid step of every disc is one compiled loop
(`_refinement_kernels.centroid_step`).
"""

from __future__ import annotations

import numpy as np

from app.core.detection import _refinement_kernels as kernels
from app.core.detection._frame import Pyramid, as_gray
from app.core.geometry import homographies, jacobians, perspective_bias
from app.core.markers import DISC_CENTRES, DISC_RADIUS

__all__ = [
    "MAX_REFINE_SHIFT",
    "REFINE_CONVERGED",
    "REFINE_EXTRA_ITERATIONS",
    "REFINE_ITERATIONS",
    "REFINE_MAX_HALF",
    "REFINE_RING",
    "REFINE_SETTLED",
    "REFINE_TAPER",
    "REFINE_WHITE_AGAIN",
    "REFINE_WINDOW",
    "refine_centres",
]

#: Largest move of a disc centre in refinement, in predicted disc radii (2 px at least).
MAX_REFINE_SHIFT = 0.8

#: Subpixel refinement: window (in disc radii, card units) and white ring.
REFINE_WINDOW = 1.1
REFINE_TAPER = 0.1
REFINE_RING = (1.15, 1.4)
REFINE_ITERATIONS = 2
#: Up to this many more while the last one still moved a centre by `REFINE_SETTLED` px
#: or more (a candidate far off its disc); the white ring is measured again while the
#: last move exceeded `REFINE_WHITE_AGAIN` px (else the first pass's median is kept).
REFINE_EXTRA_ITERATIONS = 3
REFINE_SETTLED = 0.1
REFINE_WHITE_AGAIN = 0.5
REFINE_CONVERGED = 0.01  # px: stop early when no centre moved more
REFINE_MAX_HALF = 16  # larger windows are measured on a pyramid level
#: `REFINE_RING` squared, as the float32 bounds on squared distances (in disc radii).
_REFINE_RING2 = np.array([REFINE_RING[0] ** 2, REFINE_RING[1] ** 2], np.float32)


def refine_centres(gray: np.ndarray, discs: np.ndarray, iterations: int = REFINE_ITERATIONS,
                   correct_perspective: bool = True, _pyramid: Pyramid | None = None,
                   _homographies: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Subpixel disc centres and imaged radii of cards.

    Each disc's centre is the centroid of darkness ``max(0, white - I)`` over the pixels
    of an elliptical window: the image of a circle of `REFINE_WINDOW` disc radii around
    the disc on the card (local affine map of the homography of the four current
    centres), with a soft edge, centred on the current centroid. The white level is the
    median of a ring around the disc on the card. Symmetric blur keeps a centroid, and
    a window symmetric about the centroid truncates the blurred tails symmetrically.
    Big discs are measured on a pyramid level (cv2.pyrDown: a symmetric blur, so the
    centroid stays; level pixel i is full-resolution pixel i * 2**L) that keeps the
    window within `REFINE_MAX_HALF` pixels: subsampling full-resolution pixels instead
    would alias the disc edge (~0.1 px errors).

    The area centroid of an imaged disc is the centre of its image ellipse, which under
    perspective is not the projection of the disc's centre; that offset follows exactly
    from the homography (the image conic of the circle) and is subtracted
    (`correct_perspective`). Iterated `iterations` times, each with the homography of
    the previous centres, and up to `REFINE_EXTRA_ITERATIONS` more while centres still
    move (a candidate far off its disc); the ring's white level is kept from the
    previous pass once the centres have settled.

    Parameters
    ----------
    gray : ndarray
        The frame: uint8 greyscale (other types and BGR are converted).
    discs : ndarray, shape (T, 4, 2)
        Approximate disc centres of T cards in full-resolution pixels, each card's in
        the layout's orientation, starting at any disc.
    iterations : int
        Centroid passes (at least 1) before the extra ones; fewer when no centre moves
        by more than `REFINE_CONVERGED` px.
    correct_perspective : bool
        Subtract the offset of the image ellipse's centre from the projected disc
        centre.
    _pyramid : Pyramid, optional
        The frame's pyramid, if already made.
    _homographies : ndarray, shape (T, 3, 3), optional
        The card homographies of `discs`, if already computed.

    Returns
    -------
    centres : ndarray, shape (T, 4, 2)
        Refined disc centres, in the order of `discs` (unchanged where a disc gave no
        darkness, all of them for non-finite input).
    radii : ndarray, shape (T, 4)
        Imaged disc radii in pixels: sqrt(dark area / pi), the area being the summed
        darkness over the disc-vs-white contrast (0 where nothing was measured).
    """
    gray = as_gray(gray)
    pyr = _pyramid if _pyramid is not None else Pyramid(gray)
    cur = np.array(discs, np.float64).reshape(-1, 4, 2)
    t = cur.shape[0]
    if t == 0 or not np.isfinite(cur).all():
        return cur, np.zeros((t, 4))
    centroid = cur.copy()  # the image-ellipse centres (what the window is centred on)
    reach = REFINE_WINDOW + REFINE_TAPER
    white = np.full((t, 4), np.nan)  # ring medians, measured again only while centres move
    total = contrast = None  # of the last pass: the radii
    groups: list[tuple[int, np.ndarray | None]] = []
    moved = np.inf
    for it in range(max(1, iterations) + REFINE_EXTRA_ITERATIONS):
        if it >= max(1, iterations) and moved < REFINE_SETTLED:
            break
        hs = _homographies if it == 0 and _homographies is not None else homographies(cur)
        jac = jacobians(hs, DISC_CENTRES)  # (T, 4, 2, 2) image offset per card offset
        det = np.abs(jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0])
        if not (det.min() > 1e-9 and det.max() < np.inf):  # False for NaN too
            break
        if not groups:
            # Half-extent of each window along x and y: reach * R * |row of J|; the level
            # is chosen once.
            ext = reach * DISC_RADIUS * np.sqrt(np.maximum(jac[..., 0, 0] ** 2 + jac[..., 0, 1] ** 2,
                                                           jac[..., 1, 0] ** 2 + jac[..., 1, 1] ** 2)).max(axis=1)
            level = np.minimum(np.ceil(np.log2(np.maximum((ext + 1.0) / REFINE_MAX_HALF, 1.0))),
                               pyr.max_level).astype(int)
            levels = sorted(set(level.tolist()))
            groups = [(lv, None if len(levels) == 1 else np.flatnonzero(level == lv)) for lv in levels]
        # The white ring is measured around the current centroid: again while the centres
        # still move (a candidate far off its disc puts the first ring partly on it).
        fresh = moved > REFINE_WHITE_AGAIN
        if len(groups) == 1:
            lv = groups[0][0]
            scale = 2.0**lv
            c, tot, con, wh = _centroid_step(pyr.get(lv), centroid / scale if lv else centroid,
                                             jac / scale if lv else jac, reach, None if fresh else white)
            new_centroid = c * scale if lv else c
            total = tot * (scale * scale)
            contrast = con
            white = wh
        else:
            new_centroid = centroid.copy()
            total = np.zeros((t, 4))
            contrast = np.ones((t, 4))
            for lv, rows in groups:
                scale = 2.0**lv
                c, tot, con, wh = _centroid_step(pyr.get(lv), centroid[rows] / scale, jac[rows] / scale, reach,
                                                 None if fresh else white[rows])
                new_centroid[rows] = c * scale
                total[rows] = tot * scale * scale
                contrast[rows] = con
                white[rows] = wh
        good = (total > 1e-6)[..., None]
        centroid = np.where(good, new_centroid, centroid)
        new = centroid - perspective_bias(hs) if correct_perspective else centroid
        prev, cur = cur, np.where(good, new, cur)
        moved = float(np.abs(cur - prev).max())
        if moved < REFINE_CONVERGED:
            break
    if total is None:
        return cur, np.zeros((t, 4))
    return cur, np.sqrt(np.maximum(total / np.maximum(contrast, 1e-3), 0.0) / np.pi)


def _centroid_step(img: np.ndarray, centroid: np.ndarray, jac: np.ndarray, reach: float,
                   white: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One centroid update of discs at `centroid` (T, 4, 2) in the pixels of `img`, with
    `jac` (T, 4, 2, 2) the image offset per card offset at each disc: (new centroids,
    summed darkness (T, 4), white - black (T, 4), white (T, 4)).

    Each disc's window is the image of a circle of `reach` disc radii around the
    centroid (a soft edge `REFINE_TAPER` wide); its white level the median of the ring
    `REFINE_RING` (measured when `white` is None), its black level the mean inside half
    a radius; the new centroid is that of the darkness ``max(0, white - I)`` in the
    window. One compiled loop over the discs (`kernels.centroid_step`: the float32
    arithmetic and summation order of the numpy reference in the refinement tests; its
    sums of ~1000 terms stay far below 1e-3 px of centroid error)."""
    t = centroid.shape[0]
    d = t * 4
    new, total, contrast = np.empty((d, 2)), np.empty(d), np.empty(d)
    white_out = np.empty(d) if white is None else np.array(white, np.float64).reshape(d)
    kernels.centroid_step(np.ascontiguousarray(img), np.ascontiguousarray(centroid, np.float64).reshape(d, 2),
                          np.ascontiguousarray(jac, np.float64).reshape(d, 2, 2), float(reach), DISC_RADIUS,
                          _REFINE_RING2, np.float32(0.25), np.float32(1.0 / REFINE_TAPER), white_out, white is None,
                          new, total, contrast)
    return new.reshape(t, 4, 2), total.reshape(t, 4), contrast.reshape(t, 4), white_out.reshape(t, 4)

