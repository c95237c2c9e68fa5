"""The printed card in views: its disc pairs, its planar poses, triangulation of its
discs, and the rigid card fitted to views whose poses are held."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from app.core.geometry import Camera, Pose
from app.core.markers import DISC_CENTRES
from app.core.survey.state import FIELD_MARGIN

#: Disc pairs of a card and their distance in card units (4 sides, 2 diagonals).
PAIRS = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [0, 2], [1, 3]])
PAIR_UNITS = np.linalg.norm(DISC_CENTRES[PAIRS[:, 0]] - DISC_CENTRES[PAIRS[:, 1]], axis=1)


def normalised(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """Normalised image coordinates (undistorted, on the plane z = 1) of pixels.

    Parameters
    ----------
    camera : Camera
        The camera.
    uv : (N, 2) ndarray
        Pixels.

    Returns
    -------
    (N, 2) ndarray
        ``(x / z, y / z)`` of the rays through them.
    """
    ideal = camera.undistort_pixels(uv)
    return np.c_[(ideal[:, 0] - camera.cx) / camera.fx, (ideal[:, 1] - camera.cy) / camera.fy]


def project_norm(pose: Pose, X: np.ndarray) -> np.ndarray:
    """Where map points appear in a view, in normalised image coordinates.

    Parameters
    ----------
    pose : Pose
        The view's pose (map to camera).
    X : (N, 3) ndarray
        Points in the map.

    Returns
    -------
    (N, 2) ndarray
        ``(x / z, y / z)`` of the points in the camera's frame.
    """
    c = pose.transform(X)
    return c[:, :2] / c[:, 2:]


def planar_poses(camera: Camera, uv: np.ndarray, model: np.ndarray) -> list[Pose]:
    """Both card-to-camera poses of one card (IPPE), best reprojection first.

    A small card seen with noise cannot tell its two tilts apart: the caller decides.

    Parameters
    ----------
    camera : Camera
        The camera.
    uv : (4, 2) ndarray
        The card's disc centres in the image.
    model : (4, 3) ndarray
        The card's disc centres in its own frame (z = 0).

    Returns
    -------
    list of Pose
        The poses with the card in front of the camera (up to 2).
    """
    x = normalised(camera, uv)
    try:
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(model, x, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        return []
    order = np.argsort(np.asarray(errs).ravel()) if errs is not None and len(errs) == n else range(n)
    poses = [Pose.from_rvec_tvec(rvecs[k], tvecs[k]) for k in order]
    return [p for p in poses if p.t[2] > 0]


def triangulate(poses: Sequence[Pose], x: np.ndarray) -> np.ndarray:
    """One point from its views, by the DLT.

    Parameters
    ----------
    poses : sequence of Pose
        The views' poses (map to camera).
    x : (V, 2) ndarray
        The point in each view, normalised coordinates.

    Returns
    -------
    (3,) ndarray
        The point; nan when it lies at infinity.
    """
    rows = []
    for pose, (u, v) in zip(poses, x, strict=True):
        P = np.c_[pose.R, pose.t]
        rows.append(u * P[2] - P[0])
        rows.append(v * P[2] - P[1])
    _, _, vt = np.linalg.svd(np.array(rows))
    X = vt[-1]
    return X[:3] / X[3] if abs(X[3]) > 1e-12 else np.full(3, np.nan)


def max_angle_deg(centres: np.ndarray, point: np.ndarray) -> float:
    """The baseline of a point's views: the widest angle between two of its rays.

    Parameters
    ----------
    centres : (V, 3) ndarray
        The cameras' centres.
    point : (3,) ndarray
        The point.

    Returns
    -------
    float
        The widest angle at ``point`` between the rays to two camera centres, degrees.
    """
    d = centres - point
    d /= np.linalg.norm(d, axis=1, keepdims=True) + 1e-300
    if len(d) > 400:  # O(V^2): the extremes of a long track are found on a subsample
        d = d[np.linspace(0, len(d) - 1, 400).astype(int)]
    cos = np.clip(d @ d.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos.min())))


def view_error(camera: Camera, pose: Pose, X: np.ndarray, uv: np.ndarray) -> float:
    """How well a card's discs fit one view of it.

    Parameters
    ----------
    camera : Camera
        The camera.
    pose : Pose
        The view's pose.
    X : (4, 3) ndarray
        The card's discs in the map.
    uv : (4, 2) ndarray
        The discs in the view, px.

    Returns
    -------
    float
        The worst reprojection error (px, per axis); inf when a disc lies behind the
        camera or outside its field (``Camera.in_field``).
    """
    cam = pose.transform(X)
    if not camera.in_field(cam, FIELD_MARGIN).all():
        return np.inf
    return float(np.abs(camera.project_map(X, pose) - uv).max())


def _card_fit_residuals(camera: Camera, poses: Sequence[Pose], uvs: Sequence[np.ndarray], model: np.ndarray,
                        R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (8V,) of a rigid card (card to map: R, t) in its views, and their
    Jacobian (8V, 6) over a rotation applied on the left and the translation."""
    X = model @ R.T + t
    r = np.empty((len(poses), 8))
    J = np.empty((len(poses), 8, 6))
    for k, (pose, uv) in enumerate(zip(poses, uvs, strict=True)):
        proj, j = cv2.projectPoints(X, pose.rvec, pose.t, camera.K, camera.dist)
        r[k] = (proj.reshape(4, 2) - uv).ravel()
        dX = (j[:, 3:6] @ pose.R).reshape(4, 2, 3)  # d uv / d X
        a = X - t  # R @ model: a small rotation moves a point by w x a = -[a]x w
        skew = np.zeros((4, 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -a[:, 2], a[:, 1], -a[:, 0]
        skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = a[:, 2], -a[:, 1], a[:, 0]
        J[k, :, :3] = -(dX @ skew).reshape(8, 3)
        J[k, :, 3:] = dX.reshape(8, 3)
    return r.ravel(), J.reshape(-1, 6)


def fit_card(camera: Camera, poses: Sequence[Pose], uvs: Sequence[np.ndarray], model: np.ndarray,
             card: Pose, iterations: int = 8) -> tuple[Pose, float]:
    """The rigid printed card that best fits its views from cameras whose poses are held.

    A card seen over a narrow baseline is placed from its planar pose in one view, where
    its two tilts fit alike; the views together tell them apart, but only once each
    tilt is fitted to all of them (unrefined, both agree with every view to a few
    pixels). A wrong tilt, once in the map, is a minimum the bundle does not leave.
    Gauss-Newton (Levenberg-Marquardt damped) with an analytic Jacobian.

    Parameters
    ----------
    camera : Camera
        The camera.
    poses : sequence of Pose
        The views' poses (held).
    uvs : sequence of (4, 2) ndarray
        The card's discs in each view, px.
    model : (4, 3) ndarray
        The card's discs in its own frame, metres.
    card : Pose
        The start: the card's pose (card to map).
    iterations : int
        At most this many steps.

    Returns
    -------
    card : Pose
        The fitted card's pose (card to map).
    cost : float
        The sum of squared reprojection errors there, px^2.
    """
    R, t = card.R.copy(), card.t.copy()
    r, J = _card_fit_residuals(camera, poses, uvs, model, R, t)
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(iterations):
        H = J.T @ J
        step = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), J.T @ r)
        dR, _ = cv2.Rodrigues(step[:3])
        new_R, new_t = dR @ R, t + step[3:]
        new_r, new_J = _card_fit_residuals(camera, poses, uvs, model, new_R, new_t)
        new_cost = float(new_r @ new_r)
        if not new_cost < cost:
            lam *= 10
            continue
        done = cost - new_cost < 1e-6 * cost
        R, t, r, J, cost = new_R, new_t, new_r, new_J, new_cost
        lam = max(lam / 10, 1e-9)
        if done:
            break
    return Pose(R, t), cost


