"""Poses in client conventions (OpenCV, OpenGL/WebXR, Unity, Unreal): round trips, and
ground truths built here from look-at vectors and from each engine's own rotation
formulas (Unity's Euler order, Unreal's FRotator), not from the code under test."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from app.core.geometry.conventions import (
    Convention,
    ConventionPose,
    covariance_to_convention,
    from_convention,
    quaternion_xyzw,
    to_convention,
)

ALL = list(Convention)

# What each convention's world coordinates are, in map coordinates (z up), and its unit
# per metre, as docs/conventions.md states them.
WORLD = {
    "opencv": lambda v: np.array([v[0], v[1], v[2]]),
    "opengl": lambda v: np.array([v[0], v[2], -v[1]]),
    "unity": lambda v: np.array([v[0], v[2], v[1]]),
    "unreal": lambda v: np.array([v[0], -v[1], v[2]]),
}
SCALE = {"opencv": 1.0, "opengl": 1.0, "unity": 1.0, "unreal": 100.0}


def _opencv_look(eye: np.ndarray, forward: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])
                 ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """An OpenCV pose (R, t) of a camera at `eye` looking along `forward` with `up` up in
    its image, and its right / up / forward directions in map coordinates."""
    f = forward / np.linalg.norm(forward)
    right = np.cross(f, up)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, f)
    R = np.stack([right, -cam_up, f])  # rows: x right, y down, z forward
    return R, -R @ eye, {"right": right, "up": cam_up, "forward": f}


def _engine_axes(convention: str, d: dict[str, np.ndarray]) -> np.ndarray:
    """The columns an engine's camera matrix must have: its camera's own x, y, z axes, in
    its world, from the camera's right / up / forward in map coordinates."""
    w = {k: WORLD[convention](v) for k, v in d.items()}
    columns = {
        "opencv": (w["right"], -w["up"], w["forward"]),    # x right, y down, z forward
        "opengl": (w["right"], w["up"], -w["forward"]),    # x right, y up, looking down -z
        "unity": (w["right"], w["up"], w["forward"]),      # x right, y up, z forward
        "unreal": (w["forward"], w["right"], w["up"]),     # x forward, y right, z up
    }[convention]
    return np.column_stack(columns)


def _matrix_of(q: np.ndarray) -> np.ndarray:
    """The standard rotation matrix of a unit quaternion [x, y, z, w] (column vectors)."""
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of quaternions [x, y, z, w] (b applied first)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])


def _about(axis: int, angle: float) -> np.ndarray:
    q = np.zeros(4)
    q[axis], q[3] = math.sin(angle / 2), math.cos(angle / 2)
    return q


def _same_rotation(q: np.ndarray, expected: np.ndarray) -> bool:
    return bool(np.allclose(q, expected, atol=1e-12) or np.allclose(q, -expected, atol=1e-12))


