"""What the survey benchmarks share: detecting a rendered walk (and tracking its features),
the survey's floor (where its final bundle adjustment settles when started from the
truth), judging a surveyed map against the truth (a fit that a wrong card does not pull,
and which cards are wrong), and tracking a walk with a map against the renderer's truth."""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np
from tqdm import tqdm

from app.core.detection import DetectedTarget, Detector
from app.core.features import FeatureTracker, exclusion_mask
from app.core.geometry import (
    Camera,
    Pose,
    PoseHistory,
    PoseUndetermined,
    RollingShutter,
    Similarity,
    TargetObservation,
    alignment_residuals,
    estimate_pose,
    extrapolate,
    position_covariance,
    rolling_shutter_pose,
    similarity_from_points,
)
from app.core.geometry.rolling import MAX_GAP
from app.core.survey import FeatureObservations, SurveyResult
from app.core.survey.features import triangulate_features
from app.core.survey.reconstruction import adjust
from app.core.survey.state import StageClock, SurveySettings, SurveyState
from app.core.survey.tracks import collect_tracks
from app.sim import FrameTruth

#: A surveyed card is wrong when one of its discs lies further than `WRONG_M` from the
#: truth after the map's fit, or further than `WRONG_SIGMA` times its reported ``std_m``.
WRONG_M = 0.05
WRONG_SIGMA = 3.0


def detect_frames(detector: Detector, frames: Iterable[tuple[np.ndarray, FrameTruth]], n: int, desc: str
                  ) -> tuple[list[list[DetectedTarget]], list[FrameTruth], float]:
    """Detections, truths and detection time (s) of `n` rendered frames, with a progress bar."""
    detections, truths, detect_s = [], [], 0.0
    for image, truth in tqdm(frames, total=n, desc=desc, unit="frame", leave=False):
        start = time.perf_counter()
        detections.append(detector.detect(image).targets)
        detect_s += time.perf_counter() - start
        truths.append(truth)
    return detections, truths, detect_s


def detect_and_track_features(detector: Detector, frames: Iterable[tuple[np.ndarray, FrameTruth]], n: int,
                              desc: str) -> tuple[list[list[DetectedTarget]], list[FrameTruth], float,
                                                  FeatureObservations, float]:
    """`detect_frames`, then the feature tracks of the same frames as the survey job makes
    them (the detected cards left out): detections, truths, detection time (s), the
    feature observations and the feature tracking time (s)."""
    images: list[np.ndarray] = []

    def kept() -> Iterator[tuple[np.ndarray, FrameTruth]]:
        for image, truth in frames:
            images.append(image)
            yield image, truth

    detections, truths, detect_s = detect_frames(detector, kept(), n, desc)
    start = time.perf_counter()
    tracker = FeatureTracker()
    for image, detected in zip(images, detections, strict=True):
        tracker.add(image, exclusion_mask(image.shape[:2], np.array([t.discs for t in detected]).reshape(-1, 4, 2)))
    return detections, truths, detect_s, FeatureObservations.from_tracks(tracker.tracks()), time.perf_counter() - start


def survey_floor(frames: list[list[DetectedTarget]], truths: list[FrameTruth], camera: Camera, marker_size_m: float,
                 true_discs: dict[int, np.ndarray], features: FeatureObservations | None,
                 exact_discs: bool = False, exact_features: bool = False) -> dict[int, np.ndarray]:
    """Where the survey's final bundle adjustment settles when started from the truth: the
    optimum of the observations themselves, the floor no survey of them can be expected
    to get below.

    The survey's state is set to the truth (every frame that observes something at its
    true pose, every card at its true discs, the true lens), the feature points are
    triangulated from it and the final bundle adjustment (lens free) runs from there.
    Detections of ids that are not in the room are left out.

    Parameters
    ----------
    frames : list of list of DetectedTarget
        The detected cards of each frame.
    truths : list of FrameTruth
        Each frame's truth.
    camera : Camera
        The true camera.
    marker_size_m : float
        The cards' printed size.
    true_discs : dict
        Each card's true discs (4, 3) by id.
    features : FeatureObservations or None
        The feature tracks (None: the cards alone); not changed.
    exact_discs : bool
        Replace the disc observations by the true discs' projections.
    exact_features : bool
        Replace the feature observations by their triangulated points' true projections.

    Returns
    -------
    dict
        The adjusted discs (4, 3) of every card detected in 2 frames or more, by id, in
        the true room's frame.
    """
    frames = [[t for t in detected if t.id in true_discs] for detected in frames]
    tracks = collect_tracks(frames, list(range(len(frames))), [])
    if features is not None:
        features = FeatureObservations(features.frame, features.track, features.uv.copy(), features.sigma_px,
                                       features.loss, features.loss_scale)
    state = SurveyState.start(tracks, camera, SurveySettings(marker_size_m), StageClock(), [], features)
    state.lens_refined = True
    rec = state.reconstruction
    # A frame with nothing in it has nothing to hold its pose: it stays out.
    observing = np.zeros(len(frames), bool)
    observing[tracks.frame] = True
    if features is not None:
        observing[features.frame] = True
    for f, truth in enumerate(truths):
        if observing[f]:
            rec.set_pose(f, truth.pose)
    for k, card in enumerate(tracks.ids):
        rec.place(k, true_discs[int(card)])
    if exact_discs:
        for f, truth in enumerate(truths):
            rows = tracks.frame == f
            tracks.uv[rows] = camera.project_map(rec.X[tracks.point[rows]], truth.pose)
    triangulate_features(state)
    if exact_features and features is not None:
        Xf = state.feature_X[features.track]
        for f, truth in enumerate(truths):
            rows = (features.frame == f) & np.isfinite(Xf[:, 0])
            features.uv[rows] = camera.project_map(Xf[rows], truth.pose)
    adjust(state, True, 3.0)
    seen = np.bincount(tracks.target[::4], minlength=len(tracks.ids)) >= 2
    X = state.reconstruction.X.reshape(-1, 4, 3)
    return {int(card): X[k].copy() for k, card in enumerate(tracks.ids) if seen[k]}


