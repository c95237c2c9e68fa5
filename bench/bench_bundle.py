"""The survey's bundle adjustment with natural-feature points, side by side with Ceres.

One problem per feature count (``--features``): the survey bench's room (an 8 x 6 x 3 m
room with 30 cards of 0.2 m, `app.sim.examples.BENCH_ROOM`, seed ``--seed``) and its
calibration walk of ``--frames`` frames at 640x480 (f 820 px, k1 -0.12). Everything
observed comes from the simulator's geometry, never from the code under test:

- disc observations: the true projection of every disc of every card seen whole,
  facing the camera by more than 0.3 and with discs over 4 px across (bench_survey's
  ideal detector), moved by Gaussian noise of the disc's own expected error
  (`disc_precision`, 0.005-0.03 px);
- feature points: points drawn uniformly on the four walls, each tracked as a tracker
  would, through a run of 3-8 consecutive frames that see it (in front, in the lens's
  field, 2 px inside the image, on a wall facing the camera by more than 0.2), and with
  probability 0.3 once more on a later return to its wall (a keyframe match: a loop
  closed); kept when its views are 2 degrees apart at least (as a triangulator would
  keep it); the true projection plus 0.5 px of Gaussian noise per axis, and 1 % of the
  observations grossly wrong (moved 10-50 px: wrong matches).

Both engines solve the same problem from the same start: the intrinsics (f, cx, cy, k1,
k2) free, every pose but the best-seen frame's, every disc and every feature point; each
disc observation weighted by its precision with Huber's loss at 2.5 expected errors, the
printed-card prior (10 um); each feature observation weighted by 1 / 0.5 px^2 with
Cauchy's loss at 2.5 sigmas (Huber's lets a wrong match on a short track drag its point
metres along the ray, slowly, in both engines alike). The start is the truth disturbed:
f +1 %, principal point (+2, -2) px, k1 +0.01, poses by 0.005 rad and 2 cm, discs by
5 mm, feature points by 5 cm (per axis, Gaussian).

- ``fidotrack``: `bundle_adjust`, the hand-written Levenberg-Marquardt (cameras
  eliminated for the discs alone, feature points eliminated with them);
- ``Ceres``: Ceres Solver through ``pyceres``, with COLMAP's compiled reprojection cost
  (``pycolmap``: the RADIAL camera, f cx cy k1 k2, is this lens model; the pose as a
  quaternion and a translation), each observation whitened by its covariance; the card
  prior as a Python cost function (one residual a disc pair); Levenberg-Marquardt,
  SPARSE_SCHUR (``--ceres-linear-solver``);
- ``Ceres, Python costs`` (``--python-ceres-max`` feature points at most; slow): Ceres
  through ``pyceres`` alone, every reprojection error a Python cost function (OpenCV's
  projection and Jacobian, the pose as a rotation vector, as fidotrack's).

Each engine runs with two stopping rules: ``converged`` (fidotrack's default: until an
iteration lowers the cost by less than 1e-12 of it; Ceres with the same function
tolerance) and ``tolerance 1e-6`` (Ceres's default function tolerance; fidotrack's
``tolerance=1e-6``). Each is timed from the start state to the adjusted one on one
thread (BLAS, OpenCV, Ceres), after a warm-up (numba's kernels compiled or loaded), the
fastest of ``--repeats`` runs: CPU time (the machine is shared, and one thread's CPU
time is its wall time on an idle machine) and wall time; Ceres's includes setting its
problem up. Errors are against the simulator's truth, in the gauge both fix (the held
frame at its true pose, the scale from the card prior): camera positions and rotations,
discs, feature points.

Run: ``.venv/bin/python bench/bench_bundle.py [--frames 300] [--features 0 1000 5000 20000]``
(markdown tables). Needs ``pip install pyceres pycolmap`` for the Ceres columns; without
them only fidotrack's are printed.
"""

from __future__ import annotations

import argparse
import copy
import ctypes
import dataclasses
import time
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

