"""What the survey benchmarks share: detecting a rendered walk (and tracking its features),
and tracking a walk with a map against the renderer's truth."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator

import numpy as np
from tqdm import tqdm

from app.core.detection import DetectedTarget, Detector
from app.core.features import FeatureTracker, exclusion_mask
from app.core.geometry import Camera, Pose, PoseUndetermined, TargetObservation, estimate_pose
from app.core.survey import FeatureObservations
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


def track_errors(frames: list[list[DetectedTarget]], truths: list[FrameTruth], discs: dict[int, np.ndarray],
                 camera: Camera, to_world: Callable[[Pose], Pose]) -> np.ndarray:
    """Camera position error (m) of each frame, nan where no pose, tracked as /track does
    (the `nonlinear` pose) with the map `discs`; `to_world` maps a pose of the map's frame
    into the room's."""
    errors = []
    for detected, truth in zip(frames, truths, strict=True):
        obs = [TargetObservation(t.id, t.discs, discs[t.id]) for t in detected if t.id in discs]
        try:
            pose = to_world(estimate_pose(obs, camera).pose)
            errors.append(float(np.linalg.norm(pose.position - truth.pose.position)))
        except PoseUndetermined:
            errors.append(np.nan)
    return np.array(errors)
