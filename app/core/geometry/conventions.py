"""Camera poses in the frames of client engines: OpenCV, OpenGL/WebXR, Unity, Unreal.

The service computes a pose as ``x_cam = R @ X_map + t`` (OpenCV's camera: x right,
y down, looking along +z; the map frame right-handed, metres). A game engine or an AR
framework wants the opposite transform, the camera object's placement in its own world
(camera to world), with its own world axes, camera axes, handedness and unit. Every
convention here is the OpenCV pose with two fixed signed permutations applied, one on
the world side and one on the camera side, plus a unit scale:

    rotation = W @ R.T @ C          position = s * W @ (-R.T @ t)

``W`` takes map coordinates to the engine's world (the map's z is taken as up: an
aligned world frame, docs/map-format.md), ``C`` holds the engine camera's own axes in
OpenCV camera coordinates (as columns) and ``s`` is the engine's length unit per metre.
Signed permutations are exact in floating point: a pose converted there and back gets
its rotation back bit for bit and its translation to round-off. See docs/conventions.md.

Pure numpy; no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "Convention",
    "ConventionPose",
    "covariance_to_convention",
    "from_convention",
    "quaternion_xyzw",
    "to_convention",
]


class Convention(StrEnum):
    """The frames a client can ask poses in (the /track config's ``frame``).

    ``opencv``: the map frame as it is, the camera x right, y down, looking along +z;
    metres. ``opengl`` (WebXR, ARKit, three.js): right-handed, y up; the camera x right,
    y up, looking along -z; metres. ``unity``: left-handed, y up; the camera x right,
    y up, looking along +z; metres. ``unreal``: left-handed, z up; the camera looking
    along +x, y right, z up; centimetres.
    """

    OPENCV = "opencv"
    OPENGL = "opengl"
    UNITY = "unity"
    UNREAL = "unreal"


class _Frames(NamedTuple):
    world: np.ndarray  # (3, 3) map coordinates -> the engine's world coordinates (a signed permutation)
    camera: np.ndarray  # (3, 3) columns: the engine camera's axes in OpenCV camera coordinates
    scale: float  # the engine's length unit per metre
    unit: str


def _frozen(rows: list[list[float]]) -> np.ndarray:
    a = np.array(rows, dtype=np.float64)
    a.setflags(write=False)
    return a


_EYE3 = _frozen([[1, 0, 0], [0, 1, 0], [0, 0, 1]])

_FRAMES: dict[Convention, _Frames] = {
    Convention.OPENCV: _Frames(_EYE3, _EYE3, 1.0, "m"),
    # (x, y, z) = (map x, map z, -map y): a proper rotation (-90 degrees about x), the
    # usual turn of a z-up scene into a y-up one (glTF, three.js). The camera's y and z flip.
    Convention.OPENGL: _Frames(_frozen([[1, 0, 0], [0, 0, 1], [0, -1, 0]]),
                               _frozen([[1, 0, 0], [0, -1, 0], [0, 0, -1]]), 1.0, "m"),
    # (x, y, z) = (map x, map z, map y): the y-z swap is the change of handedness; seen
    # from above the room is not mirrored. The camera keeps x and z, its y flips (up).
    Convention.UNITY: _Frames(_frozen([[1, 0, 0], [0, 0, 1], [0, 1, 0]]),
                              _frozen([[1, 0, 0], [0, -1, 0], [0, 0, 1]]), 1.0, "m"),
    # (x, y, z) = 100 * (map x, -map y, map z): z stays up, the y flip is the change of
    # handedness. The camera's x is OpenCV's z (forward), its y OpenCV's x (right) and
    # its z OpenCV's -y (up).
    Convention.UNREAL: _Frames(_frozen([[1, 0, 0], [0, -1, 0], [0, 0, 1]]),
                               _frozen([[0, 1, 0], [0, 0, -1], [1, 0, 0]]), 100.0, "cm"),
}


@dataclass(frozen=True, eq=False)
class ConventionPose:
    """The camera's placement in a convention's world: what an engine sets on its camera.

    Attributes
    ----------
    convention : Convention
        The convention the values are in.
    matrix : (4, 4) ndarray
        Camera to world, ``[[rotation, position], [0, 0, 0, 1]]``: the rotation's
        columns are the camera's own axes (in the convention's camera axes) in world
        coordinates; read-only.
    quaternion_xyzw : (4,) ndarray
        The rotation as a unit quaternion ``[x, y, z, w]`` with ``w >= 0``; read-only.
    position : (3,) ndarray
        The camera centre in the convention's world, in `unit`; read-only.
    unit : str
        ``"m"`` or ``"cm"``.
    """

    convention: Convention
    matrix: np.ndarray  # (4, 4) camera to world
    quaternion_xyzw: np.ndarray  # (4,) [x, y, z, w], w >= 0
    position: np.ndarray  # (3,) in `unit`
    unit: str

    def to_dict(self) -> dict[str, object]:
        """The pose as JSON-able values (the reply's ``frame_pose``).

        Returns
        -------
        dict
            ``frame`` (the convention's name), ``matrix`` (row-major: a list of 4 rows),
            ``quaternion_xyzw``, ``position`` and ``unit``.
        """
        return {
            "frame": str(self.convention),
            "matrix": self.matrix.tolist(),
            "quaternion_xyzw": self.quaternion_xyzw.tolist(),
            "position": self.position.tolist(),
            "unit": self.unit,
        }


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _check_rotation(R: np.ndarray, name: str) -> None:
    """Refuse what is not a finite 3x3 rotation (to 1e-6, as `Pose` does).

    On Python floats: per frame, a numpy check (a product, a determinant, a reduction)
    would cost several times the conversion it guards. A NaN or an infinity makes a
    comparison below false, so it is refused too.
    """
    r0, r1, r2 = R.tolist()
    dots = [sum(a * b for a, b in zip(u, v, strict=True)) for u, v in ((r0, r0), (r1, r1), (r2, r2))]
    cross = [sum(a * b for a, b in zip(u, v, strict=True)) for u, v in ((r0, r1), (r0, r2), (r1, r2))]
    det = (r0[0] * (r1[1] * r2[2] - r1[2] * r2[1]) - r0[1] * (r1[0] * r2[2] - r1[2] * r2[0])
           + r0[2] * (r1[0] * r2[1] - r1[1] * r2[0]))
    if not (all(abs(d - 1.0) <= 1e-6 for d in dots) and all(abs(c) <= 1e-6 for c in cross) and det > 0):
        raise ValueError(f"{name} must be a finite rotation matrix (orthonormal, determinant +1)")


def quaternion_xyzw(R: ArrayLike) -> np.ndarray:
    """The unit quaternion of a rotation matrix, ``[x, y, z, w]`` with ``w >= 0``.

    Shepperd's method: the largest of the four squared components is taken from the
    diagonal and the others from off-diagonal sums, so the answer keeps full precision
    at every angle, 180 degrees included. Of the two quaternions of a rotation the one
    with ``w > 0`` is returned; at exactly 180 degrees (``w = 0``) the one whose first
    non-zero component is positive.

    Parameters
    ----------
    R : (3, 3) array_like
        A rotation matrix (acting on column vectors, ``v' = R @ v``).

    Returns
    -------
    (4,) ndarray
        ``[x, y, z, w]``, unit length; the standard formula (``R[0, 0] = 1 - 2(y² + z²)``,
        ``R[0, 1] = 2(xy - zw)``, ...) gives `R` back.
    """
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = np.asarray(R, dtype=np.float64).reshape(3, 3).tolist()
    trace = r00 + r11 + r22
    # Python floats: a dozen scalar operations cost less than one numpy call.
    if trace >= max(r00, r11, r22):
        w = 0.5 * math.sqrt(max(1.0 + trace, 0.0))
        f = 0.25 / w
        x, y, z = (r21 - r12) * f, (r02 - r20) * f, (r10 - r01) * f
    elif r00 >= r11 and r00 >= r22:
        x = 0.5 * math.sqrt(max(1.0 + r00 - r11 - r22, 0.0))
        f = 0.25 / x
        w, y, z = (r21 - r12) * f, (r01 + r10) * f, (r02 + r20) * f
    elif r11 >= r22:
        y = 0.5 * math.sqrt(max(1.0 - r00 + r11 - r22, 0.0))
        f = 0.25 / y
        w, x, z = (r02 - r20) * f, (r01 + r10) * f, (r12 + r21) * f
    else:
        z = 0.5 * math.sqrt(max(1.0 - r00 - r11 + r22, 0.0))
        f = 0.25 / z
        w, x, y = (r10 - r01) * f, (r02 + r20) * f, (r12 + r21) * f
    q = [x, y, z, w]
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    # q and -q are the same rotation: w > 0 makes the answer unique (and continuous
    # away from 180 degrees, where w = 0 and the first non-zero component decides).
    lead = w if w != 0.0 else next((c for c in (x, y, z) if c != 0.0), 1.0)
    sign = 1.0 / norm if lead > 0 else -1.0 / norm
    return np.array([c * sign for c in q])


def to_convention(R: ArrayLike, t: ArrayLike, convention: Convention | str) -> ConventionPose:
    """The camera's placement in a convention's world, from a map-to-camera pose.

    Parameters
    ----------
    R : (3, 3) array_like
        Rotation, map to camera: ``x_cam = R @ X_map + t`` (OpenCV's camera).
    t : (3,) array_like
        Translation, map to camera, metres.
    convention : Convention or str
        ``"opencv"``, ``"opengl"``, ``"unity"`` or ``"unreal"``.

    Returns
    -------
    ConventionPose
        Camera to world in the convention: ``matrix`` with rotation ``W @ R.T @ C`` and
        position ``s * W @ (-R.T @ t)`` (see the module's docstring), its quaternion,
        the position and the unit.

    Raises
    ------
    ValueError
        If the convention is unknown, the shapes are wrong, a value is not finite or
        `R` is not a rotation.
    """
    convention = _convention(convention)
    frames = _FRAMES[convention]
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"to_convention needs R (3, 3) and t (3,), got {R.shape} and {t.shape}")
    _check_rotation(R, "R")
    if not all(math.isfinite(v) for v in t.tolist()):
        raise ValueError("t must be finite")
    rotation = frames.world @ R.T @ frames.camera
    position = frames.scale * (frames.world @ (-R.T @ t))
    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = position
    return ConventionPose(
        convention=convention,
        matrix=_readonly(matrix),
        quaternion_xyzw=_readonly(quaternion_xyzw(rotation)),
        position=_readonly(position.copy()),
        unit=frames.unit,
    )


def from_convention(matrix: ArrayLike, convention: Convention | str) -> tuple[np.ndarray, np.ndarray]:
    """The map-to-camera pose of a camera placed in a convention's world.

    The inverse of `to_convention`: ``R = C @ rotation.T @ W`` and
    ``t = -R @ (W.T @ position / s)``.

    Parameters
    ----------
    matrix : (4, 4) array_like
        Camera to world in the convention, rotation and position (in the convention's
        unit), last row ``[0, 0, 0, 1]``; no scale.
    convention : Convention or str
        ``"opencv"``, ``"opengl"``, ``"unity"`` or ``"unreal"``.

    Returns
    -------
    R : (3, 3) ndarray
        Rotation, map to camera (OpenCV's camera).
    t : (3,) ndarray
        Translation, map to camera, metres.

    Raises
    ------
    ValueError
        If the convention is unknown, the matrix is not 4x4, not finite, its last row is
        not ``[0, 0, 0, 1]`` or its rotation part not a rotation (to 1e-6).
    """
    frames = _FRAMES[_convention(convention)]
    M = np.asarray(matrix, dtype=np.float64)
    if M.shape != (4, 4):
        raise ValueError(f"from_convention needs a (4, 4) matrix, got {M.shape}")
    if not np.all(np.isfinite(M)):
        raise ValueError("the matrix must be finite")
    if np.abs(M[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-9:
        raise ValueError(f"the matrix's last row must be [0, 0, 0, 1], got {M[3].tolist()}")
    _check_rotation(M[:3, :3], "the matrix's rotation part")
    R = frames.camera @ M[:3, :3].T @ frames.world
    centre = frames.world.T @ M[:3, 3] / frames.scale
    return R, -R @ centre


def covariance_to_convention(covariance: ArrayLike, convention: Convention | str) -> np.ndarray:
    """A position covariance (the pose's ``covariance_position``) in a convention's world.

    Parameters
    ----------
    covariance : (3, 3) array_like
        Covariance of the camera centre in map coordinates, square metres.
    convention : Convention or str
        ``"opencv"``, ``"opengl"``, ``"unity"`` or ``"unreal"``.

    Returns
    -------
    (3, 3) ndarray
        ``(s W) @ covariance @ (s W).T``: the same covariance along the convention's
        world axes, in its unit squared (cm² for ``unreal``).

    Raises
    ------
    ValueError
        If the convention is unknown or the covariance is not 3x3.
    """
    frames = _FRAMES[_convention(convention)]
    S = np.asarray(covariance, dtype=np.float64)
    if S.shape != (3, 3):
        raise ValueError(f"covariance_to_convention needs a (3, 3) covariance, got {S.shape}")
    A = frames.scale * frames.world
    return A @ S @ A.T


def _convention(convention: Convention | str) -> Convention:
    try:
        return Convention(convention)
    except ValueError:
        known = ", ".join(c.value for c in Convention)
        raise ValueError(f"unknown convention {convention!r}; known: {known}") from None
