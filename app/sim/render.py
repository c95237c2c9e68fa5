"""Render textured planar quads seen by a `Camera`: the simulator's source of images.

Pipeline (per frame):

1. Painter's algorithm: quads are drawn far to near. A quad lying wholly in front of
   another's plane is drawn after it (so a card on a wall is drawn after the wall even
   when its centre is farther away than the wall's centre); otherwise by the camera
   depth of the centres (see _paint_order). Quads must not pierce each other. Quads
   wholly closer than the near plane, or seen from behind, are skipped.
2. Each quad is clipped in 3D against the near plane ``z_cam >= near``, projected into a
   supersampled *ideal pinhole* canvas, and only the bounding box of its visible part is
   warped (cv2.warpPerspective with a translated homography, INTER_LINEAR). The
   homography plane -> image is exact (``K [R e1 | R e2 | R c0 + t]`` composed with the
   texture's pixel-centre parametrisation), so it stays valid for quads crossing the
   near plane; the clipped polygon only bounds the work and masks pixels whose rays hit
   the plane behind the camera.
3. Textures are mip-mapped (INTER_AREA pyramid) and sampled trilinearly: a per-pixel
   level of detail from the homography's Jacobian (largest singular value, texels per
   canvas pixel) blends the two nearest levels, so a texture far larger than its image
   does not alias and a floor receding to the horizon gets the right level everywhere.
4. Coverage (anti-aliased edges) is the same homography applied to an all-ones mask
   with a zero border: the bilinear ramp puts the 50 % level exactly on the quad's edge.
   The mask's resolution is chosen so its texels are about one canvas pixel where the
   quad is closest. Compositing is ``canvas += coverage * (layer - canvas)``.
5. For a camera with lens distortion the supersampled canvas is remapped (bilinear)
   to the distorted image's sub-pixel samples, applying OpenCV's distortion model to
   the whole frame (the ideal canvas, `Camera.ideal_canvas`, is larger than the image
   for barrel distortion). Then it is box-filtered down by `supersample` (INTER_AREA:
   pixel ``x = (x_ss - (s - 1) / 2) / s``): each pixel integrates the distorted image
   over its area. (Distorting after the box filter would resample pixel values at a
   sub-pixel phase that varies over the frame, a blur varying across a small disc that
   moves its centroid by ~0.01 px.)

Texture mapping: texture corners (0, 0), (1, 0), (1, 1), (0, 1) in texture units are the
quad's corners 0..3 (top-left, top-right, bottom-right, bottom-left of the image), and
texture pixel (i, j) (row, column) has its centre at texture units
((j + 0.5) / w, (i + 0.5) / h). Card unit u of `markers.render_card` is thus texture
unit u, whatever the texture's resolution.

Front face: the side from which the texture reads correctly (not mirrored). Its normal
is ``(c3 - c0) x (c1 - c0)`` (texture-down x texture-right); `TexturedQuad.normal`.
A quad is drawn only if the camera centre is strictly on that side of its plane.

Known limits: edges shared by two quads (room corners) are each anti-aliased against
what lies behind them, so ~25 % of the background shows through along the seam (put a
backdrop of a similar tone behind, or overlap the quads slightly). Coverage edges of a
steeply receding quad are sharper (less anti-aliased) at its far end. No lighting,
blur or noise: the caller adds those.

Pure numpy/OpenCV; no I/O.
"""

from __future__ import annotations

import functools
import heapq
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike

from app.core.geometry import Camera, Pose

__all__ = ["NEAR_M", "TexturedQuad", "render", "visible_points"]

#: Near clipping distance (metres along the optical axis).
NEAR_M: float = 0.01

_PLANE_EPS_M = 1e-6  # quads closer than this to a plane count as on it (paint order)
_LOD_GRID = 16  # canvas pixels between samples of the level-of-detail field
_LOD_SPREAD_CONST = 0.05  # below this spread of levels over a quad, use one constant LOD
_MIN_LEVEL_SIZE = 4  # the mip pyramid stops when both sides are at most this
_MAX_MASK_SIZE = 4096  # coverage-mask texture side cap (memory, int16 remap limits)
_MIN_MASK_SIZE = 2