from app.core.detection import DetectedTarget
from app.core.geometry import Camera, Pose
from app.core.survey import Reconstruction, bundle_adjust
from app.core.survey._bundle_kernels import warm_up
from app.core.survey.bundle import ReducedSolver, camera_from_intrinsics
from app.core.survey.cards import PAIR_UNITS, PAIRS
from app.core.survey.points import FeatureObservations, RobustLoss
from app.core.survey.policy import FeatureKeyframes
from app.core.survey.state import Tracks
from app.core.survey.tracks import collect_tracks
from app.sim import BENCH_CAMERA, BENCH_ROOM, frame_truth

CARD_M = 0.2
PRIOR = (CARD_M, 1e-5)  # the printed card, 10 um
LOSS_SCALE = 2.5  # Huber's, in expected errors, on both kinds of track
FEATURE_SIGMA_PX = 0.5
OUTLIER_FRACTION = 0.01
#: A track's widest angle between viewing rays at least: a triangulator hands the bundle
#: adjustment no point with less (its depth would be nearly free), as the survey places
#: no card from less than `place.MIN_BASELINE_DEG`.
MIN_PARALLAX_DEG = 2.0
MAX_ITERATIONS = 100
#: The stopping rules both engines are run with: fidotrack's default (until an iteration
#: gains nothing within rounding) and Ceres's default function tolerance.
CONVERGED_TOLERANCE = 1e-12
CERES_TOLERANCE = 1e-6
FEATURE_LOSS = RobustLoss.CAUCHY


@dataclass(frozen=True, eq=False)
class Problem:
    """One bundle adjustment: the observations, the truth and the start."""

    tracks: Tracks
    features: FeatureObservations | None
    outlier: np.ndarray  # (K,) which feature observations are wrong matches
    truth: Reconstruction
    feature_truth: np.ndarray  # (P, 3)
    start: Reconstruction
    feature_start: np.ndarray  # (P, 3)
    held: int


@dataclass(frozen=True, eq=False)
class Solution:
    """An engine's result: the adjusted map and poses, and what it took."""

    engine: str
    camera: Camera
    rvec: np.ndarray  # (F, 3) nan where not adjusted
    tvec: np.ndarray
    X: np.ndarray  # (4T, 3)
    feature_X: np.ndarray  # (P, 3)
    iterations: int
    seconds: float  # wall time
    cpu_seconds: float  # the process's CPU time (one thread: the wall time of an idle machine)
    build_seconds: float = 0.0  # of which setting the problem up (Ceres: its residual blocks), wall
    converged: bool = False  # run until a step gains nothing, else to Ceres's default function tolerance


# --- the problem, from the simulator's geometry ---------------------------------------


