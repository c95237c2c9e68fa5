"""Renderer: geometric accuracy (the simulator is the ground truth), distortion, culling,
near-plane clipping, paint order, texture mapping and anti-aliasing."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from app.core.geometry.camera import Camera, Pose
from app.core.markers import marker_layout, render_card
from app.sim.render import TexturedQuad, render, visible_points

LAYOUT = marker_layout("fido3x3", 5)
SIDE = 0.2  # card side (m): 160 px at 1 m with f = 800
CARD_PX = 512  # texture >= 3x its projected size
DIST = [-0.2, 0.05, 0.0, 0.0, 0.0]


def _rot_y(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def _card(centre, R: np.ndarray = np.eye(3), px: int = CARD_PX) -> TexturedQuad:
    """Card facing a camera at the origin looking along +z (identity pose), upright."""
    ex, ey = R @ [SIDE, 0.0, 0.0], R @ [0.0, SIDE, 0.0]
    origin = np.asarray(centre, float) - ex / 2 - ey / 2
    return TexturedQuad.from_frame(origin, ex, ey, render_card(LAYOUT, px))


def _disc_centres(q: TexturedQuad) -> np.ndarray:
    c = q.corners
    return np.array([c[0] + a * (c[1] - c[0]) + b * (c[3] - c[0]) for a, b in LAYOUT.discs])


def _centroids(img: np.ndarray, cam: Camera, q: TexturedQuad) -> np.ndarray:
    """Intensity-weighted (1 - I) centroid of each disc in a circular window of 1.35
    radii around its projected centre: only the disc and white card inside (the card
    edge and the code are >= 1.6 radii away)."""
    out = []
    for X in _disc_centres(q):
        u, v = cam.project(X)[0]
        r_px = LAYOUT.disc_radius * SIDE * cam.fx / X[2]
        h = int(np.ceil(1.35 * r_px)) + 1
        x0, y0 = int(round(u)) - h, int(round(v)) - h
        ys, xs = np.mgrid[y0 : y0 + 2 * h + 1, x0 : x0 + 2 * h + 1]
        w = 1.0 - img[y0 : y0 + 2 * h + 1, x0 : x0 + 2 * h + 1].astype(np.float64)
        w[np.hypot(xs - u, ys - v) > 1.35 * r_px] = 0.0
        out.append([(w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()])
    return np.array(out)


def _area_centroids(cam: Camera, q: TexturedQuad, n: int = 400) -> np.ndarray:
    """Exact image centroid of each disc's (distorted) projection, by integration.

    Uniform samples over the disc on the card; each is weighted by its image area
    element: 1/z^3 for a plane seen by a pinhole, times the distortion's Jacobian.
    """
    g = (np.arange(n) + 0.5) / n * 2 - 1
    gx, gy = np.meshgrid(g, g)
    inside = gx**2 + gy**2 <= 1
    c = q.corners
    out = []
    for a, b in LAYOUT.discs:
        A = a + LAYOUT.disc_radius * gx[inside]
        B = b + LAYOUT.disc_radius * gy[inside]
        X = c[0] + A[:, None] * (c[1] - c[0]) + B[:, None] * (c[3] - c[0])
        ideal = cam.project_ideal(X)
        e = 1e-3
        du = (cam.distort_pixels(ideal + [e, 0]) - cam.distort_pixels(ideal - [e, 0])) / (2 * e)
        dv = (cam.distort_pixels(ideal + [0, e]) - cam.distort_pixels(ideal - [0, e])) / (2 * e)
        w = np.abs(du[:, 0] * dv[:, 1] - du[:, 1] * dv[:, 0]) / X[:, 2] ** 3
        out.append((cam.distort_pixels(ideal) * w[:, None]).sum(0) / w.sum())
    return np.array(out)


def _err(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.hypot(a[:, 0] - b[:, 0], a[:, 1] - b[:, 1])


def _backdrop(value: float = 0.8) -> TexturedQuad:
    """A uniform grey plane at 3 m behind the card."""
    return TexturedQuad.from_frame([-4, -4, 3.0], [8, 0, 0], [0, 8, 0], np.full((8, 8), value))


# --------------------------------------------------------------------------------------
# Geometric accuracy
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("ss", [1, 2, 3])
@pytest.mark.parametrize("centre", [[0.0131, -0.0072, 1.0], [0.31, 0.207, 1.1]])
def test_fronto_parallel_disc_centroid_is_projected_centre(centre: list, ss: int) -> None:
    cam = Camera.pinhole(800.0, 640, 480)
    q = _card(centre)
    img = render(cam, Pose.identity(), [_backdrop(), q], supersample=ss)
    err = _err(_centroids(img, cam, q), cam.project(_disc_centres(q)))
    assert err.max() < 0.05, err  # measured ~0.003 px


def test_tilted_disc_centroid_is_area_centroid_not_projected_centre() -> None:
    """Under perspective the centroid of a disc's image is not the image of its centre
    (by ~0.09 px at 10 degrees here), so ground truth for discs must be the projection
    of the 3D centre; the renderer itself agrees with the exact area centroid."""
    cam = Camera.pinhole(800.0, 640, 480)
    for deg in (10.0, 30.0):
        q = _card([0.011, -0.013, 1.0], _rot_y(deg))
        img = render(cam, Pose.identity(), [_backdrop(), q])
        cents = _centroids(img, cam, q)
        assert _err(cents, _area_centroids(cam, q)).max() < 0.05
        if deg == 10.0:
            assert _err(cents, cam.project(_disc_centres(q))).min() > 0.05


def test_distortion_undistort_points_consistency() -> None:
    cam = Camera.pinhole(800.0, 640, 480, dist=DIST)
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(-1.5, 1.5, 4000), rng.uniform(-1.2, 1.2, 4000),
                         rng.uniform(1.5, 2.5, 4000)])
    vis = visible_points(cam, Pose.identity(), X)
    assert 500 < vis.sum() < 4000
    uv = cam.project(X[vis])
    und = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist, P=cam.K)[:, 0]
    assert np.abs(und - cam.project_ideal(X[vis])).max() < 0.01


@pytest.mark.parametrize("centre", [[0.011, -0.013, 1.0], [0.25, 0.17, 1.0]])
def test_distorted_disc_centroid(centre: list) -> None:
    cam = Camera.pinhole(800.0, 640, 480, dist=DIST)
    q = _card(centre)
    img = render(cam, Pose.identity(), [_backdrop(), q])
    cents = _centroids(img, cam, q)
    # The renderer applies the lens model exactly (vs integrated centroid, ~0.01 px).
    assert _err(cents, _area_centroids(cam, q)).max() < 0.03
    if centre[0] < 0.1:  # near the image centre the distortion is locally affine
        assert _err(cents, cam.project(_disc_centres(q))).max() < 0.1


def test_small_distorted_discs_keep_their_centroids() -> None:
    """Distortion is applied before the box filter (each pixel integrates the distorted
    image). Remapping the box-filtered image instead would blur by a sub-pixel phase that
    varies over the frame and move the centroids of 3-5 px discs by ~0.013 px RMS on
    these cards, as much as the detector's own error; what remains is mostly this
    window centroid's own error on small discs."""
    cam = Camera.pinhole(800.0, 640, 480, dist=DIST)
    rng = np.random.default_rng(1)
    errs = []
    for _ in range(12):
        z = rng.uniform(4.0, 6.0)
        q = _card([rng.uniform(-0.3, 0.3) * z, rng.uniform(-0.2, 0.2) * z, z])
        wall = TexturedQuad.from_frame([-40, -40, z + 1], [80, 0, 0], [0, 80, 0], np.full((8, 8), 0.8))
        img = render(cam, Pose.identity(), [wall, q], supersample=2)
        errs.append(_err(_centroids(img, cam, q), _area_centroids(cam, q)))
    rms = float(np.sqrt(np.mean(np.square(errs))))
    assert rms < 0.009, rms