def _random_poses(n: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    poses = [(R, rng.uniform(-5, 5, 3)) for R in Rotation.random(n, random_state=seed).as_matrix()]
    # Half-turns and near half-turns, where quaternions from axis-angle lose precision.
    for axis in ([1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, -2, 3]):
        unit = np.array(axis, float) / np.linalg.norm(axis)
        for angle in (math.pi, math.pi - 1e-7, math.pi - 1e-3):
            poses.append((Rotation.from_rotvec(unit * angle).as_matrix(), rng.uniform(-5, 5, 3)))
    poses.append((np.eye(3), np.zeros(3)))
    return poses


# --- round trips ------------------------------------------------------------------------


@pytest.mark.parametrize("convention", ALL)
def test_to_and_back_gives_the_pose(convention: Convention) -> None:
    for R, t in _random_poses(200):
        back_R, back_t = from_convention(to_convention(R, t, convention).matrix, convention)
        assert np.abs(back_R - R).max() < 1e-12
        assert np.abs(back_t - t).max() < 1e-12


@pytest.mark.parametrize("convention", ALL)
def test_rotation_is_proper_and_the_quaternion_reproduces_it(convention: Convention) -> None:
    for R, t in _random_poses(200, seed=1):
        pose = to_convention(R, t, convention)
        rotation = pose.matrix[:3, :3]
        assert abs(np.linalg.det(rotation) - 1.0) < 1e-12
        assert np.abs(rotation.T @ rotation - np.eye(3)).max() < 1e-12
        q = pose.quaternion_xyzw
        assert abs(np.linalg.norm(q) - 1.0) < 1e-14 and q[3] >= 0
        assert np.abs(_matrix_of(q) - rotation).max() < 1e-14
        np.testing.assert_array_equal(pose.matrix[3], [0, 0, 0, 1])
        np.testing.assert_array_equal(pose.matrix[:3, 3], pose.position)


# --- the worked example: a camera at map (1, 2, 1.5) m looking along map +x, level -------

EYE = np.array([1.0, 2.0, 1.5])


def test_example_unreal() -> None:
    R, t, _ = _opencv_look(EYE, np.array([1.0, 0.0, 0.0]))
    pose = to_convention(R, t, "unreal")
    np.testing.assert_allclose(pose.position, [100.0, -200.0, 150.0], atol=1e-12)
    np.testing.assert_allclose(pose.matrix[:3, :3], np.eye(3), atol=1e-15)
    np.testing.assert_allclose(pose.quaternion_xyzw, [0, 0, 0, 1], atol=1e-15)
    assert pose.unit == "cm"


def test_example_unity() -> None:
    R, t, _ = _opencv_look(EYE, np.array([1.0, 0.0, 0.0]))
    pose = to_convention(R, t, "unity")
    np.testing.assert_allclose(pose.position, [1.0, 1.5, 2.0], atol=1e-12)
    np.testing.assert_allclose(pose.matrix[:3, 2], [1, 0, 0], atol=1e-15)  # forward: world +x
    np.testing.assert_allclose(pose.matrix[:3, 1], [0, 1, 0], atol=1e-15)  # up: world +y
    # Quaternion.Euler(0, 90, 0): a quarter turn about y takes +z to +x.
    np.testing.assert_allclose(pose.quaternion_xyzw, [0, math.sqrt(0.5), 0, math.sqrt(0.5)], atol=1e-15)
    assert pose.unit == "m"


def test_example_opengl() -> None:
    R, t, _ = _opencv_look(EYE, np.array([1.0, 0.0, 0.0]))
    pose = to_convention(R, t, "opengl")
    np.testing.assert_allclose(pose.position, [1.0, 1.5, -2.0], atol=1e-12)
    np.testing.assert_allclose(-pose.matrix[:3, 2], [1, 0, 0], atol=1e-15)  # looks down -z
    np.testing.assert_allclose(pose.matrix[:3, 1], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(pose.quaternion_xyzw, [0, -math.sqrt(0.5), 0, math.sqrt(0.5)], atol=1e-15)


def test_example_opencv() -> None:
    R, t, _ = _opencv_look(EYE, np.array([1.0, 0.0, 0.0]))
    pose = to_convention(R, t, "opencv")
    expected = np.eye(4)
    expected[:3, :3], expected[:3, 3] = R.T, -R.T @ t
    np.testing.assert_allclose(pose.matrix, expected, atol=1e-15)
    np.testing.assert_allclose(pose.position, EYE, atol=1e-12)


# --- any camera: the matrix's columns are the camera's axes in the engine's world -------


@pytest.mark.parametrize("convention", ALL)
def test_columns_are_the_engine_camera_axes(convention: Convention) -> None:
    rng = np.random.default_rng(2)
    for _ in range(50):
        eye, forward = rng.uniform(-4, 4, 3), rng.normal(size=3)
        tilt = np.array([0.0, 0.0, 1.0]) + 0.5 * rng.normal(size=3)  # rolled cameras too
        R, t, axes = _opencv_look(eye, forward, tilt)
        pose = to_convention(R, t, convention)
        np.testing.assert_allclose(pose.matrix[:3, :3], _engine_axes(convention, axes), atol=1e-12)
        np.testing.assert_allclose(pose.position, SCALE[convention] * WORLD[convention](eye), atol=1e-12)


def _heading_camera(azimuth: float, elevation: float) -> tuple[np.ndarray, np.ndarray]:
    """A level camera (no roll) looking at `azimuth` from map +x towards +y and
    `elevation` above the horizon."""
    forward = np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                        math.sin(elevation)])
    R, t, _ = _opencv_look(np.array([0.3, -0.7, 1.2]), forward)
    return R, t


