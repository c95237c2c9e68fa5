"""A rolling shutter in the survey: each frame's observations moved to its middle row's moment.

A phone reads a frame's rows one after another (`app.core.geometry.rolling`), so each
row of a survey video sees the room from where the camera was when that row was read.
One pose a frame cannot fit such views: the bundle adjustment bends the map and the lens
to absorb the shear, and the lens check may refuse the footage.

Before every bundle adjustment (`reconstruction.adjust`), `undo_readout` gives each
registered frame its motion through the readout from its neighbours in the trajectory
(the step from the frame before to the frame after), and moves every observation, discs
and feature points alike, from where it was detected to where the frame's middle-row
pose sees its point. So the poses, the map and the motion improve together as the map
grows and is refined.
"""

from __future__ import annotations

import cv2
import numpy as np

from app.core.geometry import CameraMotion, RollingShutter
from app.core.survey.state import Readout, Reconstruction, SurveyState

__all__ = ["frame_motions", "undo_readout"]

#: The farthest (video frames) a neighbour may be to give a frame its motion.
MAX_NEIGHBOUR_FRAMES = 10.0


def frame_motions(reconstruction: Reconstruction, frame_numbers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each registered frame's motion, per video frame, from its registered neighbours:
    the step from the one before to the one after (the step to or from one of them where
    the other is missing or too far); none without a neighbour.

    Parameters
    ----------
    reconstruction : Reconstruction
    frame_numbers : (F,) ndarray
        Each survey frame's place in the video, in video frames (increasing).

    Returns
    -------
    angular, linear : (F, 3) ndarray
        Per video frame, in each frame's camera axes (zero where unknown).
    """
    registered = np.flatnonzero(reconstruction.registered())
    n = len(reconstruction.rvec)
    angular, linear = np.zeros((n, 3)), np.zeros((n, 3))
    for k, f in enumerate(registered):
        before = registered[k - 1] if k > 0 else None
        after = registered[k + 1] if k + 1 < len(registered) else None
        if before is not None and frame_numbers[f] - frame_numbers[before] > MAX_NEIGHBOUR_FRAMES:
            before = None
        if after is not None and frame_numbers[after] - frame_numbers[f] > MAX_NEIGHBOUR_FRAMES:
            after = None
        a = before if before is not None else f
        b = after if after is not None else f
        if a == b:
            continue
        motion = CameraMotion.between(reconstruction.pose(a), reconstruction.pose(b),
                                      float(frame_numbers[b] - frame_numbers[a]))
        angular[f], linear[f] = motion.angular, motion.linear
    return angular, linear


def _shift(reconstruction: Reconstruction, shutter: RollingShutter, frame: np.ndarray, X: np.ndarray,
           uv: np.ndarray, angular: np.ndarray, linear: np.ndarray) -> np.ndarray:
    """(M, 2) how far the readout moved each observation (raw pixels `uv` of points `X`
    in `frame`) from where the frame's middle-row pose sees it; zero where unknown."""
    shift = np.zeros_like(uv)
    known = np.isfinite(X[:, 0]) & reconstruction.registered()[frame]
    if not known.any():
        return shift
    camera = reconstruction.camera
    f = frame[known]
    R = np.stack([cv2.Rodrigues(r.reshape(3, 1))[0] for r in reconstruction.rvec[f]]) if len(f) else np.zeros((0, 3, 3))
    at_frame = (R @ X[known][:, :, None])[:, :, 0] + reconstruction.tvec[f]
    times = shutter.row_times(uv[known, 1], camera.height)
    seen = CameraMotion(angular[f], linear[f]).seen(at_frame, times)
    shift[known] = camera.project(seen) - camera.project(at_frame)
    return shift


def undo_readout(state: SurveyState) -> float:
    """Move every observation to where its frame's middle-row pose sees it (in place), as
    the reconstruction has it now: a survey without a readout (`SurveyState.readout`)
    is left as it is.

    Parameters
    ----------
    state : SurveyState
        The survey; its tracks' and feature observations' pixels are replaced.

    Returns
    -------
    float
        The largest move, pixels.
    """
    readout = state.readout
    if readout is None:
        return 0.0
    rec = state.reconstruction
    angular, linear = frame_motions(rec, readout.frame_numbers)
    tracks = state.tracks
    shift = _shift(rec, readout.shutter, tracks.frame, rec.X[tracks.point], readout.raw_uv, angular, linear)
    # In place: the views' pixels are a view of the tracks'.
    tracks.uv[...] = readout.raw_uv - shift
    largest = float(np.abs(shift).max()) if len(shift) else 0.0
    features = state.features
    if len(features.frame):
        feature_shift = _shift(rec, readout.shutter, features.frame, state.feature_X[features.track],
                               readout.raw_feature_uv, angular, linear)
        features.uv[...] = readout.raw_feature_uv - feature_shift
        largest = max(largest, float(np.abs(feature_shift).max()))
    return largest