def test_texture_mapping_is_exact_at_one_texel_per_pixel() -> None:
    """Texel (i, j) centre = texture units ((j + .5)/w, (i + .5)/h); mapped 1:1 onto
    pixel centres the rendered image reproduces the texture."""
    f, z = 800.0, 2.0
    cam = Camera.pinhole(f, 640, 480)
    tex = np.random.default_rng(1).random((64, 64)).astype(np.float32)
    # texture unit 0 at pixel edge 99.5 -> texel (i, j) lands on pixel (50 + i, 100 + j)
    origin = [(99.5 - cam.cx) / f * z, (49.5 - cam.cy) / f * z, z]
    s = 64 / f * z
    q = TexturedQuad.from_frame(origin, [s, 0, 0], [0, s, 0], tex)
    img = render(cam, Pose.identity(), [q], supersample=1, background=0.0)
    assert np.abs(img[50:114, 100:164] - tex).max() < 1e-4
    assert np.all(img[:49] == 0.0) and np.all(img[:, :99] == 0.0)


def test_mipmaps_prevent_aliasing() -> None:
    cam = Camera.pinhole(800.0, 640, 480)
    i = np.arange(1024)
    checker = ((i[:, None] + i[None, :]) % 2).astype(np.float32)  # 1-texel cells
    q = TexturedQuad.from_frame([-0.1, -0.1, 1.0], [0.2, 0, 0], [0, 0.2, 0], checker)
    assert [lv.shape[0] for lv in q.mip_levels()] == [1024, 512, 256, 128, 64, 32, 16, 8, 4]
    img = render(cam, Pose.identity(), [q], supersample=1)
    inner = img[180:300, 260:380]
    assert abs(inner.mean() - 0.5) < 0.01 and inner.std() < 0.02
    no_mip = TexturedQuad(q.corners, checker, mipmaps=[checker])
    aliased = render(cam, Pose.identity(), [no_mip], supersample=1)[180:300, 260:380]
    assert aliased.std() > 0.1  # what the pyramid prevents