ANGLES = [(a, e) for a in np.radians([0, 30, 90, 135, 180, -60, -150]) for e in np.radians([0, 25, -40, 80])]


@pytest.mark.parametrize(("azimuth", "elevation"), ANGLES)
def test_unreal_quaternion_is_frotators(azimuth: float, elevation: float) -> None:
    """Unreal: yaw turns +x towards +y, pitch raises the nose; world y is map -y, so the
    camera's yaw is -azimuth and its pitch the elevation. FRotator::Quaternion's formula."""
    pitch, yaw, roll = elevation, -azimuth, 0.0
    sp, cp = math.sin(pitch / 2), math.cos(pitch / 2)
    sy, cy = math.sin(yaw / 2), math.cos(yaw / 2)
    sr, cr = math.sin(roll / 2), math.cos(roll / 2)
    expected = np.array([cr * sp * sy - sr * cp * cy, -cr * sp * cy - sr * cp * sy,
                         cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy])
    assert _same_rotation(to_convention(*_heading_camera(azimuth, elevation), "unreal").quaternion_xyzw, expected)


@pytest.mark.parametrize(("azimuth", "elevation"), ANGLES)
def test_unity_quaternion_is_quaternion_euler(azimuth: float, elevation: float) -> None:
    """Unity: Quaternion.Euler(x, y, 0) turns about x, then about y; +x pitches the
    camera down and +y turns +z towards +x. Map +y is world +z, so the camera's yaw is
    90 degrees - azimuth and its x angle -elevation."""
    expected = _product(_about(1, math.pi / 2 - azimuth), _about(0, -elevation))
    assert _same_rotation(to_convention(*_heading_camera(azimuth, elevation), "unity").quaternion_xyzw, expected)


@pytest.mark.parametrize(("azimuth", "elevation"), ANGLES)
def test_opengl_quaternion_is_yaw_then_pitch(azimuth: float, elevation: float) -> None:
    """OpenGL / three.js (Euler order 'YXZ', the usual camera order): the camera looks
    down -z; yaw about y turns -z towards -x, pitch about x raises it. Map +y is world
    -z, so the yaw is azimuth - 90 degrees and the pitch the elevation."""
    expected = _product(_about(1, azimuth - math.pi / 2), _about(0, elevation))
    assert _same_rotation(to_convention(*_heading_camera(azimuth, elevation), "opengl").quaternion_xyzw, expected)


# --- quaternions --------------------------------------------------------------------------


def test_quaternion_is_scipys_and_exact_near_a_half_turn() -> None:
    for R, _ in _random_poses(500, seed=3):
        q = quaternion_xyzw(R)
        assert np.abs(_matrix_of(q) - R).max() < 1e-14
        assert _same_rotation(q, Rotation.from_matrix(R).as_quat())
        assert q[3] >= 0


def test_quaternion_sign_is_unique_at_a_half_turn() -> None:
    np.testing.assert_array_equal(quaternion_xyzw(np.diag([1.0, -1.0, -1.0])), [1, 0, 0, 0])
    np.testing.assert_array_equal(quaternion_xyzw(np.diag([-1.0, -1.0, 1.0])), [0, 0, 1, 0])
    q = quaternion_xyzw(np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]]))  # half-turn about (1, 1, 0)
    np.testing.assert_allclose(q, [math.sqrt(0.5), math.sqrt(0.5), 0, 0], atol=1e-15)


# --- covariance ---------------------------------------------------------------------------


