"""Natural-feature points: the second kind of track of the bundle adjustment.

A feature point is a point of the scene itself (a corner of a picture frame, a knot in
the wood) tracked through the video. Unlike a disc it has no printed shape and no
expected precision of its own: every observation of every feature point shares one
noise level, ``sigma_px``, and a robust loss of the whitened error (error / sigma), since
a tracker's wrong matches are not rare. `FeatureObservations` holds them flat, one row
per observation, the way a feature tracker hands them over (frame, track, uv); their 3D
points live beside the reconstruction as an (P, 3) array, nan where not triangulated.

The losses follow the disc observations' convention (`bundle`): the cost of a whitened
error e is half of rho(e^2), with Huber's rho(s) = s up to the scale k and
2 k sqrt(s) - k^2 beyond it, or Cauchy's rho(s) = k^2 log(1 + s / k^2); the iteratively
reweighted least squares weight is rho'(e^2).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Protocol

import numpy as np

#: The expected error of a feature observation, px per axis: the feature tracker's points
#: on the example walks fit their adjusted points to 0.13-0.15 px RMS (2D), and to
#: 0.07 px (median) the points triangulated from the true poses.
DEFAULT_SIGMA_PX = 0.15


class RobustLoss(StrEnum):
    """The robust loss of a feature point's whitened reprojection error.

    ``huber``: quadratic up to the scale, linear beyond it (convex: safe from any start,
    but a wrong match still pulls with a bounded force). ``cauchy``: logarithmic beyond
    the scale, so a grossly wrong match pulls almost nothing (not convex: needs a start
    near the optimum, as the survey's bundle adjustments have).
    """

    HUBER = "huber"
    CAUCHY = "cauchy"

    def cost(self, e: np.ndarray, scale: float) -> np.ndarray:
        """Half the loss of each whitened error.

        Parameters
        ----------
        e : ndarray
            Whitened errors (error / sigma), non-negative.
        scale : float
            The loss's scale k, in the same units.

        Returns
        -------
        ndarray
            ``rho(e**2) / 2``, the shape of ``e``.
        """
        if self is RobustLoss.HUBER:
            return np.where(e <= scale, 0.5 * e**2, scale * (e - 0.5 * scale))
        return 0.5 * scale**2 * np.log1p((e / scale) ** 2)

    def weight(self, e: np.ndarray, scale: float) -> np.ndarray:
        """Each whitened error's weight in iteratively reweighted least squares.

        Parameters
        ----------
        e : ndarray
            Whitened errors, non-negative.
        scale : float
            The loss's scale.

        Returns
        -------
        ndarray
            ``rho'(e**2)``: 1 for small errors, falling beyond the scale.
        """
        if self is RobustLoss.HUBER:
            return np.where(e <= scale, 1.0, scale / np.maximum(e, 1e-300))
        return 1.0 / (1.0 + (e / scale) ** 2)


class TrackArrays(Protocol):
    """What a feature tracker hands over: flat arrays, one row per observation."""

    frame: np.ndarray
    track: np.ndarray
    uv: np.ndarray


@dataclass(frozen=True, eq=False)
class FeatureObservations:
    """Observations of natural-feature points and their noise model.

    Attributes
    ----------
    frame : (M,) ndarray of int
        Each observation's frame, an index into the survey's frames (the
        reconstruction's poses).
    track : (M,) ndarray of int
        Its feature point: a row of the feature points' (P, 3) array.
    uv : (M, 2) ndarray
        Where it was seen, px (distorted image; centre of the top-left pixel at (0, 0)).
    sigma_px : float
        The expected error of every observation, px per axis.
    loss : RobustLoss
        The robust loss of the whitened error: Cauchy's by default. A wrong keyframe
        match merges two points' tracks, and Huber's loss still pulls the map towards
        each with a bounded force: with 2 % of a walk's tracks merged at random the
        survey of the feature test walk lost every card under Huber's loss and mapped
        all 11 under Cauchy's (also with 10 %); on the example walks Cauchy's maps are
        as good (tests/core/survey/test_features.py, docs/benchmarks/walks.md).
    loss_scale : float
        Where the loss stops being quadratic, in sigmas.
    """

    frame: np.ndarray
    track: np.ndarray
    uv: np.ndarray
    sigma_px: float = DEFAULT_SIGMA_PX
    loss: RobustLoss = RobustLoss.CAUCHY
    loss_scale: float = 2.5

    def __post_init__(self) -> None:
        m = len(self.frame)
        if len(self.track) != m or np.shape(self.uv) != (m, 2):
            raise ValueError(f"frame, track and uv must have one row per observation: {m}, {len(self.track)}, "
                             f"{np.shape(self.uv)}")
        if not (self.sigma_px > 0 and self.loss_scale > 0):
            raise ValueError(f"sigma_px and loss_scale must be positive: {self.sigma_px}, {self.loss_scale}")

    def __len__(self) -> int:
        return len(self.frame)

    @classmethod
    def from_tracks(cls, tracks: TrackArrays, sigma_px: float = DEFAULT_SIGMA_PX, loss: RobustLoss = RobustLoss.CAUCHY,
                    loss_scale: float = 2.5) -> FeatureObservations:
        """The observations of a feature tracker's tracks, with a noise model.

        Parameters
        ----------
        tracks : TrackArrays
            Anything with flat ``frame``, ``track`` and ``uv`` arrays (a tracker's
            feature tracks, frames numbered as the survey's).
        sigma_px : float
            The expected error of an observation, px per axis.
        loss : RobustLoss
            The robust loss.
        loss_scale : float
            Its scale, in sigmas.

        Returns
        -------
        FeatureObservations
            The same rows, as int and float arrays.
        """
        return cls(np.asarray(tracks.frame, dtype=np.int64), np.asarray(tracks.track, dtype=np.int64),
                   np.asarray(tracks.uv, dtype=np.float64).reshape(-1, 2), sigma_px, loss, loss_scale)

    @classmethod
    def empty(cls) -> FeatureObservations:
        """No observations.

        Returns
        -------
        FeatureObservations
            Zero rows, the default noise model.
        """
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))

    def in_frames(self, used: np.ndarray) -> FeatureObservations:
        """The observations of some frames only, renumbered as those frames.

        Parameters
        ----------
        used : (F,) ndarray of int
            The frames kept, increasing (as `tracks.subsample_frames` gives them).

        Returns
        -------
        FeatureObservations
            The observations of those frames, ``frame`` now an index into ``used``; the
            same tracks and noise model.
        """
        used = np.asarray(used, dtype=np.int64)
        position = np.searchsorted(used, self.frame)
        keep = (position < len(used)) & (used[np.minimum(position, len(used) - 1)] == self.frame)
        return FeatureObservations(position[keep], self.track[keep], self.uv[keep], self.sigma_px, self.loss,
                                   self.loss_scale)

    @property
    def n_points(self) -> int:
        """The number of feature points (one past the largest track index)."""
        return int(self.track.max()) + 1 if len(self.track) else 0

    def whitened(self, residuals: np.ndarray) -> np.ndarray:
        """The whitened error of each residual.

        Parameters
        ----------
        residuals : (K, 2) ndarray
            Reprojection residuals, px.

        Returns
        -------
        (K,) ndarray
            Their lengths in sigmas.
        """
        return np.linalg.norm(residuals, axis=1) / self.sigma_px

    def cost(self, residuals: np.ndarray) -> np.ndarray:
        """The robust cost of each residual.

        Parameters
        ----------
        residuals : (K, 2) ndarray
            Reprojection residuals, px.

        Returns
        -------
        (K,) ndarray
            Half the loss of each whitened error.
        """
        return self.loss.cost(self.whitened(residuals), self.loss_scale)

    def weights(self, residuals: np.ndarray) -> np.ndarray:
        """The weight of each residual in the normal equations.

        Parameters
        ----------
        residuals : (K, 2) ndarray
            Reprojection residuals, px.

        Returns
        -------
        (K,) ndarray
            The loss's weight over the variance, px^-2: what a disc observation's
            precision times Huber's weight is to the discs.
        """
        return self.loss.weight(self.whitened(residuals), self.loss_scale) / self.sigma_px**2
