"""The whole fiducial detector of the paper (§4), frame in, identified targets out:
disc candidates (fast classifier + condensed nearest neighbour over a 4-level pyramid),
grouping by Delaunay triangulation, verification, subpixel centres, identification."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from app.core.candidates import DiscClassifier, detect_windows
from app.core.markers import DEFAULT_FAMILY, get_family
from app.core.targets import DetectedTarget, assemble_targets


@dataclass(frozen=True)
class Detection:
    """Targets found in one frame, every candidate disc, and where the time went."""

    targets: list[DetectedTarget]
    candidates: np.ndarray  # (N, 4) [u, v, radius, score]
    timing_ms: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class Detector:
    classifier: DiscClassifier
    family: str = DEFAULT_FAMILY

    def __post_init__(self) -> None:
        get_family(self.family)  # KeyError now rather than at the first frame

    def detect(self, gray: np.ndarray) -> Detection:
        """Detect targets in a uint8 greyscale frame."""
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise ValueError(f"expected a uint8 greyscale image, got {gray.dtype} {gray.shape}")
        start = time.perf_counter()
        candidates, s1, _ = detect_windows(gray, self.classifier)
        found = time.perf_counter()
        stages: dict[str, float] = {}
        # The candidate stage's pyramid serves the targets' sampling too.
        targets = assemble_targets(gray, candidates, self.family, timing=stages, pyramid=s1.levels)
        done = time.perf_counter()
        timing = {"candidates": (found - start) * 1e3, "targets": (done - found) * 1e3}
        timing.update({f"targets.{k}": v for k, v in stages.items()})  # group, verify, refine, identify
        timing["detect"] = (done - start) * 1e3
        return Detection(targets=targets, candidates=candidates, timing_ms=timing)