def disc_rms_mm(discs: dict[int, np.ndarray], truth: dict[int, np.ndarray], ids: Iterable[int] | None = None
                ) -> float:
    """The RMS distance (mm) of the discs of the cards `ids` (default: all of `discs`) from
    the true ones after the best similarity transform of those cards; nan with none."""
    ids = sorted(discs if ids is None else (i for i in ids if i in discs and i in truth))
    if not ids:
        return float("nan")
    src = np.concatenate([discs[i] for i in ids])
    dst = np.concatenate([truth[i] for i in ids])
    return 1000 * float(np.sqrt(np.mean(alignment_residuals(similarity_from_points(src, dst), src, dst) ** 2)))


def robust_fit(discs: dict[int, np.ndarray], truth: dict[int, np.ndarray], with_scale: bool = True,
               tolerance_m: float = WRONG_M) -> tuple[Similarity, set[int]]:
    """The transform of a surveyed map onto the truth that a few wrong cards do not pull.

    Every pair of cards proposes a transform (and all the cards together one more); the
    one that brings the most cards within `tolerance_m` of the truth (every disc), then
    the smallest RMS over them, wins; it is refitted on those cards until they no longer
    change.

    Parameters
    ----------
    discs : dict
        The surveyed cards' discs (4, 3) by id.
    truth : dict
        The true discs by id (cards not in it take no part).
    with_scale : bool
        A similarity (True) or a rigid motion.
    tolerance_m : float
        How far a card's discs may lie from the truth to count as fitting.

    Returns
    -------
    Similarity
        The transform.
    set of int
        The cards it rests on (within `tolerance_m`); empty when none is.

    Raises
    ------
    ValueError
        When no card of `discs` is in `truth`.
    """
    ids = sorted(i for i in discs if i in truth)
    if not ids:
        raise ValueError("no surveyed card is in the room")
    src = {i: np.asarray(discs[i], np.float64) for i in ids}
    all_src = np.concatenate([src[i] for i in ids])
    all_dst = np.concatenate([truth[i] for i in ids])

    def fit(on: list[int]) -> Similarity:
        return similarity_from_points(np.concatenate([src[i] for i in on]), np.concatenate([truth[i] for i in on]),
                                      with_scale=with_scale)

    def worst(transform: Similarity) -> np.ndarray:
        return alignment_residuals(transform, all_src, all_dst).reshape(-1, 4).max(axis=1)

    def score(transform: Similarity) -> tuple[int, float]:
        w = worst(transform)
        good = w <= tolerance_m
        return int(good.sum()), -float(np.sqrt(np.mean(w[good] ** 2))) if good.any() else 0.0

    proposals = [ids] + ([list(pair) for pair in itertools.combinations(ids, 2)] if len(ids) > 2 else [])
    best: tuple[tuple[int, float], Similarity] | None = None
    for on in proposals:
        try:
            transform = fit(on)
        except ValueError:  # degenerate (collinear) discs propose nothing
            continue
        s = score(transform)
        if best is None or s > best[0]:
            best = (s, transform)
    if best is None:
        raise ValueError("the surveyed cards' discs are degenerate")
    transform = best[1]
    inliers = [i for i, w in zip(ids, worst(transform), strict=True) if w <= tolerance_m]
    for _ in range(20):
        if not inliers:
            break
        transform = fit(inliers)
        again = [i for i, w in zip(ids, worst(transform), strict=True) if w <= tolerance_m]
        if again == inliers or not again:
            break
        inliers = again
    return transform, set(inliers)


