"""Bundle adjustment: the lens, every pose and every disc at once (survey steps 3-4).

Robust sparse Levenberg-Marquardt with the cameras eliminated (Schur complement). A
survey has few points (4 per target) and many cameras, and with only 1-2 targets per
frame it is badly conditioned (cards are small, the chain of frames is hinged about the
line between two targets). A trust-region solver with a sparse Jacobian and inexact
(LSMR) steps, such as SciPy's, stalls there far from the optimum (0.008 px RMS left on
noise-free data, discs 0.3 m off). Eliminating the cameras instead (each a 6x6 block,
independent given the points) leaves a small dense system over intrinsics + points that
is solved exactly every iteration.

Each observation is weighted by its precision (`disc_precision`: thin discs are measured
worse) and by Huber's loss of its whitened error (error / expected error; IRLS).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from app.core.geometry import Camera
from app.core.survey.cards import PAIR_UNITS, PAIRS
from app.core.survey.state import Reconstruction, Tracks, project_frame

#: Huber's threshold (whitened) while the map grows: loose, since residuals of pixels are
#: then the unrefined lens's and poses' error, not outliers.
GROWTH_LOSS_SCALE = 100.0


@dataclass(frozen=True, eq=False)
class BundleInfo:
    """What a bundle adjustment did, and the quantities at its end."""

    iterations: int
    cost: float  # robust cost (half the sum of Huber's loss of the whitened errors, plus the prior's)
    rms_px: float  # reprojection RMS (2D) over the observations used
    obs: np.ndarray  # (N,) the observations used (indices into the tracks)
    points: np.ndarray  # (P,) the points adjusted (indices into Reconstruction.X)
    n_intr: int  # intrinsics adjusted: 5 (f, cx, cy, k1, k2) or 0
    residuals: np.ndarray  # (N, 2) px
    weights: np.ndarray  # (N,) IRLS weights (precision times Huber's weight)
    covariance: np.ndarray | None  # marginal covariance of [intrinsics, points] when asked for
    held_frame: int  # the frame whose pose is held (the gauge)

    def disc_std(self, n_points: int) -> np.ndarray:
        """RMS 3D standard deviation of every disc, from the marginal covariance.

        Parameters
        ----------
        n_points : int
            The number of points in the reconstruction.

        Returns
        -------
        (n_points,) ndarray
            sqrt of each point's covariance trace (the cameras' uncertainty included);
            nan for points not adjusted, or all when no covariance was computed.
        """
        std = np.full(n_points, np.nan)
        C = self.covariance
        if C is None:
            return std
        diag = np.clip(np.diag(C)[self.n_intr :], 0.0, None).reshape(-1, 3)
        std[self.points] = np.sqrt(diag.sum(axis=1))
        return std


def camera_from_intrinsics(intr: np.ndarray, width: int, height: int) -> Camera:
    """The camera of intrinsics ``[f, cx, cy, k1, k2]`` (square pixels, no skew).

    Parameters
    ----------
    intr : (5,) ndarray
        Focal length, principal point (px) and radial distortion.
    width, height : int
        The image size, px.

    Returns
    -------
    Camera
        The camera.
    """
    f, cx, cy, k1, k2 = intr
    return Camera(np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]]), np.array([k1, k2, 0, 0, 0.0]), width, height)


@dataclass(frozen=True, eq=False)
class _Problem:
    """The fixed structure of one bundle adjustment: which observations, frames and
    points take part, where each frame's observations sit, and the robust weighting."""

    camera: Camera  # the camera at the start (kept when the intrinsics are held)
    free_intrinsics: bool
    obs: np.ndarray  # (N,) observations, sorted by frame
    frames: np.ndarray  # (C,) frames with an observation
    points: np.ndarray  # (P,) points with an observation
    op: np.ndarray  # (N,) each observation's point, local index
    uv: np.ndarray  # (N, 2) the observations, px
    slices: list[slice]  # each frame's observations
    ycols: list[np.ndarray]  # each frame's columns in y = [intrinsics, points]
    held: int  # the frame (local index) whose pose is held: the gauge
    n_intr: int
    n_y: int
    precision: np.ndarray  # (N,)
    root_precision: np.ndarray  # (N,)
    loss_scale: float
    prior_pairs: np.ndarray  # (Q, 2) local point pairs of the card prior
    prior_len: np.ndarray  # (Q,) their printed distances, metres
    prior_sigma: float