# --------------------------------------------------------------------------------------
# Culling, clipping, order
# --------------------------------------------------------------------------------------


def test_card_seen_from_behind_is_invisible() -> None:
    cam = Camera.pinhole(800.0, 640, 480)
    q = _card([0.0, 0.0, 1.0])
    assert np.dot(q.normal, [0, 0, -1]) > 0.99  # front faces the camera at the origin
    # Same card turned around (mirror the corners' order): the camera sees its back.
    c = q.corners
    back = TexturedQuad(np.stack([c[1], c[0], c[3], c[2]]), q.texture)
    img = render(cam, Pose.identity(), [back], background=0.3)
    assert np.all(img == np.float32(0.3))
    # Or walk behind the original card and look at it.
    img = render(cam, Pose.look_at([0, 0, 2.0], [0, 0, 1.0], up=[0, -1, 0]), [q], background=0.3)
    assert np.all(img == np.float32(0.3))
    assert not np.all(render(cam, Pose.identity(), [q], background=0.3) == np.float32(0.3))


def test_floor_extending_behind_camera() -> None:
    """A big floor crossing the near plane: nothing above the horizon, no crash."""
    cam = Camera.pinhole(600.0, 640, 480, dist=DIST)
    i = np.arange(1024) // 16
    checker = (((i[:, None] + i[None, :]) % 2) * 0.3).astype(np.float32)  # 0 / 0.3
    floor = TexturedQuad.from_frame([-20, 20, 0], [40, 0, 0], [0, -40, 0], checker)
    assert np.allclose(floor.normal, [0, 0, 1])
    pose = Pose.look_at([0.3, -0.2, 1.6], [5, -0.2, 1.6])  # level: horizon at row 239.5
    img = render(cam, pose, [floor], background=0.8)
    assert np.all(img[:240] == np.float32(0.8))
    assert np.all(img[300:] <= 0.3 + 1e-6)  # floor everywhere below
    # Rolled and pitched: the bounding box of the floor's visible part now includes
    # sky, where the plane homography "sees" the floor behind the camera.
    pose = Pose.look_at([0.3, -0.2, 1.6], [5, 1, 1.0], up=[0, 0.6, 1])
    img = render(cam, pose, [floor], background=0.8)
    vs, us = np.mgrid[0:480, 0:640]
    ideal = cam.undistort_pixels(np.stack([us.ravel(), vs.ravel()], axis=1))
    rays = np.column_stack([ideal, np.ones(len(ideal))]) @ np.linalg.inv(cam.K).T @ pose.R
    sky = (rays[:, 2] > 0).reshape(480, 640)
    assert 20000 < sky.sum() < 640 * 480 - 20000
    assert np.all(img[sky] == np.float32(0.8))
    assert np.count_nonzero(img[~sky] <= 0.3 + 1e-6) > 20000  # floor (below the horizon)
    # Looking down and rolled; the camera right above the floor's edge.
    for eye, target in (([0.0, 0.0, 0.5], [2, 1, 0]), ([19.9, 0, 0.3], [25, 0, 0.2])):
        img = render(cam, Pose.look_at(eye, target, up=[0, 0.3, 1]), [floor], background=0.8)
        assert np.isfinite(img).all() and img.min() >= 0 and img.max() <= 1


