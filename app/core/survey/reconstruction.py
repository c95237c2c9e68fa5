"""Automatic survey of the targets by structure from motion (paper §3 step 4, §5.1).

Input: the identified targets of every frame of a calibration video (the caller runs
the detector, so it can report progress and reuse detections). Output: the camera
(focal length, principal point, radial distortion), the 3D centre of every disc of
every target (the map), with its uncertainty, and the camera trajectory.

Every disc of every target id is one track (4 tracks per id); as in the paper (§5.1)
each disc gets its own 3D point, so cards that are not flat are surveyed as they are.
A detection whose discs cannot be an image of a card's face (mirrored, folded) is
ignored. The pipeline:

1. initial lens from the card homographies (a card is a planar square; with square
   pixels and the principal point at the image centre each tilted card gives Zhang's
   two constraints on f), a robust closed-form fit over all cards of all frames, then
   the maximum-likelihood f and k1 over the cards (each card its own pose): the closed
   form alone is biased by detector noise (``lens_from_cards``);
2. a metric start from two frames that share several targets seen from some degrees
   apart: relative pose by the essential matrix (5-point RANSAC over the shared disc
   centres, so a misread code is an outlier), discs by triangulation, scale from the
   printed card size. No card is placed from its own planar pose here: for small cards
   the two tilts fit alike and a wrong one misleads everything registered against it
   (fallback when no pair qualifies: the frame that sees most targets, planar poses);
3. incremental growth, in passes: frames are registered by PnP against the discs known
   so far (robust over targets, `pose.nonlinear`; targets it refuses are set aside in
   that frame); a bundle adjustment refines them (and the lens); only then are new
   targets placed, from the refined poses: triangulated by consensus over pairs of
   registered views (DLT; views of a misread card disagree and are left out; the card
   must come out with its printed shape) or, while the baseline is narrow or the rays
   disagree, as the rigid printed card fitted to its views (the start most views agree
   with, then the tilt their own planar fits favour). A frame that rests on a single
   card takes a tilt its image does not refute that fits the camera's motion (its
   neighbours' poses), which also refuses a card with a misread code. The map is then
   judged by every view, also those set aside: a frame or a target most of whose views
   do not fit is taken out (a target is placed again only from more views), single
   views that do not fit are set aside and taken back once they fit. A view of a point
   behind the camera or outside its field never fits (a point past the edge of the
   field can project into the image, folded back by the distortion polynomial);
4. bundle adjustment over f, principal point, k1, k2, every pose and every disc, each
   observation weighted by its expected precision (``disc_precision``), Huber loss,
   analytic Jacobian, Levenberg-Marquardt with the cameras eliminated (Schur complement;
   see ``bundle_adjust`` for why); judged as in 3, with the loss and the threshold from
   the noise level of the whitened errors (``HUBER_K``, ``OUTLIER_K``: views that do not
   fit are a misidentified target, a broken track, a disc under glare), and it is run
   again;
5. metric scale: the least-squares scale that gives the known disc-to-disc distances of
   every card (sides 0.6 s, diagonals 0.6 sqrt(2) s) — optionally also as a soft prior
   inside the bundle adjustment (``card_prior_m``);
6. disc uncertainty from the bundle's Jacobian, warnings about weak parts of the map.

numpy / OpenCV / SciPy only; no I/O.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from app.core.markers import DISC_CENTRES
from app.core.detection import DetectedTarget
from app.core.geometry import Camera, Pose, PoseUndetermined, TargetObservation, disc_axes, nonlinear

Progress = Callable[[str, float], None]

#: Disc pairs of a card and their distance in card units (4 sides, 2 diagonals).
_PAIRS = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [0, 2], [1, 3]])
_PAIR_UNITS = np.linalg.norm(DISC_CENTRES[_PAIRS[:, 0]] - DISC_CENTRES[_PAIRS[:, 1]], axis=1)

#: A target seen in fewer views, or from a narrower range of directions, is flagged.
MIN_VIEWS = 3
MIN_BASELINE_DEG = 2.0

#: A target triangulated with a disc-to-disc distance this far (relative) from the
#: printed card is not placed by triangulation (yet): its rays do not agree.
MAX_SHAPE_ERROR = 0.05


class SurveyError(ValueError):
    """The survey cannot be done from this input (the message says why, for a user)."""


# --------------------------------------------------------------------------------------
# Result
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SurveyedTarget:
    """One target of the map: its 4 disc centres (metres, DESIGN.md order)."""

    id: int
    discs: np.ndarray  # (4, 3)
    std_m: np.ndarray  # (4,) RMS 3D position uncertainty of each disc (1 sigma)
    n_views: int  # registered frames in which the target was used
    baseline_deg: float  # widest angle between two of those views, at the target

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": int(self.id),
            "discs": np.round(self.discs, 6).tolist(),
            "std_m": [float(f"{s:.3g}") for s in self.std_m],
            "n_views": int(self.n_views),
        }


@dataclass(eq=False)
class SurveyResult:
    camera: Camera
    targets: list[SurveyedTarget]
    rms_px: float  # reprojection RMS (2D) over every observation kept
    trajectory: list[Pose | None]  # one per input frame; None: not used or not registered
    warnings: list[str]
    intrinsics_fixed: bool
    frames_used: list[int]  # input frame indices after subsampling
    n_observations: int  # disc observations in the final bundle adjustment
    n_rejected_views: int  # (frame, target) views dropped as not fitting
    scale_residual_m: float  # RMS of the card disc-distance residuals after scaling
    timing_s: dict[str, float] = field(default_factory=dict)

    @property
    def n_registered(self) -> int:
        return sum(p is not None for p in self.trajectory)

    def target(self, target_id: int) -> SurveyedTarget:
        for t in self.targets:
            if t.id == target_id:
                return t
        raise KeyError(target_id)

    def to_map_document(self, frame: str = "survey", survey_job_id: str | None = None) -> dict[str, Any]:
        """DESIGN.md's map document."""
        return {
            "frame": frame,
            "units": "m",
            "camera": self.camera.to_dict(),
            "targets": [t.to_dict() for t in sorted(self.targets, key=lambda t: t.id)],
            "rms_px": float(round(self.rms_px, 4)),
            "survey_job_id": survey_job_id,
        }

    def summary(self) -> dict[str, Any]:
        """Small JSON-able digest for a job result."""
        return {
            "n_frames": len(self.frames_used),
            "n_registered": self.n_registered,
            "n_targets": len(self.targets),
            "rms_px": float(self.rms_px),
            "focal_px": self.camera.fx,
            "principal_point": [self.camera.cx, self.camera.cy],
            "dist": self.camera.dist.tolist(),
            "warnings": list(self.warnings),
            "timing_s": dict(self.timing_s),
        }


# --------------------------------------------------------------------------------------
# Observations
# --------------------------------------------------------------------------------------


@dataclass
class _Tracks:
    """Every disc observation, flat, sorted by frame."""

    frame: np.ndarray  # (M,) index into the used frames
    target: np.ndarray  # (M,) index into ids
    disc: np.ndarray  # (M,) 0..3
    uv: np.ndarray  # (M, 2) pixels
    ids: np.ndarray  # (T,) target id of each target index
    n_frames: int
    precision: np.ndarray  # (M,) inverse expected variance of each observation, px^-2 (`disc_precision`)

    @property
    def point(self) -> np.ndarray:
        return self.target * 4 + self.disc


def _is_face(discs: np.ndarray) -> bool:
    """Whether 4 disc centres (printed order) can be an image of a card's printed face:
    a convex quadrilateral turning the way the printed one does (perspective keeps
    both, a lens keeps them over a card's extent). A mirrored, folded or collinear
    quad is a broken detection, or a point beyond the edge of the lens's field that a
    distortion polynomial folds back into the image: either way no view of the card."""
    e = np.roll(discs, -1, axis=0) - discs
    turn = e[:, 0] * np.roll(e, -1, axis=0)[:, 1] - e[:, 1] * np.roll(e, -1, axis=0)[:, 0]
    return bool((turn > 0).all())


#: Expected error of a disc centre (px per axis) against the minor semi-axis b of the
#: disc's image: ``DISC_ERROR_PX[0] + DISC_ERROR_PX[1] / b**2``. A thin disc is measured
#: worse (fewer pixels across, the card's edge and code closer). Fitted to the robust
#: spread (median 2-D error / 1.1774) of `disc_fit`'s centres by bins of b, 4 rooms x
#: 1000 frames of bench_survey's walk (session 7, ad-hoc): 0.030 px at b 1-1.25,
#: 0.016 at 1.5-1.75, 0.011 at 2-2.5, 0.008 at 3-3.5, 0.0066 at 4-5.
DISC_ERROR_PX = (0.0048, 0.032)

#: The final bundle adjustment's robust loss and outlier test, on whitened errors (error
#: / expected error) in units of their robust spread (median / 1.1774, re-measured every
#: round, so a noisier video than `DISC_ERROR_PX` assumes is judged by its own noise):
#: Huber's loss from HUBER_K spreads on, views with a disc beyond OUTLIER_K spreads
#: (and beyond MIN_OUTLIER_PX) are set aside, and taken back below half that. Why: a
#: fitted centre is good to ~0.01 px, but a few in a thousand are 0.3-0.9 px off (glare
#: or an occluder on one disc); at the old fixed thresholds (Huber from ~100 expected
#: errors, outliers from 3 px) they kept full weight, and at 300 frames they moved the
#: maps by up to 1 mm (bench_survey, 4 rooms, same detections, ad-hoc: discs 0.36-0.96
#: -> 0.19-0.28 mm, median tracking ratio 2.14 -> 1.23; at 1000 frames 0.19-0.29 ->
#: 0.12-0.17 mm, 1.15 -> 1.13).
HUBER_K = 2.5
OUTLIER_K = 8.0
MIN_OUTLIER_PX = 0.05

#: Huber's threshold (whitened) while the map grows: loose, since residuals of pixels are
#: then the unrefined lens's and poses' error, not outliers.
GROWTH_LOSS_SCALE = 100.0


def disc_precision(discs: np.ndarray) -> np.ndarray:
    """Weights (T, 4) of disc centres in views `discs` (T, 4, 2): the inverse expected
    variance (`DISC_ERROR_PX`), px^-2."""
    b = np.maximum(disc_axes(discs)[..., 1], 0.5)
    sigma = DISC_ERROR_PX[0] + DISC_ERROR_PX[1] / b**2
    return 1.0 / sigma**2


