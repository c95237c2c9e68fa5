"""The automatic survey (paper §3, §5.1): every disc's 3D position and the camera's
intrinsics from a video of the room, by structure from motion over the cards.

`survey` runs the stages in order over one `SurveyState` (`reconstruction`); each stage
is a module of its own: `lens`, `seed`, `register`, `place`, `bundle`, `prune`, `scale`,
`result`, with the re-bundle policy in `policy` (docs/survey.md). `points` holds the
second kind of track the bundle adjustment takes beside the discs: natural-feature points
with their own noise level and a robust loss.
"""

from app.core.survey.advice import MapWarning, WarningKind
from app.core.survey.bundle import BundleInfo, bundle_adjust
from app.core.survey.lens import focal_from_cards, lens_from_cards
from app.core.survey.points import FeatureObservations, RobustLoss
from app.core.survey.policy import ShouldBundle, ShouldFitLens
from app.core.survey.reconstruction import survey
from app.core.survey.result import SurveyedTarget, SurveyResult
from app.core.survey.state import Progress, Reconstruction, SurveyError, SurveyStage, SurveyState
from app.core.survey.tracks import DISC_ERROR_PX, disc_precision

__all__ = [
    "DISC_ERROR_PX",
    "BundleInfo",
    "FeatureObservations",
    "MapWarning",
    "Progress",
    "Reconstruction",
    "RobustLoss",
    "ShouldBundle",
    "ShouldFitLens",
    "SurveyError",
    "SurveyResult",
    "SurveyStage",
    "SurveyState",
    "SurveyedTarget",
    "WarningKind",
    "bundle_adjust",
    "disc_precision",
    "focal_from_cards",
    "lens_from_cards",
    "survey",
]
