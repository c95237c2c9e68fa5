"""The survey's state: what its stages share, as explicit typed fields.

`SurveyState` holds the observations (`Tracks`, grouped into `Views`), the current
estimate (`Reconstruction`: the camera, a pose per frame, a point per disc), which views
are used, the settings, the random stream and the progress clock. Every stage is a
function over it (see `reconstruction.survey` for the order).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from functools import cached_property

import cv2
import numpy as np

from app.core.geometry import Camera, Pose, RollingShutter
from app.core.markers import DISC_CENTRES
from app.core.survey.points import FeatureObservations

#: A progress callback: stage name, fraction done in [0, 1].
Progress = Callable[[str, float], None]

#: A view of a point counts only within this multiple of the image corners' radius
#: (Camera.field_radius, short of the lens's fold): a 10% band for the poses' and the
#: lens's own errors during the survey.
FIELD_MARGIN = 1.1


class SurveyError(ValueError):
    """The survey cannot be done from this input (the message says why, for a user)."""


class SurveyStage(StrEnum):
    """The stages a survey reports to its progress callback, in order (also the keys
    of `SurveyResult.timing_s`, but for ``done``)."""

    INTRINSICS = "intrinsics"
    INITIAL = "initial"
    REGISTER = "register"
    BUNDLE = "bundle"
    SCALE = "scale"
    COVARIANCE = "covariance"
    DONE = "done"


@dataclass
class StageClock:
    """Reports progress to the caller and times the stages."""

    progress: Progress | None = None
    timing_s: dict[str, float] = field(default_factory=dict)
    last: float = field(default_factory=time.perf_counter)
    done: float = 0.0  # the largest fraction reported so far

    def report(self, stage: SurveyStage, fraction: float) -> None:
        """Tell the caller that ``stage`` is under way, ``fraction`` (clipped to [0, 1]) of the survey done.

        The fraction never goes back: growth measures it by the frames registered, and
        pruning can take some out again.

        Parameters
        ----------
        stage : SurveyStage
            The stage now running.
        fraction : float
            How much of the whole survey is done.
        """
        self.done = max(self.done, float(min(max(fraction, 0.0), 1.0)))
        if self.progress is not None:
            self.progress(stage.value, self.done)

    def lap(self, stage: SurveyStage) -> None:
        """Add the time since the last lap to ``stage``'s.

        Parameters
        ----------
        stage : SurveyStage
            The stage that just ended.
        """
        now = time.perf_counter()
        self.timing_s[stage.value] = self.timing_s.get(stage.value, 0.0) + now - self.last
        self.last = now


@dataclass(frozen=True)
class SurveySettings:
    """The caller's settings (see `survey`)."""

    marker_size_m: float
    outlier_px: float = 3.0
    card_prior_m: float | None = 1e-5
    intrinsics_given: bool = False

    @property
    def loose_px(self) -> float:
        """How far (px) a view may be off before the lens is fitted: the image is then off
        by the unmodelled distortion, several pixels at the edges."""
        return 2 * self.outlier_px if self.intrinsics_given else 4 * self.outlier_px

    @property
    def card_prior(self) -> tuple[float, float] | None:
        """The card prior of `bundle_adjust`: (metres per card unit, sigma in metres)."""
        return None if self.card_prior_m is None else (self.marker_size_m, float(self.card_prior_m))

    @cached_property
    def card_model(self) -> np.ndarray:
        """(4, 3) disc centres in the card's own frame (x right, y down as printed, z = 0), metres."""
        return np.c_[DISC_CENTRES * self.marker_size_m, np.zeros(4)]


@dataclass(frozen=True)
class Misread:
    """An id taken for a misread of another card's code (`tracks.probable_misreads`): read
    in a few frames only, each read weak or where another card is."""

    id: int
    frames: tuple[int, ...]  # the input frames it was read in
    of_id: int | None  # the card seen where it was read, if any
    weak: bool  # every read's code was weak (`tracks.MISREAD_WEAK_GAP`)