@dataclass(frozen=True)
class MapCheck:
    """A surveyed map against the truth (`check_map`)."""

    fit: Similarity  # the robust similarity onto the truth
    inliers: set[int]  # the cards it rests on
    errors_m: np.ndarray  # (4 N,) each surveyed disc's distance from the truth after `fit` (nan: no such card)
    rigid_errors_m: np.ndarray  # (4 N,) the same after the best rigid motion of the inliers
    std_m: np.ndarray  # (4 N,) each disc's reported std_m
    wrong: set[int]  # cards wrong: a disc over WRONG_M or WRONG_SIGMA std_m off, or not in the room
    named: set[int]  # cards a map warning names

    @property
    def wrong_named(self) -> set[int]:
        """Wrong cards that a warning names."""
        return self.wrong & self.named

    @property
    def wrong_silent(self) -> set[int]:
        """Wrong cards that no warning names."""
        return self.wrong - self.named


def check_map(result: SurveyResult, truth: dict[int, np.ndarray]) -> MapCheck:
    """Judge a surveyed map against the truth: which cards are wrong, and which of them
    the survey's warnings name.

    A card is wrong when one of its discs lies more than `WRONG_M` from the truth after a
    similarity fit (`robust_fit`: the wrong cards do not pull it), or more than
    `WRONG_SIGMA` of its reported ``std_m`` (where that is finite); a mapped id that is
    no card of the room is wrong too. A card is named when one of the result's typed
    ``map_warnings`` lists it, whatever the warning's kind.

    Parameters
    ----------
    result : SurveyResult
        The survey's result (at least one target).
    truth : dict
        The true discs (4, 3) by id.

    Returns
    -------
    MapCheck
    """
    discs = {t.id: t.discs for t in result.targets}
    fit, inliers = robust_fit(discs, truth)
    rigid = similarity_from_points(np.concatenate([discs[i] for i in sorted(inliers)]),
                                   np.concatenate([truth[i] for i in sorted(inliers)]),
                                   with_scale=False) if inliers else fit
    errors, rigid_errors, wrong = [], [], set()
    for t in result.targets:
        if t.id not in truth:
            errors.append(np.full(4, np.nan))
            rigid_errors.append(np.full(4, np.nan))
            wrong.add(t.id)
            continue
        e = alignment_residuals(fit, t.discs, truth[t.id])
        errors.append(e)
        rigid_errors.append(alignment_residuals(rigid, t.discs, truth[t.id]))
        std = np.asarray(t.std_m, np.float64)
        if e.max() > WRONG_M or bool(np.any(np.isfinite(std) & (e > WRONG_SIGMA * std))):
            wrong.add(t.id)
    named = {int(i) for w in getattr(result, "map_warnings", []) for i in w.target_ids}
    return MapCheck(fit, inliers, np.concatenate(errors), np.concatenate(rigid_errors),
                    np.concatenate([t.std_m for t in result.targets]), wrong, named)


def map_fit(result: SurveyResult, truth: dict[int, np.ndarray], with_scale: bool = True
            ) -> tuple[Similarity, np.ndarray]:
    """The surveyed map taken into the room's frame (the best similarity, or with
    ``with_scale=False`` the best rigid motion: the survey claims metric scale), and the
    error of each surveyed disc after it (m), in the targets' order."""
    src = np.concatenate([t.discs for t in result.targets])
    dst = np.concatenate([truth[t.id] for t in result.targets])
    fit = similarity_from_points(src, dst, with_scale=with_scale)
    return fit, alignment_residuals(fit, src, dst)


def track_errors(frames: list[list[DetectedTarget]], truths: list[FrameTruth], discs: dict[int, np.ndarray],
                 camera: Camera, to_world: Similarity | None = None) -> np.ndarray:
    """Camera position error (m) of each frame, nan where no pose, tracked as /track does
    (the `nonlinear` pose) with the map `discs`; `to_world` takes the map's frame into
    the room's (None: they are one)."""
    return track_walk(frames, truths, discs, camera, to_world)[0]


