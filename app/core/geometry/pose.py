"""Camera pose from the disc centres of every identified target (paper §5.2-5.3).

``nonlinear`` (default): a robust initial pose (SQPnP on all points, with RANSAC over
targets so a misidentified target cannot drag it), then minimisation of the reprojection
error (eq. 5) with the full lens model: Gauss-Newton with the analytic Jacobian, OpenCV's
Levenberg-Marquardt when the start is poor; optionally with the focal length free (zoom
lenses, §5.3). The covariance comes from the Jacobian at the optimum with the noise
level estimated from the residuals; a pose that is not determined (too few points,
degenerate geometry) is refused rather than reported.

``posit``, ``mean`` and ``single`` are kept for comparison, as in the paper's Table 1.
``mean`` averages the single-target poses with each target's planar two-fold ambiguity
(its two tilts) resolved by the other targets, as a practitioner would.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import partial
from typing import NamedTuple

import cv2
import numpy as np

from app.core.geometry.camera import Camera, Pose

__all__ = [
    "METHODS",
    "PoseEstimate",
    "PoseUndetermined",
    "TargetObservation",
    "cramer_rao_position_rms",
    "estimate_pose",
    "mean",
    "nonlinear",
    "posit",
    "position_covariance",
    "refine_with_focal",
    "residuals",
    "single",
    "single_target_poses",
    "target_poses",
]

#: The pose methods `estimate_pose` knows, the paper's first.
METHODS = ("nonlinear", "posit", "mean", "single")


class PoseUndetermined(ValueError):
    """The observations do not determine a pose; the message says why."""


@dataclass(frozen=True)
class TargetObservation:
    """One identified target: its disc centres in the image and in the map.

    Attributes
    ----------
    id : int
        The target's id.
    image : (4, 2) ndarray
        Disc centres in pixels, in disc order (0 top-left, 1 top-right, 2 bottom-right,
        3 bottom-left as printed).
    map : (4, 3) ndarray
        The same discs' centres in map coordinates, metres.
    map_std : (4,) ndarray or None
        Each disc's 3D position uncertainty in the map (RMS over the three axes, 1
        sigma, metres: the map document's ``std_m``); None takes the map as exact.
        With it the pose's covariance includes the map's uncertainty.
    """

    id: int
    image: np.ndarray  # (4, 2) pixels
    map: np.ndarray  # (4, 3) metres
    map_std: np.ndarray | None = None  # (4,) metres


@dataclass(frozen=True, eq=False)
class PoseEstimate:
    """A camera pose with its fit and uncertainty.

    Attributes
    ----------
    pose : Pose
        Map-to-camera transform, ``x_cam = R @ X_map + t``.
    rms_px : float
        RMS reprojection error over the points the pose rests on, pixels.
    n_targets, n_points : int
        Targets and disc centres the pose rests on.
    covariance : ndarray
        Covariance of (rvec, tvec[, f]) at the optimum (radians, metres, pixels), the
        noise level estimated from the residuals.
    covariance_position : (3, 3) ndarray
        Covariance of the camera centre, square metres.
    focal_px : float
        The focal length used (estimated when the focal length was free), pixels.
    target_ids : list of int
        The targets the pose rests on (inliers).
    rejected_ids : list of int
        Targets refused as outliers.
    method : str
        One of `METHODS`.
    ambiguous : bool
        The pose rests on one target whose two tilts both fit its discs (the planar
        two-fold ambiguity): the other tilt was a candidate too.
    tilt_from_track : bool
        A prior pose (the track's prediction) chose a tilt other than the one with the
        lower reprojection error: without the track the pose would have flipped.
    """

    pose: Pose
    rms_px: float
    n_targets: int
    n_points: int
    covariance: np.ndarray  # over (rvec, tvec[, f]) at the optimum
    covariance_position: np.ndarray  # (3, 3) of the camera centre, m^2
    focal_px: float
    target_ids: list[int]  # the targets the pose rests on (inliers)
    rejected_ids: list[int]  # targets refused as outliers
    method: str
    ambiguous: bool = False
    tilt_from_track: bool = False

    def to_dict(self) -> dict[str, object]:
        """The estimate as JSON-able values (the service's pose document).

        Returns
        -------
        dict
            ``R``, ``t``, ``position`` (metres), ``reprojection_rms_px``, ``n_targets``,
            ``n_points``, ``covariance_position`` (m^2), ``focal_px``, ``method``,
            ``rejected_targets``, ``ambiguous`` and ``tilt_from_track``.
        """
        return {
            "R": self.pose.R.tolist(),
            "t": self.pose.t.tolist(),
            "position": self.pose.position.tolist(),
            "reprojection_rms_px": float(self.rms_px),
            "n_targets": self.n_targets,
            "n_points": self.n_points,
            "covariance_position": self.covariance_position.tolist(),
            "focal_px": float(self.focal_px),
            "method": self.method,
            "rejected_targets": self.rejected_ids,
            "ambiguous": self.ambiguous,
            "tilt_from_track": self.tilt_from_track,
        }


# --- building blocks ------------------------------------------------------------------
#
# The hot path (one frame, a few targets) keeps the pose as OpenCV (rvec, tvec) arrays
# and calls cv2 and small numpy operations directly: at 12 points a pose costs ~0.1 ms,
# where each numpy.linalg call (~8 us) or validated Pose (~20 us) is a visible share.
# One Pose is built, at the end.


def _stack(observations: Sequence[TargetObservation]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All image points (N, 2), map points (N, 3), and the number of points per target."""
    images = [np.asarray(o.image, np.float64).reshape(-1, 2) for o in observations]
    maps = [np.asarray(o.map, np.float64).reshape(-1, 3) for o in observations]
    counts = [len(a) for a in images]
    if counts != [len(m) for m in maps]:
        o, a, m = next((o, a, m) for o, a, m in zip(observations, images, maps, strict=True) if len(a) != len(m))
        raise PoseUndetermined(f"target {o.id}: {len(a)} image points but {len(m)} map points")
    return np.concatenate(images), np.concatenate(maps), np.array(counts)


def _map_variance(observations: Sequence[TargetObservation]) -> np.ndarray | None:
    """Per stacked point, the map's variance along each axis (m^2); None if no target
    carries one. A disc's ``map_std`` is an RMS over three axes: a third of its square
    per axis (taken isotropic). Targets without one count as exact."""
    if all(o.map_std is None for o in observations):
        return None
    parts = [np.zeros(len(np.asarray(o.map).reshape(-1, 3))) if o.map_std is None
             else np.square(np.asarray(o.map_std, np.float64).reshape(-1)) / 3.0 for o in observations]
    return np.concatenate(parts)


def _map_groups(counts: np.ndarray) -> np.ndarray:
    """The group of every stacked point whose map errors move together
    (`CARD_RIGID_MAP_ERRORS`): its target's, or its own."""
    return _owner(counts) if CARD_RIGID_MAP_ERRORS else np.arange(int(np.sum(counts)))


def _owner(counts: np.ndarray) -> np.ndarray:
    """The target index of every stacked point."""
    return np.repeat(np.arange(len(counts)), counts)


def _check_determined(world: np.ndarray) -> np.ndarray:
    """Refuse undetermined point sets; return the singular values of their spread."""
    if len(world) < 4:
        raise PoseUndetermined(f"{len(world)} points: at least 4 (one whole target) are needed")
    if not np.isfinite(world).all():
        raise PoseUndetermined("map points must be finite")
    spread = cv2.SVDecomp(world - world.mean(axis=0), flags=cv2.SVD_NO_UV)[0].ravel()
    if spread[1] < 1e-6 * max(spread[0], 1e-12):
        raise PoseUndetermined("the points are collinear (or coincide): the pose is not determined")
    return spread


def _ideal(camera: Camera, image: np.ndarray) -> np.ndarray:
    """Normalised pinhole coordinates of pixel measurements (distortion removed)."""
    ideal = camera.undistort_pixels(image)
    k_inv = np.linalg.inv(camera.K)
    return np.ascontiguousarray((np.c_[ideal, np.ones(len(ideal))] @ k_inv.T)[:, :2])


def residuals(camera: Camera, pose: Pose, world: np.ndarray, image: np.ndarray) -> np.ndarray:
    """Reprojection residuals of measured image points.

    Parameters
    ----------
    camera : Camera
    pose : Pose
        Map-to-camera transform.
    world : (N, 3) ndarray
        Points in map coordinates, metres.
    image : (N, 2) ndarray
        Their measured pixel positions.

    Returns
    -------
    (N, 2) ndarray
        Projected minus measured, pixels.
    """
    return camera.project(pose.transform(world)) - image


def _worst_per_target(residual: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The largest reprojection error (px) among each target's points."""
    error = np.sqrt((residual * residual).sum(axis=1))
    worst = np.zeros(len(counts))
    np.maximum.at(worst, _owner(counts), error)
    return worst


def _planar_poses(world: np.ndarray, image: np.ndarray, K: np.ndarray,
                  dist: np.ndarray | None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Both poses (R, t) (IPPE) of points that lie close to a plane, in the map frame.

    IPPE wants exactly coplanar points; surveyed discs are a little off their card's
    plane (each disc is its own 3D point), so the points are projected onto their
    best-fit plane first and the poses taken back to the map frame. The two are the
    two tilts a small or far planar target cannot tell apart; the caller refines both.
    """
    centre = world.mean(axis=0)
    _, _, Vt = np.linalg.svd(world - centre)
    if np.linalg.det(Vt) < 0:
        Vt[2] *= -1
    planar = (world - centre) @ Vt.T
    planar[:, 2] = 0.0
    try:
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(planar, image, K, dist, flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        return []
    poses = []
    for rvec, tvec in zip(rvecs, tvecs, strict=False):
        R = cv2.Rodrigues(rvec)[0] @ Vt
        poses.append((R, tvec.ravel() - R @ centre))
    return poses


def _linearise(K: np.ndarray, dist: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, world: np.ndarray,
               image: np.ndarray, with_focal: bool) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (N, 2) and their Jacobian (2N, 6 [+1]) over (rvec, t[, f]), full lens model."""
    projected, jac = cv2.projectPoints(world, rvec, tvec, K, dist)
    J = jac[:, :6]
    if with_focal:  # f moves fx and fy together: the aspect ratio is fixed
        J = np.column_stack((J, jac[:, 6] + (K[1, 1] / K[0, 0]) * jac[:, 7]))
    return projected.reshape(-1, 2) - image, J


def _refine_focal(K: np.ndarray, dist: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, world: np.ndarray,
                  image: np.ndarray, iterations: int = 30
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Levenberg-Marquardt over (rvec, t, f); returns rvec, tvec, the new K and the
    (residual, Jacobian) at the optimum (for the covariance)."""
    aspect = K[1, 1] / K[0, 0]
    params = np.concatenate((np.ravel(rvec), np.ravel(tvec), [K[0, 0]]))

    def evaluate(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        Kf = K.copy()
        Kf[0, 0], Kf[1, 1] = p[6], p[6] * aspect
        return (*_linearise(Kf, dist, p[:3], p[3:6], world, image, True), Kf)

    residual, J, Kf = evaluate(params)
    cost, lam = float((residual**2).sum()), 1e-3
    for _ in range(iterations):
        JtJ, gradient = J.T @ J, J.T @ residual.ravel()
        for _ in range(10):
            step = np.linalg.solve(JtJ + lam * np.diag(np.diag(JtJ) + 1e-12), -gradient)
            new = params + step
            res_new, J_new, K_new = evaluate(new)
            cost_new = float((res_new**2).sum())
            if cost_new < cost:
                break
            lam *= 10
        else:
            break  # no step lowers the cost: at the minimum
        done = cost - cost_new < 1e-12 * max(cost, 1e-12)
        params, residual, J, Kf, cost = new, res_new, J_new, K_new, cost_new
        lam = max(lam / 10, 1e-9)
        if done:
            break
    return params[:3].reshape(3, 1), params[3:6].reshape(3, 1), Kf, (residual, J)


def refine_with_focal(camera: Camera, pose: Pose, world: np.ndarray, image: np.ndarray,
                      iterations: int = 30) -> tuple[Pose, float]:
    """Refine a pose and the focal length together (the paper's zoom lens, §5.3).

    Levenberg-Marquardt on the reprojection error over (rvec, t, f); the aspect
    ratio, principal point and distortion stay fixed.

    Parameters
    ----------
    camera : Camera
        The lens; its focal length is the start.
    pose : Pose
        Start pose, map to camera.
    world : (N, 3) ndarray
        Points in map coordinates, metres.
    image : (N, 2) ndarray
        Their measured pixel positions.
    iterations : int, optional
        Most Levenberg-Marquardt iterations.

    Returns
    -------
    pose : Pose
        The refined pose.
    focal_px : float
        The refined focal length fx, pixels.
    """
    rvec, tvec, K, _ = _refine_focal(camera.K, camera.dist, pose.rvec, pose.t, world, image, iterations)
    return Pose.from_rvec_tvec(rvec.ravel(), tvec.ravel()), float(K[0, 0])


def _position_jacobian(R: np.ndarray, dR: np.ndarray, t: np.ndarray) -> np.ndarray:
    """d c / d (rvec, t) of the camera centre c = -R^T t; dR is Rodrigues's (3, 9)."""
    jac = np.empty((3, 6))
    jac[:, :3] = -(t @ dR.reshape(3, 3, 3)).T  # column k: -(dR/drvec_k)^T t
    jac[:, 3:] = -R.T
    return jac


def position_covariance(pose: Pose, covariance: np.ndarray) -> np.ndarray:
    """Covariance of the camera centre c = -R^T t from that of (rvec, t), to first order.

    Parameters
    ----------
    pose : Pose
        The pose the covariance belongs to.
    covariance : (6, 6) or larger ndarray
        Covariance over (rvec, tvec[, ...]) (radians, metres); the leading 6x6 is used.

    Returns
    -------
    (3, 3) ndarray
        Covariance of the camera centre in map coordinates, square metres.
    """
    R, dR = cv2.Rodrigues(pose.rvec)  # dR: (3, 9), d vec(R) / d rvec, row-major R
    jac = _position_jacobian(R, dR, pose.t)
    return jac @ covariance[:6, :6] @ jac.T


def _estimate(K: np.ndarray, dist: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, world: np.ndarray,
              image: np.ndarray, with_focal: bool, method: str, ids: list[int], rejected: list[int],
              linearised: tuple[np.ndarray, np.ndarray] | None = None, pose: Pose | None = None,
              map_variance: np.ndarray | None = None, map_group: np.ndarray | None = None) -> PoseEstimate:
    """Package a pose with its residual RMS and covariance (noise from the residuals,
    plus the map's own uncertainty when ``map_variance`` gives it per point, the points
    of one ``map_group`` moving together).
    ``linearised`` = (residual, J) at the pose when the caller has them already."""
    rvec, tvec = np.asarray(rvec, np.float64).reshape(3, 1), np.asarray(tvec, np.float64).reshape(3, 1)
    residual, J = linearised if linearised is not None else _linearise(K, dist, rvec, tvec, world, image,
                                                                       with_focal)
    JtJ = J.T @ J
    # SVD inverse; its return value is the inverse condition number, eig_min / eig_max.
    inverse_condition, inverse = cv2.invert(JtJ, flags=cv2.DECOMP_SVD)
    if not inverse_condition > 1e-12:
        raise PoseUndetermined("the geometry does not determine the pose (singular Jacobian)")
    squares = float(np.dot(residual.ravel(), residual.ravel()))
    dof = residual.size - JtJ.shape[0]
    if map_variance is not None and map_variance.any():
        group = np.arange(len(map_variance)) if map_group is None else map_group
        image_part, map_part = _map_covariance(inverse, J, map_variance, group)
        # The residuals hold the map's errors too (the part the pose does not absorb):
        # only what is left of them is the image noise.
        covariance = inverse * (max(squares - image_part, 0.0) / dof if dof > 0 else float("nan")) + map_part
    else:
        covariance = inverse * (squares / dof if dof > 0 else float("nan"))
    R, dR = cv2.Rodrigues(rvec)
    t = tvec.ravel()
    if pose is None:
        pose = Pose(R, t)
    jac = _position_jacobian(R, dR, t)
    return PoseEstimate(
        pose=pose,
        rms_px=float(np.sqrt(squares / len(residual))),
        n_targets=len(ids),
        n_points=len(world),
        covariance=covariance,
        covariance_position=jac @ covariance[:6, :6] @ jac.T,
        focal_px=float(K[0, 0]),
        target_ids=ids,
        rejected_ids=rejected,
        method=method,
    )


#: How a surveyed map's errors are taken to move its discs: each card's four discs
#: together (the card prior holds the printed square, so a card is off as a whole), or
#: each disc on its own. ``bench/bench_survey.py`` measures both against the truth.
CARD_RIGID_MAP_ERRORS = True


def _map_covariance(inverse: np.ndarray, J: np.ndarray, variance: np.ndarray,
                    group: np.ndarray) -> tuple[float, np.ndarray]:
    """What the map points' own errors do to a least-squares pose, to first order.

    A map point moved by ``dX`` moves its residual by ``J_t R dX`` (``J_t``: the
    Jacobian over the translation, since the point enters only through ``R X + t``);
    points of one group move by one ``dX``, isotropic of variance ``v`` per axis, so
    ``R`` drops out. The pose then moves by ``-(J^T J)^-1 J^T dr``. The map's errors
    are shared by every frame: a pose on a surveyed map is no more precise than its
    map, however well it fits; and a card that is off as a whole leaves no residual.

    Parameters
    ----------
    inverse : (p, p) ndarray
        ``(J^T J)^-1``.
    J : (2n, p) ndarray
        The residuals' Jacobian over (rvec, t[, f]).
    variance : (n,) ndarray
        Each point's map variance per axis, m^2.
    group : (n,) ndarray of int
        The points that move together share a group (0 .. groups - 1).

    Returns
    -------
    expected_squares : float
        The sum of squared residuals the map's errors leave on average (the part of
        them the pose does not absorb).
    covariance : (p, p) ndarray
        The covariance of the parameters the map's errors cause.
    """
    n, p = len(variance), len(inverse)
    groups = int(group.max()) + 1
    v = np.zeros(groups)
    np.maximum.at(v, group, variance)  # a group's points share one error: its largest variance
    Jt = J[:, 3:6].reshape(n, 2, 3)
    Jp = J.reshape(n, 2, p)
    moves = np.zeros((groups, p, 3))  # d params / d (the group's shift)
    np.add.at(moves, group, np.einsum("pq,nkq,nkj->npj", inverse, Jp, Jt))
    covariance = np.einsum("g,gpj,gqj->pq", v, moves, moves)
    # Residual moves per group shift: (I - J (J^T J)^-1 J^T) J_t over the group's rows.
    rows = np.zeros((groups, n, 2, 3))
    rows[group, np.arange(n)] = Jt
    after = rows - np.einsum("nkp,gpj->gnkj", Jp, moves)
    expected_squares = float(np.einsum("g,gnkj,gnkj->", v, after, after))
    return expected_squares, covariance


#: Points whose spread off their best-fit plane is below this fraction of their
#: extent are treated as (nearly) coplanar: both planar poses are tried as starts.
NEAR_PLANAR = 0.05

#: Gauss-Newton has converged when its last step moves no image point by more than
#: this (px): the step is then taken and the residuals updated to first order (the
#: neglected second-order terms are ~1e-7 px).
CONVERGED_PX = 0.01
GAUSS_NEWTON_ITERATIONS = 8
#: A further start is refined only if its cost is below this multiple of the best
#: optimum's cost (floored at FLOOR_PX per point): see `_fit_all`.
HOPELESS_START = 1e3
FLOOR_PX = 0.1
#: One target's two tilts are both candidates when the worse one's reprojection cost is
#: within this multiple of the better one's (floored at AMBIGUOUS_FLOOR_PX per point).
#: Four discs leave two degrees of freedom over the pose, so at the true tilt the cost
#: is noise alone and often larger than the wrong tilt's; beyond a tenfold cost the
#: worse tilt does not fit (bench/bench_motion.py counts the flips either way).
AMBIGUOUS_COST_RATIO = 10.0
AMBIGUOUS_FLOOR_PX = 0.3
#: ... and when their rotations are this far apart (rad, 2 degrees): a near-frontal card's
#: two optima lie closer, and which one is taken changes nothing a client would notice.
AMBIGUOUS_APART_RAD = np.radians(2.0)


class _Fit(NamedTuple):
    cost: float  # sum of squared reprojection errors, px^2
    rvec: np.ndarray  # (3, 1)
    tvec: np.ndarray  # (3, 1)
    linearised: tuple[np.ndarray, np.ndarray]  # residuals (N, 2) and Jacobian at the pose


def _refine(K: np.ndarray, dist: np.ndarray, world: np.ndarray, image: np.ndarray, rvec: np.ndarray,
            tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Minimise the reprojection error (paper eq. 5) from a start: Gauss-Newton with the
    analytic Jacobian of the full lens model (cv2.projectPoints).

    From SQPnP's start on a dozen discs one step converges (it moves the image by
    ~0.003 px and lands within 0.01 mm of the optimum, closer than OpenCV's LM with its
    float-epsilon stop). A start that is poor (no descent, or no convergence within a
    few steps) is left to OpenCV's damped LM. Returns the pose and the (residual,
    Jacobian) for the covariance, so no further projection is needed.
    """
    x = np.concatenate((rvec.ravel(), tvec.ravel()))  # (np.r_ costs 14 us)
    previous = np.inf
    for _ in range(GAUSS_NEWTON_ITERATIONS):
        residual, J = _linearise(K, dist, x[:3], x[3:], world, image, False)
        r = residual.ravel()
        cost = float(np.dot(r, r))
        if not cost <= previous:  # not a descent (or NaN)
            break
        ok, step = cv2.solve(J.T @ J, -(J.T @ r).reshape(-1, 1), flags=cv2.DECOMP_CHOLESKY)
        if not ok:
            break
        step = step.ravel()
        change = J @ step
        if float(np.abs(change).max()) < CONVERGED_PX:
            x += step
            return x[:3].reshape(3, 1), x[3:].reshape(3, 1), (residual + change.reshape(-1, 2), J)
        rvec, tvec = x[:3].reshape(3, 1), x[3:].reshape(3, 1)  # the best so far: LM goes on from here
        x = x + step
        previous = cost
    rvec, tvec = cv2.solvePnPRefineLM(world, image, K, dist, rvec.copy(), tvec.copy())
    return rvec, tvec, _linearise(K, dist, rvec, tvec, world, image, False)


def _fit_all(K: np.ndarray, dist: np.ndarray, world: np.ndarray, image: np.ndarray,
             spread: np.ndarray | None = None) -> list[_Fit]:
    """Every local optimum reached from the initial poses, best (lowest cost) first:
    a global initial pose (SQPnP), refined on the reprojection error (``_refine``).

    Coplanar points (one target, or targets on one wall) have two nearly equally good
    poses when seen small. SQPnP alone is not enough there: on points that are only
    nearly coplanar (a surveyed card: each disc is its own 3D point, a fraction of a
    millimetre off the plane) it can return the wrong tilt, a pose metres away that
    fits almost as well. So near-planar point sets also start from both planar poses
    (IPPE on the best-fit plane); every start is refined.
    """
    if spread is None:
        spread = cv2.SVDecomp(world - world.mean(axis=0), flags=cv2.SVD_NO_UV)[0].ravel()
    starts: list[tuple[np.ndarray, np.ndarray]] = []
    if spread[2] < NEAR_PLANAR * spread[0]:
        starts += [(cv2.Rodrigues(R)[0], t.reshape(3, 1)) for R, t in _planar_poses(world, image, K, dist)]
    if spread[2] >= 1e-4 * spread[0] or not starts:
        try:
            ok, rvec, tvec = cv2.solvePnP(world, image, K, dist, flags=cv2.SOLVEPNP_SQPNP)
        except cv2.error:
            ok = False
        if ok:
            starts.append((rvec, tvec))
    if len(starts) > 1:
        # Best start first; a start whose reprojection cost is orders of magnitude above
        # the best optimum found so far (the wrong tilt of points that span much of the
        # image) is not refined: its descent would cost a damped LM run, and it ends
        # in a poorer optimum or the same one. Ambiguous tilts start close in cost.
        costs = [float(np.square(cv2.projectPoints(world, r, t, K, dist)[0].reshape(-1, 2) - image).sum())
                 for r, t in starts]
        starts = [starts[k] for k in np.argsort(costs)]
        costs.sort()
    found: list[_Fit] = []
    for k, (rvec, tvec) in enumerate(starts):
        if found and costs[k] > HOPELESS_START * max(found[0].cost, len(world) * FLOOR_PX**2):
            break
        rvec, tvec, linearised = _refine(K, dist, world, image, rvec, tvec)
        # A pose with points behind the camera is no pose, however well it "fits".
        if float((world @ cv2.Rodrigues(rvec)[0][2]).min()) + tvec[2, 0] <= 0:
            continue
        residual = linearised[0].ravel()
        found.append(_Fit(float(np.dot(residual, residual)), rvec, tvec, linearised))
        found.sort(key=lambda fit: fit.cost)
    return found


def _fit(K: np.ndarray, dist: np.ndarray, world: np.ndarray, image: np.ndarray,
         spread: np.ndarray | None = None) -> _Fit:
    """The lowest-cost pose over the starts of ``_fit_all``."""
    found = _fit_all(K, dist, world, image, spread)
    if not found:
        raise PoseUndetermined("no initial pose found")
    return found[0]


# --- the methods ----------------------------------------------------------------------


def _choose_tilt(found: list[_Fit], n_points: int, prior: Pose | None) -> tuple[_Fit, bool, bool]:
    """One target's optimum (``found``: distinct, best first): (fit, ambiguous,
    tilt_from_track).

    When both tilts fit, the one nearer in rotation to ``prior`` (the track's
    prediction) is taken: a track does not turn by tens of degrees between frames, the
    wrong tilt does.
    """
    best = found[0]
    bound = AMBIGUOUS_COST_RATIO * max(best.cost, n_points * AMBIGUOUS_FLOOR_PX**2)
    R_best = cv2.Rodrigues(best.rvec)[0]
    apart = 1 + 2 * np.cos(AMBIGUOUS_APART_RAD)  # trace(R_a R_b^T) = 1 + 2 cos(angle)
    candidates = [best] + [fit for fit in found[1:]
                           if fit.cost <= bound and float(np.trace(cv2.Rodrigues(fit.rvec)[0] @ R_best.T)) < apart]
    if len(candidates) < 2:
        return best, False, False
    if prior is None:
        return best, True, False

    def turn(fit: _Fit) -> float:  # the rotation angle to the prior, via its cosine
        return -float(np.trace(cv2.Rodrigues(fit.rvec)[0] @ prior.R.T))

    chosen = min(candidates, key=turn)
    return chosen, True, chosen is not best


def nonlinear(
    observations: Sequence[TargetObservation],
    camera: Camera,
    estimate_focal: bool = False,
    outlier_px: float = 3.0,
    prior: Pose | None = None,
) -> PoseEstimate:
    """The paper's method: minimise reprojection error over every visible target.

    A target whose discs do not fit the others (misidentified, a wrong disc) is found by
    consensus over targets and dropped. The fast path (all fit) costs one SQPnP and one
    Gauss-Newton step, whose Jacobian also gives the covariance (~0.1 ms at 12 points).

    Parameters
    ----------
    observations : sequence of TargetObservation
        The identified targets with known map positions.
    camera : Camera
        Intrinsics and distortion of the image.
    estimate_focal : bool, optional
        Free the focal length too (zoom lenses; needs at least 2 targets).
    outlier_px : float, optional
        A target whose worst disc is off by more than this (pixels) is an outlier.
    prior : Pose, optional
        The pose expected (a track's prediction): with one target whose two tilts both
        fit, the tilt nearer to it is taken rather than the one with the lower error.

    Returns
    -------
    PoseEstimate

    Raises
    ------
    PoseUndetermined
        If the points do not determine a pose (fewer than 4, collinear, singular).
    """
    image, world, counts = _stack(observations)
    variance, group = _map_variance(observations), _map_groups(counts)
    spread = _check_determined(world)
    n = len(observations)
    if estimate_focal and n < 2:
        raise PoseUndetermined("estimating the focal length needs at least 2 targets")
    K, dist = camera.K, camera.dist
    ambiguous = from_track = False
    if n == 1:
        found = _distinct(_fit_all(K, dist, world, image, spread))
        if not found:
            raise PoseUndetermined("no initial pose found")
        (_, rvec, tvec, linearised), ambiguous, from_track = _choose_tilt(found, len(world), prior)
    else:
        _, rvec, tvec, linearised = _fit(K, dist, world, image, spread)
    inliers = np.ones(n, bool)
    residual = linearised[0]
    # Every point within outlier_px (the usual case) <=> every target's worst point is.
    if n >= 2 and float((residual * residual).sum(axis=1).max()) > outlier_px**2:
        owner = _owner(counts)
        if n >= 3:
            inliers = _consensus(camera, image, world, owner, n, outlier_px)
        keep = inliers[owner]
        _check_determined(world[keep])
        _, rvec, tvec, linearised = _fit(K, dist, world[keep], image[keep])
        residual = cv2.projectPoints(world, rvec, tvec, K, dist)[0].reshape(-1, 2) - image
        fits = _worst_per_target(residual, counts) <= outlier_px
        if fits.any() and not np.array_equal(fits, inliers):
            inliers = fits
            keep = inliers[owner]
            _check_determined(world[keep])
            _, rvec, tvec, linearised = _fit(K, dist, world[keep], image[keep])
        world, image = world[keep], image[keep]
        variance, group = (None, None) if variance is None else (variance[keep], group[keep])
    if estimate_focal:
        rvec, tvec, K, linearised = _refine_focal(K, dist, rvec, tvec, world, image)
    if inliers.all():
        ids, rejected = [o.id for o in observations], []
    else:
        ids = [o.id for o, k in zip(observations, inliers, strict=True) if k]
        rejected = [o.id for o, k in zip(observations, inliers, strict=True) if not k]
    estimate = _estimate(K, dist, rvec, tvec, world, image, estimate_focal, "nonlinear", ids, rejected, linearised,
                         map_variance=variance, map_group=group)
    return replace(estimate, ambiguous=ambiguous, tilt_from_track=from_track) if ambiguous else estimate


def _consensus(camera: Camera, image: np.ndarray, world: np.ndarray, owner: np.ndarray, n: int,
               outlier_px: float) -> np.ndarray:
    """RANSAC over targets: each target's own pose (IPPE) votes for the targets it
    explains; the largest consensus wins (exhaustive: there are few targets)."""
    best, best_score = np.ones(n, bool), -1.0
    normalised = _ideal(camera, image)
    for k in range(n):
        mine = owner == k
        # Both tilts of the target vote: the wrong one explains few others.
        for R, t in _planar_poses(world[mine], normalised[mine], np.eye(3), None):
            cam = world @ R.T + t
            if (cam[:, 2] <= 0).any():
                continue
            error = np.linalg.norm(camera.project(cam) - image, axis=1)
            worst = np.zeros(n)
            np.maximum.at(worst, owner, error)
            # A single target's pose is coarse far away: be generous, refine decides.
            agree = worst < 8 * outlier_px
            score = agree.sum() - 1e-3 * np.median(error)
            if score > best_score:
                best, best_score = agree, score
    return best if best.sum() >= 1 else np.ones(n, bool)


def single(observations: Sequence[TargetObservation], camera: Camera, prior: Pose | None = None) -> PoseEstimate:
    """Pose from the single target that is largest in the image, nonlinear on its discs.

    Parameters
    ----------
    observations : sequence of TargetObservation
        Identified targets; only the largest is used.
    camera : Camera
    prior : Pose, optional
        The pose expected: of two tilts that both fit, the nearer is taken.

    Returns
    -------
    PoseEstimate

    Raises
    ------
    PoseUndetermined
        If that target's discs do not determine a pose.
    """
    def area(o: TargetObservation) -> float:
        return float(cv2.contourArea(np.asarray(o.image, np.float32)))

    return _single(max(observations, key=area), camera, prior)


def _single(observation: TargetObservation, camera: Camera, prior: Pose | None = None) -> PoseEstimate:
    image, world, counts = _stack([observation])
    _check_determined(world)
    found = _optima(camera.K, camera.dist, world, image)
    if not found:
        raise PoseUndetermined("no initial pose found")
    (_, rvec, tvec, linearised), ambiguous, from_track = _choose_tilt(found, len(world), prior)
    estimate = _estimate(camera.K, camera.dist, rvec, tvec, world, image, False, "single", [observation.id], [],
                         linearised, map_variance=_map_variance([observation]), map_group=_map_groups(counts))
    return replace(estimate, ambiguous=ambiguous, tilt_from_track=from_track) if ambiguous else estimate


#: Two optima whose rotations differ by less than this (rad, ~0.1 deg) are one: on a
#: near-frontal card the cost is flat and starts stop a few hundredths of a degree apart.
SAME_OPTIMUM_RAD = 2e-3


def _optima(K: np.ndarray, dist: np.ndarray, world: np.ndarray, image: np.ndarray) -> list[_Fit]:
    """The distinct local optima reached from the starts of ``_fit_all``, best first."""
    return _distinct(_fit_all(K, dist, world, image))


def _distinct(found: list[_Fit]) -> list[_Fit]:
    """``found`` (best first) without the optima that repeat a better one."""
    distinct: list[tuple[_Fit, np.ndarray]] = []
    for fit in found:
        R = cv2.Rodrigues(fit.rvec)[0]
        # |R_a - R_b| entries are at most the angle between them (small angles)
        if all(np.abs(R - other).max() > SAME_OPTIMUM_RAD for _, other in distinct):
            distinct.append((fit, R))
    return [fit for fit, _ in distinct]


def target_poses(observation: TargetObservation, camera: Camera) -> list[Pose]:
    """The distinct local optima of one target's own reprojection error.

    For a small or far card these are its two tilts.

    Parameters
    ----------
    observation : TargetObservation
    camera : Camera

    Returns
    -------
    list of Pose
        Nonlinear fits on its discs, best fit first.

    Raises
    ------
    PoseUndetermined
        If its discs do not determine a pose.
    """
    image, world, _ = _stack([observation])
    _check_determined(world)
    return [Pose.from_rvec_tvec(f.rvec.ravel(), f.tvec.ravel()) for f in _optima(camera.K, camera.dist, world, image)]


def single_target_poses(observations: Sequence[TargetObservation], camera: Camera) -> list[Pose]:
    """Each target's own pose (nonlinear on its 4 discs), in the order given.

    A small card seen from afar has two poses that fit its own discs almost alike (the
    planar two-fold ambiguity: the card tilted one way or the other); its own residual
    picks the wrong one in a large share of frames (bench_pose: 1 in 6 at 3.3 m), a
    camera position up to metres off. A practitioner resolves this with the other
    targets in view: of each target's tilts the one that best explains the *other*
    targets' discs (median reprojection error) is taken. With one target, its own
    residual decides.

    Parameters
    ----------
    observations : sequence of TargetObservation
    camera : Camera

    Returns
    -------
    list of Pose
        One pose per observation, in the order given.

    Raises
    ------
    PoseUndetermined
        If a target's discs do not determine a pose.
    """
    image, world, counts = _stack(observations)
    owner = _owner(counts)
    K, dist = camera.K, camera.dist
    chosen = []
    for k, observation in enumerate(observations):
        mine = owner == k
        _check_determined(world[mine])
        found = _optima(K, dist, world[mine], image[mine])
        if not found:
            raise PoseUndetermined(f"target {observation.id}: no pose found")
        best = found[0]
        if len(observations) > 1 and len(found) > 1:
            others = ~mine

            def disagreement(candidate: _Fit) -> float:
                R = cv2.Rodrigues(candidate.rvec)[0]
                if float((world[others] @ R[2]).min()) + candidate.tvec[2, 0] <= 0:
                    return np.inf  # the others would be behind the camera
                projected = cv2.projectPoints(world[others], candidate.rvec, candidate.tvec, K, dist)[0]
                return float(np.median(np.linalg.norm(projected.reshape(-1, 2) - image[others], axis=1)))

            best = min(found, key=disagreement)
        chosen.append(Pose.from_rvec_tvec(best.rvec.ravel(), best.tvec.ravel()))
    return chosen


def mean(observations: Sequence[TargetObservation], camera: Camera) -> PoseEstimate:
    """Mean of the single-target poses ("mean of three positions", Table 1): each
    target's own pose with its tilt resolved by the others (``single_target_poses``),
    then the mean camera centre and the mean rotation (quaternion average). Better
    than one target, worse than all at once.

    Parameters
    ----------
    observations : sequence of TargetObservation
    camera : Camera

    Returns
    -------
    PoseEstimate
        Its residual and covariance are those of the mean pose on all the discs.

    Raises
    ------
    PoseUndetermined
        If a target's discs do not determine a pose.
    """
    poses = single_target_poses(observations, camera)
    position = np.mean([p.position for p in poses], axis=0)
    quaternions = np.array([_quaternion(p.R) for p in poses])
    # The average rotation is the dominant eigenvector of sum q q^T (sign-invariant).
    _, vectors = np.linalg.eigh(quaternions.T @ quaternions)
    R = _rotation(vectors[:, -1])
    pose = Pose(R, -R @ position)
    image, world, counts = _stack(observations)
    return _estimate(camera.K, camera.dist, pose.rvec, pose.t, world, image, False, "mean",
                     [o.id for o in observations], [], pose=pose, map_variance=_map_variance(observations),
                     map_group=_map_groups(counts))


def posit(observations: Sequence[TargetObservation], camera: Camera, iterations: int = 100) -> PoseEstimate:
    """DeMenthon & Davis's POSIT (scaled orthographic iterations).

    The coplanar variant (Oberkampf, DeMenthon & Davis) is used when all points lie in
    a plane, e.g. one target. Distortion is removed from the measurements first.

    Parameters
    ----------
    observations : sequence of TargetObservation
    camera : Camera
    iterations : int, optional
        Most POSIT iterations.

    Returns
    -------
    PoseEstimate

    Raises
    ------
    PoseUndetermined
        If the points do not determine a pose or none lies in front of the camera.
    """
    image, world, counts = _stack(observations)
    spread = _check_determined(world)
    normalised = _ideal(camera, image)
    coplanar = spread[2] < 1e-3 * spread[0]
    pose = _posit_coplanar(world, normalised, iterations) if coplanar else _posit(world, normalised, iterations)
    return _estimate(camera.K, camera.dist, pose.rvec, pose.t, world, image, False, "posit",
                     [o.id for o in observations], [], pose=pose, map_variance=_map_variance(observations),
                     map_group=_map_groups(counts))


def _posit(world: np.ndarray, x: np.ndarray, iterations: int) -> Pose:
    A = world[1:] - world[0]
    B = np.linalg.pinv(A)
    eps = np.zeros(len(A))
    for _ in range(iterations):
        xp = x[1:, 0] * (1 + eps) - x[0, 0]
        yp = x[1:, 1] * (1 + eps) - x[0, 1]
        I, J = B @ xp, B @ yp
        pose, z0, k = _posit_pose(I, J, x[0], world[0])
        new_eps = A @ k / z0
        if np.abs(new_eps - eps).max() < 1e-12:
            break
        eps = new_eps
    return pose


def _posit_pose(I: np.ndarray, J: np.ndarray, x0: np.ndarray, m0: np.ndarray) -> tuple[Pose, float, np.ndarray]:
    s = np.sqrt(np.linalg.norm(I) * np.linalg.norm(J))
    i, j = I / np.linalg.norm(I), J / np.linalg.norm(J)
    k = np.cross(i, j)
    k /= np.linalg.norm(k)
    j = np.cross(k, i)
    R = np.array([i, j, k])
    u, _, vt = np.linalg.svd(R)
    R = u @ vt
    z0 = 1.0 / s
    t = np.array([x0[0] * z0, x0[1] * z0, z0]) - R @ m0
    return Pose(R, t), z0, R[2]


def _posit_coplanar(world: np.ndarray, x: np.ndarray, iterations: int) -> Pose:
    A = world[1:] - world[0]
    _, _, vt = np.linalg.svd(A)
    u = vt[2]  # unit normal of the object plane
    B = np.linalg.pinv(A)
    best: tuple[float, Pose] | None = None
    for sign in (1.0, -1.0):  # the two branches of the coplanar solution
        eps = np.zeros(len(A))
        pose = None
        for _ in range(iterations):
            xp = x[1:, 0] * (1 + eps) - x[0, 0]
            yp = x[1:, 1] * (1 + eps) - x[0, 1]
            I0, J0 = B @ xp, B @ yp
            c, d = J0 @ J0 - I0 @ I0, -(I0 @ J0)
            rho = np.sqrt(np.sqrt(c * c + 4 * d * d))
            # lambda^2 - mu^2 = c and lambda mu = d: (lambda + i mu)^2 = c + 2 i d.
            theta = np.arctan2(2 * d, c) / 2
            lam, mu = rho * np.cos(theta), rho * np.sin(theta)
            candidates = []
            for s in (sign, -sign) if pose is not None else (sign,):
                I, J = I0 + s * lam * u, J0 + s * mu * u
                cand, z0, k = _posit_pose(I, J, x[0], world[0])
                cam = cand.transform(world)
                if (cam[:, 2] <= 0).any():
                    continue
                err = np.linalg.norm(cam[:, :2] / cam[:, 2:] - x, axis=1).sum()
                candidates.append((err, cand, z0, k))
            if not candidates:
                break
            _, pose, z0, k = min(candidates, key=lambda c: c[0])
            new_eps = A @ k / z0
            if np.abs(new_eps - eps).max() < 1e-12:
                break
            eps = new_eps
        if pose is not None:
            cam = pose.transform(world)
            err = float(np.linalg.norm(cam[:, :2] / cam[:, 2:] - x, axis=1).sum())
            if best is None or err < best[0]:
                best = (err, pose)
    if best is None:
        raise PoseUndetermined("POSIT found no pose in front of the camera")
    return best[1]


def _quaternion(R: np.ndarray) -> np.ndarray:
    rvec = cv2.Rodrigues(R)[0].ravel()
    angle = np.linalg.norm(rvec)
    axis = rvec / angle if angle > 0 else np.array([1.0, 0, 0])
    return np.r_[np.cos(angle / 2), np.sin(angle / 2) * axis]


def _rotation(q: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q)
    angle = 2 * np.arctan2(np.linalg.norm(q[1:]), q[0])
    axis = q[1:] / np.linalg.norm(q[1:]) if np.linalg.norm(q[1:]) > 0 else np.array([1.0, 0, 0])
    return cv2.Rodrigues(axis * angle)[0]


def estimate_pose(
    observations: Sequence[TargetObservation],
    camera: Camera,
    method: str = "nonlinear",
    estimate_focal: bool = False,
    prior: Pose | None = None,
) -> PoseEstimate:
    """The camera pose from the identified targets in one image (paper §5.2-5.3).

    Parameters
    ----------
    observations : sequence of TargetObservation
        Identified targets whose discs' map positions are known.
    camera : Camera
        Intrinsics and distortion of the image.
    method : {"nonlinear", "posit", "mean", "single"}, optional
        "nonlinear" is the paper's method; the others are for comparison (Table 1).
    estimate_focal : bool, optional
        Free the focal length too ("nonlinear" only, at least 2 targets).
    prior : Pose, optional
        The pose a track expects ("nonlinear" and "single"): a lone target's two tilts,
        when both fit, are decided by it rather than by the lower error.

    Returns
    -------
    PoseEstimate
        Its pose is map to camera, ``x_cam = R @ X_map + t``, in metres.

    Raises
    ------
    PoseUndetermined
        If there are no observations or they do not determine a pose.
    ValueError
        If `method` is unknown.
    """
    if not observations:
        raise PoseUndetermined("no identified target with a known map position")
    if method not in METHODS:
        raise ValueError(f"unknown pose method {method!r}; known: {', '.join(METHODS)}")
    if estimate_focal and method != "nonlinear":
        raise PoseUndetermined(f"focal estimation needs the nonlinear method, not {method!r}")
    estimator = {"nonlinear": partial(nonlinear, estimate_focal=estimate_focal, prior=prior), "posit": posit,
                 "mean": mean, "single": partial(single, prior=prior)}[method]
    try:
        return estimator(observations, camera)
    except (np.linalg.LinAlgError, cv2.error) as exc:
        # A camera or map at the edge of what is representable (a focal length of a
        # thousandth of a pixel, discs a thousand kilometres away) can make the linear
        # algebra fail: no pose, said as such, rather than a server error.
        raise PoseUndetermined(f"the {method} pose computation failed numerically ({exc.__class__.__name__})") from None


def cramer_rao_position_rms(camera: Camera, pose: Pose, world: np.ndarray, sigma_px: float) -> float:
    """Lower bound on the RMS camera-position error of any unbiased estimator.

    Parameters
    ----------
    camera : Camera
    pose : Pose
        The true pose, map to camera.
    world : (N, 3) ndarray
        The observed points in map coordinates, metres.
    sigma_px : float
        Standard deviation of isotropic Gaussian noise on every image point, pixels.

    Returns
    -------
    float
        The Cramer-Rao bound on the RMS camera-centre error, metres.
    """
    _, J = _linearise(camera.K, camera.dist, pose.rvec, pose.t, world, np.zeros((len(world), 2)), False)
    covariance = np.linalg.inv(J.T @ J) * sigma_px**2
    return float(np.sqrt(np.trace(position_covariance(pose, covariance))))