def test_quad_wholly_behind_or_outside_view_is_skipped() -> None:
    cam = Camera.pinhole(800.0, 640, 480)
    behind = _card([0, 0, -1.0])
    aside = _card([5.0, 0, 1.0])
    edge_on = TexturedQuad.from_frame([0, -0.1, 0.5], [0, 0, 1.0], [0, 0.2, 0], np.ones((4, 4)))
    img = render(cam, Pose.identity(), [behind, aside, edge_on], background=0.25)
    assert np.all(img == np.float32(0.25))
    assert np.all(render(cam, Pose.identity(), [], background=0.7) == np.float32(0.7))


def test_paint_order_card_on_wall_and_occlusion() -> None:
    cam = Camera.pinhole(500.0, 640, 480)
    # A long wall seen obliquely; a card on its far part has a centre farther away than
    # the wall's centre, yet must be drawn over the wall.
    wall = TexturedQuad.from_frame([-1, -1.5, 1.0], [0, 0, 8.0], [0, 3.0, 0], np.full((4, 4), 0.5))
    assert wall.normal[0] > 0.99
    pose = Pose.look_at([1.0, 0.0, 0.0], [-1.0, 0.0, 3.0], up=[0, -1, 0])
    card = TexturedQuad.from_frame([-0.998, -0.1, 5.8], [0, 0, 0.2], [0, 0.2, 0], np.zeros((8, 8)))
    assert pose.transform(card.centre)[0, 2] > pose.transform(wall.centre)[0, 2]
    img = render(cam, pose, [card, wall], background=1.0)
    u, v = cam.project_map(card.centre, pose)[0]
    assert img[int(round(v)), int(round(u))] < 0.05
    # A near card hides a far one regardless of list order.
    near_card = TexturedQuad.from_frame([-0.1, -0.1, 1], [0.2, 0, 0], [0, 0.2, 0], np.zeros((4, 4)))
    far_card = TexturedQuad.from_frame([-0.2, -0.2, 2], [0.4, 0, 0], [0, 0.4, 0], np.ones((4, 4)))
    for order in ([near_card, far_card], [far_card, near_card]):
        img = render(Camera.pinhole(800.0, 640, 480), Pose.identity(), order, background=0.5)
        assert img[240, 320] == 0.0


def test_visible_points() -> None:
    cam = Camera.pinhole(800.0, 640, 480, dist=DIST)
    pose = Pose.identity()
    X = np.array([
        [0.0, 0.0, 2.0],  # centre
        [0.0, 0.0, -2.0],  # behind
        [0.0, 0.0, 0.001],  # nearer than the near plane
        [3.0, 0.0, 1.0],  # far outside the image
        [0.41, 0.0, 1.0],  # ideal u = 647.5 but barrel distortion pulls it into the image
    ])
    assert cam.project_ideal(X[4])[0, 0] > 640 and cam.project(X[4])[0, 0] < 639
    assert visible_points(cam, pose, X).tolist() == [True, False, False, False, True]
    # Strong barrel distortion folds far-off points back into the image (the
    # polynomial turns over): they are not visible.
    folding = Camera.pinhole(800.0, 640, 480, dist=[-0.4, 0, 0, 0, 0])
    Y = np.array([[1.7, 0.0, 1.0], [0.3, 0.0, 1.0]])
    assert 0 < folding.project(Y[0])[0, 0] < 639
    assert visible_points(folding, pose, Y).tolist() == [False, True]
    facing = visible_points(cam, pose, X[:1], normals=[0, 0, -1])
    away = visible_points(cam, pose, X[:1], normals=[[0, 0, 1]])
    assert facing.tolist() == [True] and away.tolist() == [False]


# --------------------------------------------------------------------------------------
# Quads
# --------------------------------------------------------------------------------------


def test_quad_validation_and_texture_conversion() -> None:
    tex8 = np.full((6, 10), 255, np.uint8)
    q = TexturedQuad.from_frame([0, 0, 1], [1, 0, 0], [0, 0.5, 0], tex8)
    assert q.texture.dtype == np.float32 and q.texture.max() == 1.0
    assert np.allclose(q.centre, [0.5, 0.25, 1])
    assert [lv.shape for lv in q.mip_levels()] == [(6, 10), (3, 5), (2, 3)]
    with pytest.raises(ValueError):
        TexturedQuad(np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0.3], [0, 1, 0]]), tex8)  # not planar
    with pytest.raises(ValueError):
        TexturedQuad(np.zeros((4, 3)), tex8)
    with pytest.raises(ValueError):
        TexturedQuad(q.corners, np.zeros((4, 4, 3), np.uint8))  # colour
    with pytest.raises(ValueError):
        render(Camera.pinhole(100.0, 64, 48), Pose.identity(), [q], supersample=0)