@dataclass(frozen=True)
class JointMapCovariance:
    """A survey's joint covariance of its discs (`SurveyResult.disc_covariance`), for
    poses that take the map's uncertainty from it rather than from each card's
    ``std_m`` (what /track has)."""

    rows: dict[int, np.ndarray]  # target id -> its 12 rows (x, y, z of each disc)
    covariance: np.ndarray
    cards_apart: bool = False  # keep each card's own block only: cards independent

    @classmethod
    def of(cls, result: SurveyResult, cards_apart: bool = False) -> JointMapCovariance:
        assert result.disc_covariance is not None
        return cls({t.id: np.arange(12 * k, 12 * k + 12) for k, t in enumerate(result.targets)},
                   result.disc_covariance, cards_apart)

    def of_cards(self, ids: list[int]) -> np.ndarray:
        """The covariance of the cards' stacked discs (m^2)."""
        rows = np.concatenate([self.rows[i] for i in ids])
        covariance = self.covariance[np.ix_(rows, rows)]
        if self.cards_apart:
            same = np.repeat(np.arange(len(ids)), 12)
            covariance = np.where(same[:, None] == same[None, :], covariance, 0.0)
        return covariance

    def position_part(self, pose: Pose, camera: Camera, observations: list[TargetObservation]) -> np.ndarray:
        """What the map's errors do to the camera centre of a least-squares pose, to
        first order: the pose moves by ``-(J^T J)^-1 J^T dr`` when the discs move by
        ``dX`` (``dr = J_t R dX``: the discs enter through ``R X + t``)."""
        world = np.concatenate([o.map for o in observations])
        _, jac = cv2.projectPoints(world, pose.rvec, pose.t, camera.K, camera.dist)
        J = jac[:, :6]
        moved = np.zeros((len(J), 3 * len(world)))
        for k in range(len(world)):
            moved[2 * k : 2 * k + 2, 3 * k : 3 * k + 3] = J[2 * k : 2 * k + 2, 3:6] @ pose.R
        D = -np.linalg.solve(J.T @ J, J.T @ moved)
        return position_covariance(pose, D @ self.of_cards([o.id for o in observations]) @ D.T)


def track_walk(frames: list[list[DetectedTarget]], truths: list[FrameTruth], discs: dict[int, np.ndarray],
               camera: Camera, to_world: Similarity | None = None, std: dict[int, np.ndarray] | None = None,
               shutter: RollingShutter | None = None, joint: JointMapCovariance | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """`track_errors`, and each pose's normalised squared position error against the
    truth (NEES, e^T C^-1 e with the pose's `covariance_position`; chi-square with 3
    degrees of freedom if the covariance is honest). With `std` (each card's ``std_m``)
    the poses carry the map's uncertainty, as /track's do with a surveyed map; with
    `joint` they carry it from the survey's joint covariance instead, added to the
    covariance of the pose's own fit. With `shutter` the frames are tracked as /track
    does with its ``rolling_shutter`` config: the motion through each readout fitted with
    the pose, from the track's last poses."""
    assert joint is None or (std is None and shutter is None)
    errors, nees = [], []
    history = PoseHistory()
    posed: list[tuple[int, Pose]] = []  # the last two poses: /track's prior (constant velocity)
    for k, (detected, truth) in enumerate(zip(frames, truths, strict=True)):
        obs = [TargetObservation(t.id, t.discs, discs[t.id], None if std is None else std[t.id])
               for t in detected if t.id in discs]
        try:
            if shutter is None or not obs:
                estimate = estimate_pose(obs, camera)
            else:
                track = history.motion_for(k)
                prior = None
                if track is not None:
                    prior = track.previous
                    if len(posed) == 2 and 0 < posed[1][0] - posed[0][0] <= MAX_GAP:
                        prior = extrapolate(posed[0][1], posed[1][1], (k - posed[1][0]) / (posed[1][0] - posed[0][0]))
                estimate = rolling_shutter_pose(obs, camera, shutter, track, prior).estimate
        except PoseUndetermined:
            errors.append(np.nan)
            nees.append(np.nan)
            history.add(k, None)
            continue
        history.add(k, estimate.pose)
        posed = [*posed[-1:], (k, estimate.pose)]
        pose, covariance = estimate.pose, estimate.covariance_position
        if joint is not None:
            covariance = covariance + joint.position_part(pose, camera, [o for o in obs
                                                                         if o.id in estimate.target_ids])
        if to_world is not None:
            pose = to_world.apply_pose(pose)
            covariance = to_world.scale**2 * to_world.R @ covariance @ to_world.R.T
        error = pose.position - truth.pose.position
        errors.append(float(np.linalg.norm(error)))
        nees.append(float(error @ np.linalg.solve(covariance, error)))
    return np.array(errors), np.array(nees)