_ones_cache: np.ndarray | None = None


def _ones(h: int, w: int) -> np.ndarray:
    """A (h, w) uint8 view of one shared all-255 buffer (no per-quad allocation)."""
    global _ones_cache
    if _ones_cache is None:
        _ones_cache = np.full((_MAX_MASK_SIZE, _MAX_MASK_SIZE), 255, dtype=np.uint8)
        _ones_cache.setflags(write=False)
    return _ones_cache[:h, :w]


# --------------------------------------------------------------------------------------
# Quads
# --------------------------------------------------------------------------------------


@dataclass(eq=False)  # eq=False: ndarray fields
class TexturedQuad:
    """A planar parallelogram (usually a rectangle) in map coordinates with a texture.

    Parameters
    ----------
    corners : (4, 3) array_like
        Map coordinates (metres) of the texture's top-left, top-right, bottom-right and
        bottom-left corners; corner 2 must equal c1 + c3 - c0 (the map from texture
        units to the plane is affine, hence a homography to the image).
    texture : (h, w) ndarray
        Greyscale, uint8 (0..255) or float in [0, 1]; stored float32 in [0, 1].
    mipmaps : list of ndarray, optional
        The texture pyramid, level 0 = texture; built on first use (`mip_levels`).

    Raises
    ------
    ValueError
        If the corners are not a finite, non-degenerate parallelogram or the texture
        is not a non-empty 2-D image.
    """

    corners: np.ndarray
    texture: np.ndarray
    mipmaps: list[np.ndarray] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        c = np.array(self.corners, dtype=np.float64, copy=True)
        if c.shape != (4, 3) or not np.all(np.isfinite(c)):
            raise ValueError(f"corners must be a finite (4, 3) array, got shape {c.shape}")
        e1, e2 = c[1] - c[0], c[3] - c[0]
        scale = max(float(np.linalg.norm(e1)), float(np.linalg.norm(e2)))
        if np.linalg.norm(np.cross(e1, e2)) <= 1e-12 * max(scale * scale, 1e-300):
            raise ValueError("corners are degenerate (zero area)")
        if np.linalg.norm(c[2] - (c[1] + c[3] - c[0])) > 1e-6 * scale:
            raise ValueError("corners must form a planar parallelogram: c2 == c1 + c3 - c0")
        c.setflags(write=False)
        self.corners = c
        tex = np.asarray(self.texture)
        if tex.ndim != 2 or tex.size == 0:
            raise ValueError(f"texture must be a non-empty greyscale (h, w) image, got {tex.shape}")
        if tex.dtype == np.uint8:
            tex = tex.astype(np.float32) * np.float32(1.0 / 255.0)
        else:
            tex = np.ascontiguousarray(tex, dtype=np.float32)
        self.texture = tex

    @classmethod
    def from_frame(
        cls, origin: ArrayLike, x_edge: ArrayLike, y_edge: ArrayLike, texture: np.ndarray
    ) -> TexturedQuad:
        """A quad from its top-left corner and two edge vectors.

        Parameters
        ----------
        origin : (3,) array_like
            Map coordinates of the texture's top-left corner, metres.
        x_edge : (3,) array_like
            The whole top edge, left to right, metres.
        y_edge : (3,) array_like
            The whole left edge, top to bottom, metres.
        texture : (h, w) ndarray
            As for the class.

        Returns
        -------
        TexturedQuad
        """
        o = np.asarray(origin, np.float64)
        ex, ey = np.asarray(x_edge, np.float64), np.asarray(y_edge, np.float64)
        return cls(np.stack([o, o + ex, o + ex + ey, o + ey]), texture)

    @property
    def normal(self) -> np.ndarray:
        """Unit normal out of the front face (the side the texture reads correctly)."""
        c = self.corners
        n = np.cross(c[3] - c[0], c[1] - c[0])
        return n / np.linalg.norm(n)

    @property
    def centre(self) -> np.ndarray:
        """Mean of the corners, map coordinates."""
        return self.corners.mean(axis=0)

    def mip_levels(self) -> list[np.ndarray]:
        """The texture's mip pyramid, built on first use and kept.

        Returns
        -------
        list of ndarray
            [texture, half, quarter, ...] (INTER_AREA box filter), float32, down to a
            few texels a side.
        """
        if self.mipmaps is None:
            levels = [self.texture]
            while max(levels[-1].shape) > _MIN_LEVEL_SIZE:
                h, w = levels[-1].shape
                nw, nh = (w + 1) // 2, (h + 1) // 2
                levels.append(cv2.resize(levels[-1], (nw, nh), interpolation=cv2.INTER_AREA))
            self.mipmaps = levels
        return self.mipmaps


