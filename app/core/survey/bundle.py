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

Natural-feature points (`points.FeatureObservations`: a second kind of track, thousands
of points each seen in a few frames, with their own noise level and robust loss) link
the frames that see them, so the cameras are no longer independent given the points.
With them, the feature points are eliminated instead (each a 3x3 block, independent
given the cameras and the intrinsics) and the system over [intrinsics, discs, cameras] is
solved exactly every iteration: block-sparse (cameras linked only where they share a
feature point), factorised by SuperLU in a fill-reducing order (`ReducedSolver`; the
dense Cholesky is kept as the reference). The two loops over many tiny blocks (each
observation's terms, each point's Schur complement) are compiled (`_bundle_kernels`).
Beyond `policy.FeatureKeyframes` frames with feature observations, those of every k-th
frame only are adjusted jointly and the other frames' poses are fitted to the result.
Without feature points nothing of this runs: the result is the discs' alone, to the bit.
The benchmark against Ceres is ``bench/bench_bundle.py``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import cv2
import numpy as np
import scipy.sparse
from scipy.linalg import cho_factor, cho_solve
from scipy.sparse.linalg import splu

from app.core.geometry import Camera
from app.core.survey._bundle_kernels import (
    add_discs_sparse,
    add_observations,
    add_observations_sparse,
    camera_pairs,
    eliminate_points,
    eliminate_points_sparse,
)
from app.core.survey.cards import PAIR_UNITS, PAIRS
from app.core.survey.points import FeatureObservations
from app.core.survey.policy import FeatureKeyframes
from app.core.survey.state import Reconstruction, Tracks, project_frame

#: Huber's threshold (whitened) while the map grows: loose, since residuals of pixels are
#: then the unrefined lens's and poses' error, not outliers.
GROWTH_LOSS_SCALE = 100.0
#: The longest lag (observations of one point) summed in `correlation_time`, and the
#: fewest pairs of observations a lag's correlation is estimated from.
MAX_CORRELATION_LAG = 60
MIN_CORRELATION_PAIRS = 50


class ReducedSolver(str, Enum):
    """How the reduced system over [intrinsics, discs, cameras] is solved when feature
    points take part."""

    SPARSE = "sparse"  # SuperLU over the cameras' block pattern, a fill-reducing order
    DENSE = "dense"  # dense Cholesky: cubic in the frames (the reference)


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
    # The feature points (empty when none took part):
    feature_X: np.ndarray | None = None  # (P, 3) every feature point after the adjustment; None: none given
    feature_obs: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (K,) observations used
    feature_points: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (Pf,) points adjusted
    feature_residuals: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (K, 2) px
    feature_weights: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (K,) the loss's weight / sigma^2
    feature_rms_px: float = float("nan")  # reprojection RMS (2D) of the feature observations used
    # How many of a disc's observations, consecutive in time, count as one independent
    # measurement in the covariance (`correlation_time`); 1 without a covariance.
    correlation_time: float = 1.0

    def intrinsics_std(self) -> np.ndarray | None:
        """Standard deviations of the adjusted intrinsics, from the marginal covariance.

        Intrinsics do not change with a rigid motion or a scaling of the whole map, so
        the gauge (the held frame) does not enter them.

        Returns
        -------
        (5,) ndarray or None
            1 sigma of ``[f, cx, cy, k1, k2]`` (px, px, px, -, -); None when the
            intrinsics were held or no covariance was computed.
        """
        if self.covariance is None or self.n_intr != 5:
            return None
        return np.sqrt(np.clip(np.diag(self.covariance)[:5], 0.0, None))

    def disc_covariance(self, X: np.ndarray) -> np.ndarray | None:
        """Joint covariance of the adjusted points relative to the map, from the
        marginal covariance.

        The covariance is that of a gauge: the held frame's pose is exact, so every
        point inherits how uncertain its position is relative to that one camera, an
        error shared by all the discs alike. The map's frame is a choice, not a
        measurement: a motion of the whole map is no error in it (tracking, alignment
        and the benchmarks against the truth all see the map up to one rigid motion).
        So the rigid motions of the adjusted points are projected out of their
        covariance (the least-squares gauge over the discs): ``P C P^T``.

        Parameters
        ----------
        X : (n_points, 3) ndarray
            The reconstruction's points.

        Returns
        -------
        (3 * len(points), 3 * len(points)) ndarray or None
            Over the adjusted points (`points`, in that order), x, y, z of each (m^2 in
            the reconstruction's units); None when no covariance was computed.
        """
        C = self.covariance
        if C is None:
            return None
        points = np.asarray(X, np.float64)[self.points]
        C = C[self.n_intr :, self.n_intr :]
        if len(points) < 3:
            return C.copy()
        # G: each point's motion under a small translation (3) and rotation (3) of the
        # whole map about its centroid; P = I - G G^+ projects those out.
        d = points - points.mean(axis=0)
        G = np.zeros((len(points), 3, 6))
        G[:, :, :3] = np.eye(3)
        G[:, 0, 4], G[:, 0, 5] = d[:, 2], -d[:, 1]
        G[:, 1, 3], G[:, 1, 5] = -d[:, 2], d[:, 0]
        G[:, 2, 3], G[:, 2, 4] = d[:, 1], -d[:, 0]
        G = G.reshape(-1, 6)
        PC = C - G @ (np.linalg.pinv(G) @ C)
        projected = PC - (PC @ np.linalg.pinv(G).T) @ G.T
        return (projected + projected.T) / 2.0

    def disc_std(self, X: np.ndarray, joint: np.ndarray | None = None) -> np.ndarray:
        """RMS 3D standard deviation of every disc relative to the map: the square root
        of the trace of its 3x3 block of `disc_covariance`.

        Parameters
        ----------
        X : (n_points, 3) ndarray
            The reconstruction's points.
        joint : ndarray, optional
            `disc_covariance` of `X`, when the caller has it already.

        Returns
        -------
        (n_points,) ndarray
            sqrt of each point's covariance trace; nan for points not adjusted, or all
            when no covariance was computed.
        """
        std = np.full(len(X), np.nan)
        C = self.disc_covariance(X) if joint is None else joint
        if C is None:
            return std
        diag = np.clip(np.diag(C), 0.0, None).reshape(-1, 3)
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
    frame: np.ndarray  # (N,) each observation's frame
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
    # obs sorted by frame: one run per frame (none without observations)
    bounds = np.r_[0, np.flatnonzero(np.diff(tracks.frame[obs])) + 1, len(obs)] if len(obs) else np.zeros(1, int)
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
        camera=rec.camera, free_intrinsics=free_intrinsics, obs=obs, frame=tracks.frame[obs], frames=frames,
        points=points, op=op,
        uv=tracks.uv[obs], slices=slices,
        ycols=[np.r_[np.arange(n_intr), (n_intr + 3 * op[s][:, None] + np.arange(3)).ravel()] for s in slices],
        held=int(np.argmax(counts)) if len(counts) else -1, n_intr=n_intr, n_y=n_intr + 3 * len(points),
        precision=precision, root_precision=np.sqrt(precision), loss_scale=loss_scale, prior_pairs=prior_pairs,
        prior_len=prior_len, prior_sigma=prior_sigma,
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