def _wall_points(rng: np.random.Generator, size: tuple[float, float, float], n: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """n points uniform on the four side walls (10 cm from floor and ceiling) and each
    one's wall normal (into the room)."""
    w, d, h = size
    lengths = np.array([w, w, d, d])
    wall = rng.choice(4, n, p=lengths / lengths.sum())
    along = rng.uniform(0, 1, n) * lengths[wall]
    z = rng.uniform(0.1, h - 0.1, n)
    x = np.select([wall == 0, wall == 1, wall == 2], [along, along, np.zeros(n)], np.full(n, w))
    y = np.select([wall == 0, wall == 1, wall == 2], [np.zeros(n), np.full(n, d), along], along)
    normals = np.array([[0, 1, 0], [0, -1, 0], [1, 0, 0], [-1, 0, 0]], float)[wall]
    return np.c_[x, y, z], normals


def _seen(camera: Camera, poses: list[Pose], P: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, N) whether each frame sees each point, and (F, N, 2) where (px)."""
    seen = np.zeros((len(poses), len(P)), bool)
    uv = np.full((len(poses), len(P), 2), np.nan)
    for f, pose in enumerate(poses):
        cam = pose.transform(P)
        to_camera = pose.position - P
        facing = (normals * to_camera).sum(axis=1) / np.linalg.norm(to_camera, axis=1) > 0.2
        ok = camera.in_field(cam) & facing
        proj, _ = cv2.projectPoints(P[ok].reshape(-1, 1, 3), pose.rvec, pose.t, camera.K, camera.dist)
        proj = proj.reshape(-1, 2)
        inside = ((proj >= 2) & (proj <= [camera.width - 3, camera.height - 3])).all(axis=1)
        idx = np.flatnonzero(ok)[inside]
        seen[f, idx] = True
        uv[f, idx] = proj[inside]
    return seen, uv


def _track(rng: np.random.Generator, frames: np.ndarray) -> np.ndarray:
    """The frames a tracker follows a point through, of the frames that see it: a run of
    3-8 consecutive ones, and with probability 0.3 a second run on a later return."""
    runs = np.split(frames, np.flatnonzero(np.diff(frames) > 1) + 1)
    runs = [r for r in runs if len(r) >= 2]
    if not runs:
        return np.zeros(0, int)
    first = int(rng.integers(len(runs)))
    picked = []
    for k in [first] + ([int(rng.integers(first + 1, len(runs)))] if first + 1 < len(runs) and rng.random() < 0.3
                        else []):
        run = runs[k]
        n = min(len(run), int(rng.integers(3, 9)))
        s = int(rng.integers(0, len(run) - n + 1))
        picked.append(run[s : s + n])
    return np.concatenate(picked)


def _parallax_deg(point: np.ndarray, centres: np.ndarray) -> float:
    """The widest angle between the rays from camera centres to a point, degrees."""
    rays = point - centres
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    return float(np.degrees(np.arccos(np.clip((rays @ rays.T).min(), -1.0, 1.0))))


def make_problem(seed: int, n_frames: int, n_features: int) -> Problem:
    """The bench's problem for ``n_features`` feature points (see the module docstring).

    Parameters
    ----------
    seed : int
        The room, the walk, the noise and the start.
    n_frames : int
        Frames of the calibration walk.
    n_features : int
        Feature points (0: the discs alone).

    Returns
    -------
    Problem
        Observations, truth and start.
    """
    room = BENCH_ROOM.walk(seed, n_frames)
    camera = BENCH_CAMERA
    rng = np.random.default_rng([seed, 18])
    detections = []
    for pose in room.poses:
        truth = frame_truth(camera, pose, room.scene)
        detections.append([DetectedTarget(t.id, t.discs_px, 1.0) for t in truth.targets
                           if t.visible and t.facing_cos > 0.3 and t.disc_diameter_px > 4.0])
    tracks = collect_tracks(detections, list(range(n_frames)), [])
    tracks = dataclasses.replace(tracks, uv=tracks.uv + rng.normal(0, 1, tracks.uv.shape) * tracks.expected_px[:, None])
    true_discs = {t.id: t.discs for t in room.scene.targets}
    truth_rec = Reconstruction.empty(camera, n_frames, tracks.n_targets)
    for k, target_id in enumerate(tracks.ids):
        truth_rec.place(k, true_discs[int(target_id)])
    for f in np.unique(tracks.frame):
        truth_rec.set_pose(int(f), room.poses[f])

    features, outlier, P = None, np.zeros(0, bool), np.zeros((0, 3))
    if n_features:
        # Candidates, a batch at a time, until n_features points are tracked through two
        # frames at least.
        registered = truth_rec.registered()
        centres = np.array([pose.position for pose in room.poses])
        kept, rows = [], []
        while len(kept) < n_features:
            P, normals = _wall_points(rng, room.scene.room_size, 5000)
            seen, uv = _seen(camera, room.poses, P, normals)
            for j in range(len(P)):
                frames = _track(rng, np.flatnonzero(seen[:, j] & registered))
                if (len(frames) >= 2 and len(kept) < n_features
                        and _parallax_deg(P[j], centres[frames]) >= MIN_PARALLAX_DEG):
                    rows.append((frames, np.full(len(frames), len(kept)), uv[frames, j]))
                    kept.append(P[j])
        P = np.array(kept)
        frame = np.concatenate([r[0] for r in rows])
        track = np.concatenate([r[1] for r in rows])
        obs = np.concatenate([r[2] for r in rows]) + rng.normal(0, FEATURE_SIGMA_PX, (len(frame), 2))
        outlier = rng.random(len(frame)) < OUTLIER_FRACTION
        angle = rng.uniform(0, 2 * np.pi, int(outlier.sum()))
        obs[outlier] += rng.uniform(10, 50, len(angle))[:, None] * np.c_[np.cos(angle), np.sin(angle)]
        order = np.lexsort((track, frame))  # as a tracker hands them over: by frame, then track
        features = FeatureObservations(frame[order], track[order], obs[order], sigma_px=FEATURE_SIGMA_PX,
                                       loss=FEATURE_LOSS, loss_scale=LOSS_SCALE)
        outlier = outlier[order]

    use = np.ones(len(tracks.frame), bool)
    _, info = bundle_adjust(truth_rec, tracks, use, True, PRIOR, max_iterations=0)
    start = copy.deepcopy(truth_rec)
    cam = camera
    start.camera = camera_from_intrinsics(np.array([cam.fx * 1.01, cam.cx + 2, cam.cy - 2, cam.dist[0] + 0.01,
                                                    cam.dist[1]]), cam.width, cam.height)
    moved = start.registered()
    moved[info.held_frame] = False
    start.X += rng.normal(0, 0.005, start.X.shape)
    start.rvec[moved] += rng.normal(0, 0.005, (int(moved.sum()), 3))
    start.tvec[moved] += rng.normal(0, 0.02, (int(moved.sum()), 3))
    return Problem(tracks, features, outlier, truth_rec, P, start, P + rng.normal(0, 0.05, P.shape),
                   info.held_frame)


# --- the engines ----------------------------------------------------------------------


def solve_fidotrack(problem: Problem, converged: bool, solver: ReducedSolver = ReducedSolver.SPARSE) -> Solution:
    """`bundle_adjust` on the problem: until a step gains nothing (its default), or with
    Ceres's default function tolerance; every frame's feature observations adjusted
    jointly (no keyframes: the same problem Ceres solves), the reduced system solved by
    ``solver``."""
    use = np.ones(len(problem.tracks.frame), bool)
    start, cpu = time.perf_counter(), time.process_time()
    out, info = bundle_adjust(problem.start, problem.tracks, use, True, PRIOR, loss_scale=LOSS_SCALE,
                              max_iterations=MAX_ITERATIONS, features=problem.features,
                              feature_X=problem.feature_start if problem.features is not None else None,
                              tolerance=CONVERGED_TOLERANCE if converged else CERES_TOLERANCE, solver=solver,
                              keyframes=FeatureKeyframes(None))
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
    feature_X = info.feature_X if info.feature_X is not None else np.zeros((0, 3))
    return Solution("fidotrack", out.camera, out.rvec, out.tvec, out.X, feature_X, info.iterations, seconds, cpu,
                    converged=converged)


def _ceres_modules():  # type: ignore[no-untyped-def]
    """pyceres and pycolmap (with its cost functions), or None when not installed."""
    try:
        import pyceres
        import pycolmap
        import pycolmap.cost_functions
    except ImportError:
        return None
    return pyceres, pycolmap


_KEEP_ALIVE: list[object] = []


def _pose_manifold(pyceres, pycolmap):  # type: ignore[no-untyped-def]
    """The manifold of a COLMAP pose block [qx, qy, qz, qw, tx, ty, tz]: a unit quaternion
    times R^3. pyceres 2.6 does not bind Ceres's ProductManifold, so it is taken from a
    bundle adjuster pycolmap sets up on a two-frame reconstruction. The pointer it hands
    out is owned by that adjuster's problem and by the Python object both: both are kept
    alive for the process's life (never freed), else it would be freed twice."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="RADIAL", width=640, height=480,
                                                    params=[800.0, 320.0, 240.0, 0.0, 0.0], camera_id=1))
    for i in range(2):
        image = pycolmap.Image(name=str(i), keypoints=np.array([[300.0, 200.0], [310.0, 220.0], [330.0, 250.0]]),
                               camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0, 0, 0, 1.0])),
                                                                 np.array([0.1 * i, 0, 0])))
    for j in range(3):
        point = rec.add_point3D(np.array([0.1 * j, 0.05, 3.0]), pycolmap.Track())
        for i in range(2):
            rec.add_observation(point, pycolmap.TrackElement(i + 1, j))
    config = pycolmap.BundleAdjustmentConfig()
    for i in range(2):
        config.add_image(i + 1)
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(pycolmap.BundleAdjustmentOptions(), config, rec)
    manifold = adjuster.problem.get_manifold(rec.frame(2).rig_from_world.params)
    for o in (rec, adjuster, manifold):
        _KEEP_ALIVE.append(o)
        ctypes.pythonapi.Py_IncRef(ctypes.py_object(o))
    return manifold