@dataclass
class Tracks:
    """Every disc observation, flat, sorted by frame (4 rows per view, discs in order)."""

    frame: np.ndarray  # (M,) index into the used frames
    target: np.ndarray  # (M,) index into ids
    disc: np.ndarray  # (M,) 0..3
    uv: np.ndarray  # (M, 2) pixels
    ids: np.ndarray  # (T,) target id of each target index
    n_frames: int
    precision: np.ndarray  # (M,) inverse expected variance of each observation, px^-2 (`disc_precision`)
    misreads: tuple[Misread, ...] = ()  # ids left out as probable misreads (`tracks.probable_misreads`)

    @property
    def point(self) -> np.ndarray:
        """(M,) index of each observation's 3D point: 4 per target, one per disc."""
        return self.target * 4 + self.disc

    @property
    def n_targets(self) -> int:
        """The number of targets (ids) seen."""
        return len(self.ids)

    @property
    def expected_px(self) -> np.ndarray:
        """(M,) expected error of each observation, px (1 / sqrt of its precision)."""
        return 1.0 / np.sqrt(self.precision)


@dataclass(frozen=True, eq=False)
class Views:
    """Every view (one target in one frame): rows ``4 k .. 4 k + 3`` of the tracks."""

    frame: np.ndarray  # (V,) index into the used frames
    target: np.ndarray  # (V,) index into the tracks' ids
    uv: np.ndarray  # (V, 4, 2) disc centres, px
    area: np.ndarray  # (V,) the card's area in the image, px^2
    of_frame: list[np.ndarray]  # the views of each frame
    of_target: list[np.ndarray]  # the views of each target

    @classmethod
    def from_tracks(cls, tracks: Tracks) -> Views:
        """Group the tracks into views.

        Parameters
        ----------
        tracks : Tracks
            The disc observations.

        Returns
        -------
        Views
            One view per detection kept, in the tracks' order.
        """
        frame, target = tracks.frame[::4], tracks.target[::4]
        uv = tracks.uv.reshape(-1, 4, 2)
        return cls(
            frame=frame,
            target=target,
            uv=uv,
            area=np.array([abs(cv2.contourArea(q.astype(np.float32))) for q in uv]),
            of_frame=[np.flatnonzero(frame == f) for f in range(tracks.n_frames)],
            of_target=[np.flatnonzero(target == t) for t in range(tracks.n_targets)],
        )

    def __len__(self) -> int:
        return len(self.frame)


