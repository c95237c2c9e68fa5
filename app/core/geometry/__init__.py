"""Geometry shared by every part: the camera model, poses, pose estimation (paper
§5.2-5.3), similarity alignment, card homographies and the tracking regions a pose
predicts."""

from app.core.geometry.alignment import Similarity, alignment_residuals, similarity_from_points, target_origin_alignment
from app.core.geometry.camera import Camera, Pose
from app.core.geometry.homography import apply_homographies, disc_axes, homographies
from app.core.geometry.pose import (
    METHODS,
    PoseEstimate,
    PoseUndetermined,
    TargetObservation,
    cramer_rao_position_rms,
    estimate_pose,
    nonlinear,
)
from app.core.geometry.regions import MapTargets, Region, RegionParams, predict_regions

__all__ = [
    "METHODS",
    "Camera",
    "MapTargets",
    "Pose",
    "PoseEstimate",
    "PoseUndetermined",
    "Region",
    "RegionParams",
    "Similarity",
    "TargetObservation",
    "alignment_residuals",
    "apply_homographies",
    "cramer_rao_position_rms",
    "disc_axes",
    "estimate_pose",
    "homographies",
    "nonlinear",
    "predict_regions",
    "similarity_from_points",
    "target_origin_alignment",
]