@dataclass(frozen=True, eq=False)
class _NormalEquations:
    """The normal equations over y = [intrinsics, points] and the cameras (one block per
    frame; None for the held frame)."""

    V: np.ndarray  # (n_y, n_y) the y block
    g_y: np.ndarray  # (n_y,) gradient over y
    U: list[np.ndarray | None]  # (6, 6) camera blocks
    E: list[np.ndarray | None]  # (6, k) camera-y blocks, over each frame's y columns
    g_c: list[np.ndarray | None]  # (6,) camera gradients


def _problem(rec: Reconstruction, tracks: Tracks, use: np.ndarray, free_intrinsics: bool,
             card_prior: tuple[float, float] | None, loss_scale: float) -> _Problem:
    use = use & rec.registered()[tracks.frame] & rec.placed()[tracks.point]
    obs = np.flatnonzero(use)
    frames = np.unique(tracks.frame[obs])
    points = np.unique(tracks.point[obs])
    ppos = np.full(len(rec.X), -1)
    ppos[points] = np.arange(len(points))
    n_intr = 5 if free_intrinsics else 0
    op = ppos[tracks.point[obs]]
    bounds = np.r_[0, np.flatnonzero(np.diff(tracks.frame[obs])) + 1, len(obs)]  # obs sorted by frame
    counts = np.diff(bounds)
    slices = [slice(bounds[k], bounds[k + 1]) for k in range(len(bounds) - 1)]
    prior_pairs = np.zeros((0, 2), int)
    prior_len = np.zeros(0)
    prior_sigma = 1.0
    if card_prior is not None:
        unit, prior_sigma = card_prior
        whole = [t for t in np.unique(points // 4) if (ppos[4 * t : 4 * t + 4] >= 0).all()]
        if whole:
            prior_pairs = np.concatenate([ppos[4 * t + PAIRS] for t in whole])
            prior_len = np.tile(PAIR_UNITS * unit, len(whole))
    precision = tracks.precision[obs]
    return _Problem(
        camera=rec.camera, free_intrinsics=free_intrinsics, obs=obs, frames=frames, points=points, op=op,
        uv=tracks.uv[obs], slices=slices,
        ycols=[np.r_[np.arange(n_intr), (n_intr + 3 * op[s][:, None] + np.arange(3)).ravel()] for s in slices],
        held=int(np.argmax(counts)), n_intr=n_intr, n_y=n_intr + 3 * len(points), precision=precision,
        root_precision=np.sqrt(precision), loss_scale=loss_scale, prior_pairs=prior_pairs, prior_len=prior_len,
        prior_sigma=prior_sigma,
    )


def _camera_of(p: _Problem, intr: np.ndarray) -> Camera:
    return camera_from_intrinsics(intr, p.camera.width, p.camera.height) if p.free_intrinsics else p.camera


def _residuals(p: _Problem, cam: Camera, cams: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(N, 2) reprojection residuals, px."""
    out = np.empty((len(p.obs), 2))
    for k, s in enumerate(p.slices):
        out[s], _ = project_frame(cam, cams[k, :3], cams[k, 3:], X[p.op[s]], False)
    return out - p.uv


def _weights(p: _Problem, r: np.ndarray) -> np.ndarray:
    """IRLS: each observation's precision times Huber's weight of its whitened error."""
    e = np.linalg.norm(r, axis=1) * p.root_precision
    return p.precision * np.where(e <= p.loss_scale, 1.0, p.loss_scale / np.maximum(e, 1e-300))


def _prior_residuals(p: _Problem, X: np.ndarray) -> np.ndarray:
    """The card prior's residuals: each pair's distance off the printed one, in sigmas."""
    if not len(p.prior_pairs):
        return np.zeros(0)
    d = np.linalg.norm(X[p.prior_pairs[:, 0]] - X[p.prior_pairs[:, 1]], axis=1)
    return (d - p.prior_len) / p.prior_sigma


def _robust_cost(p: _Problem, r: np.ndarray, rp: np.ndarray) -> float:
    e = np.linalg.norm(r, axis=1) * p.root_precision
    c = np.where(e <= p.loss_scale, 0.5 * e**2, p.loss_scale * (e - 0.5 * p.loss_scale))
    return float(c.sum() + 0.5 * (rp**2).sum())


def _normal_equations(p: _Problem, intr: np.ndarray, cams: np.ndarray, X: np.ndarray, r: np.ndarray
                      ) -> _NormalEquations:
    """The weighted normal equations at (intr, cams, X) with residuals ``r``."""
    cam = _camera_of(p, intr)
    w = _weights(p, r)
    n_intr = p.n_intr
    V = np.zeros((p.n_y, p.n_y))
    g_y = np.zeros(p.n_y)
    U_list: list[np.ndarray | None] = []
    E_list: list[np.ndarray | None] = []
    gc_list: list[np.ndarray | None] = []
    for k, s in enumerate(p.slices):
        n = s.stop - s.start
        _, jac = project_frame(cam, cams[k, :3], cams[k, 3:], X[p.op[s]], True)
        assert jac is not None
        R, _ = cv2.Rodrigues(cams[k, :3])
        Jc = jac[:, :6]
        Jy = np.zeros((2 * n, n_intr + 3 * n))
        if n_intr:
            Jy[:, 0] = jac[:, 6] + jac[:, 7]  # fx = fy = f
            Jy[:, 1:3] = jac[:, 8:10]
            Jy[:, 3:5] = jac[:, 10:12]
        Jp = (jac[:, 3:6] @ R).reshape(n, 2, 3)  # d/dX = d/dt R  (x_cam = R X + t)
        rows = np.arange(2 * n).reshape(n, 2)
        cidx = n_intr + 3 * np.arange(n)[:, None] + np.arange(3)
        Jy[rows[:, :, None], cidx[:, None, :]] = Jp
        sw = np.repeat(w[s], 2)[:, None]
        rk = r[s].ravel()
        cols = p.ycols[k]
        JyW = Jy * sw
        V[np.ix_(cols, cols)] += JyW.T @ Jy
        g_y[cols] += JyW.T @ rk
        if k == p.held:
            U_list.append(None)
            E_list.append(None)
            gc_list.append(None)
            continue
        JcW = Jc * sw
        U_list.append(JcW.T @ Jc)
        E_list.append(JcW.T @ Jy)
        gc_list.append(JcW.T @ rk)
    if len(p.prior_pairs):
        diff = X[p.prior_pairs[:, 0]] - X[p.prior_pairs[:, 1]]
        u = diff / (np.linalg.norm(diff, axis=1, keepdims=True) + 1e-300) / p.prior_sigma
        rp = _prior_residuals(p, X)
        for side, sign in ((0, 1.0), (1, -1.0)):
            for side2, sign2 in ((0, 1.0), (1, -1.0)):
                ia = n_intr + 3 * p.prior_pairs[:, side][:, None] + np.arange(3)
                ib = n_intr + 3 * p.prior_pairs[:, side2][:, None] + np.arange(3)
                blocks = sign * sign2 * u[:, :, None] * u[:, None, :]
                np.add.at(V, (ia[:, :, None], ib[:, None, :]), blocks)
            ia = n_intr + 3 * p.prior_pairs[:, side][:, None] + np.arange(3)
            np.add.at(g_y, ia, sign * u * rp[:, None])
    return _NormalEquations(V, g_y, U_list, E_list, gc_list)


def _schur(p: _Problem, ne: _NormalEquations, lam: float
           ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray | None]]:
    """The damped system over y with the cameras eliminated: (S, rhs, each camera
    block's inverse)."""
    S = ne.V + lam * np.diag(np.diag(ne.V) + 1e-12)
    rhs = ne.g_y.copy()
    inv_list: list[np.ndarray | None] = []
    for k in range(len(p.slices)):
        Uk, Ek, gk = ne.U[k], ne.E[k], ne.g_c[k]
        if Uk is None or Ek is None or gk is None:
            inv_list.append(None)
            continue
        U = Uk + lam * np.diag(np.diag(Uk) + 1e-12)
        Ui = np.linalg.inv(U)
        inv_list.append(Ui)
        cols = p.ycols[k]
        EtUi = Ek.T @ Ui
        S[np.ix_(cols, cols)] -= EtUi @ Ek
        rhs[cols] -= EtUi @ gk
    return S, rhs, inv_list


def _camera_steps(p: _Problem, ne: _NormalEquations, inv_list: list[np.ndarray | None], dy: np.ndarray,
                  shape: tuple[int, ...]) -> np.ndarray:
    """Back-substitution: each camera's step given the step ``dy`` over y."""
    dc = np.zeros(shape)
    for k in range(len(p.slices)):
        Ui, Ek, gk = inv_list[k], ne.E[k], ne.g_c[k]
        if Ui is None or Ek is None or gk is None:
            continue
        dc[k] = -Ui @ (gk + Ek @ dy[p.ycols[k]])
    return dc


def bundle_adjust(
    rec: Reconstruction,
    tracks: Tracks,
    use: np.ndarray,
    free_intrinsics: bool,
    card_prior: tuple[float, float] | None = None,
    loss_scale: float = GROWTH_LOSS_SCALE,
    max_iterations: int = 100,
    with_covariance: bool = False,
) -> tuple[Reconstruction, BundleInfo]:
    """Robust sparse bundle adjustment (Levenberg-Marquardt, cameras eliminated).

    Adjusts [f, cx, cy, k1, k2] when ``free_intrinsics``, the pose (rvec, t) of every
    frame with an observation but one (the best-seen frame is held: it fixes the gauge),
    and the 3D point of every disc with an observation.

    Parameters
    ----------
    rec : Reconstruction
        The start; not changed.
    tracks : Tracks
        The observations.
    use : (M,) ndarray of bool
        The observations to use (those of unregistered frames or unplaced points are
        left out anyway).
    free_intrinsics : bool
        Adjust the intrinsics too.
    card_prior : (float, float), optional
        (metres per card unit, sigma in metres): each card's six disc-to-disc distances
        as soft residuals, which also fixes the scale.
    loss_scale : float
        Huber's threshold on the whitened error: the loss is quadratic up to it.
    max_iterations : int
        At most this many iterations (0: only measure the start).
    with_covariance : bool
        Also compute the marginal covariance of the intrinsics and points.

    Returns
    -------
    rec : Reconstruction
        The adjusted reconstruction (a new one).
    info : BundleInfo
        Iterations, cost, residuals, weights and covariance at the end.
    """
    p = _problem(rec, tracks, use, free_intrinsics, card_prior, loss_scale)
    intr = np.array([rec.camera.fx, rec.camera.cx, rec.camera.cy, rec.camera.dist[0], rec.camera.dist[1]])
    cams = np.c_[rec.rvec[p.frames], rec.tvec[p.frames]]
    X = rec.X[p.points].copy()

    r = _residuals(p, _camera_of(p, intr), cams, X)
    cost = _robust_cost(p, r, _prior_residuals(p, X))
    lam = 1e-4
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        ne = _normal_equations(p, intr, cams, X, r)
        # Damped solves until the cost goes down.
        improved = False
        for _ in range(12):
            S, rhs, inv_list = _schur(p, ne, lam)
            try:
                dy = -np.linalg.solve(S, rhs)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            dc = _camera_steps(p, ne, inv_list, dy, cams.shape)
            intr_new = intr.copy()
            if p.n_intr:
                intr_new = intr + dy[:5]
            X_new = X + dy[p.n_intr :].reshape(-1, 3)
            cams_new = cams + dc
            try:
                r_new = _residuals(p, _camera_of(p, intr_new), cams_new, X_new)
            except ValueError:  # an impossible camera (f <= 0): a shorter step
                lam *= 10
                continue
            cost_new = _robust_cost(p, r_new, _prior_residuals(p, X_new))
            if np.isfinite(cost_new) and cost_new < cost:
                improved = True
                break
            lam *= 10
        if not improved:
            break
        gain = cost - cost_new
        intr, X, cams, r, cost = intr_new, X_new, cams_new, r_new, cost_new
        lam = max(lam / 10, 1e-12)
        step = max(np.abs(dy).max() if len(dy) else 0.0, np.abs(dc).max() if dc.size else 0.0)
        if gain < 1e-12 * max(cost, 1e-12) or step < 1e-12:
            break
    covariance = None
    if with_covariance and len(p.points):
        # Marginal covariance of intrinsics + points: inverse of the undamped reduced
        # system; a pseudo-inverse drops what the gauge leaves free (scale w/o prior).
        ne = _normal_equations(p, intr, cams, X, r)
        S, _, _ = _schur(p, ne, 0.0)
        dof = max(2 * len(p.obs) - len(cams) * 6 - p.n_y + 6, 1)
        w = _weights(p, r)
        sigma2 = float((w[:, None] * r**2).sum() / dof)
        covariance = np.linalg.pinv(S, rcond=1e-12, hermitian=True) * sigma2
    out = Reconstruction(_camera_of(p, intr), rec.rvec.copy(), rec.tvec.copy(), rec.X.copy())
    out.rvec[p.frames], out.tvec[p.frames] = cams[:, :3], cams[:, 3:]
    out.X[p.points] = X
    info = BundleInfo(
        iterations=iterations, cost=cost, rms_px=float(np.sqrt((r**2).sum(axis=1).mean())), obs=p.obs,
        points=p.points, n_intr=p.n_intr, residuals=r, weights=_weights(p, r), covariance=covariance,
        held_frame=int(p.frames[p.held]),
    )
    return out, info
