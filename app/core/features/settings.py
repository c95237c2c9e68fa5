"""How features are tracked: the method and its settings.

The defaults are the ones the feature benchmark chose (docs/benchmarks/features.md):
KLT optical flow between consecutive frames, ORB descriptors at keyframes for the loops.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

__all__ = ["Descriptor", "FeatureSettings", "Method"]


class Descriptor(StrEnum):
    """The descriptors that match features across keyframes (OpenCV's)."""

    ORB = "orb"
    SIFT = "sift"


class Method(StrEnum):
    """How tracks are linked from frame to frame, and which descriptors match keyframes."""

    KLT = "klt"  # optical flow between consecutive frames; no keyframe matching
    KLT_ORB = "klt+orb"  # optical flow; ORB descriptors of the tracked points at keyframes
    KLT_SIFT = "klt+sift"  # optical flow; SIFT descriptors of the tracked points at keyframes
    ORB = "orb"  # ORB keypoints detected in every frame, matched frame to frame and at keyframes
    SIFT = "sift"  # SIFT keypoints, likewise

    @property
    def flow(self) -> bool:
        """Whether consecutive frames are linked by optical flow (else by descriptors)."""
        return self in (Method.KLT, Method.KLT_ORB, Method.KLT_SIFT)

    @property
    def descriptor(self) -> Descriptor | None:
        """The descriptor of the keyframes (and, without flow, of every frame); None: no
        keyframe matching."""
        return {Method.KLT: None, Method.KLT_ORB: Descriptor.ORB, Method.KLT_SIFT: Descriptor.SIFT,
                Method.ORB: Descriptor.ORB, Method.SIFT: Descriptor.SIFT}[self]


@dataclass(frozen=True)
class FeatureSettings:
    """The feature tracker's settings.

    Attributes
    ----------
    method : Method
        How frames and keyframes are linked.
    max_features : int
        Most features tracked (or detected) per frame.
    min_distance_px : float
        Least distance between two features of one frame, px: lost tracks are replaced
        only this far from the live ones.
    quality_level : float
        A new corner's smaller structure-tensor eigenvalue relative to the frame's best
        (`cv2.goodFeaturesToTrack`).
    min_eigenvalue : float
        The smallest eigenvalue a new corner needs in absolute terms (OpenCV's
        `cornerMinEigenVal` scale, grey levels 0..1): a plain wall's sensor noise makes
        corners of its own that track nothing real.
    shading_px : int or None
        The optical flow reads frames with their shading removed, a box mean this many
        px either side (`klt.flow_image`): exposure, gain and light change from frame to
        frame. None: the frames as they are.
    window_px : int
        Side of the optical flow window, px.
    pyramid_levels : int
        Pyramid levels of the optical flow above the full image (each halves the size;
        3 find a point ~80 px from where its last motion predicts it).
    forward_backward_px : float
        How far a point tracked forward and back again may land from where it started, px.
    geometric_px : float
        How far a link between consecutive frames may lie from what the camera's motion
        explains (its epipolar line, or a homography's transfer), px.
    keyframe_interval : int
        Every so many frames is a keyframe, matched against the earlier ones.
    ratio : float
        Lowe's ratio test: a descriptor match counts when the best distance is below this
        fraction of the second best (of another track).
    loop_geometric_px : float
        Likewise for a keyframe match, px (keyframes lie far apart: the lens's and the
        points' own errors weigh more).
    loop_min_inliers : int
        Fewest verified matches that join two keyframes (and at least half of the
        descriptor matches grouped with them must agree).
    loop_min_spread : float
        The least part of the new keyframe's area that the verified matches must span
        (their convex hull): a repeated pattern matches over its own small patch only.
    loop_same_px : float
        How far from a keyframe match the optical flow from the earlier keyframe may put
        the earlier point, px, for the two to be one point.
    loop_min_confirmed : int
        Fewest matches so confirmed for the keyframes' tracks to merge.
    """

    method: Method = Method.KLT_ORB
    max_features: int = 500
    min_distance_px: float = 8.0
    quality_level: float = 0.01
    min_eigenvalue: float = 3e-4
    shading_px: int | None = 20
    window_px: int = 21
    pyramid_levels: int = 3
    forward_backward_px: float = 0.5
    geometric_px: float = 1.0
    keyframe_interval: int = 10
    ratio: float = 0.8
    loop_geometric_px: float = 2.0
    loop_min_inliers: int = 20
    loop_min_spread: float = 0.15
    loop_same_px: float = 1.0
    loop_min_confirmed: int = 8

    def __post_init__(self) -> None:
        if self.max_features < 1 or self.keyframe_interval < 1 or self.window_px < 5 or self.pyramid_levels < 0:
            raise ValueError("max_features and keyframe_interval must be positive, window_px at least 5, "
                             "pyramid_levels not negative")
        if not 0 < self.ratio <= 1:
            raise ValueError("ratio must lie in (0, 1]")
        if self.loop_min_inliers < 8:
            raise ValueError("loop_min_inliers must be at least 8 (fewer matches prove nothing about a motion)")