def _collect(frames: Sequence[Sequence[DetectedTarget]], used: list[int]) -> tuple[_Tracks, int, int]:
    """Flatten detections; an id found twice in one frame is ambiguous there: dropped,
    as are detections that cannot be a card's face (``_is_face``). Returns the tracks
    and the counts of both."""
    rows: list[tuple[int, int, np.ndarray]] = []
    duplicates = malformed = 0
    for fi, index in enumerate(used):
        seen: dict[int, int] = {}
        for det in frames[index]:
            seen[int(det.id)] = seen.get(int(det.id), 0) + 1
        for det in frames[index]:
            discs = np.asarray(det.discs, np.float64).reshape(4, 2)
            if seen[int(det.id)] > 1 or not np.isfinite(discs).all():
                duplicates += 1
                continue
            if not _is_face(discs):
                malformed += 1
                continue
            rows.append((fi, int(det.id), discs))
    ids = np.array(sorted({r[1] for r in rows}), dtype=int)
    lookup = {int(i): k for k, i in enumerate(ids)}
    n = len(rows)
    tracks = _Tracks(
        frame=np.repeat(np.array([r[0] for r in rows], int), 4) if n else np.zeros(0, int),
        target=np.repeat(np.array([lookup[r[1]] for r in rows], int), 4) if n else np.zeros(0, int),
        disc=np.tile(np.arange(4), n),
        uv=np.concatenate([r[2] for r in rows]) if n else np.zeros((0, 2)),
        ids=ids,
        n_frames=len(used),
        precision=disc_precision(np.array([r[2] for r in rows])).ravel() if n else np.zeros(0),
    )
    return tracks, duplicates, malformed


# --------------------------------------------------------------------------------------
# Initial focal length
# --------------------------------------------------------------------------------------


def focal_from_cards(cards_px: Sequence[np.ndarray], width: int, height: int) -> float | None:
    """Focal length (px) from the homographies of many planar square cards.

    Zhang's constraints with square pixels, no skew and the principal point at the
    image centre: for H = [h1 h2 h3] (card plane -> centred pixels) and w = 1/f^2,
        (h11 h12 + h21 h22) w + h31 h32 = 0,
        (h11^2 + h21^2 - h12^2 - h22^2) w + h31^2 - h32^2 = 0.
    A card seen head-on gives 0 = 0 (no information) and weighs nothing in the joint
    least squares; equations that disagree (a bad detection) are trimmed iteratively.
    None when the cards do not determine f (all seen head-on, too few).
    """
    scale = float(max(width, height))
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    model = DISC_CENTRES.astype(np.float32)
    a_list, b_list = [], []
    for quad in cards_px:
        q = ((np.asarray(quad, np.float64) - centre) / scale).astype(np.float32)
        try:
            H = cv2.getPerspectiveTransform(model, q)
        except cv2.error:
            continue
        if not np.isfinite(H).all():
            continue
        # Normalise so that the equations of near and far cards weigh alike.
        H = H / np.sqrt((H[:2, :2] ** 2).sum() / 2)
        h1, h2 = H[:, 0], H[:, 1]
        a_list += [h1[0] * h2[0] + h1[1] * h2[1], h1[0] ** 2 + h1[1] ** 2 - h2[0] ** 2 - h2[1] ** 2]
        b_list += [h1[2] * h2[2], h1[2] ** 2 - h2[2] ** 2]
    if len(a_list) < 4:
        return None
    a, b = np.array(a_list), -np.array(b_list)  # a w = b
    keep = np.ones(len(a), bool)
    w = 0.0
    for _ in range(5):
        if (a[keep] ** 2).sum() <= 1e-18:
            return None
        w = float((a[keep] * b[keep]).sum() / (a[keep] ** 2).sum())
        r = a * w - b
        mad = 1.4826 * np.median(np.abs(r[keep])) + 1e-12
        new = np.abs(r) < 3 * mad
        if new.sum() < 4 or np.array_equal(new, keep):
            break
        keep = new
    if not np.isfinite(w) or w <= 0:
        return None
    f = scale / np.sqrt(w)
    # Lenses from fisheye-ish (~140 deg) to long (~10 deg): outside is a failed estimate.
    return f if 0.2 * scale < f < 6.0 * scale else None


