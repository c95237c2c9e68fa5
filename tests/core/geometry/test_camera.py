"""Camera model and pose: OpenCV conventions, projection, undistortion, distortion maps."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from app.core.geometry.camera import Camera, Pose

DIST = [-0.2, 0.05, 0.0012, -0.0008, 0.01]


@pytest.fixture
def cam() -> Camera:
    return Camera.pinhole(800.0, 640, 480, dist=DIST, cx=322.3, cy=236.9)


def _random_points(rng: np.random.Generator, n: int = 500) -> np.ndarray:
    """Points in front of the camera spanning (and exceeding) the field of view."""
    X = rng.uniform([-1.0, -0.8, 0.0], [1.0, 0.8, 0.0], (n, 3))
    X[:, 2] = rng.uniform(1.0, 4.0, n)
    return X


# --------------------------------------------------------------------------------------
# Camera
# --------------------------------------------------------------------------------------


def test_pinhole_defaults() -> None:
    c = Camera.pinhole(500.0, 640, 480)
    assert (c.cx, c.cy) == (319.5, 239.5)  # centre of the top-left pixel is (0, 0)
    assert c.fx == c.fy == 500.0
    assert c.dist.shape == (5,) and not c.has_distortion
    assert c.K.dtype == np.float64 and c.size == (640, 480)
    with pytest.raises(ValueError):
        c.K[0, 0] = 1.0  # read-only: cached maps depend on the parameters


def test_project_matches_cv2_projectPoints(cam: Camera) -> None:
    rng = np.random.default_rng(0)
    X = _random_points(rng)
    ours = cam.project(X)
    ref, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    assert np.abs(ours - ref[:, 0]).max() < 1e-6

    pose = Pose.from_rvec_tvec([0.1, -0.3, 0.2], [0.2, -0.1, 0.5])
    ours = cam.project_map(X, pose)
    ref, _ = cv2.projectPoints(X, pose.rvec, pose.t, cam.K, cam.dist)
    assert np.abs(ours - ref[:, 0]).max() < 1e-6


def test_project_with_skew_matches_cv2_without_distortion() -> None:
    K = np.array([[700.0, 0.0, 300.0], [0.0, 710.0, 250.0], [0.0, 0.0, 1.0]])
    c = Camera(K, np.zeros(5), 600, 500)
    X = _random_points(np.random.default_rng(1))
    ref, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, np.zeros(5))
    assert np.abs(c.project(X) - ref[:, 0]).max() < 1e-6
    assert np.abs(c.project_ideal(X) - c.project(X)).max() == 0.0


def test_undistort_inverts_project(cam: Camera) -> None:
    X = _random_points(np.random.default_rng(2))
    uv = cam.project(X)
    ideal = cam.project_ideal(X)
    assert np.abs(cam.undistort_pixels(uv) - ideal).max() < 1e-8
    assert np.abs(cam.distort_pixels(ideal) - uv).max() < 1e-8
    # Inside the image cv2.undistortPoints (5 fixed-point steps) agrees closely.
    inside = (uv[:, 0] > 0) & (uv[:, 0] < 639) & (uv[:, 1] > 0) & (uv[:, 1] < 479)
    ref = cv2.undistortPoints(uv[inside].reshape(-1, 1, 2), cam.K, cam.dist, P=cam.K)[:, 0]
    assert np.abs(ref - ideal[inside]).max() < 0.01


def test_no_distortion_is_identity() -> None:
    c = Camera.pinhole(600.0, 320, 240)
    uv = np.array([[0.0, 0.0], [100.5, 37.25]])
    assert np.array_equal(c.undistort_pixels(uv), uv)
    mx, my = c.distortion_maps()
    assert np.array_equal(mx[5], np.arange(320, dtype=np.float32))
    assert np.array_equal(my[:, 7], np.arange(240, dtype=np.float32))


def test_distortion_maps_round_trip(cam: Camera) -> None:
    mx, my = cam.distortion_maps()
    assert mx.shape == my.shape == (480, 640) and mx.dtype == np.float32
    assert cam.distortion_maps()[0] is mx  # cached per camera
    # Every distorted pixel's ideal location distorts back onto it.
    vs, us = np.mgrid[0:480:7, 0:640:7]
    ideal = np.stack([mx[vs, us].ravel(), my[vs, us].ravel()], axis=1).astype(np.float64)
    back = cam.distort_pixels(ideal)
    assert np.abs(back - np.stack([us.ravel(), vs.ravel()], axis=1)).max() < 1e-3

    # Image round trip: ideal -> distorted (our maps) -> ideal (OpenCV's undistort maps).
    yy, xx = np.mgrid[0:480, 0:640].astype(np.float32)
    ideal_img = (0.5 + 0.25 * np.sin(xx / 17.0) * np.cos(yy / 23.0)).astype(np.float32)
    distorted = cv2.remap(ideal_img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    ux, uy = cv2.initUndistortRectifyMap(cam.K, cam.dist, None, cam.K, cam.size, cv2.CV_32FC1)
    again = cv2.remap(distorted, ux, uy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    assert np.abs(again - ideal_img)[40:-40, 40:-40].max() < 0.01


def test_ideal_canvas_covers_barrel_field(cam: Camera) -> None:
    ic = cam.ideal_canvas
    mx, my = cam.distortion_maps()
    # k1 < 0: the distorted image sees beyond the ideal image of the same size.
    assert ic.x0 < 0 and ic.y0 < 0 and ic.width > 640 and ic.height > 480
    assert np.allclose(ic.map_x + ic.x0, mx, atol=1e-4)
    assert np.allclose(ic.map_y + ic.y0, my, atol=1e-4)
    assert ic.map_x.min() >= 0 and ic.map_x.max() <= ic.width - 1
    assert ic.map_y.min() >= 0 and ic.map_y.max() <= ic.height - 1


@pytest.mark.parametrize("k1", [-0.05, -0.12, -0.4])
def test_fold_radius_matches_the_analytic_fold(k1: float) -> None:
    # r (1 + k1 r^2) stops increasing where 1 + 3 k1 r^2 = 0.
    c = Camera.pinhole(820.0, 640, 480, dist=[k1, 0, 0, 0, 0])
    assert c.fold_radius == pytest.approx(1.0 / np.sqrt(-3.0 * k1), rel=1e-12)


@pytest.mark.parametrize("dist", [[-0.3, 0.02, 0, 0, 0.001], [-0.3, 0.1, 0, 0, -0.02], [0, 0, 0, 0, -0.01],
                                  [-0.25, 0.01, 0.001, -0.001, 0.0]])
def test_fold_radius_is_where_the_radial_slope_first_vanishes(dist: list[float]) -> None:
    c = Camera.pinhole(820.0, 640, 480, dist=dist)
    k1, k2, _, _, k3 = dist
    r = np.linspace(1e-3, 5.0, 500_001)
    u = r * r
    bad = np.flatnonzero(1 + 3 * k1 * u + 5 * k2 * u**2 + 7 * k3 * u**3 <= 0)
    assert bad.size  # each of these lenses folds within r = 5
    assert c.fold_radius == pytest.approx(r[bad[0]], abs=2e-5)
    assert c.field_radius(100.0) == pytest.approx(0.95 * c.fold_radius)


def test_fold_radius_is_inf_when_the_polynomial_never_folds() -> None:
    assert Camera.pinhole(820.0, 640, 480).fold_radius == np.inf
    assert Camera.pinhole(820.0, 640, 480, dist=[0.1, 0, 0, 0, 0]).fold_radius == np.inf
    assert Camera.pinhole(820.0, 640, 480, dist=[-0.2, 0.05, 0, 0, 0]).fold_radius == np.inf  # 9 k1^2 < 20 k2
    assert Camera.pinhole(820.0, 640, 480, dist=DIST).fold_radius == np.inf


def test_field_radius_is_the_farthest_image_corner_short_of_the_fold(cam: Camera) -> None:
    # The farthest corner (pixel-area edge) of an off-centre principal point, undistorted.
    w, h = cam.width, cam.height
    edges = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    ideal = cam.undistort_pixels(edges)
    corner = np.hypot((ideal[:, 0] - cam.cx) / cam.fx, (ideal[:, 1] - cam.cy) / cam.fy).max()
    assert cam.field_radius() == pytest.approx(corner, rel=1e-9)
    assert cam.field_radius(1.25) == pytest.approx(1.25 * corner, rel=1e-9)
    # A pixel in every corner sees a ray inside the field; 1% further out is outside.
    rays = np.c_[(ideal - [cam.cx, cam.cy]) / [cam.fx, cam.fy], np.ones(4)]
    assert cam.in_field(rays * [0.999, 0.999, 1]).all()
    assert not cam.in_field(rays * [1.01, 1.01, 1]).all()
    # Never past 0.95 of the fold, however large the margin.
    strong = Camera.pinhole(820.0, 640, 480, dist=[-0.4, 0, 0, 0, 0])
    assert strong.field_radius(10.0) == pytest.approx(0.95 * strong.fold_radius)
    # A lens whose polynomial turns back before the image's corners: the fold bounds it.
    wild = Camera.pinhole(300.0, 640, 480, dist=[-0.4, 0.1, 0, 0, -0.01])
    assert wild.field_radius() == pytest.approx(0.95 * wild.fold_radius)


def test_point_folded_into_the_image_is_outside_the_field() -> None:
    c = Camera.pinhole(820.0, 640, 480, dist=[-0.12, 0, 0, 0, 0])
    off = np.tan(np.radians(70.0))  # 70 degrees off axis, beyond the fold (59 degrees)
    X = np.array([[off, 0.0, 1.0], [0.3, 0.2, 1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0]])
    assert off > c.fold_radius
    u, v = c.project(X[0])[0]
    assert 0 <= u <= 639 and 0 <= v <= 479  # the polynomial folds it into the image
    assert c.in_field(X).tolist() == [False, True, False, False]  # folded, in view, behind, z = 0
    assert c.in_field(X[1]).tolist() == [True]
    # Cached by value: an equal camera built anew gives the same field.
    again = Camera.from_dict(c.to_dict())
    assert again is not c and again.field_radius(1.1) == c.field_radius(1.1)


def test_dict_round_trip_eq_hash(cam: Camera) -> None:
    d = cam.to_dict()
    assert set(d) == {"width", "height", "K", "dist"}
    assert len(d["dist"]) == 5 and np.array(d["K"]).shape == (3, 3)
    again = Camera.from_dict(d)
    assert again == cam and hash(again) == hash(cam)
    assert again != Camera.pinhole(800.0, 640, 480)
    assert {cam: 1}[again] == 1
    four = Camera(cam.K, cam.dist[:4], 640, 480)  # [k1, k2, p1, p2] is accepted
    assert four.dist.shape == (5,) and four.dist[4] == 0.0


@pytest.mark.parametrize(
    "kwargs",
    [
        {"K": np.eye(2), "dist": np.zeros(5), "width": 10, "height": 10},
        {"K": np.diag([-1.0, 1.0, 1.0]), "dist": np.zeros(5), "width": 10, "height": 10},
        {"K": np.eye(3), "dist": np.zeros(3), "width": 10, "height": 10},
        {"K": np.eye(3), "dist": np.zeros(5), "width": 0, "height": 10},
    ],
)
def test_camera_validation(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        Camera(**kwargs)
    with pytest.raises(ValueError):
        Camera.from_dict({"width": 10, "height": 10, "K": np.eye(3).tolist()})


# --------------------------------------------------------------------------------------
# Pose
# --------------------------------------------------------------------------------------


def test_pose_rvec_position_inverse() -> None:
    rvec, tvec = np.array([0.3, -0.2, 0.9]), np.array([0.5, -1.0, 2.0])
    pose = Pose.from_rvec_tvec(rvec, tvec)
    assert np.allclose(pose.rvec, rvec)
    R, _ = cv2.Rodrigues(rvec)
    assert np.allclose(pose.R, R) and np.array_equal(pose.t, tvec)
    assert np.allclose(pose.transform(pose.position), 0.0)  # camera centre -> origin
    X = np.random.default_rng(3).normal(size=(10, 3))
    assert np.allclose(pose.transform(X), X @ R.T + tvec)
    assert np.allclose(pose.inverse().transform(pose.transform(X)), X)
    assert np.allclose(pose.compose(pose.inverse()).R, np.eye(3))
    assert pose == Pose.from_rvec_tvec(rvec, tvec) and hash(pose) == hash(Pose(pose.R, pose.t))
    d = pose.to_dict()
    assert np.allclose(d["position"], pose.position)
    with pytest.raises(ValueError):
        Pose(np.diag([1.0, 1.0, -1.0]), np.zeros(3))  # a reflection is not a pose


@pytest.mark.parametrize(
    "eye,target",
    [([0, 0, 1.5], [4, 1, 1.2]), ([2, -3, 0.5], [0, 0, 2.0]), ([1, 1, 1], [1.2, 0.9, 1])],
)
def test_look_at(eye: list, target: list) -> None:
    c = Camera.pinhole(600.0, 640, 480)
    pose = Pose.look_at(eye, target)
    assert np.allclose(pose.R @ pose.R.T, np.eye(3)) and np.isclose(np.linalg.det(pose.R), 1)
    assert np.allclose(pose.position, eye)
    uv = c.project_map(np.array([target], float), pose)[0]
    assert np.allclose(uv, [c.cx, c.cy], atol=1e-9)  # target at the principal point
    above = c.project_map(np.array([target], float) + [0, 0, 0.1], pose)[0]
    assert above[1] < c.cy - 1 and abs(above[0] - c.cx) < 1e-6  # world up is image up
    # Looking along +x with z up, the world's -y side is on the image's right.
    p = Pose.look_at([0, 0, 0], [1, 0, 0])
    assert c.project_map(np.array([[1.0, -0.1, 0.0]]), p)[0, 0] > c.cx
    with pytest.raises(ValueError):
        Pose.look_at([0, 0, 0], [0, 0, 1])  # up parallel to the viewing direction