def _card_prior_cost(pyceres):  # type: ignore[no-untyped-def]
    class CardPriorCost(pyceres.CostFunction):
        """One disc pair's distance off its printed one, in sigmas (fidotrack's card prior)."""

        def __init__(self, length: float, sigma: float) -> None:
            super().__init__()
            self.set_num_residuals(1)
            self.set_parameter_block_sizes([3, 3])
            self.length, self.sigma = length, sigma

        def Evaluate(self, parameters, residuals, jacobians):  # type: ignore[no-untyped-def]
            d = parameters[0] - parameters[1]
            n = float(np.linalg.norm(d))
            residuals[0] = (n - self.length) / self.sigma
            if jacobians is not None:
                u = d / (n * self.sigma)
                jacobians[0][:] = u
                jacobians[1][:] = -u
            return True

    return CardPriorCost


def _python_reprojection_costs(pyceres):  # type: ignore[no-untyped-def]
    def project(X, rvec, t, intr):  # type: ignore[no-untyped-def]
        K = np.array([[intr[0], 0, intr[1]], [0, intr[0], intr[2]], [0, 0, 1.0]])
        uv, jac = cv2.projectPoints(X.reshape(1, 1, 3), rvec, t, K, np.array([intr[3], intr[4], 0, 0, 0]))
        return uv.ravel(), jac

    def intrinsics_jacobian(J):  # type: ignore[no-untyped-def]
        return np.c_[J[:, 6] + J[:, 7], J[:, 8:10], J[:, 10:12]]

    class ReprojectionCost(pyceres.CostFunction):
        """A whitened reprojection error over [X, rvec, t, f cx cy k1 k2]."""

        def __init__(self, uv: np.ndarray, root_precision: float) -> None:
            super().__init__()
            self.set_num_residuals(2)
            self.set_parameter_block_sizes([3, 3, 3, 5])
            self.uv, self.s = uv, root_precision

        def Evaluate(self, parameters, residuals, jacobians):  # type: ignore[no-untyped-def]
            X, rvec, t, intr = parameters
            uv, jac = project(X, rvec, t, intr)
            residuals[:] = (uv - self.uv) * self.s
            if jacobians is not None:
                J = jac * self.s
                jacobians[0][:] = (J[:, 3:6] @ cv2.Rodrigues(rvec)[0]).ravel()
                jacobians[1][:] = J[:, 0:3].ravel()
                jacobians[2][:] = J[:, 3:6].ravel()
                jacobians[3][:] = intrinsics_jacobian(J).ravel()
            return True

    class HeldFrameCost(pyceres.CostFunction):
        """The same for the held frame (its pose a constant: Ceres hands a Python cost
        no Jacobian buffer for a constant block)."""

        def __init__(self, uv: np.ndarray, root_precision: float, rvec: np.ndarray, t: np.ndarray) -> None:
            super().__init__()
            self.set_num_residuals(2)
            self.set_parameter_block_sizes([3, 5])
            self.uv, self.s, self.rvec, self.t = uv, root_precision, rvec, t

        def Evaluate(self, parameters, residuals, jacobians):  # type: ignore[no-untyped-def]
            X, intr = parameters
            uv, jac = project(X, self.rvec, self.t, intr)
            residuals[:] = (uv - self.uv) * self.s
            if jacobians is not None:
                J = jac * self.s
                jacobians[0][:] = (J[:, 3:6] @ cv2.Rodrigues(self.rvec)[0]).ravel()
                jacobians[1][:] = intrinsics_jacobian(J).ravel()
            return True

    return ReprojectionCost, HeldFrameCost


