"""A /track connection's poses as its client asked for them: in its client convention
(config ``frame``), smoothed (``smoothing``) and predicted ahead (``predict_ms``).

The filter's clock is the server's: each frame's time is when its message arrived, which
for a camera streaming live is its capture time plus a constant delay.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.core.geometry import Convention, OneEuroParams, Pose, PoseEstimate, PoseFilter, to_convention
from app.schemas import FilteredPoseOut, ClientPose, PoseFrame, PoseOut, Smoothing, TrackConfig

assert set(PoseFrame.__args__) == {c.value for c in Convention}  # type: ignore[attr-defined]
# A connection's `{"smoothing": {}}` is the core filter's defaults.
assert (Smoothing().min_cutoff_hz, Smoothing().beta, Smoothing().beta_rotation) == (
    OneEuroParams().min_cutoff_hz, OneEuroParams().beta, OneEuroParams().beta_rotation)


def frame_pose(R: np.ndarray, t: np.ndarray, frame: PoseFrame) -> ClientPose:
    """The pose (map to camera) in the client convention `frame`."""
    return ClientPose.model_validate(to_convention(R, t, Convention(frame)).to_dict())


@dataclass(frozen=True)
class ShapedPose:
    """One frame's poses for the reply and for FreeD."""

    pose: PoseOut | None  # the measured pose, with its frame_pose
    filtered: FilteredPoseOut | None  # smoothed and/or predicted, when asked for
    R: np.ndarray | None  # the pose to send on (filtered if asked for), map to camera
    t: np.ndarray | None


class PoseOutput:
    """One connection's filter state and the shaping of its poses (frames in order)."""

    def __init__(self) -> None:
        self._filter: PoseFilter | None = None
        self._settings: tuple[Smoothing | None, bool] | None = None

    def _filter_for(self, config: TrackConfig) -> PoseFilter | None:
        settings = (config.smoothing, config.predict_ms > 0)
        if settings != self._settings:  # a new filter when the config changes how it filters
            self._settings = settings
            smoothing, predicting = settings
            if smoothing is None and not predicting:
                self._filter = None
            else:
                params = OneEuroParams() if smoothing is None else OneEuroParams(
                    min_cutoff_hz=smoothing.min_cutoff_hz, beta=smoothing.beta, beta_rotation=smoothing.beta_rotation)
                self._filter = PoseFilter(params, smooth=smoothing is not None)
        return self._filter

    def shape(self, estimate: PoseEstimate | None, arrived_s: float, config: TrackConfig) -> ShapedPose:
        """The frame's poses, its pose having been measured on a frame that arrived at
        `arrived_s` (monotonic seconds)."""
        filter_ = self._filter_for(config)
        if estimate is None:
            return ShapedPose(None, None, None, None)
        R, t = estimate.pose.R, estimate.pose.t
        pose = PoseOut(**estimate.to_dict(), frame_pose=frame_pose(R, t, config.frame))
        if filter_ is None:
            return ShapedPose(pose, None, R, t)
        out: Pose = filter_.update(arrived_s, estimate.pose)
        if config.predict_ms > 0:
            out = filter_.predict(config.predict_ms / 1e3)
        filtered = FilteredPoseOut(R=out.R.tolist(), t=out.t.tolist(), position=out.position.tolist(),
                                   smoothed=config.smoothing is not None, predict_ms=config.predict_ms,
                                   frame_pose=frame_pose(out.R, out.t, config.frame))
        return ShapedPose(pose, filtered, out.R, out.t)