def _rotations(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of rotation vectors w (N, 3) (Rodrigues, batched)."""
    angle = np.linalg.norm(w, axis=1)
    k = w / np.where(angle > 0, angle, 1.0)[:, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def _card_residuals(quads: np.ndarray, model: np.ndarray, R: np.ndarray, t: np.ndarray, f: float, k1: float,
                    centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (N, 8) of planar cards (``model`` (4, 3), poses R (N, 3, 3), t (N, 3))
    seen by a lens (f, k1, principal point ``centre``), and their Jacobian (N, 8, 8)
    over a rotation applied on the left, the translation, f and k1."""
    a = np.einsum("nij,kj->nki", R, model)  # (N, 4, 3): R @ model
    X = a + t[:, None, :]
    z = X[..., 2]
    x, y = X[..., 0] / z, X[..., 1] / z
    r2 = x * x + y * y
    d = 1 + k1 * r2
    res = np.stack([f * x * d + centre[0], f * y * d + centre[1]], axis=-1) - quads  # (N, 4, 2)
    dx = np.stack([1 / z, np.zeros_like(z), -x / z], axis=-1)
    dy = np.stack([np.zeros_like(z), 1 / z, -y / z], axis=-1)
    dd = 2 * k1 * (x[..., None] * dx + y[..., None] * dy)
    gu = f * (d[..., None] * dx + x[..., None] * dd)  # d u / d X
    gv = f * (d[..., None] * dy + y[..., None] * dd)
    J = np.empty((len(quads), 4, 2, 8))
    # A small rotation w moves a by w x a: d u / d w = a x (d u / d X).
    J[:, :, 0, :3], J[:, :, 1, :3] = np.cross(a, gu), np.cross(a, gv)
    J[:, :, 0, 3:6], J[:, :, 1, 3:6] = gu, gv
    J[:, :, 0, 6], J[:, :, 1, 6] = x * d, y * d
    J[:, :, 0, 7], J[:, :, 1, 7] = f * x * r2, f * y * r2
    return res.reshape(-1, 8), J.reshape(-1, 8, 8)


def lens_from_cards(cards_px: Sequence[np.ndarray], width: int, height: int, focal: float,
                    max_cards: int = 1000) -> tuple[float, float] | None:
    """Focal length and radial distortion k1 from many planar square cards, by maximum
    likelihood: every card a planar square with its own pose, one lens for all (Zhang's
    refinement, principal point at the image centre), from the closed-form ``focal``.

    Why: the closed form is biased by detector noise, and strongly (small far cards:
    their perspective terms are mostly noise; f +8 % at 0.03 px, +40 % at 0.1 px in the
    bench room), and it ignores the distortion. The survey's start and every frame
    registered against it inherit the wrong lens (cameras 0.3-0.5 m off at 6 m), and the
    bundle adjustment settled in a wrong minimum (f 871 px for 820). The reprojection
    error has no such bias (bench room, 0.03 px: 822 px, k1 -0.105 for -0.12).

    Variable projection: for a lens, each card's pose is fitted on its own (both tilts
    tried: a small card's two tilts fit alike; all cards at once, Gauss-Newton); the
    lens then takes a Newton step on that profile cost (normal equations with the card
    poses eliminated). A joint step that moves poses linearly crawls: the cost of a
    small card is far from quadratic in its tilt. Cards that fit far worse than the
    others (misread, a wrong disc, a folded projection) are trimmed. None when the cards
    do not determine f (all seen head-on, too few).
    """
    quads = np.asarray([q for q in cards_px if np.isfinite(q).all()], np.float64).reshape(-1, 4, 2)
    if len(quads) > max_cards:  # evenly over the video (a bound on the time, ~1 s)
        quads = quads[np.linspace(0, len(quads) - 1, max_cards).round().astype(int)]
    if len(quads) < 4:
        return None
    model = np.c_[DISC_CENTRES, np.zeros(4)].astype(np.float64)  # card units: scale is free
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])

    def refine(th: np.ndarray, R: np.ndarray, t: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every card's pose for the lens ``th`` by damped Gauss-Newton (each card its own
        damping), from (R, t); with the residuals and Jacobian there."""
        r, J = _card_residuals(quads, model, R, t, th[0], th[1], centre)
        cost = (r**2).sum(axis=1)
        lam = np.full(len(quads), 1e-3)
        for _ in range(20):
            A = J[:, :, :6]
            H = A.transpose(0, 2, 1) @ A
            H = H + lam[:, None, None] * (np.eye(6) * (np.diagonal(H, axis1=1, axis2=2)[:, None, :] + 1e-12))
            step = -np.linalg.solve(H, np.einsum("nij,ni->nj", A, r)[..., None])[..., 0]
            new_R, new_t = _rotations(step[:, :3]) @ R, t + step[:, 3:]
            new_r, new_J = _card_residuals(quads, model, new_R, new_t, th[0], th[1], centre)
            new_cost = (new_r**2).sum(axis=1)
            better = new_cost < cost  # (NaN: behind the camera, refused)
            gain = np.where(better, cost - new_cost, 0.0)
            R[better], t[better], r[better], J[better], cost[better] = (
                new_R[better], new_t[better], new_r[better], new_J[better], new_cost[better])
            lam = np.where(better, np.maximum(lam / 10, 1e-9), lam * 10)
            if not (gain > 1e-10 * cost).any():
                break
        return R, t, r, J

    def fit(th: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every card's better tilt for the lens ``th``: both IPPE poses, refined."""
        K = np.array([[th[0], 0, centre[0]], [0, th[0], centre[1]], [0, 0, 1.0]])
        dist = np.array([th[1], 0.0, 0.0, 0.0, 0.0])
        R, t = np.tile(np.eye(3), (2, len(quads), 1, 1)), np.zeros((2, len(quads), 3))
        t[:, :, 2] = np.nan  # no pose (refused below)
        for i, q in enumerate(quads):
            try:
                _, rvecs, tvecs, _ = cv2.solvePnPGeneric(model, q, K, dist, flags=cv2.SOLVEPNP_IPPE)
            except cv2.error:
                continue
            for k, (rvec, tvec) in enumerate(zip(rvecs[:2], tvecs[:2], strict=False)):
                R[k, i], t[k, i] = cv2.Rodrigues(rvec)[0], tvec.ravel()
            if len(rvecs) == 1:
                R[1, i], t[1, i] = R[0, i], t[0, i]
        tilts = [refine(th, R[k], t[k]) for k in range(2)]
        first = (tilts[0][2] ** 2).sum(axis=1) <= (tilts[1][2] ** 2).sum(axis=1)
        return tuple(np.where(first.reshape((-1,) + (1,) * (a.ndim - 1)), a, b)  # type: ignore[return-value]
                     for a, b in zip(tilts[0], tilts[1], strict=True))

    def reduced(r: np.ndarray, J: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normal equations of the lens with the card poses eliminated (Schur complement)."""
        A, B, rk = J[keep, :, :6], J[keep, :, 6:], r[keep]
        U = A.transpose(0, 2, 1) @ A + 1e-12 * np.eye(6)
        W = A.transpose(0, 2, 1) @ B
        UiW = np.linalg.solve(U, W)
        S = np.einsum("nij,nik->jk", B, B) - np.einsum("nij,nik->jk", W, UiW)
        g = np.einsum("nij,ni->j", B, rk) - np.einsum("nij,ni->j", UiW, np.einsum("nij,ni->nj", A, rk))
        return S, g

    def fitting(r: np.ndarray, keep: np.ndarray | None) -> np.ndarray:
        """Cards that fit no worse than 5 times the typical one (misread, a wrong disc,
        a folded projection from outside the field: left in, they pulled k1 to +1.5)."""
        card_rms = np.sqrt((r**2).mean(axis=1))
        ok = np.isfinite(card_rms)
        base = ok if keep is None else keep & ok
        typical = float(np.median(card_rms[base])) if base.any() else 0.0
        return ok & (card_rms < max(5 * typical, 1e-3))

    theta = np.array([float(focal), 0.0])  # f, k1
    R, t, r, J = fit(theta)
    keep = fitting(r, None)
    for _ in range(3):  # fit, trim the cards that do not fit, fit again
        if keep.sum() < 4:
            return None
        cost = float((r[keep] ** 2).sum())
        lam = 1e-4
        for _ in range(30):
            S, g = reduced(r, J, keep)
            try:
                step = -np.linalg.solve(S + lam * np.diag(np.diag(S) + 1e-12), g)
            except np.linalg.LinAlgError:
                return None
            new = theta + step
            if 0.2 * focal < new[0] < 5 * focal and abs(new[1]) < 2:
                new_R, new_t, new_r, new_J = refine(new, R.copy(), t.copy())
                new_cost = float((new_r[keep] ** 2).sum())
                if new_cost < cost:
                    done = cost - new_cost < 1e-7 * cost or abs(step[0]) < 1e-6 * theta[0]
                    theta, R, t, r, J, cost = new, new_R, new_t, new_r, new_J, new_cost
                    lam = max(lam / 10, 1e-9)
                    if done:
                        break
                    continue
            lam *= 10
            if lam > 1e4:
                break
        # A card's better tilt may have changed with the lens: both again.
        R, t, r, J = fit(theta)
        new_keep = fitting(r, keep)
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    # The cards must determine f (not all head-on): its standard deviation from the
    # reduced normal equations, the noise level from the residuals (2 dof per card).
    S, _ = reduced(r, J, keep)
    sigma2 = float((r[keep] ** 2).sum()) / max(2 * int(keep.sum()) - 2, 1)
    try:
        var_f = float(np.linalg.inv(S)[0, 0]) * sigma2
    except np.linalg.LinAlgError:
        return None
    f, k1 = float(theta[0]), float(theta[1])
    if not (np.isfinite(f) and np.isfinite(k1) and np.isfinite(var_f)) or np.sqrt(max(var_f, 0.0)) > 0.05 * f:
        return None
    scale = float(max(width, height))
    return (f, k1) if 0.2 * scale < f < 6.0 * scale else None


# --------------------------------------------------------------------------------------
# Geometry helpers
# --------------------------------------------------------------------------------------


def _card_model(marker_size_m: float) -> np.ndarray:
    """Disc centres in the card's own frame (x right, y down as printed, z = 0), metres."""
    return np.c_[DISC_CENTRES * marker_size_m, np.zeros(4)]


def _normalised(camera: Camera, uv: np.ndarray) -> np.ndarray:
    ideal = camera.undistort_pixels(uv)
    return np.c_[(ideal[:, 0] - camera.cx) / camera.fx, (ideal[:, 1] - camera.cy) / camera.fy]


def _planar_poses(camera: Camera, uv: np.ndarray, model: np.ndarray) -> list[Pose]:
    """Both card-to-camera poses of one card (IPPE), best reprojection first: a small
    card seen with noise cannot tell its two tilts apart, the caller decides."""
    x = _normalised(camera, uv)
    try:
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(model, x, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        return []
    order = np.argsort(np.asarray(errs).ravel()) if errs is not None and len(errs) == n else range(n)
    poses = [Pose.from_rvec_tvec(rvecs[k], tvecs[k]) for k in order]
    return [p for p in poses if p.t[2] > 0]


def _rotation_angle(a: Pose, b: Pose) -> float:
    return float(np.arccos(np.clip((np.trace(a.R @ b.R.T) - 1) / 2, -1.0, 1.0)))


def _triangulate(poses: Sequence[Pose], x: np.ndarray) -> np.ndarray:
    """DLT triangulation of one point from normalised coordinates x (V, 2)."""
    rows = []
    for pose, (u, v) in zip(poses, x, strict=True):
        P = np.c_[pose.R, pose.t]
        rows.append(u * P[2] - P[0])
        rows.append(v * P[2] - P[1])
    _, _, vt = np.linalg.svd(np.array(rows))
    X = vt[-1]
    return X[:3] / X[3] if abs(X[3]) > 1e-12 else np.full(3, np.nan)


def _max_angle_deg(centres: np.ndarray, point: np.ndarray) -> float:
    """Widest angle at ``point`` between the rays to the camera ``centres`` (V, 3)."""
    d = centres - point
    d /= np.linalg.norm(d, axis=1, keepdims=True) + 1e-300
    if len(d) > 400:  # O(V^2): the extremes of a long track are found on a subsample
        d = d[np.linspace(0, len(d) - 1, 400).astype(int)]
    cos = np.clip(d @ d.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos.min())))


def _fit_card(camera: Camera, poses: Sequence[Pose], uvs: Sequence[np.ndarray], model: np.ndarray,
              card: Pose, iterations: int = 8) -> tuple[Pose, float]:
    """The pose (card -> map) of a rigid printed card that best fits its views from
    cameras whose poses are held (Gauss-Newton, analytic Jacobian, from ``card``), and
    the sum of squared reprojection errors (px^2) there.

    Why: a card seen over a narrow baseline is placed from its planar pose in one view,
    where its two tilts fit alike; the views together tell them apart, but only once
    each tilt is fitted to all of them (unrefined, both agree with every view to a few
    pixels). A wrong tilt, once in the map, is a minimum the bundle does not leave.
    """
    R, t = card.R.copy(), card.t.copy()

    def residuals(R: np.ndarray, t: np.ndarray, jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
        X = model @ R.T + t
        r = np.empty((len(poses), 8))
        J = np.empty((len(poses), 8, 6)) if jac else None
        for k, (pose, uv) in enumerate(zip(poses, uvs, strict=True)):
            proj, j = cv2.projectPoints(X, pose.rvec, pose.t, camera.K, camera.dist)
            r[k] = (proj.reshape(4, 2) - uv).ravel()
            if J is not None:
                dX = (j[:, 3:6] @ pose.R).reshape(4, 2, 3)  # d uv / d X
                a = X - t  # R @ model: a small rotation moves a point by w x a = -[a]x w
                skew = np.zeros((4, 3, 3))
                skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -a[:, 2], a[:, 1], -a[:, 0]
                skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = a[:, 2], -a[:, 1], a[:, 0]
                J[k, :, :3] = -(dX @ skew).reshape(8, 3)
                J[k, :, 3:] = dX.reshape(8, 3)
        return r.ravel(), (J.reshape(-1, 6) if J is not None else None)

    r, J = residuals(R, t, True)
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(iterations):
        assert J is not None
        H = J.T @ J
        step = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), J.T @ r)
        dR, _ = cv2.Rodrigues(step[:3])
        new_R, new_t = dR @ R, t + step[3:]
        new_r, new_J = residuals(new_R, new_t, True)
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