def project_frame(camera: Camera, rvec: np.ndarray, tvec: np.ndarray, X: np.ndarray,
                  jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """Project points into one frame.

    Parameters
    ----------
    camera : Camera
        The camera.
    rvec, tvec : (3,) ndarray
        The frame's pose (map to camera), as a rotation vector and a translation.
    X : (N, 3) ndarray
        Points in the map.
    jacobian : bool
        Whether to return the Jacobian too.

    Returns
    -------
    uv : (N, 2) ndarray
        The points' images, px.
    jac : (2N, 14) ndarray or None
        OpenCV's Jacobian (rvec, tvec, fx, fy, cx, cy, dist) when asked for.
    """
    uv, jac = cv2.projectPoints(X.reshape(-1, 1, 3), rvec, tvec, camera.K, camera.dist)
    return uv.reshape(-1, 2), (jac if jacobian else None)


@dataclass
class Reconstruction:
    """The survey's estimate: the camera, the pose of every registered frame and the 3D
    point of every placed disc (4 per target, in disc order)."""

    camera: Camera
    rvec: np.ndarray  # (F, 3), nan for frames not registered
    tvec: np.ndarray  # (F, 3)
    X: np.ndarray  # (4T, 3), nan for discs not yet placed

    @classmethod
    def empty(cls, camera: Camera, n_frames: int, n_targets: int) -> Reconstruction:
        """A reconstruction with no frame registered and no target placed.

        Parameters
        ----------
        camera : Camera
            The camera.
        n_frames, n_targets : int
            The frames and targets of the survey.

        Returns
        -------
        Reconstruction
            Every pose and point nan.
        """
        return cls(camera, np.full((n_frames, 3), np.nan), np.full((n_frames, 3), np.nan),
                   np.full((4 * n_targets, 3), np.nan))

    def registered(self) -> np.ndarray:
        """Which frames have a pose.

        Returns
        -------
        (F,) bool ndarray
            True where the frame is registered.
        """
        return np.isfinite(self.rvec[:, 0])

    def placed(self) -> np.ndarray:
        """Which discs have a point.

        Returns
        -------
        (4T,) bool ndarray
            True where the disc is placed (4 per target, in disc order).
        """
        return np.isfinite(self.X[:, 0])

    @property
    def n_registered(self) -> int:
        """The number of frames with a pose."""
        return int(self.registered().sum())

    def pose(self, f: int) -> Pose:
        """The pose of a registered frame.

        Parameters
        ----------
        f : int
            The frame's index among the survey's frames.

        Returns
        -------
        Pose
            Map to camera, ``x_cam = R @ X_map + t``.
        """
        return Pose.from_rvec_tvec(self.rvec[f], self.tvec[f])

    def set_pose(self, f: int, pose: Pose) -> None:
        """Register a frame.

        Parameters
        ----------
        f : int
            The frame's index.
        pose : Pose
            Its pose, map to camera.
        """
        self.rvec[f], self.tvec[f] = pose.rvec, pose.t

    def unregister(self, f: int) -> None:
        """Take a frame's pose out (it is registered again later, or never).

        Parameters
        ----------
        f : int
            The frame's index.
        """
        self.rvec[f] = self.tvec[f] = np.nan

    def discs(self, t: int) -> np.ndarray:
        """A target's disc points.

        Parameters
        ----------
        t : int
            The target's index among the survey's targets.

        Returns
        -------
        (4, 3) ndarray
            Its discs' points in disc order: a view into ``X``.
        """
        return self.X[4 * t : 4 * t + 4]

    def place(self, t: int, discs: np.ndarray) -> None:
        """Place a target.

        Parameters
        ----------
        t : int
            The target's index.
        discs : (4, 3) ndarray
            Its discs' points in disc order.
        """
        self.X[4 * t : 4 * t + 4] = discs

    def unplace(self, t: int) -> None:
        """Take a target's discs out (it is placed again later, or never).

        Parameters
        ----------
        t : int
            The target's index.
        """
        self.X[4 * t : 4 * t + 4] = np.nan

    def errors(self, tracks: Tracks, obs: np.ndarray) -> np.ndarray:
        """Reprojection errors of observations.

        Inf where the point lies behind the camera or outside its field of view
        (``FIELD_MARGIN``): such an observation cannot be of that point, however well
        its projection fits (a point past the lens's field can project into the image,
        folded by the distortion).

        Parameters
        ----------
        tracks : Tracks
            The observations.
        obs : (N,) ndarray of int
            Indices of the observations to judge.

        Returns
        -------
        (N,) ndarray
            2D reprojection error (px) of each; nan where the frame is not registered or
            the point not placed.
        """
        err = np.full(len(obs), np.nan)
        if not len(obs):
            return err
        of = tracks.frame[obs]
        order = np.argsort(of, kind="stable")
        obs_sorted = obs[order]
        bounds = np.r_[0, np.flatnonzero(np.diff(of[order])) + 1, len(obs)]
        for k in range(len(bounds) - 1):
            s, e = bounds[k], bounds[k + 1]
            f = tracks.frame[obs_sorted[s]]
            pts = tracks.point[obs_sorted[s:e]]
            X = self.X[pts]
            ok = np.isfinite(X[:, 0])
            if not ok.any() or not np.isfinite(self.rvec[f, 0]):
                continue
            uv, _ = project_frame(self.camera, self.rvec[f], self.tvec[f], X[ok], False)
            idx = order[s:e][ok]
            cam = self.pose(f).transform(X[ok])
            seen = self.camera.in_field(cam, FIELD_MARGIN)
            err[idx] = np.where(seen, np.linalg.norm(uv - tracks.uv[obs_sorted[s:e][ok]], axis=1), np.inf)
        return err


@dataclass(frozen=True, eq=False)
class Readout:
    """A survey's rolling shutter and its observations as detected.

    Attributes
    ----------
    shutter : RollingShutter
        The readout, in video frames.
    frame_numbers : (F,) ndarray
        Each survey frame's place in the video, in video frames (increasing).
    raw_uv : (M, 2) ndarray
        The disc observations as detected (the tracks' order).
    raw_feature_uv : (K, 2) ndarray
        The feature observations as tracked.
    """

    shutter: RollingShutter
    frame_numbers: np.ndarray
    raw_uv: np.ndarray
    raw_feature_uv: np.ndarray

    @classmethod
    def of(cls, state: SurveyState, shutter: RollingShutter, frame_numbers: np.ndarray) -> Readout:
        """The readout of a survey whose observations are still as detected.

        Parameters
        ----------
        state : SurveyState
            The survey, before any observation is moved.
        shutter : RollingShutter
            The readout, in video frames.
        frame_numbers : (F,) ndarray
            Each survey frame's place in the video, in video frames.

        Returns
        -------
        Readout
        """
        return cls(shutter, np.asarray(frame_numbers, np.float64), state.tracks.uv.copy(), state.features.uv.copy())


@dataclass(eq=False)
class SurveyState:
    """Everything the survey's stages share.

    The settings do not change, nor do the observations except through a rolling
    shutter (`shutter.undo_readout` moves their pixels); the reconstruction and the
    bookkeeping below do, stage by stage.
    """

    tracks: Tracks
    views: Views
    settings: SurveySettings
    reconstruction: Reconstruction
    clock: StageClock
    warnings: list[str]  # for the user, in the order found
    rng: np.random.Generator  # samples view pairs in `cards.triangulate_robust` (seeded: the survey is deterministic)
    usable: np.ndarray  # (V,) views not (yet) found to be wrong
    placed_by_plane: np.ndarray  # (T,) placed as the rigid printed card: triangulated once the baseline allows
    weak: np.ndarray  # (F,) registered from a single target
    unplaced_at: np.ndarray  # (T,) registered views of a target when it was found wrong; -1: never
    lens_fixed: bool  # the bundle adjustment holds the intrinsics
    lens_refined: bool  # the intrinsics are given or fitted: views are judged by ``outlier_px``
    seed_frame: int = -1  # the frame that fixes the map frame (identity pose; never taken out)
    attempted: dict[int, int] = field(default_factory=dict)  # frame -> placed targets seen when last tried
    # The second kind of track (`features`): the scene's own points.
    features: FeatureObservations = field(default_factory=FeatureObservations.empty)
    feature_X: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (P, 3), nan: not triangulated
    feature_usable: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # (K,) views not found wrong
    feature_attempted: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (P,) views when last tried
    feature_tried: dict[int, int] = field(default_factory=dict)  # frame -> feature points seen when last tried
    # A rolling shutter: the observations are moved before each bundle adjustment (`shutter.undo_readout`).
    readout: Readout | None = None

    @classmethod
    def start(cls, tracks: Tracks, camera: Camera, settings: SurveySettings, clock: StageClock,
              warnings: list[str], features: FeatureObservations | None = None) -> SurveyState:
        """The state before the first frame is registered.

        Parameters
        ----------
        tracks : Tracks
            The observations.
        camera : Camera
            The initial camera (`lens.initial_camera`).
        settings : SurveySettings
            The caller's settings.
        clock : StageClock
            Progress and timing.
        warnings : list of str
            Warnings so far; the state appends to it.
        features : FeatureObservations, optional
            Feature tracks beside the cards, their frames numbered as the tracks'.

        Returns
        -------
        SurveyState
            Nothing registered or placed, every view usable.
        """
        views = Views.from_tracks(tracks)
        features = FeatureObservations.empty() if features is None else features
        n_points = features.n_points
        return cls(
            tracks=tracks,
            views=views,
            settings=settings,
            reconstruction=Reconstruction.empty(camera, tracks.n_frames, tracks.n_targets),
            clock=clock,
            warnings=warnings,
            rng=np.random.default_rng(0),
            usable=np.ones(len(views), bool),
            placed_by_plane=np.zeros(tracks.n_targets, bool),
            weak=np.zeros(tracks.n_frames, bool),
            unplaced_at=np.full(tracks.n_targets, -1),
            lens_fixed=settings.intrinsics_given,
            lens_refined=settings.intrinsics_given,
            features=features,
            feature_X=np.full((n_points, 3), np.nan),
            feature_usable=np.ones(len(features), bool),
            feature_attempted=np.zeros(n_points, np.int64),
        )

    @property
    def tolerance_px(self) -> float:
        """How far (px) a view may be off and still agree with a placement: loose until the
        lens is fitted (the initial focal length may be ~10 % off)."""
        return self.settings.outlier_px if self.lens_refined else self.settings.loose_px

    @property
    def pose_fit_px(self) -> float:
        """How far (px) a frame's pose may fit its views while the map grows: the map is
        still coarse, the bundle adjustment tightens it."""
        return (2 if self.lens_refined else 10) * self.settings.outlier_px
