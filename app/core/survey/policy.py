"""When the survey adjusts the map again, and when it lets the lens move."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.core.survey.state import SurveyState


@dataclass(frozen=True)
class ShouldBundle:
    """While the map grows: bundle-adjust after every pass that registered a frame or
    placed a target, once ``min_frames`` frames are registered. Frames registered and
    targets placed later rest on the refined poses (and lens): cameras left 0.3 m off at
    6 m by the start's lens triangulate narrow targets 1-2 m off."""

    min_frames: int = 3
    max_iterations: int = 10  # a step towards the optimum, not the optimum: the map changes again

    def __call__(self, state: SurveyState, changed: bool) -> bool:
        """Whether to bundle-adjust now.

        Parameters
        ----------
        state : SurveyState
            The growing survey.
        changed : bool
            Whether the last pass registered a frame or placed a target.

        Returns
        -------
        bool
            True to bundle-adjust.
        """
        return changed and state.reconstruction.n_registered >= self.min_frames


@dataclass(frozen=True)
class ShouldFitLens:
    """Whether the bundle adjustment fits the intrinsics: never when they are given;
    while the map grows, once ``growing_min_frames`` frames are registered (before, the
    few frames would fit noise); for the final map, only if ``final_min_frames`` frames
    are registered (five lens parameters from a handful of frames are not determined:
    the initial estimate is kept)."""

    growing_min_frames: int = 15
    final_min_frames: int = 10

    def while_growing(self, state: SurveyState) -> bool:
        """Whether the growing map's bundle adjustment fits the intrinsics now.

        Parameters
        ----------
        state : SurveyState
            The growing survey.

        Returns
        -------
        bool
            True to fit them.
        """
        return not state.lens_fixed and state.reconstruction.n_registered >= self.growing_min_frames

    def at_the_end(self, state: SurveyState) -> bool:
        """Whether the final bundle adjustments fit the intrinsics.

        Parameters
        ----------
        state : SurveyState
            The grown survey.

        Returns
        -------
        bool
            True to fit them.
        """
        return not state.lens_fixed and state.reconstruction.n_registered >= self.final_min_frames


@dataclass(frozen=True)
class FeatureKeyframes:
    """Which frames' feature observations the bundle adjustment solves with jointly.

    Feature points are followed through many consecutive frames (a median of 18 in the
    bench room's 1000-frame walk) and returns to a wall link frames far apart, so the
    reduced camera system is half full: its factorisation grows as the cube of the frames
    even sparse (a 1000-frame survey: 4 s an iteration, against 0.2 s over 250 frames).
    Consecutive frames add little to each other, so beyond ``max_frames`` frames with
    feature observations the adjustment takes those of every k-th frame (evenly, k the
    least that keeps them within ``max_frames``); the other frames keep their disc
    observations in it, and their poses are then fitted to the adjusted map alone. None:
    every frame."""

    max_frames: int | None = 250

    def __call__(self, frames: np.ndarray) -> np.ndarray:
        """The keyframes among ``frames``.

        Parameters
        ----------
        frames : (F,) ndarray of int
            The frames with feature observations, increasing.

        Returns
        -------
        (F,) ndarray of bool
            True for a keyframe.
        """
        if self.max_frames is None or len(frames) <= self.max_frames:
            return np.ones(len(frames), bool)
        stride = -(-len(frames) // self.max_frames)
        return np.arange(len(frames)) % stride == 0