def correlation_time(point: np.ndarray, frame: np.ndarray, whitened: np.ndarray, max_lag: int = MAX_CORRELATION_LAG
                     ) -> float:
    """How many consecutive observations of a point carry one independent measurement's
    worth of information: the integrated autocorrelation time of the residuals along
    each point's observations in frame order.

    The covariance of a least-squares fit counts every observation as independent. A
    video's disc centres are not: the same blur, the same compression blocks copied
    along motion vectors and the same lighting move a disc's centre alike in the frames
    that follow, so n observations of it are worth about n / tau independent ones, and
    the covariance is tau times too small. With rho_m the correlation of the residuals m
    observations apart (both axes pooled), ``tau = 1 + 2 sum_m rho_m``, summed while
    rho_m stays positive (the initial positive sequence: beyond it the estimates are
    noise).

    Parameters
    ----------
    point : (N,) ndarray of int
        Each observation's point.
    frame : (N,) ndarray of int
        Each observation's frame.
    whitened : (N, 2) ndarray
        The residuals, each divided by its expected error.
    max_lag : int
        The longest lag summed, in observations.

    Returns
    -------
    float
        tau, at least 1.
    """
    order = np.lexsort((frame, point))
    pt, e = np.asarray(point)[order], np.asarray(whitened, np.float64)[order]
    tau = 1.0
    for lag in range(1, min(max_lag, len(pt) - 1) + 1):
        same = pt[lag:] == pt[:-lag]
        if same.sum() < MIN_CORRELATION_PAIRS:
            break
        a, b = e[lag:][same], e[:-lag][same]
        rho = float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum() + 1e-300))
        if not rho > 0.0:
            break
        tau += 2.0 * rho
    return tau


def _disc_correlation_time(p: _Problem, r: np.ndarray) -> float:
    """`correlation_time` of the disc observations' residuals, each whitened by its
    weight (its precision and the robust loss's: an outlier must not set it)."""
    return correlation_time(p.op, p.frame, r * np.sqrt(_weights(p, r))[:, None])


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


# --- feature points: the second kind of track ---------------------------------------------
#
# Two frames that see one feature point are linked through it, so the cameras stay in the
# reduced system x = [intrinsics, discs, cameras] and the feature points are eliminated.
# The discs' normal equations are those above, their camera blocks moved to the joint
# columns; the damping is the same (each block's diagonal, before elimination).


@dataclass(frozen=True, eq=False)
class _FeatureProblem:
    """The fixed structure of the feature points' part of one bundle adjustment, over the
    frames of both kinds of track (joint camera indices)."""

    features: FeatureObservations  # the noise model
    obs: np.ndarray  # (K,) feature observations used, sorted by frame
    cam: np.ndarray  # (K,) each observation's camera, joint index
    op: np.ndarray  # (K,) each observation's point, local index
    points: np.ndarray  # (Pf,) the feature points adjusted (rows of the feature points' array)
    uv: np.ndarray  # (K, 2) px
    slices: list[tuple[int, slice]]  # (camera, its observations)
    by_point: np.ndarray  # (K,) the observations sorted by point
    bounds: np.ndarray  # (Pf + 1,) point j's observations are by_point[bounds[j]:bounds[j + 1]]
    col: np.ndarray  # (K,) the first column of each observation's camera; -1 for the held one


@dataclass(frozen=True, eq=False)
class _Joint:
    """The cameras of both kinds of track and the columns of the reduced system
    x = [intrinsics, disc points, cameras] (the feature points eliminated)."""

    frames: np.ndarray  # (C,) frames with an observation of either kind
    dmap: np.ndarray  # (Cd,) each disc frame's joint index
    held: int  # the held camera, joint index
    ccol: np.ndarray  # (C,) the column of each camera's first parameter; -1 for the held one
    n_y: int  # intrinsics + disc point parameters
    n: int  # the reduced system's size


@dataclass(frozen=True, eq=False)
class _FeatureSystem:
    """The undamped normal equations of one iteration: the reduced-side block over x with
    the feature points' direct terms, and what eliminating the feature points needs."""

    H: np.ndarray  # (n, n)
    g: np.ndarray  # (n,)
    W: np.ndarray  # (Pf, 3, 3) the feature point blocks
    g_p: np.ndarray  # (Pf, 3)
    F_c: np.ndarray  # (K, 6, 3) camera-point coupling of each observation
    C_i: np.ndarray  # (Pf, n_intr, 3) intrinsics-point coupling of each point