@pytest.mark.parametrize("convention", ALL)
def test_covariance_follows_the_position(convention: Convention) -> None:
    """The covariance of the engine's position is J S J^T with J the (linear) map from the
    map camera centre to the engine position, here measured through `to_convention`."""
    rng = np.random.default_rng(4)
    A = rng.normal(size=(3, 3))
    S = A @ A.T * 1e-6
    R = Rotation.random(random_state=5).as_matrix()
    centre = rng.normal(size=3)
    base = to_convention(R, -R @ centre, convention).position
    J = np.column_stack([to_convention(R, -R @ (centre + e), convention).position - base for e in np.eye(3)])
    np.testing.assert_allclose(covariance_to_convention(S, convention), J @ S @ J.T, rtol=1e-9, atol=1e-18)


def test_covariance_along_map_y() -> None:
    S = np.diag([0.0, 4e-6, 0.0])  # 2 mm along map y
    np.testing.assert_allclose(covariance_to_convention(S, "unity"), np.diag([0, 0, 4e-6]))
    np.testing.assert_allclose(covariance_to_convention(S, "opengl"), np.diag([0, 0, 4e-6]))
    np.testing.assert_allclose(covariance_to_convention(S, "unreal"), np.diag([0, 0.04, 0]))  # cm^2


# --- the reply and refusals ---------------------------------------------------------------


def test_to_dict_is_the_replys_frame_pose() -> None:
    R, t, _ = _opencv_look(EYE, np.array([1.0, 0.0, 0.0]))
    pose = to_convention(R, t, Convention.UNREAL)
    document = json.loads(json.dumps(pose.to_dict()))
    assert set(document) == {"frame", "matrix", "quaternion_xyzw", "position", "unit"}
    assert document["frame"] == "unreal" and document["unit"] == "cm"
    assert len(document["matrix"]) == 4 and document["matrix"][0][3] == pytest.approx(100.0)  # row-major
    assert document["matrix"][3] == [0.0, 0.0, 0.0, 1.0]
    assert isinstance(pose, ConventionPose) and not pose.matrix.flags.writeable


def test_names_are_the_config_values() -> None:
    assert [c.value for c in Convention] == ["opencv", "opengl", "unity", "unreal"]
    assert Convention("unity") == "unity"
    with pytest.raises(ValueError, match="unknown convention"):
        to_convention(np.eye(3), np.zeros(3), "blender")


def test_refuses_what_is_not_a_pose() -> None:
    with pytest.raises(ValueError, match="rotation"):
        to_convention(np.diag([1.0, 1.0, -1.0]), np.zeros(3), "opengl")  # a reflection
    with pytest.raises(ValueError, match="rotation"):
        to_convention(np.full((3, 3), np.nan), np.zeros(3), "opengl")
    with pytest.raises(ValueError, match="finite"):
        to_convention(np.eye(3), [0.0, np.inf, 0.0], "opengl")
    with pytest.raises(ValueError, match=r"\(3, 3\)"):
        to_convention(np.eye(4), np.zeros(3), "opengl")
    scaled = np.diag([2.0, 2.0, 2.0, 1.0])
    with pytest.raises(ValueError, match="rotation"):
        from_convention(scaled, "unity")
    bad_row = np.eye(4)
    bad_row[3, 0] = 1.0
    with pytest.raises(ValueError, match="last row"):
        from_convention(bad_row, "unity")
    with pytest.raises(ValueError, match=r"\(4, 4\)"):
        from_convention(np.eye(3), "unity")
    with pytest.raises(ValueError, match=r"\(3, 3\)"):
        covariance_to_convention(np.eye(2), "unity")


def test_a_float32_matrix_from_a_client_is_taken() -> None:
    R, t = _random_poses(1, seed=6)[0]
    matrix = to_convention(R, t, "unity").matrix.astype(np.float32)
    back_R, back_t = from_convention(matrix, "unity")
    assert np.abs(back_R - R).max() < 1e-6 and np.abs(back_t - t).max() < 1e-5