# --------------------------------------------------------------------------------------
# Geometry helpers
# --------------------------------------------------------------------------------------


def _clip_polygon(poly: np.ndarray, a: np.ndarray, b: float) -> np.ndarray:
    """Sutherland-Hodgman: the part of convex polygon `poly` (M, d) with a.p + b >= 0."""
    d = poly @ a + b
    if np.all(d >= 0):
        return poly
    out = []
    m = len(poly)
    for i in range(m):
        j = (i + 1) % m
        if d[i] >= 0:
            out.append(poly[i])
        if (d[i] >= 0) != (d[j] >= 0):
            s = d[i] / (d[i] - d[j])
            out.append(poly[i] + s * (poly[j] - poly[i]))
    return np.array(out, dtype=np.float64).reshape(-1, poly.shape[1])


def _clip_rect(poly: np.ndarray, x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    for a, b in (((1.0, 0.0), -x0), ((-1.0, 0.0), x1), ((0.0, 1.0), -y0), ((0.0, -1.0), y1)):
        if len(poly) < 3:
            break
        poly = _clip_polygon(poly, np.array(a), b)
    return poly


def _texel_to_unit(w: int, h: int) -> np.ndarray:
    """Texture pixel (x = column, y = row) -> texture units; pixel centres at +0.5."""
    return np.array([[1.0 / w, 0.0, 0.5 / w], [0.0, 1.0 / h, 0.5 / h], [0.0, 0.0, 1.0]])


def _lod(G: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """log2 of the largest singular value of d(texel)/d(pixel) for homography G
    (pixel -> texel) at pixels (x, y): how many texels one pixel step spans, at most."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        W = G[2, 0] * x + G[2, 1] * y + G[2, 2]
        u = (G[0, 0] * x + G[0, 1] * y + G[0, 2]) / W
        v = (G[1, 0] * x + G[1, 1] * y + G[1, 2]) / W
        j00 = (G[0, 0] - u * G[2, 0]) / W
        j01 = (G[0, 1] - u * G[2, 1]) / W
        j10 = (G[1, 0] - v * G[2, 0]) / W
        j11 = (G[1, 1] - v * G[2, 1]) / W
        a = j00 * j00 + j01 * j01 + j10 * j10 + j11 * j11
        det = j00 * j11 - j01 * j10
        s2 = 0.5 * (a + np.sqrt(np.maximum(a * a - 4.0 * det * det, 0.0)))
        lam = 0.5 * np.log2(np.maximum(s2, 1e-30))
    return np.nan_to_num(lam, nan=60.0, posinf=60.0, neginf=-60.0)


def _translate(dx: float, dy: float) -> np.ndarray:
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------


def _draw_quad(
    canvas: np.ndarray, P: np.ndarray, quad: TexturedQuad, Xc: np.ndarray, near: float
) -> None:
    """Composite one quad (corners `Xc` in camera coordinates) onto `canvas`.

    P maps camera coordinates to homogeneous canvas pixels (its last row is [0, 0, 1]).
    """
    ch, cw = canvas.shape
    poly3 = _clip_polygon(Xc, np.array([0.0, 0.0, 1.0]), -near)
    if len(poly3) < 3:
        return
    clipped = bool(np.any(Xc[:, 2] < near))
    ph = poly3 @ P.T
    poly = ph[:, :2] / ph[:, 2:3]
    # Clip in 2D too: the near-plane vertices can project millions of pixels away.
    poly = _clip_rect(poly, -2.0, -2.0, cw + 1.0, ch + 1.0)
    if len(poly) < 3:
        return
    bx0 = max(int(math.floor(poly[:, 0].min())) - 1, 0)
    by0 = max(int(math.floor(poly[:, 1].min())) - 1, 0)
    bx1 = min(int(math.ceil(poly[:, 0].max())) + 2, cw)
    by1 = min(int(math.ceil(poly[:, 1].max())) + 2, ch)
    if bx1 <= bx0 or by1 <= by0:
        return
    bw, bh = bx1 - bx0, by1 - by0

    # Texture units (a, b) -> camera (c0 + a e1 + b e2) -> canvas -> bounding box.
    e1, e2 = Xc[1] - Xc[0], Xc[3] - Xc[0]
    Hu = _translate(-bx0, -by0) @ P @ np.column_stack([e1, e2, Xc[0]])
    levels = quad.mip_levels()
    h0, w0 = levels[0].shape
    G0 = np.linalg.inv(Hu @ _texel_to_unit(w0, h0))  # bbox pixel -> level-0 texel
    vx, vy = poly[:, 0] - bx0, poly[:, 1] - by0
    lam_v = _lod(G0, vx, vy)  # extremes of the LOD are at the polygon's vertices
    top = len(levels) - 1
    lo = float(np.clip(lam_v.min(), 0, top))
    hi = float(np.clip(lam_v.max(), 0, top))

    def warp(level: int, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
        tex = levels[level]
        th, tw = tex.shape
        H = _translate(-x0, -y0) @ Hu @ _texel_to_unit(tw, th)
        return cv2.warpPerspective(
            tex, H, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )

    l_lo, l_hi = int(math.floor(lo)), int(math.ceil(hi))
    if l_lo == l_hi:
        layer = warp(l_lo, 0, 0, bw, bh)
    elif hi - lo < _LOD_SPREAD_CONST:
        lam = 0.5 * (lo + hi)
        f = lam - l_lo
        layer = warp(l_lo, 0, 0, bw, bh)
        layer *= np.float32(1.0 - f)
        layer += np.float32(f) * warp(l_lo + 1, 0, 0, bw, bh)
    else:
        layer = _trilinear(warp, G0, poly - (bx0, by0), bw, bh, top, l_lo, l_hi)

    # Coverage: the homography applied to an all-ones mask with a zero border.
    sigma_near = 2.0 ** float(lam_v.min())  # level-0 texels per pixel where most magnified
    mw = int(np.clip(math.ceil(w0 / max(sigma_near, 1e-9)), _MIN_MASK_SIZE, _MAX_MASK_SIZE))
    mh = int(np.clip(math.ceil(h0 / max(sigma_near, 1e-9)), _MIN_MASK_SIZE, _MAX_MASK_SIZE))
    m8 = cv2.warpPerspective(
        _ones(mh, mw), Hu @ _texel_to_unit(mw, mh), (bw, bh),
        flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0,
    )
    mask = m8.astype(np.float32)
    mask *= np.float32(1.0 / 255.0)
    if clipped:
        # Pixels whose ray meets the plane behind the camera (or nearer than `near`)
        # would otherwise be textured through the homography's projective wrap-around.
        # Inverse depth along the ray through a pixel is affine in the pixel coordinates.
        n = np.cross(e1, e2)
        c = float(n @ Xc[0])
        a = (n @ np.linalg.inv(_translate(-bx0, -by0) @ P)) / c
        xs = np.arange(bw, dtype=np.float64)
        ys = np.arange(bh, dtype=np.float64)
        invz = (a[0] * xs)[None, :] + (a[1] * ys + a[2])[:, None]
        mask[(invz <= 0) | (invz > 1.0 / near)] = 0.0

    region = canvas[by0:by1, bx0:bx1]
    layer -= region
    layer *= mask
    region += layer


def _trilinear(
    warp: Callable[[int, int, int, int, int], np.ndarray],
    G0: np.ndarray,
    poly: np.ndarray,
    bw: int,
    bh: int,
    top: int,
    l_lo: int,
    l_hi: int,
) -> np.ndarray:
    """Blend mip levels l_lo..l_hi with per-pixel weights max(0, 1 - |lod - L|).

    The LOD field is evaluated on a coarse grid and upsampled bilinearly (it is smooth);
    each level is warped only over the cells where its weight can be non-zero and the
    quad is present.
    """
    g = _LOD_GRID
    nx, ny = -(-bw // g), -(-bh // g)
    gx = (np.arange(nx, dtype=np.float64) + 0.5) * g - 0.5  # cv2.resize's cell centres
    gy = (np.arange(ny, dtype=np.float64) + 0.5) * g - 0.5
    lam_c = np.clip(_lod(G0, gx[None, :], gy[:, None]), 0, top).astype(np.float32)
    lam_f = cv2.resize(lam_c, (nx * g, ny * g), interpolation=cv2.INTER_LINEAR)[:bh, :bw]
    present = np.zeros((ny, nx), np.uint8)
    cpoly = np.round(((poly + 0.5) / g - 0.5) * 16).astype(np.int32)
    cv2.fillConvexPoly(present, cpoly, 1, lineType=cv2.LINE_8, shift=4)
    present = cv2.dilate(present, np.ones((3, 3), np.uint8)).astype(bool)
    layer = np.zeros((bh, bw), np.float32)
    for level in range(l_lo, l_hi + 1):
        cells = present & (np.abs(lam_c - level) < 1.0)
        if not cells.any():
            continue
        cells = cv2.dilate(cells.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        rows, cols = np.flatnonzero(cells.any(axis=1)), np.flatnonzero(cells.any(axis=0))
        x0, x1 = int(cols[0]) * g, min((int(cols[-1]) + 1) * g, bw)
        y0, y1 = int(rows[0]) * g, min((int(rows[-1]) + 1) * g, bh)
        weight = lam_f[y0:y1, x0:x1] - np.float32(level)
        np.abs(weight, out=weight)
        np.subtract(np.float32(1.0), weight, out=weight)
        np.maximum(weight, 0.0, out=weight)
        weight *= warp(level, x0, y0, x1, y1)
        layer[y0:y1, x0:x1] += weight
    return layer


def _paint_order(quads: Sequence[TexturedQuad], depths: Sequence[float]) -> list[int]:
    """Indices of `quads` (all facing the camera) in drawing order, far to near.

    Sorting by centre depth alone fails for a card on a large wall (the card's centre
    can be farther than the wall's). So: if quad j lies wholly on the front side of quad
    i's plane and i does not lie wholly on the front side of j's plane, i cannot hide j
    and is drawn first. Coplanar quads (decals) draw larger first. Everything else
    (quads that cannot overlap, or that straddle each other's planes) falls back to
    centre depth, farthest first; a topological sort combines the two.
    """
    n = len(quads)
    if n <= 1:
        return list(range(n))
    corners = np.stack([q.corners for q in quads])  # (n, 4, 3)
    normals = np.stack([q.normal for q in quads])
    offsets = np.einsum("id,id->i", normals, corners[:, 0])
    # dist[i, j, k]: signed distance of corner k of quad j from the plane of quad i
    dist = np.einsum("id,jkd->ijk", normals, corners) - offsets[:, None, None]
    eps = _PLANE_EPS_M
    front = np.all(dist >= -eps, axis=2)
    coplanar = np.all(np.abs(dist) <= eps, axis=2)
    coplanar &= coplanar.T
    area = np.linalg.norm(
        np.cross(corners[:, 1] - corners[:, 0], corners[:, 3] - corners[:, 0]), axis=1
    )
    before = (front & ~front.T) | (coplanar & (area[:, None] > area[None, :]))
    np.fill_diagonal(before, False)  # before[i, j]: draw i before j
    indeg = before.sum(axis=0)
    heap = [(-depths[i], i) for i in range(n) if indeg[i] == 0]
    heapq.heapify(heap)
    order: list[int] = []
    done = np.zeros(n, dtype=bool)
    while len(order) < n:
        if not heap:  # a cycle (degenerate geometry): break it by depth
            i = max((k for k in range(n) if not done[k]), key=lambda k: (depths[k], -k))
        else:
            _, i = heapq.heappop(heap)
            if done[i]:
                continue
        done[i] = True
        order.append(i)
        for j in np.flatnonzero(before[i]):
            indeg[j] -= 1
            if indeg[j] == 0 and not done[j]:
                heapq.heappush(heap, (-depths[j], int(j)))
    return order


def render(
    camera: Camera,
    pose: Pose,
    quads: Sequence[TexturedQuad],
    background: float = 0.5,
    supersample: int = 2,
    near: float = NEAR_M,
) -> np.ndarray:
    """The image that `camera` at `pose` sees of a set of textured quads.

    Lens distortion is applied to the whole frame; see the module docstring.

    Parameters
    ----------
    camera : Camera
        Intrinsics, distortion and image size.
    pose : Pose
        Map-to-camera transform, ``x_cam = R @ X_map + t``.
    quads : sequence of TexturedQuad
        The scene, in map coordinates; quads must not pierce each other.
    background : float, optional
        Grey level where no quad is drawn, 0..1.
    supersample : int, optional
        Samples per pixel along each axis (each pixel is their box-filtered mean).
    near : float, optional
        Near clipping distance along the optical axis, metres.

    Returns
    -------
    (height, width) ndarray of float32
        Grey levels in [0, 1], pixel centre of the top-left pixel at (0, 0).

    Raises
    ------
    ValueError
        If `supersample` is not a positive integer or `near` is not positive.
    """
    s = int(supersample)
    if s != supersample or s < 1:
        raise ValueError(f"supersample must be a positive integer, got {supersample!r}")
    if not near > 0:
        raise ValueError("near must be positive")
    distorted = camera.has_distortion
    if distorted:
        ic = camera.ideal_canvas
        x0, y0, cw, ch = ic.x0, ic.y0, ic.width, ic.height
    else:
        x0, y0, cw, ch = 0, 0, camera.width, camera.height
    canvas = np.full((ch * s, cw * s), np.float32(background), dtype=np.float32)
    # Camera coordinates -> supersampled canvas pixels (ideal pixel x <-> s (x - x0) + (s-1)/2).
    P = np.array(
        [[s, 0.0, (s - 1) / 2.0 - s * x0], [0.0, s, (s - 1) / 2.0 - s * y0], [0.0, 0.0, 1.0]]
    ) @ camera.K

    eye = pose.position
    todo: list[tuple[float, int, TexturedQuad, np.ndarray]] = []
    for i, q in enumerate(quads):
        if float(q.normal @ (eye - q.corners[0])) <= 0.0:
            continue  # seen from behind or edge-on
        Xc = pose.transform(q.corners)
        if float(Xc[:, 2].max()) <= near:
            continue
        todo.append((float(Xc[:, 2].mean()), i, q, Xc))
    for k in _paint_order([q for _, _, q, _ in todo], [d for d, _, _, _ in todo]):
        _draw_quad(canvas, P, todo[k][2], todo[k][3], near)

    if distorted:
        # Distort before the box filter (see the module docstring, step 5).
        map_x, map_y = _supersampled_maps(camera, s)
        canvas = cv2.remap(
            canvas, map_x, map_y, cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT, borderValue=float(background),
        )
    w, h = camera.width, camera.height
    img = canvas if s == 1 else cv2.resize(canvas, (w, h), interpolation=cv2.INTER_AREA)
    np.clip(img, 0.0, 1.0, out=img)
    return img


def _supersampled_maps(camera: Camera, s: int) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps (float32, (height * s, width * s)) from the distorted image's
    sub-pixel samples (pixel x's samples at x + (i - (s - 1) / 2) / s) into the
    supersampled ideal canvas of `Camera.ideal_canvas` (ideal pixel x at canvas column
    s (x - x0) + (s - 1) / 2). For s == 1, the camera's own maps."""
    ic = camera.ideal_canvas
    if s == 1:
        return ic.map_x, ic.map_y
    return _supersampled_maps_of(camera._key(), s, ic.x0, ic.y0)


@functools.lru_cache(maxsize=8)
def _supersampled_maps_of(key: tuple[bytes, bytes, int, int], s: int, x0: int, y0: int
                          ) -> tuple[np.ndarray, np.ndarray]:
    K, dist, w, h = key
    camera = Camera(np.frombuffer(K).reshape(3, 3), np.frombuffer(dist), w, h)
    sub = (np.arange(s, dtype=np.float64) - (s - 1) / 2.0) / s
    us = (np.arange(w, dtype=np.float64)[:, None] + sub[None, :]).ravel()
    vs = (np.arange(h, dtype=np.float64)[:, None] + sub[None, :]).ravel()
    uu, vv = np.meshgrid(us, vs)
    ideal = camera.undistort_pixels(np.stack([uu.ravel(), vv.ravel()], axis=1))
    map_x = (s * (ideal[:, 0] - x0) + (s - 1) / 2.0).reshape(h * s, w * s).astype(np.float32)
    map_y = (s * (ideal[:, 1] - y0) + (s - 1) / 2.0).reshape(h * s, w * s).astype(np.float32)
    map_x.setflags(write=False)
    map_y.setflags(write=False)
    return map_x, map_y


def visible_points(
    camera: Camera,
    pose: Pose,
    X_map: ArrayLike,
    normals: ArrayLike | None = None,
    near: float = NEAR_M,
) -> np.ndarray:
    """Which map points the camera sees (occlusion aside).

    A point is visible when it lies in front of the camera (z_cam > near), projects
    inside the image (pixel areas: -0.5 <= u < width - 0.5, likewise v) after
    distortion, and, if `normals` are given, lies on a surface facing the camera.

    With distortion the ideal projection must also lie in the region the lens actually
    sees (Camera.ideal_canvas): far-off points can fold back into the image through the
    distortion polynomial. For a lens whose image lies inside its fold this is the same
    as ``Camera.in_field(margin=1.0)``; the canvas is kept because it is what `render`
    draws, also for a wild lens whose image reaches the fold (where the two differ).

    Parameters
    ----------
    camera : Camera
    pose : Pose
        Map-to-camera transform.
    X_map : (N, 3) array_like
        Points in map coordinates, metres.
    normals : (N, 3) or (3,) array_like, optional
        Normals of the surfaces the points lie on (out of the visible side).
    near : float, optional
        Near clipping distance, metres.

    Returns
    -------
    (N,) ndarray of bool
    """
    X = np.asarray(X_map, dtype=np.float64).reshape(-1, 3)
    Xc = pose.transform(X)
    ok = Xc[:, 2] > near
    uv = camera.project(Xc)
    with np.errstate(invalid="ignore"):
        ok &= np.all(np.isfinite(uv), axis=1)
        ok &= (uv[:, 0] >= -0.5) & (uv[:, 0] < camera.width - 0.5)
        ok &= (uv[:, 1] >= -0.5) & (uv[:, 1] < camera.height - 0.5)
        if camera.has_distortion:
            ic = camera.ideal_canvas
            ideal = camera.project_ideal(Xc)
            ok &= (ideal[:, 0] >= ic.x0) & (ideal[:, 0] <= ic.x0 + ic.width - 1)
            ok &= (ideal[:, 1] >= ic.y0) & (ideal[:, 1] <= ic.y0 + ic.height - 1)
    if normals is not None:
        n = np.broadcast_to(np.asarray(normals, dtype=np.float64), X.shape)
        ok &= np.einsum("ij,ij->i", n, pose.position - X) > 0
    return ok
