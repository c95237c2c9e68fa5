"""Camera pose and intrinsics with OpenCV's conventions (see docs/map-format.md).

* Pose: ``x_cam = R @ X_map + t`` (OpenCV's rvec/tvec meaning), metres; the camera
  looks along +z_cam, x_cam to the right and y_cam down in the image.
* Camera: ``K`` 3x3 and ``dist = [k1, k2, p1, p2, k3]`` (OpenCV's model); pixel
  coordinates with the centre of the top-left pixel at (0, 0), x right, y down.

Projection is done in numpy (vectorised, float64) and matches ``cv2.projectPoints`` to
round-off; the simulator and the trackers call it for thousands of points per frame,
where the per-call overhead of cv2 and its (N, 1, 3) reshapes would dominate.
Pure numpy/OpenCV; no I/O.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike

__all__ = ["FOLD_FRACTION", "Camera", "IdealCanvas", "Pose", "rotation_angle"]

#: The lens's usable field stops at this fraction of the radius where the distortion
#: polynomial folds back (Camera.field_radius): at the fold the radial map's slope is
#: zero, so just inside it projections are degenerate and undistortion ill-conditioned.
FOLD_FRACTION = 0.95

#: How far the ideal (undistorted) rendering canvas may extend beyond the image on each
#: side, as a fraction of the image size. Strong barrel distortion sends the corners'
#: undistorted positions very far out; past this they are rendered as background.
_MAX_CANVAS_MARGIN = 1.0


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64, copy=True)
    a.setflags(write=False)
    return a


def _points(X: ArrayLike, dim: int, name: str) -> np.ndarray:
    """(N, dim) float64 view of X; a single point of shape (dim,) becomes (1, dim)."""
    a = np.asarray(X, dtype=np.float64)
    if a.ndim == 1 and a.shape[0] == dim:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != dim:
        raise ValueError(f"{name} must have shape (N, {dim}), got {np.shape(X)}")
    return a


# --------------------------------------------------------------------------------------
# Pose
# --------------------------------------------------------------------------------------


_EYE3 = np.eye(3)


@dataclass(frozen=True, eq=False)  # eq=False: generated __eq__ on ndarrays is ambiguous
class Pose:
    """Rigid map-to-camera transform: ``x_cam = R @ X_map + t``.

    Parameters
    ----------
    R : (3, 3) array_like
        Rotation from the map frame to the camera frame (stored float64, read-only).
    t : (3,) array_like
        Translation in metres: the map origin in camera coordinates.

    Raises
    ------
    ValueError
        If the shapes are wrong, a value is not finite, or `R` is not a rotation.
    """

    R: np.ndarray  # (3, 3) rotation, float64, read-only
    t: np.ndarray  # (3,) translation, float64, read-only

    def __post_init__(self) -> None:
        R = np.asarray(self.R, dtype=np.float64)
        t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        if R.shape != (3, 3) or t.shape != (3,):
            raise ValueError(f"Pose needs R (3, 3) and t (3,), got {R.shape} and {t.shape}")
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise ValueError("Pose R and t must be finite")
        # Plain max/det rather than np.allclose: poses are built per frame on the hot path.
        det = (R[0, 0] * (R[1, 1] * R[2, 2] - R[1, 2] * R[2, 1]) - R[0, 1] * (R[1, 0] * R[2, 2] - R[1, 2] * R[2, 0])
               + R[0, 2] * (R[1, 0] * R[2, 1] - R[1, 1] * R[2, 0]))
        if np.abs(R @ R.T - _EYE3).max() > 1e-6 or det < 0:
            raise ValueError("Pose R must be a rotation matrix")
        object.__setattr__(self, "R", _readonly(R))
        object.__setattr__(self, "t", _readonly(t))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Pose):
            return NotImplemented
        return bool(np.array_equal(self.R, other.R) and np.array_equal(self.t, other.t))

    def __hash__(self) -> int:
        return hash((self.R.tobytes(), self.t.tobytes()))

    @classmethod
    def identity(cls) -> Pose:
        """The camera at the map origin, looking along +z_map.

        Returns
        -------
        Pose
            ``R = I``, ``t = 0``.
        """
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_rvec_tvec(cls, rvec: ArrayLike, tvec: ArrayLike) -> Pose:
        """The pose of OpenCV's Rodrigues vector and translation (solvePnP's output).

        Parameters
        ----------
        rvec : (3,) array_like
            Rotation vector (axis times angle, radians), map to camera.
        tvec : (3,) array_like
            Translation, metres.

        Returns
        -------
        Pose
        """
        rvec = np.asarray(rvec, dtype=np.float64).reshape(3, 1)
        R, _ = cv2.Rodrigues(rvec)
        return cls(R, np.asarray(tvec, dtype=np.float64).reshape(3))

    @classmethod
    def look_at(
        cls, eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)
    ) -> Pose:
        """Camera at `eye` looking at `target`; world `up` appears up in the image.

        +z_cam points at the target, y_cam (image down) is the component of -up
        orthogonal to the viewing direction, x_cam = y_cam x z_cam (image right).

        Parameters
        ----------
        eye : (3,) array_like
            Camera centre in map coordinates, metres.
        target : (3,) array_like
            Point the optical axis passes through, map coordinates.
        up : (3,) array_like, optional
            Map direction that appears up in the image (default +z_map).

        Returns
        -------
        Pose

        Raises
        ------
        ValueError
            If `eye` and `target` coincide, or `up` is parallel to the viewing
            direction (the roll is then undefined).
        """
        eye = np.asarray(eye, dtype=np.float64).reshape(3)
        target = np.asarray(target, dtype=np.float64).reshape(3)
        up = np.asarray(up, dtype=np.float64).reshape(3)
        z = target - eye
        nz = np.linalg.norm(z)
        if nz == 0:
            raise ValueError("look_at: eye and target coincide")
        z /= nz
        x = np.cross(z, up)
        nx = np.linalg.norm(x)
        if nx < 1e-9 * max(np.linalg.norm(up), 1e-300):
            raise ValueError("look_at: up is parallel to the viewing direction")
        x /= nx
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        return cls(R, -R @ eye)

    @property
    def position(self) -> np.ndarray:
        """Camera centre in map coordinates, ``-R.T @ t``."""
        return -self.R.T @ self.t

    @property
    def rvec(self) -> np.ndarray:
        """OpenCV Rodrigues vector, shape (3,)."""
        rvec, _ = cv2.Rodrigues(self.R)
        return rvec.reshape(3)

    def transform(self, X: ArrayLike) -> np.ndarray:
        """Map points in camera coordinates: ``R @ X + t``.

        Parameters
        ----------
        X : (N, 3) or (3,) array_like
            Points in map coordinates, metres.

        Returns
        -------
        (N, 3) ndarray
            The points in camera coordinates (a single (3,) point gives (1, 3)).
        """
        return _points(X, 3, "X") @ self.R.T + self.t

    def inverse(self) -> Pose:
        """The camera-to-map transform, ``X_map = R.T @ x_cam - R.T @ t``.

        Returns
        -------
        Pose
        """
        return Pose(self.R.T, -self.R.T @ self.t)

    def compose(self, other: Pose) -> Pose:
        """``self`` after ``other``: ``x = self.R @ (other.R @ X + other.t) + self.t``.

        Parameters
        ----------
        other : Pose
            The transform applied first.

        Returns
        -------
        Pose
        """
        return Pose(self.R @ other.R, self.R @ other.t + self.t)

    def to_dict(self) -> dict[str, Any]:
        """The pose as JSON-able lists.

        Returns
        -------
        dict
            ``R`` (3x3), ``t`` (3,) and ``position`` (the camera centre, metres).
        """
        return {
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "position": self.position.tolist(),
        }


def rotation_angle(a: Pose, b: Pose) -> float:
    """The angle of the rotation between two poses.

    Parameters
    ----------
    a, b : Pose
        The poses.

    Returns
    -------
    float
        The angle of ``a.R @ b.R.T``, radians, in [0, pi].
    """
    return float(np.arccos(np.clip((np.trace(a.R @ b.R.T) - 1) / 2, -1.0, 1.0)))


# --------------------------------------------------------------------------------------
# Camera
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class IdealCanvas:
    """Where to render an undistorted (ideal pinhole) image so that `map_x`, `map_y`
    (cv2.remap) turn it into this camera's distorted image.

    Attributes
    ----------
    x0, y0 : int
        Ideal-pixel column and row (same K) of the canvas's top-left pixel.
    width, height : int
        Canvas size in pixels: it covers ideal columns x0 .. x0 + width - 1 and rows
        y0 .. y0 + height - 1.
    map_x, map_y : (height, width) ndarray of float32
        For each pixel of the camera's image (its height and width), its position on
        the canvas.
    """

    x0: int
    y0: int
    width: int
    height: int
    map_x: np.ndarray
    map_y: np.ndarray


@dataclass(frozen=True, eq=False)  # eq/hash below compare the parameter values
class Camera:
    """Pinhole camera with OpenCV's lens distortion ``[k1, k2, p1, p2, k3]``.

    Pixel coordinates put the centre of the top-left pixel at (0, 0), x right, y down.

    Parameters
    ----------
    K : (3, 3) array_like
        Intrinsic matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``, pixels.
    dist : (5,) or (4,) array_like or None
        OpenCV distortion ``[k1, k2, p1, p2, k3]`` (a 4-vector gets k3 = 0; None: none).
    width, height : int
        Image size in pixels.

    Raises
    ------
    ValueError
        If `K` is not upper triangular with positive focal lengths, `dist` is not 4 or
        5 finite values, or the size is not positive integers.
    """

    K: np.ndarray  # (3, 3) float64, read-only
    dist: np.ndarray  # (5,) float64, read-only
    width: int
    height: int

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        dist = np.zeros(5) if self.dist is None else np.asarray(self.dist, np.float64).ravel()
        if K.shape != (3, 3):
            raise ValueError(f"K must be 3x3, got {K.shape}")
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError("K must be finite with positive focal lengths")
        if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            raise ValueError("K must be upper triangular with K[2, 2] == 1")
        if dist.shape == (4,):
            dist = np.append(dist, 0.0)  # [k1, k2, p1, p2] is a valid OpenCV vector
        if dist.shape != (5,) or not np.all(np.isfinite(dist)):
            raise ValueError(f"dist must be [k1, k2, p1, p2, k3] (5 finite values), got {dist}")
        w, h = int(self.width), int(self.height)
        if w != self.width or h != self.height or w <= 0 or h <= 0:
            raise ValueError(
                f"width and height must be positive integers: {self.width}x{self.height}"
            )
        object.__setattr__(self, "K", _readonly(K))
        object.__setattr__(self, "dist", _readonly(dist))
        object.__setattr__(self, "width", w)
        object.__setattr__(self, "height", h)

    def _key(self) -> tuple[bytes, bytes, int, int]:
        return (self.K.tobytes(), self.dist.tobytes(), self.width, self.height)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    def __repr__(self) -> str:
        return (
            f"Camera(f=({self.fx:.6g}, {self.fy:.6g}), c=({self.cx:.6g}, {self.cy:.6g}), "
            f"dist={self.dist.tolist()}, size={self.width}x{self.height})"
        )

    # ---- construction / serialisation ------------------------------------------------

    @classmethod
    def pinhole(
        cls,
        f: float,
        width: int,
        height: int,
        dist: ArrayLike | None = None,
        cx: float | None = None,
        cy: float | None = None,
    ) -> Camera:
        """A camera with square pixels and no skew.

        Parameters
        ----------
        f : float
            Focal length in pixels.
        width, height : int
            Image size in pixels.
        dist : (5,) array_like, optional
            Distortion ``[k1, k2, p1, p2, k3]``; none by default.
        cx, cy : float, optional
            Principal point in pixels; by default the image centre,
            ((width - 1) / 2, (height - 1) / 2), as the top-left pixel's centre is (0, 0).

        Returns
        -------
        Camera
        """
        cx = (width - 1) / 2.0 if cx is None else float(cx)
        cy = (height - 1) / 2.0 if cy is None else float(cy)
        K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]], dtype=np.float64)
        return cls(K, np.zeros(5) if dist is None else np.asarray(dist, np.float64), width, height)

    def to_dict(self) -> dict[str, Any]:
        """The map document's "camera" object (docs/map-format.md).

        Returns
        -------
        dict
            ``width``, ``height``, ``K`` (3x3 lists) and ``dist`` (5 values).
        """
        return {
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Camera:
        """The camera of a map document's "camera" object (the inverse of `to_dict`).

        Parameters
        ----------
        d : dict
            With ``K``, ``dist``, ``width`` and ``height``.

        Returns
        -------
        Camera

        Raises
        ------
        ValueError
            If a key is missing or a value is invalid.
        """
        try:
            return cls(np.asarray(d["K"], np.float64), np.asarray(d["dist"], np.float64),
                       int(d["width"]), int(d["height"]))
        except KeyError as e:
            raise ValueError(f"camera document lacks {e.args[0]!r}") from None

    def scaled_to(self, width: int, height: int) -> Camera:
        """The same lens at another resolution (a stream downscaled by the client).

        Pixel-centre coordinates scale about the top-left pixel's corner (-0.5, -0.5).

        Parameters
        ----------
        width, height : int
            The new image size in pixels.

        Returns
        -------
        Camera
            K scaled; the distortion (in normalised coordinates) unchanged.
        """
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, 0], K[0, 1], K[1, 1] = K[0, 0] * sx, K[0, 1] * sx, K[1, 1] * sy
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return Camera(K, self.dist, int(width), int(height))

    def with_focal(self, focal_px: float) -> Camera:
        """The same camera zoomed to another focal length (fx, the skew and fy scaled alike).

        Parameters
        ----------
        focal_px : float
            The new fx, pixels.

        Returns
        -------
        Camera
        """
        scale = focal_px / self.fx
        K = self.K.copy()
        K[0, :2] *= scale
        K[1, 1] *= scale
        return Camera(K, self.dist, self.width, self.height)

    # ---- parameters -------------------------------------------------------------------

    @property
    def fx(self) -> float:
        """Horizontal focal length, pixels."""
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        """Vertical focal length, pixels."""
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        """Principal point column, pixels."""
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        """Principal point row, pixels."""
        return float(self.K[1, 2])

    @property
    def size(self) -> tuple[int, int]:
        """(width, height), the order cv2 wants."""
        return (self.width, self.height)

    @property
    def has_distortion(self) -> bool:
        """Whether any distortion coefficient is non-zero."""
        return bool(np.any(self.dist != 0))

    # ---- projection -------------------------------------------------------------------

    def _distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """OpenCV's distortion of normalised coordinates (x, y) = (X/Z, Y/Z)."""
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy2 = 2.0 * x * y
        xd = x * radial + p1 * xy2 + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + p2 * xy2
        return xd, yd

    def _to_pixels(self, xd: np.ndarray, yd: np.ndarray) -> np.ndarray:
        K = self.K
        u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
        v = K[1, 1] * yd + K[1, 2]
        return np.stack([u, v], axis=-1)

    def _to_normalised(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        K = self.K
        y = (uv[:, 1] - K[1, 2]) / K[1, 1]
        x = (uv[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        return x, y

    def project(self, X_cam: ArrayLike) -> np.ndarray:
        """Project camera-frame points to (distorted) pixels, as cv2.projectPoints.

        No visibility test: points behind the camera still get a (meaningless) pixel
        and Z == 0 gives inf/nan; `in_field` tells which rays can reach the image.

        Parameters
        ----------
        X_cam : (N, 3) or (3,) array_like
            Points in camera coordinates, metres.

        Returns
        -------
        (N, 2) ndarray
            Pixel coordinates (x, y).
        """
        X = _points(X_cam, 3, "X_cam")
        with np.errstate(divide="ignore", invalid="ignore"):
            x = X[:, 0] / X[:, 2]
            y = X[:, 1] / X[:, 2]
            if self.has_distortion:
                x, y = self._distort(x, y)
            return self._to_pixels(x, y)

    def project_map(self, X_map: ArrayLike, pose: Pose) -> np.ndarray:
        """Project map points seen from `pose` to (distorted) pixels.

        Parameters
        ----------
        X_map : (N, 3) or (3,) array_like
            Points in map coordinates, metres.
        pose : Pose
            Map-to-camera transform.

        Returns
        -------
        (N, 2) ndarray
            Pixel coordinates (x, y).
        """
        return self.project(pose.transform(X_map))

    def project_ideal(self, X_cam: ArrayLike) -> np.ndarray:
        """Project camera-frame points through the pinhole alone (no distortion).

        Parameters
        ----------
        X_cam : (N, 3) or (3,) array_like
            Points in camera coordinates, metres.

        Returns
        -------
        (N, 2) ndarray
            Ideal pixel coordinates (x, y) of the same K.
        """
        X = _points(X_cam, 3, "X_cam")
        with np.errstate(divide="ignore", invalid="ignore"):
            return self._to_pixels(X[:, 0] / X[:, 2], X[:, 1] / X[:, 2])

    def distort_pixels(self, uv_ideal: ArrayLike) -> np.ndarray:
        """Distort ideal pinhole pixels (the inverse of `undistort_pixels`).

        Parameters
        ----------
        uv_ideal : (N, 2) or (2,) array_like
            Ideal pixel coordinates of this camera's K.

        Returns
        -------
        (N, 2) ndarray
            The distorted pixel coordinates (same K).
        """
        x, y = self._to_normalised(_points(uv_ideal, 2, "uv_ideal"))
        if self.has_distortion:
            x, y = self._distort(x, y)
        return self._to_pixels(x, y)

    def undistort_pixels(self, uv: ArrayLike, iterations: int = 20) -> np.ndarray:
        """Remove the lens distortion from pixel coordinates.

        Like cv2.undistortPoints(..., P=K), but solved to round-off with Newton's
        method (cv2's default is 5 fixed-point steps, ~0.01 px off at the corners of a
        strongly distorted lens). Where the distortion polynomial folds over (far
        outside the lens's valid field) the answer is a best effort.

        Parameters
        ----------
        uv : (N, 2) or (2,) array_like
            Distorted pixel coordinates.
        iterations : int, optional
            Most Newton steps (it stops at ~1e-9 px, after 3-5 steps).

        Returns
        -------
        (N, 2) ndarray
            Ideal pinhole pixel coordinates of the same K.
        """
        uv = _points(uv, 2, "uv")
        if not self.has_distortion:
            return uv.copy()
        xd, yd = self._to_normalised(uv)
        k1, k2, p1, p2, k3 = self.dist
        x, y = xd.copy(), yd.copy()
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
            ux, uy = self._distort(x, y)
            ex, ey = ux - xd, uy - yd
            # Jacobian of the distortion map
            a = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
            b = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
            d = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
            det = a * d - b * b
            ok = np.abs(det) > 1e-12
            det = np.where(ok, det, 1.0)
            dx = np.where(ok, (d * ex - b * ey) / det, ex)
            dy = np.where(ok, (a * ey - b * ex) / det, ey)
            # Damp huge steps (fold-over region) so nothing explodes to inf.
            step = np.maximum(np.hypot(dx, dy), 1e-300)
            scale = np.minimum(1.0, 0.5 * (1.0 + np.hypot(x, y)) / step)
            x -= dx * scale
            y -= dy * scale
            if float(np.max(step, initial=0.0)) < 1e-12:  # ~1e-9 px; Newton needs 3-5 steps
                break
        return self._to_pixels(x, y)

    # ---- field of view ----------------------------------------------------------------

    @property
    def fold_radius(self) -> float:
        """Normalised radius (X/Z, no unit) where the radial map r -> r (1 + k1 r^2 +
        k2 r^4 + k3 r^6) first stops increasing; inf when it never does.

        Beyond it the distortion polynomial folds back: a point far off the image (even
        70 degrees off axis) can `project` into it. Exact: the smallest positive root of
        the slope 1 + 3 k1 u + 5 k2 u^2 + 7 k3 u^3 in u = r^2 (tangential terms, tiny
        for real lenses, are ignored). Cached per camera value (_field_extent).
        """
        return _field_extent(self)[1]

    def field_radius(self, margin: float = 1.0) -> float:
        """Normalised radius (X/Z) of the field this camera sees.

        The one place that answers "could this ray be in the image": within it
        `project` is trustworthy, beyond it a point is off the image however its
        (possibly folded) projection looks.

        Parameters
        ----------
        margin : float, optional
            Multiple of the image's farthest corner's radius: 1.0 is exactly the image's
            rays (an in-image point never lies beyond, for a radial lens); > 1 adds a
            safety band.

        Returns
        -------
        float
            ``margin`` times the corner radius, never past FOLD_FRACTION of
            `fold_radius`.
        """
        corner, fold = _field_extent(self)
        return min(margin * corner, FOLD_FRACTION * fold)

    def in_field(self, points_cam: ArrayLike, margin: float = 1.0) -> np.ndarray:
        """Which camera-frame points lie on rays that can reach the image.

        The test to apply before trusting `project`, which folds far-off points into
        the image.

        Parameters
        ----------
        points_cam : (N, 3) or (3,) array_like
            Points in camera coordinates, metres.
        margin : float, optional
            As in `field_radius`.

        Returns
        -------
        (N,) ndarray of bool
            In front of the camera (z > 0) and within ``field_radius(margin)``.
        """
        X = _points(points_cam, 3, "points_cam")
        limit = self.field_radius(margin)
        z = X[:, 2]
        return (z > 0) & (np.hypot(X[:, 0], X[:, 1]) <= limit * z)

    # ---- whole-image distortion -------------------------------------------------------

    @functools.cached_property
    def _distortion_maps(self) -> tuple[np.ndarray, np.ndarray]:
        us, vs = np.meshgrid(
            np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64)
        )
        ideal = self.undistort_pixels(np.stack([us.ravel(), vs.ravel()], axis=1))
        map_x = ideal[:, 0].reshape(self.height, self.width).astype(np.float32)
        map_y = ideal[:, 1].reshape(self.height, self.width).astype(np.float32)
        map_x.setflags(write=False)
        map_y.setflags(write=False)
        return map_x, map_y

    def distortion_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """Maps from this camera's (distorted) image into the ideal pinhole image.

        ``cv2.remap(ideal, map_x, map_y, INTER_LINEAR)`` turns an undistorted image into
        the distorted one (cv2.initUndistortRectifyMap is the opposite direction).
        Without distortion the maps are the identity.

        Returns
        -------
        map_x, map_y : (height, width) ndarray of float32
            For every pixel, its location in the ideal image of the same K; read-only,
            cached per camera.
        """
        return self._distortion_maps

    @functools.cached_property
    def ideal_canvas(self) -> IdealCanvas:
        """The ideal-image region the distorted image sees (see IdealCanvas); cached.

        Barrel distortion (k1 < 0) sees more than the ideal image of the same size, so
        a renderer must draw a larger undistorted canvas before remapping.
        """
        map_x, map_y = self.distortion_maps()
        mx_w, mx_h = _MAX_CANVAS_MARGIN * self.width, _MAX_CANVAS_MARGIN * self.height
        mx, my = map_x[np.isfinite(map_x)], map_y[np.isfinite(map_y)]
        # One pixel of margin for bilinear interpolation; bounded for wild lenses.
        x0 = int(np.floor(max(float(mx.min()), -mx_w))) - 1
        y0 = int(np.floor(max(float(my.min()), -mx_h))) - 1
        x1 = int(np.ceil(min(float(mx.max()), self.width - 1 + mx_w))) + 2
        y1 = int(np.ceil(min(float(my.max()), self.height - 1 + mx_h))) + 2
        rx = (map_x - np.float32(x0)).astype(np.float32)
        ry = (map_y - np.float32(y0)).astype(np.float32)
        rx.setflags(write=False)
        ry.setflags(write=False)
        return IdealCanvas(x0=x0, y0=y0, width=x1 - x0, height=y1 - y0, map_x=rx, map_y=ry)


def _field_extent(camera: Camera) -> tuple[float, float]:
    """(normalised radius of the image's farthest corner, fold radius) of a camera.

    Cached by the camera's value, not its identity: a tracking stream may build a new
    Camera per frame (scaled_to, per-stream intrinsics), and this costs ~0.2 ms. The
    cache holds the parameters only, never a Camera (whose cached distortion maps
    are megabytes)."""
    return _field_extent_of(camera._key())


@functools.lru_cache(maxsize=64)
def _field_extent_of(key: tuple[bytes, bytes, int, int]) -> tuple[float, float]:
    """_field_extent of the camera with ``Camera._key() == key``.

    The corners are the pixel areas' outer edges (-0.5 and w - 0.5), undistorted:
    every pixel's ray lies within that radius. A corner that no ray reaches (a wild
    lens whose polynomial turns back before the image's edge; undistortion does not
    converge there) counts as infinitely far: the fold then bounds the field.
    """
    K, dist, w, h = key
    camera = Camera(np.frombuffer(K).reshape(3, 3), np.frombuffer(dist), w, h)
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    x, y = camera._to_normalised(camera.undistort_pixels(corners))
    radius = np.hypot(x, y)
    if camera.has_distortion:
        xd, yd = camera._to_normalised(corners)
        ux, uy = camera._distort(x, y)
        radius[np.hypot(ux - xd, uy - yd) > 1e-9 * (1.0 + np.hypot(xd, yd))] = np.inf
    corner = float(radius.max())
    k1, k2, _, _, k3 = (float(v) for v in camera.dist)
    # d/dr r (1 + k1 u + k2 u^2 + k3 u^3) with u = r^2; leading zeros dropped for np.roots.
    coeffs = np.trim_zeros(np.array([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0]), "f")
    roots = np.roots(coeffs) if len(coeffs) > 1 else np.zeros(0)
    u = [float(z.real) for z in roots if abs(z.imag) <= 1e-9 * max(1.0, abs(z.real)) and z.real > 0]
    return corner, (float(np.sqrt(min(u))) if u else float("inf"))