def _feature_problem(rec: Reconstruction, features: FeatureObservations, feature_X: np.ndarray,
                     feature_use: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The feature observations that take part, sorted by frame, and the points they adjust:
    those of registered frames and finite points, of points with two such observations at
    least (one view leaves a point free along its ray)."""
    use = np.ones(len(features), bool) if feature_use is None else feature_use.copy()
    use &= rec.registered()[features.frame] & np.isfinite(feature_X[features.track]).all(axis=1)
    use &= np.bincount(features.track[use], minlength=len(feature_X))[features.track] >= 2
    obs = np.flatnonzero(use)
    obs = obs[np.argsort(features.frame[obs], kind="stable")]
    return obs, np.unique(features.track[obs])


def _joint(p: _Problem, features: FeatureObservations, obs: np.ndarray) -> _Joint:
    """The frames of both kinds of track and the held one: the discs' best-seen frame, as
    without feature points (the frame that sees most feature points when no disc is seen)."""
    frames = np.union1d(p.frames, features.frame[obs])
    dmap = np.searchsorted(frames, p.frames)
    if len(p.frames):
        held = int(dmap[p.held])
    else:
        held = int(np.argmax(np.bincount(np.searchsorted(frames, features.frame[obs]))))
    free = np.arange(len(frames)) != held
    ccol = np.full(len(frames), -1)
    ccol[free] = p.n_y + 6 * np.arange(int(free.sum()))
    return _Joint(frames, dmap, held, ccol, p.n_y, p.n_y + 6 * int(free.sum()))


def _feature_structure(features: FeatureObservations, obs: np.ndarray, points: np.ndarray, joint: _Joint
                       ) -> _FeatureProblem:
    """Where each feature observation sits: its camera, its point, its columns."""
    cam = np.searchsorted(joint.frames, features.frame[obs])
    op = np.searchsorted(points, features.track[obs])
    starts = np.r_[0, np.flatnonzero(np.diff(cam)) + 1]  # obs sorted by frame: one run per camera
    ends = np.r_[starts[1:], len(obs)]
    slices = [(int(cam[b]), slice(b, e)) for b, e in zip(starts, ends, strict=True)]
    by_point = np.argsort(op, kind="stable")
    bounds = np.r_[0, np.cumsum(np.bincount(op, minlength=len(points)))]
    return _FeatureProblem(
        features=features, obs=obs, cam=cam, op=op, points=points, uv=features.uv[obs], slices=slices,
        by_point=by_point, bounds=bounds, col=joint.ccol[cam],
    )


def _feature_residuals(fp: _FeatureProblem, cam: Camera, cams: np.ndarray, Xf: np.ndarray) -> np.ndarray:
    """(K, 2) the feature observations' reprojection residuals, px."""
    out = np.empty((len(fp.obs), 2))
    for k, s in fp.slices:
        out[s], _ = project_frame(cam, cams[k, :3], cams[k, 3:], Xf[fp.op[s]], False)
    return out - fp.uv


def _feature_jacobians(fp: _FeatureProblem, cam: Camera, cams: np.ndarray, Xf: np.ndarray, n_intr: int
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each feature observation's Jacobian over its camera (K, 2, 6), the intrinsics
    (K, 2, n_intr) and its point (K, 2, 3)."""
    return _jacobians(len(fp.obs), fp.slices, fp.op, cam, cams, Xf, n_intr)


def _jacobians(K: int, slices: list[tuple[int, slice]], op: np.ndarray, cam: Camera, cams: np.ndarray, X: np.ndarray,
               n_intr: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Jacobians of K observations (camera ``k``'s at ``slices``, of points ``X[op]``)
    over their camera, the intrinsics and their point."""
    J_c, J_i, J_p = np.empty((K, 2, 6)), np.empty((K, 2, n_intr)), np.empty((K, 2, 3))
    for k, s in slices:
        n = s.stop - s.start
        _, jac = project_frame(cam, cams[k, :3], cams[k, 3:], X[op[s]], True)
        assert jac is not None
        jac = jac.reshape(n, 2, -1)
        J_c[s] = jac[:, :, :6]
        if n_intr:
            J_i[s, :, 0] = jac[:, :, 6] + jac[:, :, 7]  # fx = fy = f
            J_i[s, :, 1:3] = jac[:, :, 8:10]
            J_i[s, :, 3:5] = jac[:, :, 10:12]
        R, _ = cv2.Rodrigues(cams[k, :3])
        J_p[s] = jac[:, :, 3:6] @ R  # d/dX = d/dt R  (x_cam = R X + t)
    return J_c, J_i, J_p


def _per_point(fp: _FeatureProblem, a: np.ndarray) -> np.ndarray:
    """Sums of per-observation arrays over each point's observations (two at least: no
    empty run)."""
    return np.add.reduceat(a[fp.by_point], fp.bounds[:-1], axis=0)


def _feature_system(p: _Problem, fp: _FeatureProblem, joint: _Joint, intr: np.ndarray, cams: np.ndarray,
                    X: np.ndarray, Xf: np.ndarray, r: np.ndarray, rf: np.ndarray,
                    share: np.ndarray | None = None) -> _FeatureSystem:
    """The undamped normal equations over x, with the feature points' direct terms (each
    feature observation's weight times its ``share``, when given: `_track_shares`)."""
    cam = _camera_of(p, intr)
    ni, n = p.n_intr, joint.n
    H = np.zeros((n, n))
    g = np.zeros(n)
    # The discs: their y block as it is, their camera blocks moved to the joint columns.
    ne = _normal_equations(p, intr, cams[joint.dmap], X, r)
    H[: p.n_y, : p.n_y] = ne.V
    g[: p.n_y] = ne.g_y
    for k in range(len(p.slices)):
        U, E, g_c = ne.U[k], ne.E[k], ne.g_c[k]
        if U is None or E is None or g_c is None:
            continue
        c = slice(joint.ccol[joint.dmap[k]], joint.ccol[joint.dmap[k]] + 6)
        H[c, c] += U
        H[c, p.ycols[k]] += E
        H[p.ycols[k], c] += E.T
        g[c] += g_c
    # The feature points' own terms.
    J_c, J_i, J_p = _feature_jacobians(fp, cam, cams, Xf, ni)
    K, P = len(fp.obs), len(fp.points)
    W, g_p, F_c, C_i = np.zeros((P, 3, 3)), np.zeros((P, 3)), np.empty((K, 6, 3)), np.zeros((P, ni, 3))
    weights = fp.features.weights(rf) if share is None else fp.features.weights(rf) * share
    add_observations(H, g, W, g_p, F_c, C_i, J_c, J_i, J_p, weights, rf, fp.col, fp.op)
    return _FeatureSystem(H, g, W, g_p, F_c, C_i)


def _damped(A: np.ndarray, lam: float) -> np.ndarray:
    """A + lam (diag(A) + 1e-12): Levenberg-Marquardt's damping of square blocks (..., m, m)."""
    out = A.copy()
    i = np.arange(A.shape[-1])
    out[..., i, i] += lam * (A[..., i, i] + 1e-12)
    return out


def _feature_reduced(p: _Problem, fp: _FeatureProblem, joint: _Joint, fs: _FeatureSystem, lam: float = 0.0
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The damped system over x with the feature points eliminated: (H, g, each feature
    point's damped block's inverse)."""
    H = _damped(fs.H, lam)
    g = fs.g.copy()
    W_inv = np.linalg.inv(_damped(fs.W, lam)) if lam > 0 else np.linalg.pinv(fs.W, hermitian=True)
    eliminate_points(H, g, W_inv, fs.F_c, fs.C_i, fs.g_p, fp.by_point, fp.bounds, fp.col)
    return H, g, W_inv


def _feature_step(p: _Problem, fp: _FeatureProblem, joint: _Joint, fs: _FeatureSystem, lam: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The damped step: (dx over [intrinsics, discs, cameras], dXf over the feature points).

    Raises numpy's LinAlgError when the damped reduced system is not positive definite."""
    H, g, W_inv = _feature_reduced(p, fp, joint, fs, lam)
    dx = -cho_solve(cho_factor(H, check_finite=False), g, check_finite=False)
    if not np.isfinite(dx).all():
        raise np.linalg.LinAlgError("the damped reduced system is singular")
    return dx, _feature_points_step(p, fp, joint, fs.F_c, fs.C_i, fs.g_p, W_inv, dx)


def _feature_points_step(p: _Problem, fp: _FeatureProblem, joint: _Joint, F_c: np.ndarray, C_i: np.ndarray,
                         g_p: np.ndarray, W_inv: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """Back-substitution: each feature point's step given the cameras' and intrinsics'."""
    ni = p.n_intr
    dc = np.zeros((len(joint.frames), 6))
    dc[joint.ccol >= 0] = dx[joint.ccol[joint.ccol >= 0][:, None] + np.arange(6)]
    coupling = _per_point(fp, (F_c.transpose(0, 2, 1) @ dc[fp.cam][:, :, None])[:, :, 0])
    if ni:
        coupling += (C_i.transpose(0, 2, 1) @ dx[:ni])
    return -(W_inv @ (g_p + coupling)[:, :, None])[:, :, 0]


# --- the reduced system, block-sparse --------------------------------------------------------
#
# Along a video a frame shares feature points with its neighbours and, through loop
# closures, with a few frames of an earlier visit: the camera-camera block of the reduced
# system is mostly empty, and a dense Cholesky of it grows as the cube of the frames. The
# border (intrinsics and discs, n_y columns: the intrinsics couple to every camera) is
# kept dense over every row; the camera-camera block as 6x6 blocks over the pairs of
# cameras that share a feature point. The whole system is factorised by SuperLU
# (`scipy.sparse.linalg.splu`) in a fill-reducing order (minimum degree on A + A^T),
# without pivoting off the diagonal: an LDL^T in effect, whose pivots are all positive
# exactly when the system is positive definite (the test Cholesky makes).


@dataclass(frozen=True, eq=False)
class _SparsePattern:
    """The reduced system's nonzero pattern, fixed for one bundle adjustment, and how its
    parts (``Hy`` (n, n_y) and the camera blocks) map to a CSC matrix."""

    n_y: int
    n: int
    fcam: np.ndarray  # (K,) each feature observation's free camera; -1 for the held one
    dcam: np.ndarray  # (N,) each disc observation's free camera; -1 for the held one
    indptr: np.ndarray  # (n_free + 1,) block rows of the camera-camera block
    indices: np.ndarray  # (nnzb,) block columns, sorted within each row
    diag: np.ndarray  # (n_free,) each free camera's diagonal block
    bb: tuple[np.ndarray, np.ndarray]  # border-border entries kept (rows, columns)
    cb: tuple[np.ndarray, np.ndarray]  # camera-border entries kept (rows >= n_y, columns < n_y)
    order: np.ndarray  # the values in gathering order -> CSC order
    csc_indices: np.ndarray
    csc_indptr: np.ndarray


@dataclass(frozen=True, eq=False)
class _SparseSystem:
    """`_FeatureSystem` with the reduced-side block stored as `_SparsePattern` says."""

    Hy: np.ndarray  # (n, n_y) every row's border columns
    blocks: np.ndarray  # (nnzb, 6, 6) camera-camera blocks
    g: np.ndarray  # (n,)
    W: np.ndarray  # (Pf, 3, 3)
    g_p: np.ndarray  # (Pf, 3)
    F_c: np.ndarray  # (K, 6, 3)
    C_i: np.ndarray  # (Pf, n_intr, 3)


def _sparse_pattern(p: _Problem, fp: _FeatureProblem, joint: _Joint) -> _SparsePattern:
    n_y, n = joint.n_y, joint.n
    ni = p.n_intr
    free_index = np.where(joint.ccol >= 0, (joint.ccol - n_y) // 6, -1)
    n_free = int((joint.ccol >= 0).sum())
    fcam = free_index[fp.cam]
    # The feature points each free camera sees (observations are sorted by camera).
    seen = fcam >= 0
    cam_ptr = np.r_[0, np.cumsum(np.bincount(fcam[seen], minlength=n_free))]
    indptr, indices = camera_pairs(cam_ptr, fp.op[seen], fp.by_point, fp.bounds, fcam, n_free)
    block_row = np.repeat(np.arange(n_free), np.diff(indptr))
    diag = np.flatnonzero(block_row == indices)
    # Border-border: the intrinsics with everything, the discs of one card together (the
    # card prior; each disc's own 3x3 block among them).
    card = p.points // 4
    a, b = np.nonzero(card[:, None] == card[None, :])
    d_rows = (ni + 3 * a[:, None, None] + np.arange(3)[None, :, None] + 0 * np.arange(3)[None, None, :]).ravel()
    d_cols = (ni + 3 * b[:, None, None] + 0 * np.arange(3)[None, :, None] + np.arange(3)[None, None, :]).ravel()
    i_rows = np.repeat(np.arange(ni), n_y)
    i_cols = np.tile(np.arange(n_y), ni)
    bb_rows = np.r_[i_rows, i_cols[i_cols >= ni], d_rows]
    bb_cols = np.r_[i_cols, i_rows[i_cols >= ni], d_cols]
    # Camera-border: every free camera with the intrinsics, and with each disc it sees.
    disc_cam = free_index[joint.dmap[np.repeat(np.arange(len(p.slices)), [s.stop - s.start for s in p.slices])]]
    disc_cam = disc_cam.astype(np.int64).reshape(-1)
    keep = disc_cam >= 0
    pairs = np.unique(np.c_[disc_cam[keep], p.op[keep]], axis=0) if keep.any() else np.zeros((0, 2), int)
    cb_rows = np.r_[(n_y + 6 * np.arange(n_free)[:, None, None] + np.arange(6)[None, :, None]
                     + 0 * np.arange(ni)[None, None, :]).ravel(),
                    (n_y + 6 * pairs[:, 0, None, None] + np.arange(6)[None, :, None]
                     + 0 * np.arange(3)[None, None, :]).ravel()]
    cb_cols = np.r_[(0 * np.arange(n_free)[:, None, None] + 0 * np.arange(6)[None, :, None]
                     + np.arange(ni)[None, None, :]).ravel(),
                    (ni + 3 * pairs[:, 1, None, None] + 0 * np.arange(6)[None, :, None]
                     + np.arange(3)[None, None, :]).ravel()]
    blk_rows = (n_y + 6 * block_row[:, None, None] + np.arange(6)[None, :, None] + 0 * np.arange(6)[None, None, :]
                ).ravel()
    blk_cols = (n_y + 6 * indices[:, None, None] + 0 * np.arange(6)[None, :, None] + np.arange(6)[None, None, :]
                ).ravel()
    rows = np.r_[bb_rows, cb_rows, cb_cols, blk_rows]
    cols = np.r_[bb_cols, cb_cols, cb_rows, blk_cols]
    order = np.lexsort((rows, cols))
    return _SparsePattern(
        n_y=n_y, n=n, fcam=fcam, dcam=disc_cam, indptr=indptr, indices=indices, diag=diag, bb=(bb_rows, bb_cols),
        cb=(cb_rows, cb_cols), order=order, csc_indices=rows[order],
        csc_indptr=np.r_[0, np.cumsum(np.bincount(cols, minlength=n))],
    )


def _sparse_system(p: _Problem, fp: _FeatureProblem, joint: _Joint, sp: _SparsePattern, intr: np.ndarray,
                   cams: np.ndarray, X: np.ndarray, Xf: np.ndarray, r: np.ndarray, rf: np.ndarray,
                   share: np.ndarray | None = None) -> _SparseSystem:
    """`_feature_system` into the block-sparse storage."""
    cam = _camera_of(p, intr)
    ni, n_y = p.n_intr, joint.n_y
    Hy = np.zeros((joint.n, n_y))
    blocks = np.zeros((len(sp.indices), 6, 6))
    g = np.zeros(joint.n)
    # The discs: the terms of `_normal_equations`, in one compiled loop.
    d_slices = [(int(joint.dmap[k]), s) for k, s in enumerate(p.slices)]
    J_c, J_i, J_p = _jacobians(len(p.obs), d_slices, p.op, cam, cams, X, ni)
    add_discs_sparse(Hy, blocks, sp.indptr, sp.indices, g, J_c, J_i, J_p, _weights(p, r), r, sp.dcam, p.op)
    _add_prior(p, X, Hy[:n_y], g[:n_y])
    J_c, J_i, J_p = _feature_jacobians(fp, cam, cams, Xf, ni)
    K, P = len(fp.obs), len(fp.points)
    W, g_p, F_c, C_i = np.zeros((P, 3, 3)), np.zeros((P, 3)), np.empty((K, 6, 3)), np.zeros((P, ni, 3))
    weights = fp.features.weights(rf) if share is None else fp.features.weights(rf) * share
    add_observations_sparse(Hy, blocks, sp.indptr, sp.indices, g, W, g_p, F_c, C_i, J_c, J_i, J_p,
                            weights, rf, sp.fcam, fp.op)
    return _SparseSystem(Hy, blocks, g, W, g_p, F_c, C_i)


def _add_prior(p: _Problem, X: np.ndarray, V: np.ndarray, g_y: np.ndarray) -> None:
    """The card prior's normal equations, added to those over y (as `_normal_equations`)."""
    if not len(p.prior_pairs):
        return
    n_intr = p.n_intr
    diff = X[p.prior_pairs[:, 0]] - X[p.prior_pairs[:, 1]]
    u = diff / (np.linalg.norm(diff, axis=1, keepdims=True) + 1e-300) / p.prior_sigma
    rp = _prior_residuals(p, X)
    for side, sign in ((0, 1.0), (1, -1.0)):
        ia = n_intr + 3 * p.prior_pairs[:, side][:, None] + np.arange(3)
        for side2, sign2 in ((0, 1.0), (1, -1.0)):
            ib = n_intr + 3 * p.prior_pairs[:, side2][:, None] + np.arange(3)
            np.add.at(V, (ia[:, :, None], ib[:, None, :]), sign * sign2 * u[:, :, None] * u[:, None, :])
        np.add.at(g_y, ia, sign * u * rp[:, None])


def _sparse_reduced(fp: _FeatureProblem, sp: _SparsePattern, ss: _SparseSystem, lam: float = 0.0
                    ) -> tuple[scipy.sparse.csc_matrix, np.ndarray, np.ndarray]:
    """`_feature_reduced` over the pattern: (H as a CSC matrix, g, each feature point's
    damped block's inverse)."""
    Hy, blocks, g = ss.Hy.copy(), ss.blocks.copy(), ss.g.copy()
    if lam > 0:
        i = np.arange(sp.n_y)
        Hy[i, i] += lam * (Hy[i, i] + 1e-12)
        k = np.arange(6)
        diagonal = blocks[sp.diag[:, None], k, k]
        blocks[sp.diag[:, None], k, k] = diagonal + lam * (diagonal + 1e-12)
    W_inv = np.linalg.inv(_damped(ss.W, lam)) if lam > 0 else np.linalg.pinv(ss.W, hermitian=True)
    eliminate_points_sparse(Hy, blocks, sp.indptr, sp.indices, g, W_inv, ss.F_c, ss.C_i, ss.g_p, fp.by_point,
                            fp.bounds, sp.fcam)
    cb = Hy[sp.cb]
    values = np.concatenate([Hy[sp.bb], cb, cb, blocks.ravel()])
    H = scipy.sparse.csc_matrix((values[sp.order], sp.csc_indices, sp.csc_indptr), shape=(sp.n, sp.n))
    return H, g, W_inv


def _sparse_factor(H: scipy.sparse.csc_matrix) -> scipy.sparse.linalg.SuperLU:
    """H = P^T L U P^T in a fill-reducing order, pivots on the diagonal only.

    Raises numpy's LinAlgError when H is not positive definite (a pivot is not positive)."""
    try:
        lu = splu(H, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    except RuntimeError as error:  # exactly singular
        raise np.linalg.LinAlgError(str(error)) from error
    if not (np.array_equal(lu.perm_r, lu.perm_c) and (lu.U.diagonal() > 0).all()):
        raise np.linalg.LinAlgError("the reduced system is not positive definite")
    return lu


def _sparse_step(p: _Problem, fp: _FeatureProblem, joint: _Joint, sp: _SparsePattern, ss: _SparseSystem,
                 lam: float) -> tuple[np.ndarray, np.ndarray]:
    """`_feature_step` with the sparse factorisation."""
    H, g, W_inv = _sparse_reduced(fp, sp, ss, lam)
    dx = -_sparse_factor(H).solve(g)
    if not np.isfinite(dx).all():
        raise np.linalg.LinAlgError("the damped reduced system is singular")
    return dx, _feature_points_step(p, fp, joint, ss.F_c, ss.C_i, ss.g_p, W_inv, dx)


def _sparse_covariance_system(fp: _FeatureProblem, sp: _SparsePattern, ss: _SparseSystem) -> np.ndarray:
    """The undamped system over [intrinsics, discs] with the feature points and the
    cameras eliminated (the cameras through their sparse factor, the border's columns as
    right-hand sides).

    Raises numpy's LinAlgError when the cameras' block is not positive definite."""
    H, _, _ = _sparse_reduced(fp, sp, ss)
    n_y = sp.n_y
    H_cc = H[n_y:, n_y:].tocsc()
    H_cy = H[n_y:, :n_y].toarray()
    H_yy = H[:n_y, :n_y].toarray()
    solved = _sparse_factor(H_cc).solve(H_cy) if H_cc.shape[0] else np.zeros_like(H_cy)
    return H_yy - H_cy.T @ solved


def _adjust_with_features(rec: Reconstruction, p: _Problem, features: FeatureObservations, feature_X: np.ndarray,
                          obs: np.ndarray, points: np.ndarray, max_iterations: int, tolerance: float,
                          with_covariance: bool, solver: ReducedSolver) -> tuple[Reconstruction, BundleInfo]:
    """`bundle_adjust` with feature points: Levenberg-Marquardt over [intrinsics, discs,
    cameras] with the feature points eliminated."""
    joint = _joint(p, features, obs)
    fp = _feature_structure(features, obs, points, joint)
    sp = _sparse_pattern(p, fp, joint) if solver is ReducedSolver.SPARSE else None
    ni = p.n_intr
    intr = np.array([rec.camera.fx, rec.camera.cx, rec.camera.cy, rec.camera.dist[0], rec.camera.dist[1]])
    cams = np.c_[rec.rvec[joint.frames], rec.tvec[joint.frames]]
    X = rec.X[p.points].copy()
    Xf = feature_X[points].copy()
    free = joint.ccol >= 0
    free_cols = joint.ccol[free][:, None] + np.arange(6)

    def evaluate(intr: np.ndarray, cams: np.ndarray, X: np.ndarray, Xf: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, float]:
        cam = _camera_of(p, intr)
        r = _residuals(p, cam, cams[joint.dmap], X)
        rf = _feature_residuals(fp, cam, cams, Xf)
        return r, rf, _robust_cost(p, r, _prior_residuals(p, X)) + float(features.cost(rf).sum())

    r, rf, cost = evaluate(intr, cams, X, Xf)
    lam = 1e-4
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        if sp is None:
            fs: _FeatureSystem | _SparseSystem = _feature_system(p, fp, joint, intr, cams, X, Xf, r, rf)
        else:
            fs = _sparse_system(p, fp, joint, sp, intr, cams, X, Xf, r, rf)
        improved = False
        for _ in range(12):
            try:
                if isinstance(fs, _SparseSystem):
                    assert sp is not None
                    dx, dXf = _sparse_step(p, fp, joint, sp, fs, lam)
                else:
                    dx, dXf = _feature_step(p, fp, joint, fs, lam)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            intr_new = intr + dx[:5] if ni else intr.copy()
            X_new = X + dx[ni : joint.n_y].reshape(-1, 3)
            cams_new = cams.copy()
            cams_new[free] += dx[free_cols]
            Xf_new = Xf + dXf
            try:
                r_new, rf_new, cost_new = evaluate(intr_new, cams_new, X_new, Xf_new)
            except ValueError:  # an impossible camera (f <= 0): a shorter step
                lam *= 10
                continue
            if np.isfinite(cost_new) and cost_new < cost:
                improved = True
                break
            lam *= 10
        if not improved:
            break
        gain = cost - cost_new
        intr, X, cams, Xf, r, rf, cost = intr_new, X_new, cams_new, Xf_new, r_new, rf_new, cost_new
        lam = max(lam / 10, 1e-12)
        step = max(np.abs(dx).max() if len(dx) else 0.0, np.abs(dXf).max() if dXf.size else 0.0)
        if gain < tolerance * max(cost, 1e-12) or step < 1e-12:
            break
    covariance, tau = None, 1.0
    if with_covariance and len(p.points):
        tau = _disc_correlation_time(p, r)
        covariance = _feature_covariance(p, fp, joint, sp, intr, cams, X, Xf, r, rf) * tau
    out = Reconstruction(_camera_of(p, intr), rec.rvec.copy(), rec.tvec.copy(), rec.X.copy())
    out.rvec[joint.frames], out.tvec[joint.frames] = cams[:, :3], cams[:, 3:]
    out.X[p.points] = X
    adjusted = feature_X.copy()
    adjusted[points] = Xf
    info = BundleInfo(
        iterations=iterations, cost=cost, rms_px=_rms(r), obs=p.obs, points=p.points, n_intr=ni, residuals=r,
        weights=_weights(p, r), covariance=covariance, held_frame=int(joint.frames[joint.held]),
        correlation_time=tau, feature_X=adjusted, feature_obs=fp.obs, feature_points=points, feature_residuals=rf,
        feature_weights=features.weights(rf), feature_rms_px=_rms(rf),
    )
    return out, info


def _track_shares(fp: _FeatureProblem) -> np.ndarray:
    """Each feature observation's share of independent information in the covariance:
    one over its point's number of observations.

    A tracker's error in one frame is mostly still there in the next (the same patch,
    matched to a slowly moving template), so a track's views are far from independent
    measurements. Counted as independent, thousands of points pin the cameras as if their
    errors averaged out, and the cards' std_m come out five to seven times smaller than
    their errors (centre-loop walk). Counting each track once, spread over its views,
    keeps what the tracks determine (the geometry between the frames they span) and drops
    the averaging they cannot give.
    """
    return 1.0 / np.bincount(fp.op, minlength=len(fp.points))[fp.op]


def _feature_covariance(p: _Problem, fp: _FeatureProblem, joint: _Joint, sp: _SparsePattern | None,
                        intr: np.ndarray, cams: np.ndarray, X: np.ndarray, Xf: np.ndarray, r: np.ndarray,
                        rf: np.ndarray) -> np.ndarray:
    """Marginal covariance of [intrinsics, disc points] with feature points: the cameras
    and feature points eliminated from the undamped system, each track's views counted
    as one observation's worth (`_track_shares`); the noise level from every residual at
    its full weight."""
    n_y = joint.n_y
    share = _track_shares(fp)
    S: np.ndarray | None = None
    if sp is not None:
        try:
            S = _sparse_covariance_system(fp, sp, _sparse_system(p, fp, joint, sp, intr, cams, X, Xf, r, rf, share))
        except np.linalg.LinAlgError:  # a camera left free in some direction: the dense pseudo-inverse below
            S = None
    if S is None:
        fs = _feature_system(p, fp, joint, intr, cams, X, Xf, r, rf, share)
        H, _, _ = _feature_reduced(p, fp, joint, fs)
        H_yc, H_cc = H[:n_y, n_y:], H[n_y:, n_y:]
        try:
            S = H[:n_y, :n_y] - H_yc @ cho_solve(cho_factor(H_cc, check_finite=False), H_yc.T, check_finite=False)
        except np.linalg.LinAlgError:  # a camera the observations leave free in some direction
            S = H[:n_y, :n_y] - H_yc @ np.linalg.pinv(H_cc, rcond=1e-12, hermitian=True) @ H_yc.T
    n_obs = len(p.obs) + len(fp.obs)
    dof = max(2 * n_obs - 6 * len(joint.frames) - p.n_y - 3 * len(fp.points) + 6, 1)
    chi2 = float((_weights(p, r)[:, None] * r**2).sum() + (fp.features.weights(rf)[:, None] * rf**2).sum())
    return np.linalg.pinv(S, rcond=1e-12, hermitian=True) * (chi2 / dof)


def _fit_the_other_frames(rec: Reconstruction, info: BundleInfo, p: _Problem, features: FeatureObservations,
                          obs: np.ndarray, points: np.ndarray, others: np.ndarray) -> tuple[Reconstruction, BundleInfo]:
    """After an adjustment over keyframes: each other frame's pose fitted to the adjusted
    map (discs and feature points held), then each feature point that was not adjusted
    fitted to the poses; the info over every observation (the covariance is the
    keyframes' adjustment's)."""
    assert info.feature_X is not None
    Xf = info.feature_X.copy()
    adjusted = np.zeros(len(Xf), bool)
    adjusted[info.feature_points] = True
    cam = rec.camera
    # Each frame's observations of either kind (both sorted by frame).
    d_slice = dict(zip(p.frames.tolist(), p.slices, strict=True))
    held = obs[adjusted[features.track[obs]]]
    f_bounds = np.searchsorted(features.frame[held], np.r_[others, others + 1].reshape(2, -1))
    for f, b, e in zip(others.tolist(), *f_bounds, strict=True):
        if f == info.held_frame:  # the gauge
            continue
        d = np.arange(len(p.obs))[d_slice.get(f, slice(0, 0))]
        k = held[b:e]
        rec.rvec[f], rec.tvec[f] = _fit_pose(cam, rec.rvec[f], rec.tvec[f], rec.X[p.points[p.op[d]]], p.uv[d],
                                             p.precision[d], p.loss_scale, Xf[features.track[k]], features.uv[k],
                                             features)
    rest = np.setdiff1d(points, info.feature_points)
    if len(rest):
        Xf[rest] = _fit_points(cam, rec, features, obs[np.isin(features.track[obs], rest)], Xf, rest)
    joint = _joint(p, features, obs)
    fp = _feature_structure(features, obs, points, joint)
    cams = np.c_[rec.rvec[joint.frames], rec.tvec[joint.frames]]
    X = rec.X[p.points]
    r = _residuals(p, cam, cams[joint.dmap], X)
    rf = _feature_residuals(fp, cam, cams, Xf[points])
    cost = _robust_cost(p, r, _prior_residuals(p, X)) + float(features.cost(rf).sum())
    out = BundleInfo(
        iterations=info.iterations, cost=cost, rms_px=_rms(r), obs=p.obs, points=p.points, n_intr=info.n_intr,
        residuals=r, weights=_weights(p, r), covariance=info.covariance, held_frame=info.held_frame,
        correlation_time=info.correlation_time, feature_X=Xf, feature_obs=fp.obs, feature_points=points,
        feature_residuals=rf, feature_weights=features.weights(rf), feature_rms_px=_rms(rf),
    )
    return rec, out


def _fit_pose(cam: Camera, rvec: np.ndarray, tvec: np.ndarray, X: np.ndarray, uv: np.ndarray, precision: np.ndarray,
              loss_scale: float, Xf: np.ndarray, uvf: np.ndarray, features: FeatureObservations,
              max_iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """One frame's pose fitted to held points: Levenberg-Marquardt over its 6 parameters,
    the discs' observations weighted as in the adjustment, the feature points' by their
    own loss."""
    root = np.sqrt(precision)
    pts = np.r_[X, Xf]
    target = np.r_[uv, uvf]
    n_d = len(X)
    if len(pts) < 3:
        return rvec, tvec

    def residuals(x: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        proj, jac = project_frame(cam, x[:3], x[3:], pts, jacobian)
        return proj - target, None if jac is None else jac[:, :6]

    def cost(rr: np.ndarray) -> float:
        e = np.linalg.norm(rr[:n_d], axis=1) * root
        c = np.where(e <= loss_scale, 0.5 * e**2, loss_scale * (e - 0.5 * loss_scale))
        return float(c.sum() + features.cost(rr[n_d:]).sum())

    x = np.r_[rvec, tvec]
    rr, J = residuals(x, True)
    c0 = cost(rr)
    lam = 1e-4
    for _ in range(max_iterations):
        e = np.linalg.norm(rr[:n_d], axis=1) * root
        w = np.r_[precision * np.where(e <= loss_scale, 1.0, loss_scale / np.maximum(e, 1e-300)),
                  features.weights(rr[n_d:])]
        assert J is not None
        sw = np.repeat(w, 2)[:, None]
        A, b = (J * sw).T @ J, (J * sw).T @ rr.ravel()
        for _ in range(8):
            try:
                dx = -np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), b)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            r_new, _ = residuals(x + dx, False)
            c_new = cost(r_new)
            if c_new < c0:
                break
            lam *= 10
        else:
            break
        gain = c0 - c_new
        x = x + dx
        rr, J = residuals(x, True)
        c0 = c_new
        lam = max(lam / 10, 1e-12)
        if gain < 1e-6 * max(c0, 1e-12):
            break
    return x[:3], x[3:]


def _fit_points(cam: Camera, rec: Reconstruction, features: FeatureObservations, obs: np.ndarray, Xf: np.ndarray,
                points: np.ndarray, iterations: int = 5) -> np.ndarray:
    """Feature points ``points`` fitted to the poses of their observations ``obs``
    (Gauss-Newton with the features' loss, each point's step kept only where it lowers
    that point's cost)."""
    obs = obs[np.argsort(features.frame[obs], kind="stable")]
    frames = np.unique(features.frame[obs])
    cam_of = np.searchsorted(frames, features.frame[obs])
    op = np.searchsorted(points, features.track[obs])
    X = Xf[points].copy()
    starts = np.r_[0, np.flatnonzero(np.diff(cam_of)) + 1]
    ends = np.r_[starts[1:], len(obs)]

    def project(X: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray]:
        r = np.empty((len(obs), 2))
        J = np.empty((len(obs), 2, 3))
        for b, e in zip(starts, ends, strict=True):
            f = frames[cam_of[b]]
            proj, jac = project_frame(cam, rec.rvec[f], rec.tvec[f], X[op[b:e]], jacobian)
            r[b:e] = proj
            if jac is not None:
                R, _ = cv2.Rodrigues(rec.rvec[f])
                J[b:e] = jac.reshape(e - b, 2, -1)[:, :, 3:6] @ R
        return r - features.uv[obs], J

    def point_cost(r: np.ndarray) -> np.ndarray:
        return np.bincount(op, features.cost(r), minlength=len(points))

    r, J = project(X, True)
    c = point_cost(r)
    for _ in range(iterations):
        w = features.weights(r)
        W = np.zeros((len(points), 3, 3))
        g = np.zeros((len(points), 3))
        np.add.at(W, op, w[:, None, None] * np.einsum("kis,kit->kst", J, J))
        np.add.at(g, op, w[:, None] * np.einsum("kis,ki->ks", J, r))
        step = -(np.linalg.pinv(W, hermitian=True) @ g[:, :, None])[:, :, 0]
        r_new, _ = project(X + step, False)
        c_new = point_cost(r_new)
        better = c_new < c
        if not better.any():
            break
        X[better] += step[better]
        r, J = project(X, True)
        c = point_cost(r)
    return X


def _rms(r: np.ndarray) -> float:
    """2D RMS of residuals (N, 2), px; nan for none."""
    return float(np.sqrt((r**2).sum(axis=1).mean())) if len(r) else float("nan")


def bundle_adjust(
    rec: Reconstruction,
    tracks: Tracks,
    use: np.ndarray,
    free_intrinsics: bool,
    card_prior: tuple[float, float] | None = None,
    loss_scale: float = GROWTH_LOSS_SCALE,
    max_iterations: int = 100,
    with_covariance: bool = False,
    features: FeatureObservations | None = None,
    feature_X: np.ndarray | None = None,
    feature_use: np.ndarray | None = None,
    tolerance: float = 1e-12,
    solver: ReducedSolver = ReducedSolver.SPARSE,
    keyframes: FeatureKeyframes | None = None,
) -> tuple[Reconstruction, BundleInfo]:
    """Robust sparse bundle adjustment (Levenberg-Marquardt, cameras eliminated).

    Adjusts [f, cx, cy, k1, k2] when ``free_intrinsics``, the pose (rvec, t) of every
    frame with an observation but one (the best-seen frame is held: it fixes the gauge),
    and the 3D point of every disc with an observation.

    With feature points (a second kind of track: ``features`` and their points
    ``feature_X``), the frames they are seen in and every feature point seen in two of
    them at least are adjusted too, each observation weighted by the features' own
    noise level and robust loss; the feature points are then eliminated instead of the
    cameras. Without any that take part, the result is that of the discs alone, to the
    bit.

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
    tolerance : float
        Stop when an iteration lowers the cost by less than this fraction of it (the
        default: when it gains nothing within rounding).
    with_covariance : bool
        Also compute the marginal covariance of the intrinsics and points.
    features : FeatureObservations, optional
        Observations of feature points, with their noise level and robust loss.
    feature_X : (P, 3) ndarray, optional
        The feature points at the start (nan: not triangulated); needed with
        ``features``, not changed.
    feature_use : (len(features),) ndarray of bool, optional
        The feature observations to use (default: all; those of unregistered frames or
        nan points are left out anyway).
    solver : ReducedSolver
        How the reduced system is solved with feature points (the same step within
        rounding; dense: the reference, cubic in the frames).
    keyframes : FeatureKeyframes, optional
        (Default: ``FeatureKeyframes()``.) The frames whose feature observations are adjusted jointly; the other frames'
        poses are then fitted to the adjusted map (their discs' observations take part
        in the joint adjustment all the same), and feature points seen in fewer than two
        keyframes to the adjusted poses.

    Returns
    -------
    rec : Reconstruction
        The adjusted reconstruction (a new one).
    info : BundleInfo
        Iterations, cost, residuals, weights and covariance at the end; the adjusted
        feature points in ``info.feature_X``.
    """
    p = _problem(rec, tracks, use, free_intrinsics, card_prior, loss_scale)
    if features is not None:
        if feature_X is None:
            raise ValueError("feature observations need their points, feature_X")
        f_obs, f_points = _feature_problem(rec, features, feature_X, feature_use)
        seen = np.unique(features.frame[f_obs])
        key = (keyframes or FeatureKeyframes())(seen)
        if len(f_obs) and not key.all():
            k_use = np.zeros(len(features), bool)
            k_use[f_obs] = np.isin(features.frame[f_obs], seen[key])
            k_obs, k_points = _feature_problem(rec, features, feature_X, k_use)
            if len(k_obs):
                out, info = _adjust_with_features(rec, p, features, feature_X, k_obs, k_points, max_iterations,
                                                  tolerance, with_covariance, solver)
                return _fit_the_other_frames(out, info, p, features, f_obs, f_points, seen[~key])
        if len(f_obs):
            return _adjust_with_features(rec, p, features, feature_X, f_obs, f_points, max_iterations, tolerance,
                                         with_covariance, solver)
    if not len(p.obs):  # nothing to adjust: every view set aside, or nothing registered and placed
        return (Reconstruction(rec.camera, rec.rvec.copy(), rec.tvec.copy(), rec.X.copy()),
                BundleInfo(iterations=0, cost=0.0, rms_px=float("nan"), obs=p.obs, points=p.points, n_intr=p.n_intr,
                           residuals=np.zeros((0, 2)), weights=np.zeros(0), covariance=None, held_frame=-1,
                           feature_X=None if feature_X is None else feature_X.copy()))
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
        if gain < tolerance * max(cost, 1e-12) or step < 1e-12:
            break
    covariance, tau = None, 1.0
    if with_covariance and len(p.points):
        # Marginal covariance of intrinsics + points: inverse of the undamped reduced
        # system; a pseudo-inverse drops what the gauge leaves free (scale w/o prior).
        ne = _normal_equations(p, intr, cams, X, r)
        S, _, _ = _schur(p, ne, 0.0)
        dof = max(2 * len(p.obs) - len(cams) * 6 - p.n_y + 6, 1)
        w = _weights(p, r)
        sigma2 = float((w[:, None] * r**2).sum() / dof)
        tau = _disc_correlation_time(p, r)
        # ... and the observations' correlation in time.
        covariance = np.linalg.pinv(S, rcond=1e-12, hermitian=True) * (sigma2 * tau)
    out = Reconstruction(_camera_of(p, intr), rec.rvec.copy(), rec.tvec.copy(), rec.X.copy())
    out.rvec[p.frames], out.tvec[p.frames] = cams[:, :3], cams[:, 3:]
    out.X[p.points] = X
    info = BundleInfo(
        iterations=iterations, cost=cost, rms_px=float(np.sqrt((r**2).sum(axis=1).mean())), obs=p.obs,
        points=p.points, n_intr=p.n_intr, residuals=r, weights=_weights(p, r), covariance=covariance,
        correlation_time=tau,
        held_frame=int(p.frames[p.held]), feature_X=None if feature_X is None else feature_X.copy(),
    )
    return out, info
