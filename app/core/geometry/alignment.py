"""Similarity transforms between a surveyed map and the world (paper §5.1, Arun et al.).

A survey by structure from motion fixes the map only up to a rotation, translation and
(without the card layout) a scale. Two ways to bring it into a frame the user cares
about:

* ``similarity_from_points``: three or more disc positions measured in the world
  (Umeyama's least-squares similarity; the residuals say how well they fit);
* ``target_origin_alignment``: one chosen target defines the origin, its card the
  plane z = 0 and disc 0 -> disc 1 the x axis (no measuring tape needed).

``Similarity.apply*`` then maps points, camera poses and whole map documents.
Pure numpy; no I/O.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from app.core.geometry.camera import Pose

__all__ = ["Similarity", "alignment_residuals", "similarity_from_points", "target_origin_alignment"]


@dataclass(frozen=True, eq=False)
class Similarity:
    """A similarity transform between two frames: ``X_new = scale * R @ X_old + t``.

    Parameters
    ----------
    scale : float
        Positive scale (new units per old unit).
    R : (3, 3) array_like
        Rotation from the old frame to the new.
    t : (3,) array_like
        Translation, in the new frame's units.

    Raises
    ------
    ValueError
        If `R` is not a rotation or `scale` is not positive and finite.
    """

    scale: float
    R: np.ndarray  # (3, 3) rotation
    t: np.ndarray  # (3,)

    def __post_init__(self) -> None:
        R = np.asarray(self.R, np.float64)
        t = np.asarray(self.t, np.float64).reshape(3)
        if R.shape != (3, 3) or np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
            raise ValueError("Similarity R must be a 3x3 rotation matrix")
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"Similarity scale must be positive, got {self.scale}")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "scale", float(self.scale))

    @classmethod
    def identity(cls) -> Similarity:
        """The identity: scale 1, no rotation, no translation.

        Returns
        -------
        Similarity
        """
        return cls(1.0, np.eye(3), np.zeros(3))

    def apply(self, X: ArrayLike) -> np.ndarray:
        """Transform points from the old frame to the new.

        Parameters
        ----------
        X : (N, 3) or (3,) array_like
            Points in the old frame.

        Returns
        -------
        ndarray
            The points in the new frame, same shape as `X`.
        """
        X = np.asarray(X, np.float64)
        return self.scale * X @ self.R.T + self.t

    def inverse(self) -> Similarity:
        """The transform from the new frame back to the old.

        Returns
        -------
        Similarity
        """
        return Similarity(1.0 / self.scale, self.R.T, -self.R.T @ self.t / self.scale)

    def compose(self, other: Similarity) -> Similarity:
        """``self`` after ``other``: ``X -> self.apply(other.apply(X))``.

        Parameters
        ----------
        other : Similarity
            The transform applied first.

        Returns
        -------
        Similarity
        """
        return Similarity(self.scale * other.scale, self.R @ other.R, self.scale * self.R @ other.t + self.t)

    def apply_pose(self, pose: Pose) -> Pose:
        """A camera pose (``x_cam = R_c @ X_old + t_c``) re-expressed in the new frame.

        The camera frame is scaled with the map so that the new pose stays a rigid
        transform in the new frame's units: x_cam' = R_c R^T (X_new - t) + scale t_c.

        Parameters
        ----------
        pose : Pose
            Map-to-camera transform in the old frame.

        Returns
        -------
        Pose
            Map-to-camera transform in the new frame.
        """
        R = pose.R @ self.R.T
        return Pose(R, self.scale * pose.t - R @ self.t)

    def apply_poses(self, poses: Sequence[Pose | None]) -> list[Pose | None]:
        """`apply_pose` on each pose of a trajectory; None (a frame without a pose) stays.

        Parameters
        ----------
        poses : sequence of Pose or None

        Returns
        -------
        list of Pose or None
        """
        return [None if p is None else self.apply_pose(p) for p in poses]

    def apply_map_document(self, document: dict[str, Any], frame: str = "world") -> dict[str, Any]:
        """A copy of a map document (docs/map-format.md) in the new frame.

        Parameters
        ----------
        document : dict
            A map document; its targets' ``discs`` are in the old frame.
        frame : str, optional
            The new frame's name, written to the copy's ``frame``.

        Returns
        -------
        dict
            The copy, with disc positions moved and their ``std_m`` scaled.
        """
        out = copy.deepcopy(document)
        for target in out.get("targets", []):
            target["discs"] = self.apply(np.asarray(target["discs"], np.float64)).tolist()
            if target.get("std_m") is not None:
                target["std_m"] = [float(s) * self.scale for s in target["std_m"]]
        out["frame"] = frame
        return out

    def to_dict(self) -> dict[str, Any]:
        """The transform as JSON-able values.

        Returns
        -------
        dict
            ``scale``, ``R`` (3x3 lists) and ``t``.
        """
        return {"scale": self.scale, "R": self.R.tolist(), "t": self.t.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Similarity:
        """The transform of a `to_dict` document.

        Parameters
        ----------
        d : dict
            With ``scale``, ``R`` and ``t``.

        Returns
        -------
        Similarity
        """
        return cls(float(d["scale"]), np.asarray(d["R"], np.float64), np.asarray(d["t"], np.float64))


def similarity_from_points(src: ArrayLike, dst: ArrayLike, with_scale: bool = True) -> Similarity:
    """Least-squares similarity taking ``src`` onto ``dst`` (Umeyama 1991).

    Parameters
    ----------
    src : (N, 3) array_like
        Points in the old frame (e.g. surveyed disc centres).
    dst : (N, 3) array_like
        The same points measured in the new frame.
    with_scale : bool, optional
        Fit the scale too; False fixes it at 1 (a rigid transform).

    Returns
    -------
    Similarity
        The transform minimising ``sum |apply(src) - dst|^2``.

    Raises
    ------
    ValueError
        With a message for the user, for fewer than 3 points, non-finite input, or
        points that are (nearly) collinear: those leave the rotation about their line
        undetermined.
    """
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise ValueError(f"need two (N, 3) point arrays of the same shape, got {src.shape} and {dst.shape}")
    n = len(src)
    if n < 3:
        raise ValueError(f"an alignment needs at least 3 points, got {n}")
    if not (np.isfinite(src).all() and np.isfinite(dst).all()):
        raise ValueError("alignment points must be finite")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    for name, pts in (("map", a), ("world", b)):
        spread = np.linalg.svd(pts, compute_uv=False)
        # Relative test: the second direction of spread must be a real fraction of the first.
        if spread[0] <= 1e-12 or spread[1] < 1e-3 * spread[0]:
            raise ValueError(f"the {name} points are collinear (or coincide): the alignment is not determined")
    cov = b.T @ a / n
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:  # a reflection would fit better: forbid it
        D[2, 2] = -1.0
    R = U @ D @ Vt
    var_s = (a**2).sum() / n
    scale = float(np.trace(np.diag(S) @ D) / var_s) if with_scale else 1.0
    t = mu_d - scale * R @ mu_s
    return Similarity(scale, R, t)


def alignment_residuals(similarity: Similarity, src: ArrayLike, dst: ArrayLike) -> np.ndarray:
    """Distance between each transformed source point and its destination.

    Parameters
    ----------
    similarity : Similarity
    src, dst : (N, 3) array_like
        Points in the old and the new frame.

    Returns
    -------
    (N,) ndarray
        ``|similarity.apply(src) - dst|``, in the new frame's units.
    """
    return np.linalg.norm(similarity.apply(np.asarray(src, np.float64)) - np.asarray(dst, np.float64), axis=1)


def target_origin_alignment(discs: ArrayLike, origin: str = "centre") -> Similarity:
    """Rigid transform (scale 1) that makes one target the world frame.

    The new frame has x along disc 0 -> disc 1, the card in the plane z = 0 and z out of
    the printed face (towards whoever reads it), so y points up the card as printed.

    Parameters
    ----------
    discs : (4, 3) array_like
        The target's surveyed disc centres in disc order (0 top-left, 1 top-right,
        2 bottom-right, 3 bottom-left as printed), map coordinates.
    origin : {"centre", "disc0"}, optional
        The new origin: the card's centre (mean of the discs) or disc 0.

    Returns
    -------
    Similarity
        Map to the target's frame.

    Raises
    ------
    ValueError
        If `discs` is not a finite (4, 3) array, the discs coincide or are collinear,
        or `origin` is unknown.
    """
    d = np.asarray(discs, np.float64)
    if d.shape != (4, 3) or not np.isfinite(d).all():
        raise ValueError(f"a target's discs must be a finite (4, 3) array, got shape {d.shape}")
    x = (d[1] - d[0]) + (d[2] - d[3])  # both top and bottom edges: less noise
    down = (d[3] - d[0]) + (d[2] - d[1])
    nx = np.linalg.norm(x)
    if nx < 1e-12:
        raise ValueError("the target's discs coincide")
    x /= nx
    # Out of the printed face: printed x right and y down give a normal of down x right.
    z = np.cross(down, x)
    nz = np.linalg.norm(z)
    if nz < 1e-12:
        raise ValueError("the target's discs are collinear")
    z /= nz
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: new axes in old coordinates
    if origin == "centre":
        o = d.mean(axis=0)
    elif origin == "disc0":
        o = d[0]
    else:
        raise ValueError(f"origin must be 'centre' or 'disc0', got {origin!r}")
    return Similarity(1.0, R, -R @ o)