def solve_ceres(problem: Problem, modules, python_costs: bool, converged: bool,  # type: ignore[no-untyped-def]
                linear_solver: str = "SPARSE_SCHUR") -> Solution:
    """Ceres on the problem: compiled (pycolmap) or Python reprojection costs; with its
    default tolerances, or ``converged`` (as fidotrack's: until a step gains nothing)."""
    pyceres, pycolmap = modules
    start_clock, cpu = time.perf_counter(), time.process_time()
    rec, tracks = problem.start, problem.tracks
    intr = np.array([rec.camera.fx, rec.camera.cx, rec.camera.cy, rec.camera.dist[0], rec.camera.dist[1]])
    frames = np.flatnonzero(rec.registered())
    if python_costs:
        rvecs = {int(f): rec.rvec[f].copy() for f in frames}
        tvecs = {int(f): rec.tvec[f].copy() for f in frames}
        ReprojectionCost, HeldFrameCost = _python_reprojection_costs(pyceres)
    else:
        poses = {int(f): np.r_[Rotation.from_rotvec(rec.rvec[f]).as_quat(), rec.tvec[f]] for f in frames}
        manifold = _pose_manifold(pyceres, pycolmap)
        model = pycolmap.CameraModelId.RADIAL
    discs = {int(i): rec.X[i].copy() for i in np.unique(tracks.point)}
    feature_X = problem.feature_start.copy()
    points = {j: feature_X[j].copy() for j in range(len(feature_X))}
    held = problem.held
    ceres_problem = pyceres.Problem()
    disc_loss = pyceres.HuberLoss(LOSS_SCALE)
    feature_loss = (pyceres.CauchyLoss if FEATURE_LOSS is RobustLoss.CAUCHY else pyceres.HuberLoss)(LOSS_SCALE)

    def add(uv: np.ndarray, precision: float, X: np.ndarray, f: int, loss: object) -> None:
        if python_costs:
            if f == held:
                cost = HeldFrameCost(uv, np.sqrt(precision), rvecs[f], tvecs[f])
                ceres_problem.add_residual_block(cost, loss, [X, intr])
            else:
                ceres_problem.add_residual_block(ReprojectionCost(uv, np.sqrt(precision)), loss,
                                                 [X, rvecs[f], tvecs[f], intr])
        else:
            cost = pycolmap.cost_functions.ReprojErrorCost(model, np.eye(2) / precision, uv)
            ceres_problem.add_residual_block(cost, loss, [X, poses[f], intr])

    for i in range(len(tracks.frame)):
        add(tracks.uv[i], float(tracks.precision[i]), discs[int(tracks.point[i])], int(tracks.frame[i]), disc_loss)
    if problem.features is not None:
        fo = problem.features
        for k in range(len(fo)):
            add(fo.uv[k], 1.0 / fo.sigma_px**2, points[int(fo.track[k])], int(fo.frame[k]), feature_loss)
    CardPriorCost = _card_prior_cost(pyceres)
    for t in range(tracks.n_targets):
        for (a, b), units in zip(PAIRS, PAIR_UNITS, strict=True):
            ceres_problem.add_residual_block(CardPriorCost(units * PRIOR[0], PRIOR[1]), None,
                                             [discs[4 * t + a], discs[4 * t + b]])
    if not python_costs:
        for f, pose in poses.items():
            ceres_problem.set_manifold(pose, manifold)
        ceres_problem.set_parameter_block_constant(poses[held])
    options = pyceres.SolverOptions()
    options.linear_solver_type = getattr(pyceres.LinearSolverType, linear_solver)
    options.num_threads = 1
    options.max_num_iterations = MAX_ITERATIONS
    options.logging_type = pyceres.LoggingType.SILENT
    options.function_tolerance = CONVERGED_TOLERANCE if converged else CERES_TOLERANCE
    if converged:
        options.parameter_tolerance = 1e-12
        options.gradient_tolerance = 1e-16
    summary = pyceres.SolverSummary()
    build = time.perf_counter() - start_clock
    pyceres.solve(options, ceres_problem, summary)
    seconds, cpu = time.perf_counter() - start_clock, time.process_time() - cpu

    rvec, tvec = np.full_like(rec.rvec, np.nan), np.full_like(rec.tvec, np.nan)
    for f in frames:
        if python_costs:
            rvec[f], tvec[f] = rvecs[int(f)], tvecs[int(f)]
        else:
            rvec[f], tvec[f] = Rotation.from_quat(poses[int(f)][:4]).as_rotvec(), poses[int(f)][4:]
    X = rec.X.copy()
    for i, x in discs.items():
        X[i] = x
    for j, x in points.items():
        feature_X[j] = x
    camera = camera_from_intrinsics(intr, rec.camera.width, rec.camera.height)
    iterations = summary.num_successful_steps + summary.num_unsuccessful_steps
    name = "Ceres, Python costs" if python_costs else "Ceres"
    return Solution(name, camera, rvec, tvec, X, feature_X, iterations, seconds, cpu, build, converged)


