"""Card homographies: card units (the printed layout, 0..1) to image pixels.

A card's four disc centres fix the homography from its layout to the image; every
stage that reads a card (verification, refinement, identification, the disc fit, the
survey's disc weights) maps card points through it. All functions take stacks of
homographies (P, 3, 3) and work on them at once.
"""

from __future__ import annotations

import numpy as np

from app.core.geometry import _kernels
from app.core.markers import DISC_CENTRES, DISC_RADIUS

__all__ = [
    "apply_homographies",
    "disc_axes",
    "ellipse_centres",
    "homogeneous",
    "homographies",
    "jacobians",
    "perspective_bias",
]

# Layout disc centres -> unit square, so the closed-form square-to-quad mapping applies.
_LAYOUT_TO_SQUARE = np.array(
    [[1 / 0.6, 0.0, -0.2 / 0.6], [0.0, 1 / 0.6, -0.2 / 0.6], [0.0, 0.0, 1.0]], np.float64
)
assert np.allclose(DISC_CENTRES, [[0.2, 0.2], [0.8, 0.2], [0.8, 0.8], [0.2, 0.8]])


def homographies(quads: np.ndarray) -> np.ndarray:
    """Card homographies from the image points of the four disc centres, all at once
    (Heckbert's closed-form square-to-quad mapping; a Python loop over
    cv2.getPerspectiveTransform costs more than the rest of the grouping).

    Parameters
    ----------
    quads : ndarray, shape (P, 4, 2)
        Image points of the layout's disc centres 0-3 of each card.

    Returns
    -------
    ndarray, shape (P, 3, 3)
        Homographies mapping card units (the layout, 0..1) to the image.
    """
    q = np.asarray(quads, np.float64).reshape(-1, 4, 2)
    if q.shape[0] <= _FEW:
        return _homographies_few(q)
    q0, q1, q2, q3 = q[:, 0], q[:, 1], q[:, 2], q[:, 3]  # (P, 2): x, y
    d1, d2 = q1 - q2, q3 - q2
    d3 = q0 - q1 + q2 - q3
    dx1, dy1, dx2, dy2, dx3, dy3 = d1[:, 0], d1[:, 1], d2[:, 0], d2[:, 1], d3[:, 0], d3[:, 1]
    den = dx1 * dy2 - dx2 * dy1
    den = np.where(np.abs(den) > 1e-12, den, 1e-12)
    hs = np.empty((q.shape[0], 3, 3))
    g, h = hs[:, 2, 0], hs[:, 2, 1]
    np.divide(dx3 * dy2 - dx2 * dy3, den, out=g)
    np.divide(dx1 * dy3 - dx3 * dy1, den, out=h)
    hs[:, :2, 0] = q1 - q0 + g[:, None] * q1
    hs[:, :2, 1] = q3 - q0 + h[:, None] * q3
    hs[:, :2, 2] = q0
    hs[:, 2, 2] = 1.0
    return hs @ _LAYOUT_TO_SQUARE


#: Up to this many quadrilaterals (a frame's usual few), Python floats beat numpy's
#: per-call overhead (~1 us a call, whatever the size).
_FEW = 8


def _homographies_few(q: np.ndarray) -> np.ndarray:
    """`homographies` of a few quadrilaterals (P, 4, 2) in Python floats: the same
    arithmetic, operation for operation, as the vectorised code (identical results).
    """
    rows = []
    for (x0, y0), (x1, y1), (x2, y2), (x3, y3) in q.tolist():
        dx1, dy1, dx2, dy2 = x1 - x2, y1 - y2, x3 - x2, y3 - y2
        dx3, dy3 = x0 - x1 + x2 - x3, y0 - y1 + y2 - y3
        den = dx1 * dy2 - dx2 * dy1
        if not abs(den) > 1e-12:  # (NaN too, as np.where(abs > 1e-12) does)
            den = 1e-12
        g = (dx3 * dy2 - dx2 * dy3) / den
        h = (dx1 * dy3 - dx3 * dy1) / den
        rows.append([[x1 - x0 + g * x1, x3 - x0 + h * x3, x0], [y1 - y0 + g * y1, y3 - y0 + h * y3, y0], [g, h, 1.0]])
    return np.array(rows, np.float64).reshape(-1, 3, 3) @ _LAYOUT_TO_SQUARE


