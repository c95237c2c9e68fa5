"""Geometry shared by every part: the camera model, poses, pose estimation (paper
§5.2-5.3), similarity alignment, card homographies, the tracking regions a pose
predicts, poses in client conventions, and the smoothing and prediction of a stream of
poses.

Conventions: poses map map points to the camera, ``x_cam = R @ X_map + t``, in metres;
pixel coordinates put the centre of the top-left pixel at (0, 0), x right, y down; a
target's discs are ordered 0 top-left, 1 top-right, 2 bottom-right, 3 bottom-left as
printed (docs/map-format.md).
"""

from app.core.geometry.alignment import Similarity, alignment_residuals, similarity_from_points, target_origin_alignment
from app.core.geometry.camera import Camera, IdealCanvas, Pose, rotation_angle
from app.core.geometry.conventions import (
    Convention,
    ConventionPose,
    covariance_to_convention,
    from_convention,
    quaternion_xyzw,
    to_convention,
)
from app.core.geometry.filtering import OneEuroParams, PoseFilter
from app.core.geometry.homography import (
    apply_homographies,
    disc_axes,
    ellipse_centres,
    homogeneous,
    homographies,
    jacobians,
    perspective_bias,
)
from app.core.geometry.pose import (
    METHODS,
    PoseEstimate,
    PoseUndetermined,
    TargetObservation,
    cramer_rao_position_rms,
    estimate_pose,
    nonlinear,
    position_covariance,
    refine_with_focal,
    single_target_poses,
    target_poses,
)
from app.core.geometry.rolling import (
    CameraMotion,
    PoseHistory,
    RollingPose,
    RollingShutter,
    TrackedMotion,
    rolling_shutter_pose,
    undo_rolling_shutter,
)
from app.core.geometry.regions import (
    MapTargets,
    PredictedTarget,
    Region,
    RegionParams,
    decode_reduction,
    disc_diameters,
    extrapolate,
    merge_regions,
    plan_regions,
    predict_in_view,
    predict_regions,
    predict_targets,
    reduce_regions,
)

__all__ = [
    "METHODS",
    "Camera",
    "CameraMotion",
    "Convention",
    "ConventionPose",
    "IdealCanvas",
    "MapTargets",
    "OneEuroParams",
    "Pose",
    "PoseEstimate",
    "PoseFilter",
    "PoseHistory",
    "PoseUndetermined",
    "PredictedTarget",
    "Region",
    "RegionParams",
    "RollingPose",
    "RollingShutter",
    "Similarity",
    "TargetObservation",
    "TrackedMotion",
    "alignment_residuals",
    "apply_homographies",
    "covariance_to_convention",
    "cramer_rao_position_rms",
    "decode_reduction",
    "disc_axes",
    "disc_diameters",
    "ellipse_centres",
    "estimate_pose",
    "extrapolate",
    "from_convention",
    "homogeneous",
    "homographies",
    "jacobians",
    "merge_regions",
    "nonlinear",
    "perspective_bias",
    "plan_regions",
    "position_covariance",
    "predict_in_view",
    "predict_regions",
    "predict_targets",
    "quaternion_xyzw",
    "reduce_regions",
    "refine_with_focal",
    "rolling_shutter_pose",
    "rotation_angle",
    "similarity_from_points",
    "single_target_poses",
    "target_origin_alignment",
    "target_poses",
    "to_convention",
    "undo_rolling_shutter",
]
