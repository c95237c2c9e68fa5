"""Tracking: one frame's targets and camera pose from a map, and a stream's memory.

A stream of frames (a /track connection) has a `TrackState`: its last poses predict
where the map's targets appear next, so only regions around them are searched
(`app.core.geometry.regions`), and how large their discs will be, so a large frame may be
decoded smaller. `plan_frame` decides both from the frame's size alone, before any pixel
is decoded; `track_frame` detects and estimates the pose in the decoded frame, falls back
to the whole frame when the regions give no pose, and returns targets and pose in the
frame's own pixels. A lone image (no state) is scanned whole.
"""

from app.core.tracking.frame import (
    REDUCED_MIN_DISC_PX,
    REDUCED_MIN_SIDE,
    REDUCTIONS,
    FramePlan,
    TrackedFrame,
    TrackingMap,
    TrackOptions,
    detect_and_pose,
    frame_camera,
    full_scale_estimate,
    full_scale_targets,
    plan_frame,
    reduced_camera,
    reducible,
    track_frame,
)
from app.core.tracking.state import MAX_TURN_PER_FRAME_RAD, TILT_OVERRULED_LIMIT, ScanReason, TrackState

__all__ = [
    "MAX_TURN_PER_FRAME_RAD",
    "REDUCED_MIN_DISC_PX",
    "REDUCED_MIN_SIDE",
    "REDUCTIONS",
    "TILT_OVERRULED_LIMIT",
    "FramePlan",
    "ScanReason",
    "TrackOptions",
    "TrackState",
    "TrackedFrame",
    "TrackingMap",
    "detect_and_pose",
    "frame_camera",
    "full_scale_estimate",
    "full_scale_targets",
    "plan_frame",
    "reduced_camera",
    "reducible",
    "track_frame",
]