# --- measuring ------------------------------------------------------------------------


@dataclass(frozen=True)
class Scores:
    """An engine's solution scored against the truth and the objective."""

    cost: float  # the robust cost both engines minimise
    disc_rms_px: float
    feature_rms_px: float  # over the feature observations but the wrong matches
    position_mm: float  # camera positions, RMS
    rotation_deg: float  # RMS
    disc_mm: float  # RMS
    feature_mm: float  # median
    focal_pct: float


def score(problem: Problem, s: Solution) -> Scores:
    """Score a solution: the same objective, residuals and errors for every engine.

    Parameters
    ----------
    problem : Problem
        The problem solved.
    s : Solution
        An engine's result.

    Returns
    -------
    Scores
        Cost, reprojection RMS and errors against the truth.
    """
    rec = Reconstruction(s.camera, s.rvec, s.tvec, s.X)
    use = np.ones(len(problem.tracks.frame), bool)
    _, info = bundle_adjust(rec, problem.tracks, use, True, PRIOR, loss_scale=LOSS_SCALE, max_iterations=0,
                            features=problem.features,
                            feature_X=s.feature_X if problem.features is not None else None)
    truth = problem.truth
    frames = np.flatnonzero(truth.registered())
    pos = np.array([rec.pose(f).position - truth.pose(f).position for f in frames])
    rot = np.array([np.linalg.norm(Rotation.from_matrix(rec.pose(f).R @ truth.pose(f).R.T).as_rotvec())
                    for f in frames])
    seen = np.isfinite(truth.X[:, 0])
    feature_mm, feature_rms = float("nan"), float("nan")
    if problem.features is not None:
        feature_mm = 1000 * float(np.median(np.linalg.norm(s.feature_X - problem.feature_truth, axis=1)))
        good = ~problem.outlier[info.feature_obs]
        feature_rms = float(np.sqrt((info.feature_residuals[good] ** 2).sum(axis=1).mean()))
    return Scores(
        cost=info.cost, disc_rms_px=info.rms_px, feature_rms_px=feature_rms,
        position_mm=1000 * float(np.sqrt((pos**2).sum(axis=1).mean())),
        rotation_deg=float(np.degrees(np.sqrt((rot**2).mean()))),
        disc_mm=1000 * float(np.sqrt(((s.X[seen] - truth.X[seen]) ** 2).sum(axis=1).mean())),
        feature_mm=feature_mm, focal_pct=100 * (s.camera.fx / truth.camera.fx - 1),
    )


