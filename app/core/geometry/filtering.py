"""Smoothing and prediction of a stream of camera poses.

A tracked camera's poses carry noise (a tenth of a millimetre to millimetres, more with
one card in view than with ten) that shows as jitter in a rendered picture, and arrive
a frame's processing after the picture was taken, which shows as lag. `PoseFilter` is a
One Euro filter (Casiez, Roussel and Vogel, CHI 2012) on the camera centre and on its
orientation: a low-pass filter whose cut-off frequency rises with the speed, so a still
camera is smoothed hard and a moving one follows with little lag. The speed it
estimates also extrapolates the pose ahead in time (`PoseFilter.predict`), to hide the
latency between a frame and its use.

Poses are map to camera (``x_cam = R @ X_map + t``) as everywhere in
``app.core.geometry``; the filter works on the camera's centre and its camera-to-map
rotation, whose rates are the camera's own velocity and angular velocity in the map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from app.core.geometry.camera import Pose

__all__ = ["OneEuroParams", "PoseFilter"]


@dataclass(frozen=True)
class OneEuroParams:
    """The One Euro filter's settings.

    Attributes
    ----------
    min_cutoff_hz : float
        Cut-off frequency of a still camera, Hz: lower smooths more, lags more when
        motion starts.
    beta : float
        Rise of the position's cut-off with speed, Hz per m/s: higher lags less in
        motion, smooths less.
    beta_rotation : float
        Rise of the orientation's cut-off with angular speed, Hz per rad/s.
    derivative_cutoff_hz : float
        Cut-off of the speed estimate that steers the cut-off and the prediction, Hz.
    reset_after_s : float
        A gap longer than this between two poses (the track was lost) starts afresh.
    """

    min_cutoff_hz: float = 1.0
    beta: float = 20.0
    beta_rotation: float = 5.0
    derivative_cutoff_hz: float = 5.0
    reset_after_s: float = 0.5


def _alpha(cutoff_hz: float, dt: float) -> float:
    """The exponential smoothing factor of a first-order low-pass at `cutoff_hz`."""
    tau = 1.0 / (2.0 * math.pi * cutoff_hz)
    return 1.0 / (1.0 + tau / dt)


def _rotvec(R: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(R)[0].ravel()


def _rotation(rotvec: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rotvec, np.float64).reshape(3, 1))[0]


class PoseFilter:
    """One Euro filter and constant-velocity prediction of one camera's poses.

    Parameters
    ----------
    params : OneEuroParams, optional
    smooth : bool, optional
        Whether `update` returns the filtered pose (True) or the pose given, with the
        speed still estimated for `predict` (False: prediction alone).

    Examples
    --------
    >>> f = PoseFilter()
    >>> f.update(0.0, pose)            # doctest: +SKIP
    >>> f.predict(0.05)                # the pose 50 ms after the last one  # doctest: +SKIP
    """

    def __init__(self, params: OneEuroParams | None = None, smooth: bool = True) -> None:
        self.params = params or OneEuroParams()
        self.smooth = smooth
        self.reset()

    def reset(self) -> None:
        """Forget every pose: the next one is taken as it is."""
        self._time: float | None = None
        self._centre = np.zeros(3)  # filtered camera centre in the map, m
        self._orientation = np.eye(3)  # filtered camera-to-map rotation
        self._velocity = np.zeros(3)  # m/s in the map
        self._spin = np.zeros(3)  # angular velocity in the map, rad/s
        self._raw_centre = np.zeros(3)
        self._raw_orientation = np.eye(3)

    def update(self, time_s: float, pose: Pose) -> Pose:
        """Take the pose measured at `time_s` (seconds, any monotonic clock).

        Parameters
        ----------
        time_s : float
        pose : Pose
            Map to camera.

        Returns
        -------
        Pose
            The filtered pose (the pose given when smoothing is off).
        """
        centre, orientation = pose.position, pose.R.T
        p = self.params
        dt = None if self._time is None else time_s - self._time
        if dt is None or not 0 < dt <= p.reset_after_s:  # the first pose, after a gap, or out of order
            self.reset()
            self._time = time_s
            self._centre, self._orientation = centre.copy(), orientation.copy()
            self._raw_centre, self._raw_orientation = centre.copy(), orientation.copy()
            return pose
        self._time = time_s
        # The cut-offs follow the speeds so far; the speeds then follow the filtered
        # pose, which is steady where the raw one jitters (a raw difference would read
        # its noise as motion and smooth a still camera less).
        a = _alpha(p.min_cutoff_hz + p.beta * float(np.linalg.norm(self._velocity)), dt)
        a_r = _alpha(p.min_cutoff_hz + p.beta_rotation * float(np.linalg.norm(self._spin)), dt)
        centre_before, orientation_before = self._centre.copy(), self._orientation
        self._centre += a * (centre - self._centre)
        self._orientation = _rotation(a_r * _rotvec(orientation @ self._orientation.T)) @ self._orientation
        a_d = _alpha(p.derivative_cutoff_hz, dt)
        self._velocity += a_d * ((self._centre - centre_before) / dt - self._velocity)
        self._spin += a_d * (_rotvec(self._orientation @ orientation_before.T) / dt - self._spin)
        self._raw_centre, self._raw_orientation = centre.copy(), orientation.copy()
        if not self.smooth:
            return pose
        return self._pose(self._centre, self._orientation)

    def predict(self, ahead_s: float) -> Pose:
        """The pose `ahead_s` seconds after the last one given, at constant velocity.

        Parameters
        ----------
        ahead_s : float

        Returns
        -------
        Pose
            From the filtered pose (the last pose given when smoothing is off).

        Raises
        ------
        ValueError
            Before any pose was given.
        """
        if self._time is None:
            raise ValueError("no pose to predict from")
        centre = self._centre if self.smooth else self._raw_centre
        orientation = self._orientation if self.smooth else self._raw_orientation
        return self._pose(centre + self._velocity * ahead_s, _rotation(self._spin * ahead_s) @ orientation)

    @staticmethod
    def _pose(centre: np.ndarray, orientation: np.ndarray) -> Pose:
        R = orientation.T
        return Pose(R, -R @ centre)
