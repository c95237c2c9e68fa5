"""What each pixel of a frame sees: the surface point, its normal, its depth, and whether
it is a card's paper. The depth of field (`degrade.depth_defocus`) and the lighting
(`app.sim.lighting`) are computed from it.

Every surface of a scene is a planar quadrilateral (walls, a backdrop, furniture, the
cards), so each pixel's ray is cast against each of them and the nearest hit in front
of the camera kept. A card is cast as its flat square: its bend (a few millimetres)
changes neither its depth nor its normal enough to matter here. Rays follow the lens:
each pixel's ray is the one through its ideal (undistorted) position.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from app.core.geometry import Camera, Pose

__all__ = ["Surfaces", "cast_surfaces"]

#: Corners at least this far in front of the camera (metres, along its axis) let a quad
#: be cast only at the pixels inside its projected bounding box; a quad reaching behind
#: the camera is cast at every pixel.
_NEAR_M = 1e-3


@dataclass(frozen=True)
class Surfaces:
    """The surface each pixel of a frame sees.

    Attributes
    ----------
    points : (height, width, 3) ndarray
        Map coordinates of the point each pixel sees (NaN where it sees nothing).
    normals : (height, width, 3) ndarray
        Unit normal of that surface, on the camera's side (NaN where nothing).
    depth : (height, width) ndarray
        The point's depth along the optical axis, metres (inf where nothing).
    card : (height, width) ndarray of bool
        The pixel sees a card's paper.
    """

    points: np.ndarray
    normals: np.ndarray
    depth: np.ndarray
    card: np.ndarray


def cast_surfaces(camera: Camera, pose: Pose, surfaces: Sequence[np.ndarray], cards: Sequence[np.ndarray] = ()
                  ) -> Surfaces:
    """Cast every pixel's ray against the scene's planar surfaces and its cards.

    Parameters
    ----------
    camera : Camera
    pose : Pose
        Map-to-camera transform.
    surfaces : sequence of (4, 3) ndarray
        Corners of each planar parallelogram (walls, backdrop, furniture), in order
        around it, map coordinates.
    cards : sequence of (4, 3) ndarray
        Corners of each card, likewise: the pixels that see one are marked `card`.

    Returns
    -------
    Surfaces
    """
    ideal_u, ideal_v = camera.distortion_maps()  # each pixel's ideal position, cached with the camera
    x = ((ideal_u - camera.cx) / camera.fx).ravel().astype(np.float64)
    y = ((ideal_v - camera.cy) / camera.fy).ravel().astype(np.float64)
    n_px = x.size
    rays = np.column_stack([x, y, np.ones(n_px)]) @ pose.R  # map frame; length 1 along the optical axis
    eye = pose.position
    depth = np.full(n_px, np.inf)
    normal = np.full((n_px, 3), np.nan)
    card = np.zeros(n_px, bool)
    for corners, is_card in [*((c, False) for c in surfaces), *((c, True) for c in cards)]:
        corners = np.asarray(corners, np.float64)
        sel = _candidates(corners, pose, x, y)
        if sel is not None and sel.size == 0:
            continue
        d = rays if sel is None else rays[sel]
        origin, ex, ey = corners[0], corners[1] - corners[0], corners[3] - corners[0]
        n = np.cross(ex, ey)
        n /= np.linalg.norm(n)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = float((origin - eye) @ n) / (d @ n)
        hit = eye + t[:, None] * d - origin
        a, b = hit @ ex / (ex @ ex), hit @ ey / (ey @ ey)
        idx = np.arange(n_px) if sel is None else sel
        closer = (t > 0) & (t < depth[idx]) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
        idx = idx[closer]
        depth[idx] = t[closer]
        normal[idx] = n if float((eye - origin) @ n) > 0 else -n
        card[idx] = is_card
    found = np.isfinite(depth)
    points = np.full((n_px, 3), np.nan)
    points[found] = eye + depth[found, None] * rays[found]
    shape = (camera.height, camera.width)
    return Surfaces(points=points.reshape(*shape, 3), normals=normal.reshape(*shape, 3), depth=depth.reshape(shape),
                    card=card.reshape(shape))


def _candidates(corners: np.ndarray, pose: Pose, x: np.ndarray, y: np.ndarray) -> np.ndarray | None:
    """The pixels (flat indices) whose ideal ray falls in the quad's projected bounding
    box, or None (every pixel) when the quad reaches behind the camera."""
    cam = pose.transform(corners)
    if (cam[:, 2] <= _NEAR_M).any():
        return None
    px, py = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
    return np.flatnonzero((x >= px.min()) & (x <= px.max()) & (y >= py.min()) & (y <= py.max()))