def _fastest(repeats: int, solve, *args) -> Solution:  # type: ignore[no-untyped-def]
    """The run of least CPU time of ``repeats`` (the machine is shared: its speed varies)."""
    return min((solve(*args) for _ in range(repeats)), key=lambda s: s.cpu_seconds)


def _fmt(x: float, digits: int) -> str:
    return "-" if not np.isfinite(x) else f"{x:.{digits}f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=300, help="calibration walk length")
    parser.add_argument("--features", type=int, nargs="+", default=[0, 1000, 5000, 20000])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--python-ceres-max", type=int, default=5000,
                        help="Ceres with Python costs only up to this many feature points (-1: never)")
    parser.add_argument("--repeats", type=int, default=2, help="runs of each compiled engine: the fastest counts")
    parser.add_argument("--stops", nargs="+", choices=["converged", "tolerance"], default=["converged", "tolerance"],
                        help="the stopping rules to run: until converged, and at Ceres's default tolerance")
    parser.add_argument("--ceres-linear-solver", default="SPARSE_SCHUR",
                        help="Ceres's linear solver (DENSE_SCHUR and ITERATIVE_SCHUR are slower here)")
    parser.add_argument("--solver", choices=[s.value for s in ReducedSolver], default=ReducedSolver.SPARSE.value,
                        help="fidotrack's factorisation of the reduced system with feature points")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    modules = _ceres_modules()
    warm_up()
    rows = []
    with threadpool_limits(1):
        for n in args.features:
            problem = make_problem(args.seed, args.frames, n)
            solutions = []
            for converged in [rule == "converged" for rule in args.stops]:
                solutions.append(_fastest(args.repeats, solve_fidotrack, problem, converged,
                                          ReducedSolver(args.solver)))
                if modules is not None:
                    solutions.append(_fastest(args.repeats, solve_ceres, problem, modules, False, converged,
                                              args.ceres_linear_solver))
                    if not converged and n <= args.python_ceres_max:
                        solutions.append(solve_ceres(problem, modules, True, False, args.ceres_linear_solver))
            n_obs = len(problem.features) if problem.features is not None else 0
            rows.append((n, n_obs, [(s, score(problem, s)) for s in solutions]))

    print(f"\nBundle adjustment: room 8x6x3 m, 30 cards of 0.2 m, {args.frames}-frame calibration walk "
          f"(seed {args.seed}), intrinsics free, discs: Huber's loss at {LOSS_SCALE} expected errors, card prior "
          f"10 um; feature points: {FEATURE_SIGMA_PX} px noise, {100 * OUTLIER_FRACTION:.0f} % wrong matches, "
          f"{FEATURE_LOSS.value.capitalize()}'s loss at {LOSS_SCALE} sigmas; one thread\n")
    print("| feature points (observations) | engine | stops | CPU time (s) | wall time (s) | iterations | robust cost "
          "| disc RMS (px) "
          "| feature RMS (px) | camera position (mm) | rotation (deg) | discs (mm) | feature points, median (mm) "
          "| focal error |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for n, n_obs, results in rows:
        for s, sc in results:
            wall = f"{s.seconds:.2f}" + (f" ({s.build_seconds:.2f} set-up)" if s.build_seconds else "")
            stops = "converged" if s.converged else f"tolerance {CERES_TOLERANCE:g}"
            print(f"| {n} ({n_obs}) | {s.engine} | {stops} | {s.cpu_seconds:.2f} | {wall} | {s.iterations} "
                  f"| {sc.cost:.7g} "
                  f"| {_fmt(sc.disc_rms_px, 4)} | {_fmt(sc.feature_rms_px, 3)} | {sc.position_mm:.3f} "
                  f"| {sc.rotation_deg:.5f} | {sc.disc_mm:.3f} | {_fmt(sc.feature_mm, 2)} | {sc.focal_pct:+.4f} % |")
    if modules is None:
        print("\nCeres: not installed (pip install pyceres pycolmap)")
        return
    print("\nRatios, Ceres / fidotrack, each with the same stopping rule:\n")
    print("| feature points | engine | stops | CPU time | iterations | robust cost | camera position error "
          "| disc error |")
    print("|---|---|---|---|---|---|---|---|")
    for n, _, results in rows:
        for s, sc in results:
            if s.engine == "fidotrack":
                continue
            base, base_score = next((b, bs) for b, bs in results
                                    if b.engine == "fidotrack" and b.converged == s.converged)
            stops = "converged" if s.converged else f"tolerance {CERES_TOLERANCE:g}"
            print(f"| {n} | {s.engine} | {stops} | {s.cpu_seconds / base.cpu_seconds:.2f} "
                  f"| {s.iterations / max(base.iterations, 1):.2f} | {sc.cost / base_score.cost:.6f} "
                  f"| {sc.position_mm / base_score.position_mm:.3f} | {sc.disc_mm / base_score.disc_mm:.3f} |")


if __name__ == "__main__":
    main()
