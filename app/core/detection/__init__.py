"""The disc detector (Claus & Fitzgibbon, WACV 2005, section 4): frame in, identified
targets out.

A frame goes through the stages in this order, each in its own module:

- `candidates`: disc candidates from a learned classifier over a 4-level pyramid
  (a dark-blob operator and a small perceptron reject almost every 12x12 window, a
  condensed nearest-neighbour rule judges the rest; non-maximum suppression).
- `targets.assemble_targets` turns the candidates into identified targets through
  `grouping` (disc quadrilaterals), `verification` (photometric checks through each
  card's homography), `refinement` (subpixel disc centres), `identification` (the
  code, and so the printed disc order) and `completion` (cards with a disc missing
  from the candidates).
- `disc_fit`: for the survey, small discs' centres fitted with a model of the card
  around them.
- `detector.Detector` runs it all on a frame, or on the regions a tracked pose predicts.
- `draw.draw_detections` draws what was found over the frame, for a person to check.

Hot loops are numba kernels kept beside their stage (`_candidates_kernels`,
`_grouping_kernels`, ...; conventions in `_numba`); `warm_up` compiles them all (or
loads them from the cache) once, before the first frame.
"""

from app.core.detection import (
    _candidates_kernels,
    _code_reader_kernels,
    _disc_fit_kernels,
    _completion_kernels,
    _grouping_kernels,
    _refinement_kernels,
    _verification_kernels,
)
from app.core.detection._frame import as_gray
from app.core.detection.candidates import MIN_SIDE, DiscClassifier, find_candidates, load_default_classifier
from app.core.detection.detector import Detection, Detector
from app.core.detection.disc_fit import fit_disc_centres
from app.core.detection.draw import draw_detections
from app.core.detection.grouping import group_candidates
from app.core.detection.targets import DetectedTarget, assemble_targets
from app.core.geometry import _kernels as _geometry_kernels

__all__ = [
    "MIN_SIDE",
    "DetectedTarget",
    "Detection",
    "Detector",
    "DiscClassifier",
    "as_gray",
    "assemble_targets",
    "draw_detections",
    "find_candidates",
    "fit_disc_centres",
    "group_candidates",
    "load_default_classifier",
    "warm_up",
]


def warm_up() -> None:
    """Compile (or load from the cache) every kernel the detector calls, so that the
    first frame does not pay for it. Call once at service start-up."""
    for kernels in (_candidates_kernels, _grouping_kernels, _verification_kernels, _refinement_kernels,
                    _code_reader_kernels, _disc_fit_kernels, _completion_kernels, _geometry_kernels):
        kernels.warm_up()
