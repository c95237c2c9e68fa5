"""A rolling shutter in the survey: each frame's observations moved to its middle row's moment.

A phone reads a frame's rows one after another (`app.core.geometry.rolling`), so each
row of a survey video sees the room from where the camera was when that row was read.
One pose a frame cannot fit such views: the bundle adjustment bends the map and the lens
to absorb the shear, and the lens check may refuse the footage.

Before every bundle adjustment (`reconstruction.adjust`), `undo_readout` gives each
registered frame its motion through the readout from its neighbours in the trajectory
(the steps from the frame before and to the frame after: a velocity and its change),
and moves every observation, discs and feature points alike, from where it was detected
to where the frame's middle-row pose sees its point. So the poses, the map and the
motion improve together as the map grows and is refined.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.core.geometry import CameraMotion, RollingShutter
from app.core.survey.features import _rotations
from app.core.survey.state import Readout, Reconstruction, SurveyState

__all__ = ["FrameMotions", "frame_motions", "undo_readout"]

#: The farthest (video frames) a neighbour may be to give a frame its motion.
MAX_NEIGHBOUR_FRAMES = 10.0


@dataclass(frozen=True)
class FrameMotions:
    """Each survey frame's motion through its readout, in its camera axes (`frame_motions`)."""

    angular: np.ndarray  # (F, 3) rad per video frame
    linear: np.ndarray  # (F, 3) m per video frame
    angular_change: np.ndarray  # (F, 3) rad per video frame squared
    linear_change: np.ndarray  # (F, 3) m per video frame squared


def frame_motions(reconstruction: Reconstruction, frame_numbers: np.ndarray) -> FrameMotions:
    """Each registered frame's motion, per video frame, from its registered neighbours.

    With a neighbour on each side, the velocity is the mean of the steps to and from it,
    and the acceleration their change: a turn speeding up through the readout shears
    the rows unevenly, and the change of the frame's velocity across the readout is
    what a constant velocity leaves. With one neighbour, the step to or from it alone;
    with none (or farther than `MAX_NEIGHBOUR_FRAMES`), no motion.

    Parameters
    ----------
    reconstruction : Reconstruction
    frame_numbers : (F,) ndarray
        Each survey frame's place in the video, in video frames (increasing).

    Returns
    -------
    FrameMotions
        Per video frame (and per video frame squared), in each frame's camera axes; zero
        where unknown.
    """
    registered = np.flatnonzero(reconstruction.registered())
    n = len(reconstruction.rvec)
    motions = FrameMotions(np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)))
    for k, f in enumerate(registered):
        before = registered[k - 1] if k > 0 else None
        after = registered[k + 1] if k + 1 < len(registered) else None
        if before is not None and frame_numbers[f] - frame_numbers[before] > MAX_NEIGHBOUR_FRAMES:
            before = None
        if after is not None and frame_numbers[after] - frame_numbers[f] > MAX_NEIGHBOUR_FRAMES:
            after = None
        steps = [CameraMotion.between(reconstruction.pose(a), reconstruction.pose(b), float(frame_numbers[b]
                                                                                         - frame_numbers[a]))
                 for a, b in ((before, f), (f, after)) if a is not None and b is not None]
        if not steps:
            continue
        motions.angular[f] = np.mean([m.angular for m in steps], axis=0)
        motions.linear[f] = np.mean([m.linear for m in steps], axis=0)
        if len(steps) == 2:
            # The two steps' velocities belong half a step before and after the frame.
            span = 0.5 * float(frame_numbers[after] - frame_numbers[before])
            motions.angular_change[f] = (steps[1].angular - steps[0].angular) / span
            motions.linear_change[f] = (steps[1].linear - steps[0].linear) / span
    return motions


def _shift(state: SurveyState, shutter: RollingShutter, frame: np.ndarray, X: np.ndarray, uv: np.ndarray,
           motions: FrameMotions) -> np.ndarray:
    """(M, 2) how far the readout moved each observation (raw pixels `uv` of points `X`
    in `frame`) from where the frame's middle-row pose sees it; zero where unknown."""
    shift = np.zeros_like(uv)
    known = np.isfinite(X[:, 0]) & state.reconstruction.registered()[frame]
    if not known.any():
        return shift
    camera = state.reconstruction.camera
    f = frame[known]
    R, t = _rotations(state, f)
    at_frame = (R @ X[known][:, :, None])[:, :, 0] + t
    times = shutter.row_times(uv[known, 1], camera.height)
    # Moved by v t + a t^2 / 2: the velocity at the row's time, averaged from the frame's.
    half = 0.5 * times[:, None]
    seen = CameraMotion(motions.angular[f] + half * motions.angular_change[f],
                        motions.linear[f] + half * motions.linear_change[f]).seen(at_frame, times)
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
    motions = frame_motions(rec, readout.frame_numbers)
    tracks = state.tracks
    shift = _shift(state, readout.shutter, tracks.frame, rec.X[tracks.point], readout.raw_uv, motions)
    # In place: the views' pixels are a view of the tracks'.
    tracks.uv[...] = readout.raw_uv - shift
    largest = float(np.abs(shift).max()) if len(shift) else 0.0
    features = state.features
    if len(features.frame):
        feature_shift = _shift(state, readout.shutter, features.frame, state.feature_X[features.track],
                               readout.raw_feature_uv, motions)
        features.uv[...] = readout.raw_feature_uv - feature_shift
        largest = max(largest, float(np.abs(feature_shift).max()))
    return largest
