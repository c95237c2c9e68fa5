"""The disc detector (paper §4): candidate discs from a learned classifier, grouped into
targets, verified, refined to subpixel centres and identified by their code."""

from app.core.detection.candidates import MIN_SIDE, DiscClassifier, find_candidates, load_default_classifier
from app.core.detection.detector import Detection, Detector
from app.core.detection.disc_fit import fit_disc_centres
from app.core.detection.kernels import warm_up
from app.core.detection.targets import DetectedTarget, assemble_targets, group_candidates

__all__ = [
    "MIN_SIDE",
    "DetectedTarget",
    "Detection",
    "Detector",
    "DiscClassifier",
    "assemble_targets",
    "find_candidates",
    "fit_disc_centres",
    "group_candidates",
    "load_default_classifier",
    "warm_up",
]
