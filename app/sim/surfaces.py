"""What each pixel of a frame sees: the surface point, its normal, its depth, and whether
it is a card's paper. The depth of field (`degrade.depth_defocus`) and the lighting
(`app.sim.lighting`) are computed from it.

Every surface of a scene is a planar parallelogram (walls, a backdrop, furniture, the
cards), so each pixel's ray is cast against each of them and the nearest hit in front
of the camera kept. A card is cast as its flat square: its bend (a few millimetres)
changes neither its depth nor its normal enough to matter here. Rays follow the lens:
each pixel's ray is the one through its ideal (undistorted) position. A surface is cast
only over the block of pixels its projection can reach (clipped to the camera's near
plane first), so a frame of a furnished room costs tens of milliseconds, not seconds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from app.core.geometry import Camera, Pose

__all__ = ["Surfaces", "cast_surfaces", "quad_hits"]

#: The near plane a surface is clipped to before its projection bounds the pixels it
#: is cast over, metres along the camera's axis.
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
    x = (ideal_u - camera.cx) / camera.fx
    y = (ideal_v - camera.cy) / camera.fy
    shape = (camera.height, camera.width)
    rays = np.stack([x, y, np.ones(shape)], axis=-1)  # camera frame, 1 along the optical axis
    columns = (np.nanmin(x, axis=0), np.nanmax(x, axis=0))  # each column's extent, rising with u
    rows = (np.nanmin(y, axis=1), np.nanmax(y, axis=1))
    depth = np.full(shape, np.inf)
    owner = np.full(shape, -1, np.intp)
    quads = [np.asarray(c, np.float64) for c in (*surfaces, *cards)]
    normals = np.full((len(quads) + 1, 3), np.nan)  # the last row: nothing seen (owner -1)
    eye = pose.position
    for index, corners in enumerate(quads):
        n = np.cross(corners[1] - corners[0], corners[3] - corners[0])
        n /= np.linalg.norm(n)
        normals[index] = n if float((eye - corners[0]) @ n) > 0 else -n
        c = pose.transform(corners)  # camera frame
        block = _block(c, columns, rows)
        if block is None:
            continue
        v0, v1, u0, u1 = block
        t, meets = quad_hits(np.zeros(3), rays[v0:v1, u0:u1], c)  # t along a ray: its depth
        seen = depth[v0:v1, u0:u1]
        closer = meets & (t > _NEAR_M) & (t < seen)
        seen[closer] = t[closer]
        owner[v0:v1, u0:u1][closer] = index
    found = owner >= 0
    points = np.where(found[..., None], eye + np.where(found, depth, 0.0)[..., None] * (rays @ pose.R), np.nan)
    return Surfaces(points=points, normals=normals[owner], depth=depth, card=owner >= len(surfaces))


def quad_hits(origin: np.ndarray, rays: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where rays meet a planar parallelogram.

    Parameters
    ----------
    origin : (3,) ndarray
        Where the rays start.
    rays : (..., 3) ndarray
        Their directions (any lengths).
    corners : (4, 3) ndarray
        The parallelogram's corners in order around it, in the rays' frame.

    Returns
    -------
    t : (...) ndarray
        How far along each ray its line meets the parallelogram's plane, in the ray's
        lengths (NaN or inf for a ray along the plane).
    meets : (...) ndarray of bool
        The ray meets the parallelogram in front of `origin` (t > 0), within its edges.
    """
    base, ex, ey = corners[0], corners[1] - corners[0], corners[3] - corners[0]
    n = np.cross(ex, ey)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = float((base - origin) @ n) / (rays @ n)
        hit = origin + t[..., None] * rays - base
        a, b = hit @ ex / float(ex @ ex), hit @ ey / float(ey @ ey)
    return t, (t > 0) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)


def _block(corners: np.ndarray, columns: tuple[np.ndarray, np.ndarray], rows: tuple[np.ndarray, np.ndarray]
           ) -> tuple[int, int, int, int] | None:
    """The block of pixels (v0, v1, u0, u1) a quad (camera frame) can cover: its part in
    front of the near plane, projected, bounds the ideal coordinates; each column's
    (row's) extent of them picks the columns (rows) that reach the bounds. None if
    none."""
    front = _clip_near(corners)
    if len(front) == 0:
        return None
    px, py = front[:, 0] / front[:, 2], front[:, 1] / front[:, 2]
    u0 = int(np.searchsorted(columns[1], px.min()))
    u1 = int(np.searchsorted(columns[0], px.max(), side="right"))
    v0 = int(np.searchsorted(rows[1], py.min()))
    v1 = int(np.searchsorted(rows[0], py.max(), side="right"))
    if u0 >= u1 or v0 >= v1:
        return None
    return v0, v1, u0, u1


def _clip_near(polygon: np.ndarray) -> np.ndarray:
    """The part of a convex polygon (camera frame, (k, 3)) at depth `_NEAR_M` or more."""
    inside = polygon[:, 2] >= _NEAR_M
    if inside.all():
        return polygon
    out = []
    for i in range(len(polygon)):
        p, q = polygon[i], polygon[(i + 1) % len(polygon)]
        if p[2] >= _NEAR_M:
            out.append(p)
        if (p[2] >= _NEAR_M) != (q[2] >= _NEAR_M):
            s = (_NEAR_M - p[2]) / (q[2] - p[2])
            out.append(p + s * (q - p))
    return np.array(out).reshape(-1, 3)
