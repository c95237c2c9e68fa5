"""What the survey benchmarks share: detecting a rendered walk (and tracking its features),
and tracking a walk with a map against the renderer's truth."""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator

import numpy as np
from tqdm import tqdm

from app.core.detection import DetectedTarget, Detector
from app.core.features import FeatureTracker, exclusion_mask
from app.core.geometry import (
    Camera,
    PoseUndetermined,
    Similarity,
    TargetObservation,
    alignment_residuals,
    estimate_pose,
    similarity_from_points,
)
from app.core.survey import FeatureObservations, SurveyResult
from app.sim import FrameTruth


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


def track_walk(frames: list[list[DetectedTarget]], truths: list[FrameTruth], discs: dict[int, np.ndarray],
               camera: Camera, to_world: Similarity | None = None, std: dict[int, np.ndarray] | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """`track_errors`, and each pose's normalised squared position error against the
    truth (NEES, e^T C^-1 e with the pose's `covariance_position`; chi-square with 3
    degrees of freedom if the covariance is honest). With `std` (each card's ``std_m``)
    the poses carry the map's uncertainty, as /track's do with a surveyed map."""
    errors, nees = [], []
    for detected, truth in zip(frames, truths, strict=True):
        obs = [TargetObservation(t.id, t.discs, discs[t.id], None if std is None else std[t.id])
               for t in detected if t.id in discs]
        try:
            estimate = estimate_pose(obs, camera)
        except PoseUndetermined:
            errors.append(np.nan)
            nees.append(np.nan)
            continue
        pose, covariance = estimate.pose, estimate.covariance_position
        if to_world is not None:
            pose = to_world.apply_pose(pose)
            covariance = to_world.scale**2 * to_world.R @ covariance @ to_world.R.T
        error = pose.position - truth.pose.position
        errors.append(float(np.linalg.norm(error)))
        nees.append(float(error @ np.linalg.solve(covariance, error)))
    return np.array(errors), np.array(nees)