def homogeneous(pts: np.ndarray) -> np.ndarray:
    """Points with w = 1 appended.

    Parameters
    ----------
    pts : ndarray, shape (M, 2)
        Card points.

    Returns
    -------
    ndarray, shape (M, 3)
        The points, homogeneous.
    """
    return np.concatenate([pts, np.ones((pts.shape[0], 1))], axis=1)


_DISC_CENTRES_H = homogeneous(DISC_CENTRES)


def apply_homographies(hs: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Card points mapped through every homography.

    Parameters
    ----------
    hs : ndarray, shape (P, 3, 3)
        Homographies.
    pts : ndarray, shape (M, 2) or (M, 3)
        Card points, or the same homogeneous.

    Returns
    -------
    ndarray, shape (P, M, 2)
        Image points (a |w| not above 1e-12 taken as 1e-12).
    """
    x = np.matmul(pts if pts.shape[1] == 3 else homogeneous(pts), hs.transpose(0, 2, 1))
    w = x[..., 2:3]
    w = np.where(np.abs(w) > 1e-12, w, 1e-12)
    return x[..., :2] / w


def ellipse_centres(hs: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
    """Centres of the image ellipses of card circles under each homography.

    The centre of a conic is the pole of the line at infinity; pulled back to the card,
    that line is the homography's third row (g, h, 1), and the pole of it with respect to
    the circle is the card point ``c - radius**2 (g, h) / (g cx + h cy + 1)``: its image is
    the ellipse centre.

    Parameters
    ----------
    hs : ndarray, shape (P, 3, 3)
        Homographies.
    centres : ndarray, shape (K, 2)
        Circle centres on the card.
    radius : float
        Circle radius on the card.

    Returns
    -------
    ndarray, shape (P, K, 2)
        Ellipse centres in the image.
    """
    # one compiled loop (`_kernels.ellipse_centres`: the numpy arithmetic of the
    # reference in the homography tests, operation for operation)
    return _kernels.ellipse_centres(np.ascontiguousarray(hs, np.float64), np.ascontiguousarray(centres, np.float64),
                                   float(radius))


def disc_axes(discs: np.ndarray) -> np.ndarray:
    """Semi-axes of the image ellipses of the discs of cards, to first order: the singular
    values of the card homography's Jacobian at each disc times the disc radius.

    Parameters
    ----------
    discs : ndarray, shape (T, 4, 2)
        Disc centres of each card in the image (printed order).

    Returns
    -------
    ndarray, shape (T, 4, 2)
        Semi-axes in pixels, major then minor.
    """
    jac = jacobians(homographies(np.asarray(discs, np.float64).reshape(-1, 4, 2)), DISC_CENTRES)
    return np.linalg.svd(jac, compute_uv=False) * DISC_RADIUS


def perspective_bias(hs: np.ndarray) -> np.ndarray:
    """How far each disc's image-ellipse centre lies from the image of the disc's centre.

    Parameters
    ----------
    hs : ndarray, shape (P, 3, 3)
        Card homographies.

    Returns
    -------
    ndarray, shape (P, 4, 2)
        Ellipse centre minus projected centre, per disc, in pixels.
    """
    return ellipse_centres(hs, DISC_CENTRES, DISC_RADIUS) - apply_homographies(hs, _DISC_CENTRES_H)


def jacobians(hs: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Jacobians d(image)/d(card) of each homography at card points.

    Parameters
    ----------
    hs : ndarray, shape (P, 3, 3)
        Homographies.
    pts : ndarray, shape (K, 2)
        Card points.

    Returns
    -------
    ndarray, shape (P, K, 2, 2)
        Image offset per card offset at each point.
    """
    # row r: (H[r, :2] - image[r] * H[2, :2]) / w, image[r] = x[r] / w, x = H (p, 1); one
    # compiled loop (`_kernels.jacobians`, the numpy arithmetic operation for operation)
    return _kernels.jacobians(np.ascontiguousarray(hs, np.float64), np.ascontiguousarray(pts, np.float64))