def _triangulate_robust(poses: Sequence[Pose], x: np.ndarray, tol: float, rng: np.random.Generator
                        ) -> tuple[np.ndarray, np.ndarray] | None:
    """A card's 4 discs from V >= 2 views (x: (V, 4, 2) normalised), robust to views
    that belong to another card (a misidentified target moves all its 4 discs).

    Consensus over pairs of views (all pairs when few, a sample when many): each pair
    triangulates the card, the views it explains to within ``tol`` (normalised units,
    worst disc) vote; the largest consensus (then the smallest error) is triangulated
    again from all its views. None when no two views agree. Returns (X (4, 3), inlier
    mask over views).
    """
    V = len(poses)
    pairs = [(i, j) for i in range(V) for j in range(i + 1, V)]
    if len(pairs) > 40:
        pick = rng.choice(len(pairs), 40, replace=False)
        pairs = [pairs[k] for k in pick]
    best: tuple[int, float, np.ndarray] | None = None
    for i, j in pairs:
        X = np.array([_triangulate([poses[i], poses[j]], x[[i, j], d]) for d in range(4)])
        if not np.isfinite(X).all():
            continue
        err = np.array([np.abs(_project_norm(p, X) - x[k]).max() if (p.transform(X)[:, 2] > 0).all() else np.inf
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
    X = np.array([_triangulate([poses[k] for k in idx], x[idx, d]) for d in range(4)])
    if not np.isfinite(X).all():
        return None
    return X, inl


def _two_view_seed(camera: Camera, view_frame: np.ndarray, view_target: np.ndarray, view_uv: np.ndarray,
                   views_of_frame: list[np.ndarray], marker_size_m: float, tol_px: float
                   ) -> tuple[int, int, Pose, dict[int, np.ndarray]] | None:
    """The start of the map from two frames by the essential matrix (no card planarity).

    Placing a card from its own planar pose is a coin toss for small cards (two tilts
    fit equally well) and a wrong tilt misleads everything registered against it. Two
    frames that share several targets, seen from directions some degrees apart, give
    the relative pose (5-point RANSAC over all shared disc centres: a misidentified
    target is an outlier) and the discs by triangulation, with no tilt to choose. The
    printed card size gives the scale. Returns (frame a, frame b, pose of b (a is the
    identity), {target index: (4, 3) discs}) or None when no pair gives a start.
    """
    n_frames = len(views_of_frame)
    counts = np.array([len(v) for v in views_of_frame])
    x_all = _normalised(camera, view_uv.reshape(-1, 2)).reshape(-1, 4, 2)
    frame_views = [dict(zip(view_target[v].tolist(), v.tolist(), strict=True)) for v in views_of_frame]
    tol = tol_px / camera.fx
    best: tuple[float, int, int, Pose, dict[int, np.ndarray]] | None = None
    for a in np.argsort(-counts, kind="stable")[:6]:
        a = int(a)
        if counts[a] < 3:
            break
        ta = frame_views[a]
        partners = [b for b in range(n_frames) if b != a and sum(t in ta for t in frame_views[b]) >= 3]
        if len(partners) > 30:
            partners = [partners[k] for k in np.linspace(0, len(partners) - 1, 30).round().astype(int)]
        for b in partners:
            shared = [t for t in frame_views[b] if t in ta]
            x1 = np.concatenate([x_all[ta[t]] for t in shared])
            x2 = np.concatenate([x_all[frame_views[b][t]] for t in shared])
            try:
                E, mask = cv2.findEssentialMat(x1, x2, np.eye(3), cv2.RANSAC, 0.999, tol)
            except cv2.error:
                continue
            if E is None or E.shape[0] < 3 or mask is None:
                continue
            candidates = [E[3 * k : 3 * k + 3] for k in range(E.shape[0] // 3)]
            for E in candidates:
                try:
                    _, R, t, _ = cv2.recoverPose(E, x1, x2, np.eye(3), mask=mask.copy())
                except cv2.error:
                    continue
                pb = Pose(R, t.ravel())
                pa = Pose.identity()
                X = cv2.triangulatePoints(np.c_[np.eye(3), np.zeros(3)], np.c_[R, t], x1.T, x2.T)
                if (np.abs(X[3]) < 1e-12).any():
                    continue
                X = (X[:3] / X[3]).T
                err = np.maximum(np.abs(_project_norm(pa, X) - x1).max(axis=1),
                                 np.abs(_project_norm(pb, X) - x2).max(axis=1))
                ok = (err < tol) & (X[:, 2] > 0) & (pb.transform(X)[:, 2] > 0)
                ok_t = ok.reshape(-1, 4).all(axis=1)
                if ok_t.sum() < 3:
                    continue
                Xg = X.reshape(-1, 4, 3)[ok_t]
                ray_a = Xg.mean(axis=1)
                ray_b = ray_a - pb.position
                cos = (ray_a * ray_b).sum(axis=1) / (np.linalg.norm(ray_a, axis=1) * np.linalg.norm(ray_b, axis=1))
                angle = float(np.degrees(np.median(np.arccos(np.clip(cos, -1, 1)))))
                if angle < 3.0:
                    continue
                d = np.linalg.norm(Xg[:, _PAIRS[:, 0]] - Xg[:, _PAIRS[:, 1]], axis=2).ravel()
                L = np.tile(_PAIR_UNITS * marker_size_m, len(Xg))
                scale = float((d * L).sum() / (d * d).sum())
                # Cards whose triangulated shape is far from the printed one are not kept.
                shape = np.abs(scale * d - L).reshape(-1, 6).max(axis=1) < 0.25 * marker_size_m
                if shape.sum() < 3:
                    continue
                # Quality: the printed shape of the kept cards. A wrong relative pose (a
                # narrow pair whose 5-point fit is loose within the lens's unmodelled
                # distortion) still places every card within tolerance, but bent: cards
                # 5-12 % off their shape, against ~1 % for a right one. Without this a
                # wrong pair with a wide (wrong) angle tied a right one and could win.
                rel = float(np.median(np.abs(scale * d - L).reshape(-1, 6)[shape].max(axis=1))) / marker_size_m
                score = float(shape.sum()) * min(angle, 10.0) / (1.0 + (rel / 0.02) ** 2)
                if best is None or score > best[0]:
                    kept = [tg for tg, k in zip(np.array(shared)[ok_t], shape, strict=True) if k]
                    discs = {int(tg): scale * Xg[i] for i, tg in enumerate(np.array(shared)[ok_t]) if shape[i]}
                    assert len(discs) == len(kept)
                    best = (score, a, b, Pose(pb.R, scale * pb.t), discs)
    if best is None:
        return None
    return best[1], best[2], best[3], best[4]


def _make_camera(intr: np.ndarray, width: int, height: int) -> Camera:
    f, cx, cy, k1, k2 = intr
    return Camera(np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]]), np.array([k1, k2, 0, 0, 0.0]), width, height)


# --------------------------------------------------------------------------------------
# Bundle adjustment
# --------------------------------------------------------------------------------------


@dataclass
class _Bundle:
    """The state being optimised: intrinsics, poses of registered frames, points."""

    camera: Camera
    rvec: np.ndarray  # (F, 3), nan for frames not registered
    tvec: np.ndarray  # (F, 3)
    X: np.ndarray  # (4T, 3), nan for discs not yet placed

    def registered(self) -> np.ndarray:
        return np.isfinite(self.rvec[:, 0])

    def placed(self) -> np.ndarray:
        return np.isfinite(self.X[:, 0])

    def pose(self, f: int) -> Pose:
        return Pose.from_rvec_tvec(self.rvec[f], self.tvec[f])

    def set_pose(self, f: int, pose: Pose) -> None:
        self.rvec[f], self.tvec[f] = pose.rvec, pose.t


def _project_frame(camera: Camera, rvec: np.ndarray, tvec: np.ndarray, X: np.ndarray,
                   jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
    uv, jac = cv2.projectPoints(X.reshape(-1, 1, 3), rvec, tvec, camera.K, camera.dist)
    return uv.reshape(-1, 2), (jac if jacobian else None)


def bundle_adjust(
    bundle: _Bundle,
    tracks: _Tracks,
    use: np.ndarray,
    free_intrinsics: bool,
    card_prior: tuple[float, float] | None = None,
    loss_scale: float = GROWTH_LOSS_SCALE,
    max_iterations: int = 100,
    with_covariance: bool = False,
) -> tuple[_Bundle, dict[str, Any]]:
    """Robust sparse bundle adjustment (Levenberg-Marquardt) over the observations
    ``use`` (bool mask over tracks).

    Parameters: [f, cx, cy, k1, k2] when ``free_intrinsics``, (rvec, t) of every frame
    with an observation but one (the best-seen frame is held: it fixes the gauge), and
    the 3D point of every disc with an observation. ``card_prior`` = (metres per card
    unit, sigma in metres) adds each card's six disc-to-disc distances as soft
    residuals, which also fixes the scale.

    Why a hand-written solver: a survey has few points (4 per target) and many cameras,
    and with only 1-2 targets per frame it is badly conditioned (cards are small, the
    chain of frames is hinged about the line between two targets). SciPy's trust-region
    solver with a sparse Jacobian (inexact LSMR steps) stalled there far from the
    optimum (0.008 px RMS left on noise-free data, discs 0.3 m off). Eliminating the
    cameras instead (each a 6x6 block, independent given the points) leaves a small
    dense system over intrinsics + points that is solved exactly every iteration.
    Each observation is weighted by its precision (`disc_precision`: thin discs are
    measured worse) and Huber's loss of its whitened error (error / expected error; IRLS,
    quadratic up to ``loss_scale``).
    """
    use = use & bundle.registered()[tracks.frame] & bundle.placed()[tracks.point]
    obs = np.flatnonzero(use)
    frames = np.unique(tracks.frame[obs])
    points = np.unique(tracks.point[obs])
    ppos = np.full(len(bundle.X), -1)
    ppos[points] = np.arange(len(points))
    n_intr = 5 if free_intrinsics else 0
    n_y = n_intr + 3 * len(points)
    of = tracks.frame[obs]
    op = ppos[tracks.point[obs]]
    uv_obs = tracks.uv[obs]
    bounds = np.r_[0, np.flatnonzero(np.diff(of)) + 1, len(obs)]  # obs sorted by frame
    counts = np.diff(bounds)
    held = int(np.argmax(counts))  # the gauge: this frame's pose does not move
    # Local column indices (into y) of each frame's observations.
    slices = [slice(bounds[k], bounds[k + 1]) for k in range(len(bounds) - 1)]
    ycols = [np.r_[np.arange(n_intr), (n_intr + 3 * op[s][:, None] + np.arange(3)).ravel()] for s in slices]

    camera = bundle.camera
    intr = np.array([camera.fx, camera.cx, camera.cy, camera.dist[0], camera.dist[1]])
    cams = np.c_[bundle.rvec[frames], bundle.tvec[frames]]
    X = bundle.X[points].copy()

    prior_pairs = np.zeros((0, 2), int)
    prior_len = np.zeros(0)
    prior_sigma = 1.0
    if card_prior is not None:
        unit, prior_sigma = card_prior
        whole = [t for t in np.unique(points // 4) if (ppos[4 * t : 4 * t + 4] >= 0).all()]
        if whole:
            prior_pairs = np.concatenate([ppos[4 * t + _PAIRS] for t in whole])
            prior_len = np.tile(_PAIR_UNITS * unit, len(whole))

    def cam_of(intr_: np.ndarray) -> Camera:
        return _make_camera(intr_, camera.width, camera.height) if free_intrinsics else camera

    def project_all(cam: Camera, cams_: np.ndarray, X_: np.ndarray) -> np.ndarray:
        out = np.empty((len(obs), 2))
        for k, s in enumerate(slices):
            out[s], _ = _project_frame(cam, cams_[k, :3], cams_[k, 3:], X_[op[s]], False)
        return out - uv_obs

    precision = tracks.precision[obs]
    root_precision = np.sqrt(precision)

    def weights(r: np.ndarray) -> np.ndarray:
        # IRLS: each observation's precision times Huber's weight of its whitened error
        e = np.linalg.norm(r, axis=1) * root_precision
        return precision * np.where(e <= loss_scale, 1.0, loss_scale / np.maximum(e, 1e-300))

    def prior_residual(X_: np.ndarray) -> np.ndarray:
        if not len(prior_pairs):
            return np.zeros(0)
        d = np.linalg.norm(X_[prior_pairs[:, 0]] - X_[prior_pairs[:, 1]], axis=1)
        return (d - prior_len) / prior_sigma

    def robust_cost(r: np.ndarray, rp: np.ndarray) -> float:
        e = np.linalg.norm(r, axis=1) * root_precision
        c = np.where(e <= loss_scale, 0.5 * e**2, loss_scale * (e - 0.5 * loss_scale))
        return float(c.sum() + 0.5 * (rp**2).sum())

    def normal(intr: np.ndarray, cams: np.ndarray, X: np.ndarray, r: np.ndarray) -> tuple[Any, ...]:
        cam = cam_of(intr)
        w = weights(r)
        # ---- normal equations, cameras eliminated ----
        V = np.zeros((n_y, n_y))
        g_y = np.zeros(n_y)
        U_list, E_list, gc_list = [], [], []
        for k, s in enumerate(slices):
            n = s.stop - s.start
            _, jac = _project_frame(cam, cams[k, :3], cams[k, 3:], X[op[s]], True)
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
            cols = ycols[k]
            JyW = Jy * sw
            V[np.ix_(cols, cols)] += JyW.T @ Jy
            g_y[cols] += JyW.T @ rk
            if k == held:
                U_list.append(None)
                E_list.append(None)
                gc_list.append(None)
                continue
            JcW = Jc * sw
            U_list.append(JcW.T @ Jc)
            E_list.append(JcW.T @ Jy)
            gc_list.append(JcW.T @ rk)
        if len(prior_pairs):
            diff = X[prior_pairs[:, 0]] - X[prior_pairs[:, 1]]
            u = diff / (np.linalg.norm(diff, axis=1, keepdims=True) + 1e-300) / prior_sigma
            rp = prior_residual(X)
            for side, sign in ((0, 1.0), (1, -1.0)):
                for side2, sign2 in ((0, 1.0), (1, -1.0)):
                    ia = n_intr + 3 * prior_pairs[:, side][:, None] + np.arange(3)
                    ib = n_intr + 3 * prior_pairs[:, side2][:, None] + np.arange(3)
                    blocks = sign * sign2 * u[:, :, None] * u[:, None, :]
                    np.add.at(V, (ia[:, :, None], ib[:, None, :]), blocks)
                ia = n_intr + 3 * prior_pairs[:, side][:, None] + np.arange(3)
                np.add.at(g_y, ia, sign * u * rp[:, None])
        return V, g_y, U_list, E_list, gc_list

    def schur(V: np.ndarray, g_y: np.ndarray, U_list: list, E_list: list, gc_list: list, lam: float
              ) -> tuple[np.ndarray, np.ndarray, list]:
        S = V + lam * np.diag(np.diag(V) + 1e-12)
        rhs = g_y.copy()
        inv_list: list[np.ndarray | None] = []
        for k in range(len(slices)):
            if U_list[k] is None:
                inv_list.append(None)
                continue
            U = U_list[k] + lam * np.diag(np.diag(U_list[k]) + 1e-12)
            Ui = np.linalg.inv(U)
            inv_list.append(Ui)
            cols = ycols[k]
            EtUi = E_list[k].T @ Ui
            S[np.ix_(cols, cols)] -= EtUi @ E_list[k]
            rhs[cols] -= EtUi @ gc_list[k]
        return S, rhs, inv_list

    r = project_all(cam_of(intr), cams, X)
    cost = robust_cost(r, prior_residual(X))
    lam = 1e-4
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        V, g_y, U_list, E_list, gc_list = normal(intr, cams, X, r)
        # ---- damped solves until the cost goes down ----
        improved = False
        for _ in range(12):
            S, rhs, inv_list = schur(V, g_y, U_list, E_list, gc_list, lam)
            try:
                dy = -np.linalg.solve(S, rhs)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            dc = np.zeros_like(cams)
            for k in range(len(slices)):
                if inv_list[k] is None:
                    continue
                dc[k] = -inv_list[k] @ (gc_list[k] + E_list[k] @ dy[ycols[k]])
            intr_new = intr.copy()
            if n_intr:
                intr_new = intr + dy[:5]
            X_new = X + dy[n_intr:].reshape(-1, 3)
            cams_new = cams + dc
            try:
                r_new = project_all(cam_of(intr_new), cams_new, X_new)
            except ValueError:  # an impossible camera (f <= 0): a shorter step
                lam *= 10
                continue
            cost_new = robust_cost(r_new, prior_residual(X_new))
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
    if with_covariance and len(points):
        # Marginal covariance of intrinsics + points: inverse of the undamped reduced
        # system; a pseudo-inverse drops what the gauge leaves free (scale w/o prior).
        V, g_y, U_list, E_list, gc_list = normal(intr, cams, X, r)
        S, _, _ = schur(V, g_y, U_list, E_list, gc_list, 0.0)
        dof = max(2 * len(obs) - len(cams) * 6 - n_y + 6, 1)
        w = weights(r)
        sigma2 = float((w[:, None] * r**2).sum() / dof)
        covariance = np.linalg.pinv(S, rcond=1e-12, hermitian=True) * sigma2
    out = _Bundle(cam_of(intr), bundle.rvec.copy(), bundle.tvec.copy(), bundle.X.copy())
    out.rvec[frames], out.tvec[frames] = cams[:, :3], cams[:, 3:]
    out.X[points] = X
    info = {
        "iterations": iterations, "cost": cost, "rms_px": float(np.sqrt((r**2).sum(axis=1).mean())),
        "obs": obs, "points": points, "n_intr": n_intr, "residuals": r, "weights": weights(r),
        "covariance": covariance, "held_frame": int(frames[held]),
    }
    return out, info


#: A view of a point counts only within this multiple of the image corners' radius
#: (Camera.field_radius, short of the lens's fold): a 10% band for the poses' and the
#: lens's own errors during the survey.
_FIELD_MARGIN = 1.1


def _view_error(camera: Camera, pose: Pose, X: np.ndarray, uv: np.ndarray) -> float:
    """Worst reprojection error (px) of one view of a card's discs ``X``; inf when a
    disc lies behind the camera or outside its field (``Camera.in_field``)."""
    cam = pose.transform(X)
    if not camera.in_field(cam, _FIELD_MARGIN).all():
        return np.inf
    return float(np.abs(camera.project_map(X, pose) - uv).max())


def _errors(bundle: _Bundle, tracks: _Tracks, obs: np.ndarray) -> np.ndarray:
    """Reprojection error (px) of the observations ``obs`` (indices), nan if unplaced;
    inf where the point lies behind the camera or outside its field of view: such an
    observation cannot be of that point, however well its projection fits (a point
    past the lens's field can project into the image, folded by the distortion)."""
    err = np.full(len(obs), np.nan)
    of = tracks.frame[obs]
    order = np.argsort(of, kind="stable")
    obs_sorted = obs[order]
    bounds = np.r_[0, np.flatnonzero(np.diff(of[order])) + 1, len(obs)]
    for k in range(len(bounds) - 1):
        s, e = bounds[k], bounds[k + 1]
        f = tracks.frame[obs_sorted[s]]
        pts = tracks.point[obs_sorted[s:e]]
        X = bundle.X[pts]
        ok = np.isfinite(X[:, 0])
        if not ok.any() or not np.isfinite(bundle.rvec[f, 0]):
            continue
        uv, _ = _project_frame(bundle.camera, bundle.rvec[f], bundle.tvec[f], X[ok], False)
        idx = order[s:e][ok]
        cam = bundle.pose(f).transform(X[ok])
        seen = bundle.camera.in_field(cam, _FIELD_MARGIN)
        err[idx] = np.where(seen, np.linalg.norm(uv - tracks.uv[obs_sorted[s:e][ok]], axis=1), np.inf)
    return err


# --------------------------------------------------------------------------------------
# The survey
# --------------------------------------------------------------------------------------


def _subsample(n: int, max_frames: int | None, step: int) -> list[int]:
    used = list(range(0, n, max(1, int(step))))
    if max_frames is not None and len(used) > max_frames:
        if max_frames < 2:
            raise SurveyError("max_frames must be at least 2")
        pick = np.unique(np.linspace(0, len(used) - 1, int(max_frames)).round().astype(int))
        used = [used[i] for i in pick]
    return used


def survey(
    frames: Sequence[Sequence[DetectedTarget]],
    width: int,
    height: int,
    marker_size_m: float,
    intrinsics: Camera | None = None,
    progress: Progress | None = None,
    max_frames: int | None = None,
    step: int = 1,
    card_prior_m: float | None = 1e-5,
    outlier_px: float = 3.0,
) -> SurveyResult:
    """Survey the targets seen in a calibration video (see the module docstring).

    ``frames``: the detected targets of each frame, in video order. ``intrinsics``:
    a known camera (K and dist held fixed), else they are estimated. ``max_frames`` /
    ``step``: subsample long videos (evenly). ``card_prior_m``: sigma (metres) of a soft
    prior on each card's disc-to-disc distances inside the bundle adjustment (None:
    the scale is fitted afterwards only). Why on by default: a target linked to the
    rest only through frames from nearly one viewpoint can slide along the rays from
    that viewpoint, scaled, at no cost in reprojection error; its printed size is what
    pins it (bench, 300 frames, detector output: disc RMS 44 mm without, 3.9 mm with).
    Why so tight (10 um, nearly a constraint): a printed card keeps its disc-to-disc
    distances, bent or not (a bend moves a disc along the card's normal, changing the
    distances only to second order), far better than the survey measures them;
    tests/test_survey.py's synthetic walk gives discs of 0.8-1.1 mm with it and
    2.1-3.7 mm at 1 mm (4 noise seeds; until session 7 the weights were scaled so
    that the nominal 1 mm acted as 10 um).
    ``outlier_px``: how far (px) a view may be off while the map grows (the final
    bundle adjustment judges by the noise level instead). Raises ``SurveyError`` when
    the video does not allow a survey.
    """
    timing: dict[str, float] = {}
    clock = time.perf_counter()

    def report(stage: str, fraction: float) -> None:
        if progress is not None:
            progress(stage, float(min(max(fraction, 0.0), 1.0)))

    def lap(stage: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timing[stage] = timing.get(stage, 0.0) + now - clock
        clock = now

    if not (marker_size_m > 0 and np.isfinite(marker_size_m)):
        raise SurveyError(f"marker_size_m must be a positive length in metres, got {marker_size_m}")
    if intrinsics is not None and (intrinsics.width, intrinsics.height) != (width, height):
        intrinsics = intrinsics.scaled_to(width, height)
    if len(frames) < 2:
        raise SurveyError(f"a survey needs a video of at least 2 frames, got {len(frames)}")
    used = _subsample(len(frames), max_frames, step)
    tracks, duplicates, malformed = _collect(frames, used)
    warnings: list[str] = []
    if duplicates:
        warnings.append(f"{duplicates} detections of an id seen twice in the same frame were ignored "
                        "(two cards with the same id?)")
    if malformed:
        warnings.append(f"{malformed} detections whose discs do not form the card's square (mirrored or "
                        "folded) were ignored")
    if len(tracks.ids) == 0:
        raise SurveyError("no targets were detected in any frame of the video")
    n_frames, n_targets = tracks.n_frames, len(tracks.ids)
    views_per_frame = np.bincount(tracks.frame[::4], minlength=n_frames)
    if (views_per_frame > 0).sum() < 2:
        raise SurveyError("targets were detected in fewer than 2 frames: nothing to triangulate from")

    # ---- 1. intrinsics ------------------------------------------------------------------
    report("intrinsics", 0.0)
    model = _card_model(marker_size_m)
    fixed = intrinsics is not None
    if fixed:
        camera = intrinsics
    else:
        cards = tracks.uv.reshape(-1, 4, 2)
        focal = focal_from_cards(cards, width, height)
        lens = lens_from_cards(cards, width, height, focal) if focal is not None else None
        if focal is None:
            # Cards all seen head-on: start from a typical ~60 degree lens; BA refines.
            focal = 0.85 * max(width, height)
            warnings.append("the cards did not determine an initial focal length (all seen head-on?); "
                            "started from a typical lens")
        k1 = 0.0
        if lens is not None:
            focal, k1 = lens
        camera = Camera.pinhole(focal, width, height, dist=[k1, 0.0, 0.0, 0.0, 0.0])
    lap("intrinsics")

    # ---- 2. metric start ------------------------------------------------------------------
    report("initial", 0.05)
    bundle = _Bundle(camera, np.full((n_frames, 3), np.nan), np.full((n_frames, 3), np.nan),
                     np.full((4 * n_targets, 3), np.nan))
    view_frame = tracks.frame[::4]
    view_target = tracks.target[::4]
    view_uv = tracks.uv.reshape(-1, 4, 2)
    areas = np.array([abs(cv2.contourArea(q.astype(np.float32))) for q in view_uv])
    views_of_frame = [np.flatnonzero(view_frame == f) for f in range(n_frames)]
    views_of_target = [np.flatnonzero(view_target == t) for t in range(n_targets)]
    usable = np.ones(len(view_frame), bool)  # views not (yet) found to be wrong
    placed_by_plane = np.zeros(n_targets, bool)
    weak = np.zeros(n_frames, bool)  # registered from a single target
    rng = np.random.default_rng(0)  # deterministic sampling of view pairs
    # Before the lens is fitted the image is off by the unmodelled distortion (several
    # pixels at the edges): judge loosely until then.
    loose_px = 2 * outlier_px if fixed else 4 * outlier_px
    start = _two_view_seed(camera, view_frame, view_target, view_uv, views_of_frame, marker_size_m, loose_px)
    if start is not None:
        seed, partner, partner_pose, discs = start
        bundle.set_pose(seed, Pose.identity())
        bundle.set_pose(partner, partner_pose)
        for t, X in discs.items():
            bundle.X[4 * t : 4 * t + 4] = X
    else:
        # No pair of frames gives a start (too few targets shared, too little motion):
        # the frame that sees most targets (then most card area) fixes the map frame
        # and its cards are placed by their planar poses.
        score = views_per_frame * 1e9 + np.bincount(view_frame, weights=areas, minlength=n_frames)
        seed = int(np.argmax(score))
        bundle.set_pose(seed, Pose.identity())

    def place_card(views: list[int]) -> np.ndarray | None:
        """A card's discs (4, 3) from its views as the printed card, rigid, fitted to them;
        None when most views agree with no placement.

        Starts: its planar pose (both tilts) in its largest images. The start that most
        views agree with wins, then the tilt that the views' own planar fits favour. Not
        simply the largest view's planar pose: a broken detection or a folded projection
        from outside the field can be the largest (a card placed 6 m off dragged the map
        with it); and not the closest joint fit: a card 17 px wide fits 3 views 1 degree
        apart within 0.1 px in both tilts, while those frames' poses are still ~0.2 px
        off each other (a wrong tilt, 80 degrees off, ended 80 mm off: a minimum the
        bundle does not leave). In each view alone the right tilt fits 4-10 times better,
        whatever that frame's position.
        """
        tol_px = outlier_px if lens_refined else loose_px
        if len(views) > 30:  # enough to tell the tilts apart, evenly over the track
            views = [views[k] for k in np.linspace(0, len(views) - 1, 30).round().astype(int)]
        poses = [bundle.pose(view_frame[v]) for v in views]
        # Each view's two tilts: the card's orientation in the map, its fit in that view.
        tilts = [[(p.R.T @ plane.R, float(((bundle.camera.project(plane.transform(model)) - view_uv[v]) ** 2).sum()))
                  for plane in _planar_poses(bundle.camera, view_uv[v], model)]
                 for p, v in zip(poses, views, strict=True)]

        def errors(card: Pose) -> np.ndarray:
            X = card.transform(model)
            return np.array([_view_error(bundle.camera, p, X, view_uv[v])
                             for p, v in zip(poses, views, strict=True)])

        def tilt_cost(R: np.ndarray, among: np.ndarray) -> float:
            """Sum over the views ``among`` of the fit of that view's tilt nearest to R
            (the nearest rotation has the largest trace of R @ R_tilt.T: 1 + 2 cos)."""
            return float(sum(max(fits, key=lambda fit: np.trace(R @ fit[0].T))[1]
                             for k, fits in enumerate(tilts) if among[k] and fits))

        best: tuple[int, float] | None = None
        chosen: np.ndarray | None = None
        for c in sorted(views, key=lambda v: -areas[v])[:3]:
            to_map = bundle.pose(view_frame[c]).inverse()
            for plane in _planar_poses(bundle.camera, view_uv[c], model):
                card = to_map.compose(plane)
                for _ in range(2):  # fit to the views that agree, judge all
                    agree = np.flatnonzero(errors(card) < tol_px)
                    if len(agree) < 2:
                        break
                    card, _ = _fit_card(bundle.camera, [poses[k] for k in agree], [view_uv[views[k]] for k in agree],
                                        model, card)
                fit = errors(card) < tol_px
                key = (int(fit.sum()), -tilt_cost(card.R, fit))
                if best is None or key > best:
                    best, chosen = key, card.transform(model)
        return chosen if best is not None and best[0] > len(views) / 2 else None

    def place_targets() -> int:
        """Place every unplaced target seen by a registered frame."""
        registered = bundle.registered()
        added = 0
        for t in range(n_targets):
            if np.isfinite(bundle.X[4 * t, 0]) and not placed_by_plane[t]:
                continue
            # A target found wrong is placed again only from more evidence than it had.
            if int(registered[view_frame[views_of_target[t]]].sum()) <= unplaced_at[t]:
                continue
            # Only frames whose pose rests on 2+ targets place new targets: a chain of
            # single-card poses (each with its two-tilt ambiguity) drifts and flips.
            # Frames registered from one card may still triangulate (2+ views, a real
            # baseline), but never place a card from its own planar pose alone.
            views = [v for v in views_of_target[t] if registered[view_frame[v]] and usable[v]]
            strong = [v for v in views if not weak[view_frame[v]]]
            if not views:
                continue
            poses = [bundle.pose(view_frame[v]) for v in views]
            if len(views) >= 2:
                centres = np.array([p.position for p in poses])
                x = np.stack([_normalised(bundle.camera, view_uv[v]) for v in views])  # (V, 4, 2)
                tol = (outlier_px if lens_refined else loose_px) / bundle.camera.fx
                found = _triangulate_robust(poses, x, tol, rng)
                if found is not None:
                    X, inl = found
                    wide = _max_angle_deg(centres[inl], X.mean(axis=0)) >= MIN_BASELINE_DEG
                    # The card must come out with its printed shape: rays from poses that
                    # are still a little off cross metres away from the card when the
                    # baseline is narrow (3 views 3.6 degrees apart placed cards 1.2 m off,
                    # 15-27 % off their size, in a wrong minimum the bundle could not leave).
                    d = np.linalg.norm(X[_PAIRS[:, 0]] - X[_PAIRS[:, 1]], axis=1)
                    printed = bool(np.abs(d / (_PAIR_UNITS * marker_size_m) - 1).max() < MAX_SHAPE_ERROR)
                    if wide and printed and (inl.sum() >= 3 or inl.sum() == len(views)):
                        bundle.X[4 * t : 4 * t + 4] = X
                        # An upgrade from a planar placement also counts: the map changed.
                        placed_by_plane[t] = False
                        added += 1
                        continue
            if np.isfinite(bundle.X[4 * t, 0]):
                continue  # keep the planar placement until the baseline allows better
            # From frames whose pose rests on 2+ targets if any; a frame posed from one card
            # is the last resort (the only link to a part of the room seen apart).
            views = strong or views
            if not views:
                continue
            # Narrow baseline so far: the printed card, rigid, fitted to its views.
            chosen = place_card(views)
            if chosen is None:
                continue  # the views disagree: wait for more
            bundle.X[4 * t : 4 * t + 4] = chosen
            placed_by_plane[t] = True
            added += 1
        return added

    def single_target_pose(f: int, ob: TargetObservation, noise_px2: float) -> Pose | None:
        """A frame that sees one placed target: of the two poses that card allows, those
        the image does not refute (a fit worse than the other's by more than 25 in chi^2,
        with the map's residual variance ``noise_px2``), then the one closest to the
        nearest registered frame of the video (a hand-held camera moves smoothly).

        Why the image first: neighbouring frames registered on 2+ targets can be 9
        frames away, the camera having turned 40 degrees meanwhile; the wrong tilt (2 m
        and 50 degrees off) was then the closer one, though it fitted the card 12 times
        worse than the right one (0.94 against 0.08 px^2 at 0.1 px noise)."""
        registered = np.flatnonzero(bundle.registered())
        # IPPE wants exactly coplanar points: use the card's best-fit plane (the
        # surveyed discs are a little off it), then refine on the 3D discs.
        centre = ob.map.mean(axis=0)
        _, _, Vt = np.linalg.svd(ob.map - centre)
        if np.linalg.det(Vt) < 0:
            Vt[2] *= -1
        planar = np.c_[((ob.map - centre) @ Vt.T)[:, :2], np.zeros(4)]
        try:
            _, rvecs, tvecs, _ = cv2.solvePnPGeneric(planar, ob.image, bundle.camera.K, bundle.camera.dist,
                                                     flags=cv2.SOLVEPNP_IPPE)
        except cv2.error:
            return None
        fits: list[tuple[Pose, float]] = []
        for rvec, tvec in zip(rvecs, tvecs, strict=False):
            plane_pose = Pose.from_rvec_tvec(rvec, tvec)
            pose = Pose(plane_pose.R @ Vt, plane_pose.t - plane_pose.R @ Vt @ centre)
            rvec, tvec = cv2.solvePnPRefineLM(ob.map, ob.image, bundle.camera.K, bundle.camera.dist,
                                              pose.rvec.reshape(3, 1).copy(), pose.t.reshape(3, 1).copy())
            pose = Pose.from_rvec_tvec(rvec, tvec)
            residual = bundle.camera.project_map(ob.map, pose) - ob.image
            in_front = (pose.transform(ob.map)[:, 2] > 0).all()
            if in_front and np.abs(residual).max() < (2 if lens_refined else 10) * outlier_px:
                fits.append((pose, float((residual**2).sum())))
        if not fits or not len(registered):
            return None
        closest = min(sse for _, sse in fits)
        poses = [pose for pose, sse in fits if sse - closest < 25 * noise_px2]
        best = min(poses, key=lambda p: continuity(f, p))
        return best if np.isfinite(continuity(f, best)) else None

    def continuity(f: int, pose: Pose) -> float:
        """How far ``pose`` is from the nearest frame registered on 2+ targets, in units
        of the camera's typical motion over that many frames; inf when implausible or
        when there is no such frame within 10 frames.

        A pose that rests on one card is checked against the video's motion: a card
        seen from far has two tilts that fit (poses metres apart), and a card with a
        misread code fits perfectly somewhere else in the room. A hand-held camera
        moves smoothly, so the pose must lie near its neighbours'.
        """
        strong = np.flatnonzero(bundle.registered() & ~weak)
        strong = strong[strong != f]
        if not len(strong):
            return np.inf
        nearest = int(strong[np.argmin(np.abs(strong - f))])
        gap = abs(nearest - f)
        if gap > 10:
            return np.inf
        # The camera's motion per frame, from consecutive frames registered on 2+ targets.
        pairs = strong[:-1][np.diff(strong) == 1]
        if len(pairs) >= 3:
            steps = np.array([np.linalg.norm(bundle.pose(int(a)).position - bundle.pose(int(a) + 1).position)
                              for a in pairs[:: max(1, len(pairs) // 50)]])
            angles = np.array([_rotation_angle(bundle.pose(int(a)), bundle.pose(int(a) + 1))
                               for a in pairs[:: max(1, len(pairs) // 50)]])
            step, turn = float(np.median(steps)), float(np.median(angles))
        else:
            step, turn = np.inf, np.inf
        ref = bundle.pose(nearest)
        depth = float(np.linalg.norm(ref.position - bundle.X[np.isfinite(bundle.X[:, 0])].mean(axis=0)))
        max_move = max(3 * gap * step, 0.05 * depth) if np.isfinite(step) else 0.5 * depth
        max_turn = max(3 * gap * turn, np.radians(5)) if np.isfinite(turn) else np.radians(30)
        move = float(np.linalg.norm(pose.position - ref.position))
        angle = _rotation_angle(pose, ref)
        if move > max_move or angle > max_turn:
            return np.inf
        return move / max_move + angle / max_turn

    def noise_variance() -> float:
        """Variance (px^2, per coordinate) of the map's residuals now: robust (Rayleigh:
        the median 2D error is 1.1774 sigma), at least (0.01 px)^2."""
        judged = usable & bundle.registered()[view_frame] & bundle.placed()[view_target * 4]
        err = _errors(bundle, tracks, np.flatnonzero(judged.repeat(4)))
        err = err[np.isfinite(err)]
        return max(float(np.median(err)) / 1.1774 if len(err) else 1.0, 0.01) ** 2

    def register_frames(min_targets: int, attempted: dict[int, int]) -> int:
        """PnP of every unregistered frame that sees ``min_targets`` placed targets."""
        noise_px2 = noise_variance() if min_targets < 2 else 1.0
        placed = bundle.placed()[0::4]
        registered = bundle.registered()
        candidates = []
        for f in np.flatnonzero(~registered):
            views = [v for v in views_of_frame[f] if placed[view_target[v]] and usable[v]]
            if len(views) >= min_targets and attempted.get(int(f), -1) < len(views):
                candidates.append((len(views), int(f), views))
        added = 0
        for count, f, views in sorted(candidates, reverse=True):
            attempted[f] = count
            obs = [TargetObservation(int(view_target[v]), view_uv[v], bundle.X[4 * view_target[v] : 4 * view_target[v] + 4])
                   for v in views]
            est = None
            if count >= 2:
                try:
                    est = nonlinear(obs, bundle.camera, outlier_px=max(outlier_px, 4.0))
                except (PoseUndetermined, cv2.error):
                    est = None
                # The map is still coarse while it grows: accept a loose fit, BA tightens it.
                if est is not None and est.rms_px > (2 if lens_refined else 10) * outlier_px:
                    est = None
                # A pose that rests on one card after all must fit the camera's motion.
                if est is not None and len(est.target_ids) < 2 and not np.isfinite(continuity(f, est.pose)):
                    est = None
            if est is not None:
                bundle.set_pose(f, est.pose)
                weak[f] = len(est.target_ids) < 2
                # Targets that do not fit the others here (misidentified?) are not used in
                # this frame; the last rounds of the bundle adjustment may take them back.
                rejected = set(est.rejected_ids)
                for v, ob in zip(views, obs, strict=True):
                    if ob.id in rejected:
                        usable[v] = False
                added += 1
                continue
            if min_targets > 1:
                continue
            # One card at a time (a frame with one placed target, or two that disagree):
            # the card whose pose fits the camera's motion best, the others set aside.
            found = [(continuity(f, pose), k, pose) for k, ob in enumerate(obs)
                     if (pose := single_target_pose(f, ob, noise_px2)) is not None]
            if not found:
                continue
            _, k, pose = min(found, key=lambda c: c[0])
            bundle.set_pose(f, pose)
            weak[f] = True
            for j, v in enumerate(views):
                if j != k:
                    usable[v] = False
            added += 1
        return added

    unplaced_at = np.full(n_targets, -1)  # registered views of a target when found wrong
    lens_refined = fixed  # until then the initial focal length may be ~10 % off: fit loosely

    def view_errors(views: np.ndarray, px_unit: np.ndarray | None = None) -> np.ndarray:
        """Worst disc error of each view in the mask ``views`` (0 elsewhere; inf for a
        view of a point behind the camera or outside its field): in px, or in multiples
        of each observation's ``px_unit`` (M,)."""
        obs = np.flatnonzero(views.repeat(4))
        err = _errors(bundle, tracks, obs)
        if px_unit is not None:
            err = err / px_unit[obs]
        view_err = np.zeros(len(views))
        np.maximum.at(view_err, obs // 4, np.nan_to_num(err, nan=np.inf))
        return view_err

    def prune(threshold: float, px_unit: np.ndarray | None = None, readmit_below: float | None = None) -> bool:
        """Judge the map by every view of a registered frame and a placed target, also
        those set aside: a frame or a target most of whose views do not fit is wrong
        (unregistered / unplaced; the target's views get a new chance), a single view
        that does not fit is set aside (a misread card, a point outside the field), one
        set aside earlier that fits now is taken back. True if anything changed.

        Why all views: judged by the views it kept, a target placed from a few wrong
        views (a folded projection from outside the field, placed from its planar pose)
        fits them perfectly, while the 60 right ones had been set aside as outliers
        against it, one frame at a time. A view set aside is taken back below
        ``readmit_below`` (default: the threshold)."""
        changed = False
        judged = bundle.registered()[view_frame] & bundle.placed()[view_target * 4]
        errors = view_errors(judged, px_unit)
        misfit = judged & (errors > threshold)
        for f in np.flatnonzero(bundle.registered()):
            v = views_of_frame[f][judged[views_of_frame[f]]]
            if f != seed and len(v) and misfit[v].mean() > 0.5:
                bundle.rvec[f] = bundle.tvec[f] = np.nan
                changed = True
        judged &= bundle.registered()[view_frame]
        for t in np.flatnonzero(bundle.placed()[0::4]):
            v = views_of_target[t][judged[views_of_target[t]]]
            if len(v) and misfit[v].mean() > 0.5:
                bundle.X[4 * t : 4 * t + 4] = np.nan
                placed_by_plane[t] = False
                usable[views_of_target[t]] = True
                unplaced_at[t] = len(v)
                changed = True
        judged &= bundle.placed()[view_target * 4]
        bad = judged & misfit & usable
        readmit = judged & ~usable & (errors <= (threshold if readmit_below is None else readmit_below))
        usable[bad] = False
        usable[readmit] = True
        return changed or bool(bad.any() or readmit.any())

    lap("initial")

    prior = None if card_prior_m is None else (marker_size_m, float(card_prior_m))

    # ---- 3. incremental growth -----------------------------------------------------------
    attempted: dict[int, int] = {}
    placed = place_targets()
    passes = 0
    for min_targets in (2, 1):
        while passes < 100:  # a bound: pruning and re-registering must not cycle forever
            passes += 1
            added = register_frames(min_targets, attempted)
            n_reg = int(bundle.registered().sum())
            report("register", 0.05 + 0.45 * n_reg / n_frames)
            if (added or placed) and n_reg >= 3:
                # Keep the growing map consistent (the intrinsics move once there are
                # enough frames), then take back what still does not fit: a frame or a
                # target placed from a weak view is placed again later from better ones.
                lens_free = not fixed and n_reg >= 15
                # The card prior here too: a card linked to the rest only through frames
                # from nearly one viewpoint slides along their rays at no cost, and frames
                # registered against it inherit the error (noise-free walks ended 20 mm off).
                bundle, _ = bundle_adjust(bundle, tracks, usable.repeat(4), free_intrinsics=lens_free,
                                          card_prior=prior, max_iterations=10)
                # Before the lens is refined the initial focal length may be ~10 % off:
                # do not judge views by their fit yet.
                lens_refined = lens_refined or lens_free
                if lens_refined and prune(2 * outlier_px):
                    attempted.clear()  # the map changed: frames refused before may fit now
            # New targets only from poses the bundle has just refined (with the lens): the
            # first frames are registered against a start made with the initial lens, a
            # few % off, and cameras 0.3 m off at 6 m triangulated narrow targets 1-2 m off.
            placed = place_targets()
            if added == 0 and placed == 0:
                break
    lap("register")
    if bundle.registered().sum() < 2:
        raise SurveyError("fewer than 2 frames could be registered: the targets must be seen from several "
                          "viewpoints, with at least two targets together in some frames")

    # ---- 4. bundle adjustment, outlier removal ------------------------------------------
    info: dict[str, Any] = {}
    clean = False
    expected_px = 1.0 / np.sqrt(tracks.precision)

    def spread() -> float:
        """Robust spread of the usable observations' whitened errors (1: as expected)."""
        judged = bundle.registered()[view_frame] & bundle.placed()[view_target * 4] & usable
        obs = np.flatnonzero(judged.repeat(4))
        z = _errors(bundle, tracks, obs) / expected_px[obs]
        z = z[np.isfinite(z)]
        # Rayleigh: the median 2D error is 1.1774 sigma. At least 0.01: on noise-free
        # input a zero spread would make every residual an outlier of Huber's loss.
        return max(float(np.median(z)) / 1.1774, 0.01) if len(z) else 1.0

    if not fixed and bundle.registered().sum() < 10:
        # Five lens parameters from a handful of frames: not determined. Keep the
        # initial estimate rather than fit noise.
        fixed = True
        warnings.append("too few frames could be registered to calibrate the lens: the initial focal length "
                        "estimate was kept and no distortion was fitted")
    for round_ in range(5):
        report("bundle", 0.5 + 0.1 * round_)
        bundle, info = bundle_adjust(bundle, tracks, usable.repeat(4), free_intrinsics=not fixed,
                                     card_prior=prior, max_iterations=100, loss_scale=HUBER_K * spread())
        # Frames that failed before may register now that the map and lens are right.
        before = int(bundle.registered().sum())
        attempted.clear()
        register_frames(1, attempted)
        grew = place_targets() > 0 or int(bundle.registered().sum()) > before
        # Whole views are judged (a misidentified target moves all its 4 discs), also
        # those set aside while the map grew: a view that fits now is taken back; from
        # the tight threshold only well inside it, else a view near it goes in and out
        # every round (five rounds, the last two undoing each other).
        if not prune(1.0, np.maximum(OUTLIER_K * spread() * expected_px, MIN_OUTLIER_PX), 0.5) and not grew:
            clean = True
            break
        # A frame left with no usable view, or a target with none: unregister / unplace.
        for f in np.flatnonzero(bundle.registered()):
            if not usable[views_of_frame[f]].any():
                bundle.rvec[f] = bundle.tvec[f] = np.nan
        for t in range(n_targets):
            if not usable[views_of_target[t]].any():
                bundle.X[4 * t : 4 * t + 4] = np.nan
    loss_scale = HUBER_K * spread()
    if not clean:
        bundle, info = bundle_adjust(bundle, tracks, usable.repeat(4), free_intrinsics=not fixed,
                                     card_prior=prior, max_iterations=100, loss_scale=loss_scale)
    # The covariance at the optimum (no iterations: the state stays as it is).
    _, info = bundle_adjust(bundle, tracks, usable.repeat(4), free_intrinsics=not fixed, card_prior=prior,
                            max_iterations=0, with_covariance=True, loss_scale=loss_scale)
    lap("bundle")

    # ---- 5. metric scale -----------------------------------------------------------------
    report("scale", 0.9)
    registered = bundle.registered()
    used_views = usable & registered[view_frame] & bundle.placed()[view_target * 4]
    n_rejected = int((~usable & registered[view_frame] & bundle.placed()[view_target * 4]).sum())
    n_views = np.bincount(view_target[used_views], minlength=n_targets)
    surveyed = np.flatnonzero((n_views >= 2) & np.isfinite(bundle.X[0::4, 0]))
    if len(surveyed) == 0:
        raise SurveyError("no target was seen in 2 or more registered frames")
    d = np.concatenate([np.linalg.norm(bundle.X[4 * t + _PAIRS[:, 0]] - bundle.X[4 * t + _PAIRS[:, 1]], axis=1)
                        for t in surveyed])
    L = np.tile(_PAIR_UNITS * marker_size_m, len(surveyed))
    s = float((d * L).sum() / (d * d).sum())
    bundle.X *= s
    bundle.tvec *= s
    scale_rms = float(np.sqrt(np.mean((s * d - L) ** 2)))
    lap("scale")

    # ---- 6. uncertainty and warnings -----------------------------------------------------
    report("covariance", 0.95)
    std = _disc_std(info, len(bundle.X)) * s
    obs_used = info["obs"]
    err = _errors(bundle, tracks, obs_used)
    rms = float(np.sqrt(np.nanmean(err**2)))
    results: list[SurveyedTarget] = []
    for t in surveyed:
        frames_t = np.unique(view_frame[views_of_target[t][used_views[views_of_target[t]]]])
        centres = np.array([bundle.pose(f).position for f in frames_t])
        X = bundle.X[4 * t : 4 * t + 4]
        angle = _max_angle_deg(centres, X.mean(axis=0))
        results.append(SurveyedTarget(int(tracks.ids[t]), X.copy(), std[4 * t : 4 * t + 4].copy(),
                                      int(len(frames_t)), angle))
    warnings += _warnings(results, tracks, used_views, view_frame, view_target, surveyed, n_views)
    trajectory: list[Pose | None] = [None] * len(frames)
    for fi, index in enumerate(used):
        if registered[fi]:
            trajectory[index] = bundle.pose(fi)
    lap("covariance")
    if not np.isfinite(rms) or rms > 2 * outlier_px:
        raise SurveyError(f"the survey did not converge (reprojection RMS {rms:.1f} px): the video does not "
                          "show the targets from enough viewpoints, or many targets are misidentified")
    report("done", 1.0)
    return SurveyResult(
        camera=bundle.camera, targets=results, rms_px=rms, trajectory=trajectory, warnings=warnings,
        intrinsics_fixed=intrinsics is not None, frames_used=used, n_observations=int(len(obs_used)),
        n_rejected_views=n_rejected, scale_residual_m=scale_rms, timing_s=timing,
    )


def _project_norm(pose: Pose, X: np.ndarray) -> np.ndarray:
    c = pose.transform(X)
    return c[:, :2] / c[:, 2:]


def _disc_std(info: dict[str, Any], n_points: int) -> np.ndarray:
    """RMS 3D standard deviation (sqrt of the covariance trace) of every disc, from the
    bundle's marginal covariance (cameras' uncertainty included, see bundle_adjust)."""
    std = np.full(n_points, np.nan)
    C = info.get("covariance")
    if C is None:
        return std
    n_intr = info["n_intr"]
    diag = np.clip(np.diag(C)[n_intr:], 0.0, None).reshape(-1, 3)
    std[info["points"]] = np.sqrt(diag.sum(axis=1))
    return std


def _warnings(results: list[SurveyedTarget], tracks: _Tracks, used_views: np.ndarray, view_frame: np.ndarray,
              view_target: np.ndarray, surveyed: np.ndarray, n_views: np.ndarray) -> list[str]:
    out: list[str] = []
    few = [r.id for r in results if r.n_views < MIN_VIEWS]
    if few:
        out.append(f"targets {few} were seen in fewer than {MIN_VIEWS} registered frames: their positions are weak")
    narrow = [r.id for r in results if r.baseline_deg < MIN_BASELINE_DEG]
    if narrow:
        out.append(f"targets {narrow} were seen from too narrow a range of directions "
                   f"(< {MIN_BASELINE_DEG:g} degrees): walk around them more")
    missing = sorted(set(tracks.ids.tolist()) - {r.id for r in results})
    if missing:
        out.append(f"targets {missing} were detected but could not be surveyed (not seen together with the "
                   "rest of the map from registered frames, or their views did not fit)")
    # Co-visibility graph of the surveyed targets: an edge when two share a frame.
    n = len(tracks.ids)
    vf, vt = view_frame[used_views], view_target[used_views]
    inc = sp.csr_matrix((np.ones(len(vf)), (vt, vf)), shape=(n, tracks.n_frames))
    adj = (inc @ inc.T)[surveyed][:, surveyed]
    n_comp, labels = connected_components(adj, directed=False)
    if n_comp > 1:
        sizes = np.bincount(labels)
        main = int(np.argmax(sizes))
        parts = [sorted(int(tracks.ids[surveyed[i]]) for i in np.flatnonzero(labels == c))
                 for c in range(n_comp) if c != main]
        out.append(f"parts of the map are not seen together with the rest (only linked through camera motion): "
                   f"{parts}; film them together with their neighbours")
    return out
