"""Natural-feature tracks: the scene's own points followed through a video, beside the cards.

The survey registers frames through the cards; a frame that sees one card or none, or two
groups of cards never filmed together, needs more. This package tracks the walls' own
texture through the frames and hands back `FeatureTracks`: observations (frame, track,
uv), one track per physical point, flat and sorted by frame like the survey's disc
`Tracks`, so that feature points can join the reconstruction as a second kind of track.

How (the method the feature benchmark chose, docs/benchmarks/features.md; the others
stay selectable through `FeatureSettings.method`):

* **Frame to frame: KLT.** Corners (`cv2.goodFeaturesToTrack`, subpixel, at least
  ``min_distance_px`` apart, above an absolute eigenvalue floor so that sensor noise on a
  plain wall makes none) are followed by pyramidal Lucas-Kanade optical flow
  (`cv2.calcOpticalFlowPyrLK`) on frames with their shading removed (exposure, gain and
  light change from frame to frame), each point starting where its last motion predicts
  it. A point survives a frame pair only if tracking it back lands within
  ``forward_backward_px`` of its start and the camera's motion explains it within
  ``geometric_px`` (a homography, or a fundamental matrix when the view is not one plane,
  by RANSAC over the pair; nothing survives a pair where most links disagree, as after a
  cut). New corners replace the lost tracks.
* **Across the video: keyframes.** Every ``keyframe_interval`` frames the live points are
  described (ORB, or SIFT) and matched against the tracks of every earlier keyframe
  (Lowe's ratio test between distinct tracks); the matches, grouped by the earlier
  keyframe that saw them, pass a geometric check of their own, must span a part of the
  view (a repeated pattern matches over its own patch only) and must be confirmed by the
  optical flow from the earlier keyframe before their tracks merge. Returning to a wall
  thus gives its points their first visit's tracks (a loop closure, recorded as a
  `KeyframeLink`); two tracks seen in one frame never merge.
* **Excluded regions.** The caller passes, per frame, where no feature may lie: the
  detected cards (`exclusion_mask` draws them from their disc centres), whose discs are
  tracked as disc observations already. A tracked point that enters such a region ends.
* **A lens, when known**, corrects the points before every geometric check; the tracks
  keep the points as seen (distorted pixels, like the disc observations).

Empty or featureless frames give no observations and no error; the tracking is
deterministic (the same frames give the same tracks).

Modules:

* `app.core.features.tracks`: `FeatureTracks`, `KeyframeLink`.
* `app.core.features.settings`: `FeatureSettings`, `Method`, `Descriptor`.
* `app.core.features.tracker`: `FeatureTracker` (frame by frame), `track_features`.
* `app.core.features.klt`: corners and the forward-backward optical flow.
* `app.core.features.matching`: descriptors, the ratio test, the geometric check, the
  keyframe index.
* `app.core.features.masks`: where features may lie; `exclusion_mask`.
"""

from app.core.features.masks import exclusion_mask
from app.core.features.settings import Descriptor, FeatureSettings, Method
from app.core.features.tracker import FeatureTracker, track_features
from app.core.features.tracks import FeatureTracks, KeyframeLink

__all__ = [
    "Descriptor",
    "FeatureSettings",
    "FeatureTracker",
    "FeatureTracks",
    "KeyframeLink",
    "Method",
    "exclusion_mask",
    "track_features",
]