def triangulate_robust(poses: Sequence[Pose], x: np.ndarray, tol: float, rng: np.random.Generator
                       ) -> tuple[np.ndarray, np.ndarray] | None:
    """A card's 4 discs from its views, robust to views that belong to another card (a
    misidentified target moves all its 4 discs).

    Consensus over pairs of views (all pairs when few, a sample of 40 when many): each
    pair triangulates the card, the views it explains to within ``tol`` (worst disc)
    vote; the largest consensus (then the smallest error) is triangulated again from
    all its views.

    Parameters
    ----------
    poses : sequence of Pose
        The V >= 2 views' poses.
    x : (V, 4, 2) ndarray
        The card's discs in each view, normalised coordinates.
    tol : float
        How far (normalised units) a view may be off and still vote.
    rng : numpy.random.Generator
        Draws the sample of pairs.

    Returns
    -------
    X : (4, 3) ndarray
        The discs.
    inliers : (V,) ndarray of bool
        The views that agree with them.

    None when no two views agree.
    """
    V = len(poses)
    pairs = [(i, j) for i in range(V) for j in range(i + 1, V)]
    if len(pairs) > 40:
        pick = rng.choice(len(pairs), 40, replace=False)
        pairs = [pairs[k] for k in pick]
    best: tuple[int, float, np.ndarray] | None = None
    for i, j in pairs:
        X = np.array([triangulate([poses[i], poses[j]], x[[i, j], d]) for d in range(4)])
        if not np.isfinite(X).all():
            continue
        err = np.array([np.abs(project_norm(p, X) - x[k]).max() if (p.transform(X)[:, 2] > 0).all() else np.inf
                        for k, p in enumerate(poses)])
        inl = err < tol
        if inl[i] and inl[j]:
            key = (int(inl.sum()), -float(err[inl].mean()))
            if best is None or key > (best[0], best[1]):
                best = (key[0], key[1], inl)
        if best is not None and best[0] == V:
            break
    if best is None:
        return None
    inl = best[2]
    idx = np.flatnonzero(inl)
    X = np.array([triangulate([poses[k] for k in idx], x[idx, d]) for d in range(4)])
    if not np.isfinite(X).all():
        return None
    return X, inl
