"""Camera pose from the disc centres of every identified target (paper §5.2-5.3).

``nonlinear`` (default): a robust initial pose (SQPnP on all points, with RANSAC over
targets so a misidentified target cannot drag it), then Levenberg-Marquardt on the
reprojection error with the full lens model, optionally with the focal length free
(zoom lenses, §5.3). The covariance comes from the Jacobian at the optimum with the
noise level estimated from the residuals; a pose that is not determined (too few points,
degenerate geometry) is refused rather than reported.

``posit``, ``mean`` and ``single`` are kept for comparison, as in the paper's Table 1.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from app.core.camera import Camera, Pose

METHODS = ("nonlinear", "posit", "mean", "single")


class PoseUndetermined(ValueError):
    """The observations do not determine a pose (say why)."""


@dataclass(frozen=True)
class TargetObservation:
    """One identified target: its 4 disc centres in the image and in the map."""

    id: int
    image: np.ndarray  # (4, 2) pixels
    map: np.ndarray  # (4, 3) metres


@dataclass(frozen=True, eq=False)
class PoseEstimate:
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

    def to_dict(self) -> dict[str, object]:
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
        }


# --- building blocks ------------------------------------------------------------------


def _stack(observations: Sequence[TargetObservation]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    image = np.concatenate([np.asarray(o.image, np.float64).reshape(-1, 2) for o in observations])
    world = np.concatenate([np.asarray(o.map, np.float64).reshape(-1, 3) for o in observations])
    owner = np.concatenate([np.full(len(np.asarray(o.image).reshape(-1, 2)), k) for k, o in enumerate(observations)])
    return image, world, owner


def _check_determined(world: np.ndarray) -> np.ndarray:
    """Refuse undetermined point sets; return the singular values of their spread."""
    if len(world) < 4:
        raise PoseUndetermined(f"{len(world)} points: at least 4 (one whole target) are needed")
    if not np.isfinite(world).all():
        raise PoseUndetermined("map points must be finite")
    spread = np.linalg.svd(world - world.mean(axis=0), compute_uv=False)
    if spread[1] < 1e-6 * max(spread[0], 1e-12):
        raise PoseUndetermined("the points are collinear (or coincide): the pose is not determined")
    return spread


def _ideal(camera: Camera, image: np.ndarray) -> np.ndarray:
    """Normalised pinhole coordinates of pixel measurements (distortion removed)."""
    ideal = camera.undistort_pixels(image)
    k_inv = np.linalg.inv(camera.K)
    return np.ascontiguousarray((np.c_[ideal, np.ones(len(ideal))] @ k_inv.T)[:, :2])


def residuals(camera: Camera, pose: Pose, world: np.ndarray, image: np.ndarray) -> np.ndarray:
    """Reprojection residuals (N, 2) in pixels."""
    return camera.project(pose.transform(world)) - image


def _sqpnp(world: np.ndarray, normalised: np.ndarray) -> Pose:
    ok, rvec, tvec = cv2.solvePnP(world, normalised, np.eye(3), None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        raise PoseUndetermined("no initial pose found")
    return Pose.from_rvec_tvec(rvec.ravel(), tvec.ravel())


def _planar_poses(world: np.ndarray, image: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> list[Pose]:
    """Both poses (IPPE) of points that lie close to a plane, in the points' own frame.

    IPPE wants exactly coplanar points; surveyed discs are a little off their card's
    plane (each disc is its own 3D point), so the points are projected onto their
    best-fit plane first and the poses taken back to the map frame. The two are the
    two tilts a small or far planar target cannot tell apart; the caller refines both.
    """
    centre = world.mean(axis=0)
    _, _, Vt = np.linalg.svd(world - centre)
    if np.linalg.det(Vt) < 0:
        Vt[2] *= -1
    planar = np.c_[((world - centre) @ Vt.T)[:, :2], np.zeros(len(world))]
    try:
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(planar, image, K, dist, flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        return []
    poses = []
    for rvec, tvec in zip(rvecs, tvecs, strict=False):
        plane_pose = Pose.from_rvec_tvec(rvec.ravel(), tvec.ravel())
        R = plane_pose.R @ Vt
        poses.append(Pose(R, plane_pose.t - R @ centre))
    return poses


def _camera_with_focal(camera: Camera, focal: float) -> Camera:
    K = camera.K.copy()
    aspect = K[1, 1] / K[0, 0]
    K[0, 0], K[1, 1] = focal, focal * aspect
    return Camera(K, camera.dist, camera.width, camera.height)


def refine_with_focal(camera: Camera, pose: Pose, world: np.ndarray, image: np.ndarray,
                      iterations: int = 30) -> tuple[Pose, float]:
    """Levenberg-Marquardt on the reprojection error over (rvec, t, f), the aspect
    ratio, principal point and distortion fixed (the paper's zoom lens, §5.3)."""
    rvec, tvec, focal = pose.rvec.copy(), pose.t.copy(), float(camera.K[0, 0])

    def evaluate(r: np.ndarray, t: np.ndarray, f: float) -> tuple[np.ndarray, np.ndarray]:
        return _jacobian(_camera_with_focal(camera, f), Pose.from_rvec_tvec(r, t), world, image, True)

    residual, J = evaluate(rvec, tvec, focal)
    cost, lam = float((residual**2).sum()), 1e-3
    for _ in range(iterations):
        JtJ, gradient = J.T @ J, J.T @ residual.ravel()
        for _ in range(10):
            step = np.linalg.solve(JtJ + lam * np.diag(np.diag(JtJ) + 1e-12), -gradient)
            r_new, t_new, f_new = rvec + step[:3], tvec + step[3:6], focal + step[6]
            res_new, J_new = evaluate(r_new, t_new, f_new)
            cost_new = float((res_new**2).sum())
            if cost_new < cost:
                break
            lam *= 10
        else:
            break  # no step lowers the cost: at the minimum
        done = cost - cost_new < 1e-12 * max(cost, 1e-12)
        rvec, tvec, focal, residual, J, cost = r_new, t_new, f_new, res_new, J_new, cost_new
        lam = max(lam / 10, 1e-9)
        if done:
            break
    return Pose.from_rvec_tvec(rvec, tvec), focal


def position_covariance(pose: Pose, covariance: np.ndarray) -> np.ndarray:
    """Covariance of the camera centre c = -R^T t from that of (rvec, t), to first order."""
    R, dR = cv2.Rodrigues(pose.rvec)  # dR: (3, 9), d vec(R) / d rvec, row-major R
    t = pose.t
    jac = np.empty((3, 6))
    for k in range(3):
        jac[:, k] = -dR[k].reshape(3, 3).T @ t
    jac[:, 3:] = -R.T
    return jac @ covariance[:6, :6] @ jac.T


def _jacobian(camera: Camera, pose: Pose, world: np.ndarray, image: np.ndarray,
              with_focal: bool) -> tuple[np.ndarray, np.ndarray]:
    projected, jac = cv2.projectPoints(world, pose.rvec, pose.t, camera.K, camera.dist)
    J = jac[:, :6]
    if with_focal:
        aspect = camera.K[1, 1] / camera.K[0, 0]
        J = np.c_[J, jac[:, 6] + aspect * jac[:, 7]]
    return projected.reshape(-1, 2) - image, J


def _estimate(camera: Camera, pose: Pose, world: np.ndarray, image: np.ndarray, with_focal: bool,
              method: str, ids: list[int], rejected: list[int],
              linearised: tuple[np.ndarray, np.ndarray] | None = None) -> PoseEstimate:
    """Package a pose with its residual RMS and covariance (noise from the residuals).
    ``linearised`` = (residual, J) at ``pose`` when the caller has them already."""
    residual, J = linearised if linearised is not None else _jacobian(camera, pose, world, image, with_focal)
    JtJ = J.T @ J
    dof = residual.size - JtJ.shape[0]
    sigma2 = float((residual**2).sum() / dof) if dof > 0 else float("nan")
    eigen = np.linalg.eigvalsh(JtJ)
    if eigen[0] <= 1e-12 * eigen[-1]:
        raise PoseUndetermined("the geometry does not determine the pose (singular Jacobian)")
    covariance = np.linalg.inv(JtJ) * sigma2
    return PoseEstimate(
        pose=pose,
        rms_px=float(np.sqrt((residual**2).sum(axis=1).mean())),
        n_targets=len(ids),
        n_points=len(world),
        covariance=covariance,
        covariance_position=position_covariance(pose, covariance),
        focal_px=float(camera.K[0, 0]),
        target_ids=ids,
        rejected_ids=rejected,
        method=method,
    )


#: Points whose spread off their best-fit plane is below this fraction of their
#: extent are treated as (nearly) coplanar: both planar poses are tried as starts.
NEAR_PLANAR = 0.05


def _fit(camera: Camera, world: np.ndarray, image: np.ndarray, spread: np.ndarray | None = None) -> Pose:
    """A global initial pose, then OpenCV's LM with the full lens model.

    Coplanar points (one target, or targets on one wall) have two nearly equally good
    poses when seen small. SQPnP alone is not enough there: on points that are only
    nearly coplanar (a surveyed card: each disc is its own 3D point, a fraction of a
    millimetre off the plane) it can return the wrong tilt, a pose metres away that
    fits almost as well. So near-planar point sets also start from both planar poses
    (IPPE on the best-fit plane); every start is refined and the lowest cost wins.
    """
    if spread is None:
        spread = np.linalg.svd(world - world.mean(axis=0), compute_uv=False)
    starts: list[tuple[np.ndarray, np.ndarray]] = []
    if spread[2] < NEAR_PLANAR * spread[0]:
        starts += [(p.rvec.reshape(3, 1), p.t.reshape(3, 1)) for p in _planar_poses(world, image, camera.K, camera.dist)]
    if spread[2] >= 1e-4 * spread[0] or not starts:
        try:
            ok, rvec, tvec = cv2.solvePnP(world, image, camera.K, camera.dist, flags=cv2.SOLVEPNP_SQPNP)
        except cv2.error:
            ok = False
        if ok:
            starts.append((rvec, tvec))
    best: tuple[float, np.ndarray, np.ndarray] | None = None
    for rvec, tvec in starts:
        rvec, tvec = cv2.solvePnPRefineLM(world, image, camera.K, camera.dist, rvec.copy(), tvec.copy())
        # A pose with points behind the camera is no pose, however well it "fits".
        R, _ = cv2.Rodrigues(rvec)
        if ((world @ R[2]) + tvec.ravel()[2] <= 0).any():
            continue
        if len(starts) == 1:  # nothing to compare with: skip the cost
            best = (0.0, rvec, tvec)
            break
        projected, _ = cv2.projectPoints(world, rvec, tvec, camera.K, camera.dist)
        cost = float(((projected.reshape(-1, 2) - image) ** 2).sum())
        if best is None or cost < best[0]:
            best = (cost, rvec, tvec)
    if best is None:
        raise PoseUndetermined("no initial pose found")
    return Pose.from_rvec_tvec(best[1].ravel(), best[2].ravel())


def _worst_per_target(camera: Camera, pose: Pose, world: np.ndarray, image: np.ndarray, owner: np.ndarray,
                      n: int) -> np.ndarray:
    error = np.linalg.norm(camera.project(pose.transform(world)) - image, axis=1)
    worst = np.zeros(n)
    np.maximum.at(worst, owner, error)
    return worst


# --- the methods ----------------------------------------------------------------------


def nonlinear(
    observations: Sequence[TargetObservation],
    camera: Camera,
    estimate_focal: bool = False,
    outlier_px: float = 3.0,
) -> PoseEstimate:
    """The paper's method: minimise reprojection error over every visible target.

    A target whose discs do not fit the others (misidentified, a wrong disc) is found by
    consensus over targets and dropped; the fast path (all fit) costs one SQPnP and one
    LM.
    """
    image, world, owner = _stack(observations)
    spread = _check_determined(world)
    if estimate_focal and len(observations) < 2:
        raise PoseUndetermined("estimating the focal length needs at least 2 targets")
    n = len(observations)
    inliers = np.ones(n, bool)
    pose = _fit(camera, world, image, spread)
    linearised = _jacobian(camera, pose, world, image, False)
    worst = np.zeros(n)
    np.maximum.at(worst, owner, np.linalg.norm(linearised[0], axis=1))
    if n >= 2 and worst.max() > outlier_px:
        linearised = None
        if n >= 3:
            inliers = _consensus(observations, camera, image, world, owner, outlier_px)
        keep = inliers[owner]
        pose = _fit(camera, world[keep], image[keep])
        worst = _worst_per_target(camera, pose, world, image, owner, n)
        fits = worst <= outlier_px
        if fits.any() and not np.array_equal(fits, inliers):
            inliers = fits
            keep = inliers[owner]
            pose = _fit(camera, world[keep], image[keep])
    if not inliers.all():
        keep = inliers[owner]
        world, image = world[keep], image[keep]
        _check_determined(world)
    if estimate_focal:
        pose, focal = refine_with_focal(camera, pose, world, image)
        camera = _camera_with_focal(camera, focal)
        linearised = None
    ids = [o.id for o, k in zip(observations, inliers, strict=True) if k]
    rejected = [o.id for o, k in zip(observations, inliers, strict=True) if not k]
    return _estimate(camera, pose, world, image, estimate_focal, "nonlinear", ids, rejected, linearised)


def _consensus(observations: Sequence[TargetObservation], camera: Camera, image: np.ndarray, world: np.ndarray,
               owner: np.ndarray, outlier_px: float) -> np.ndarray:
    """RANSAC over targets: each target's own pose (IPPE) votes for the targets it
    explains; the largest consensus wins (exhaustive: there are few targets)."""
    best, best_score = np.ones(len(observations), bool), -1.0
    normalised = _ideal(camera, image)
    for k in range(len(observations)):
        mine = owner == k
        # Both tilts of the target vote: the wrong one explains few others.
        for pose in _planar_poses(world[mine], normalised[mine], np.eye(3), None):
            cam = pose.transform(world)
            if (cam[:, 2] <= 0).any():
                continue
            error = np.linalg.norm(camera.project(cam) - image, axis=1)
            worst = np.zeros(len(observations))
            np.maximum.at(worst, owner, error)
            # A single target's pose is coarse far away: be generous, refine decides.
            agree = worst < 8 * outlier_px
            score = agree.sum() - 1e-3 * np.median(error)
            if score > best_score:
                best, best_score = agree, score
    return best if best.sum() >= 1 else np.ones(len(observations), bool)


def single(observations: Sequence[TargetObservation], camera: Camera) -> PoseEstimate:
    """The best single target (largest in the image), nonlinear on its 4 discs."""
    def area(o: TargetObservation) -> float:
        return float(cv2.contourArea(np.asarray(o.image, np.float32)))

    return _single(max(observations, key=area), camera)


def _single(observation: TargetObservation, camera: Camera) -> PoseEstimate:
    image, world, _ = _stack([observation])
    _check_determined(world)
    return _estimate(camera, _fit(camera, world, image), world, image, False, "single", [observation.id], [])


def mean(observations: Sequence[TargetObservation], camera: Camera) -> PoseEstimate:
    """Mean of the single-target poses: mean camera centre, mean rotation (quaternion
    average). Table 1 of the paper: better than one target, worse than all at once."""
    poses = [_single(o, camera).pose for o in observations]
    position = np.mean([p.position for p in poses], axis=0)
    quaternions = np.array([_quaternion(p.R) for p in poses])
    # The average rotation is the dominant eigenvector of sum q q^T (sign-invariant).
    _, vectors = np.linalg.eigh(quaternions.T @ quaternions)
    R = _rotation(vectors[:, -1])
    pose = Pose(R, -R @ position)
    image, world, _ = _stack(observations)
    return _estimate(camera, pose, world, image, False, "mean", [o.id for o in observations], [])


def posit(observations: Sequence[TargetObservation], camera: Camera, iterations: int = 100) -> PoseEstimate:
    """DeMenthon & Davis's POSIT (scaled orthographic iterations); the coplanar variant
    (Oberkampf, DeMenthon & Davis) when all points lie in a plane, e.g. one target."""
    image, world, _ = _stack(observations)
    _check_determined(world)
    normalised = _ideal(camera, image)
    spread = np.linalg.svd(world - world.mean(axis=0), compute_uv=False)
    coplanar = spread[2] < 1e-3 * spread[0]
    pose = _posit_coplanar(world, normalised, iterations) if coplanar else _posit(world, normalised, iterations)
    return _estimate(camera, pose, world, image, False, "posit", [o.id for o in observations], [])


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
) -> PoseEstimate:
    """Pose by the named method; raises ``PoseUndetermined`` when there is none."""
    if not observations:
        raise PoseUndetermined("no identified target with a known map position")
    if method == "nonlinear":
        return nonlinear(observations, camera, estimate_focal)
    if estimate_focal:
        raise PoseUndetermined(f"focal estimation needs the nonlinear method, not {method!r}")
    if method == "posit":
        return posit(observations, camera)
    if method == "mean":
        return mean(observations, camera)
    if method == "single":
        return single(observations, camera)
    raise ValueError(f"unknown pose method {method!r}; known: {', '.join(METHODS)}")


def cramer_rao_position_rms(camera: Camera, pose: Pose, world: np.ndarray, sigma_px: float) -> float:
    """Lower bound on the RMS camera-position error of any unbiased estimator, for
    isotropic Gaussian noise of ``sigma_px`` on every image point."""
    _, J = _jacobian(camera, pose, world, camera.project(pose.transform(world)), False)
    JtJ = J.T @ J
    covariance = np.linalg.inv(JtJ) * sigma_px**2
    return float(np.sqrt(np.trace(position_covariance(pose, covariance))))
