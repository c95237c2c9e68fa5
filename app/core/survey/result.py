"""The survey's result (survey step 6): the map with each disc's uncertainty, the camera,
the trajectory, and warnings about weak parts of the map."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.core.geometry import Camera, Pose
from app.core.survey.advice import (
    MapWarning,
    TargetViews,
    lens_warning,
    map_advice,
    misread_advice,
    uncertainty_advice,
)
from app.core.survey.bundle import BundleInfo
from app.core.survey.cards import max_angle_deg
from app.core.survey.features import feature_groups
from app.core.survey.place import MIN_BASELINE_DEG
from app.core.survey.scale import MetricScale
from app.core.survey.state import SurveyError, SurveyState, Tracks, Views
from app.core.survey.verify import few_frames_lens_message, focal_std_message, uncertain_cards

#: A target seen in fewer registered frames is flagged as weak.
MIN_VIEWS = 3


@dataclass(frozen=True, eq=False)
class SurveyedTarget:
    """One target of the map: its 4 disc centres (metres, in the printed disc order of
    docs/map-format.md)."""

    id: int
    discs: np.ndarray  # (4, 3)
    std_m: np.ndarray  # (4,) RMS 3D position uncertainty of each disc (1 sigma)
    n_views: int  # registered frames in which the target was used
    baseline_deg: float  # widest angle between two of those views, at the target
    distance_m: float = float("nan")  # median distance of those views' camera centres to the target

    def to_dict(self) -> dict[str, Any]:
        """The target's entry in the map document.

        Returns
        -------
        dict
            ``id``, ``discs`` (rounded to the micrometre), ``std_m`` (3 significant
            digits) and ``n_views``: plain JSON types.
        """
        return {
            "id": int(self.id),
            "discs": np.round(self.discs, 6).tolist(),
            "std_m": [float(f"{s:.3g}") for s in self.std_m],
            "n_views": int(self.n_views),
        }


@dataclass(eq=False)
class SurveyResult:
    """What a survey found: the camera, the map, the trajectory and how well they fit."""

    camera: Camera
    targets: list[SurveyedTarget]
    rms_px: float  # reprojection RMS (2D) over every observation kept
    trajectory: list[Pose | None]  # one per input frame; None: not used or not registered
    warnings: list[str]
    intrinsics_fixed: bool
    frames_used: list[int]  # input frame indices after subsampling
    n_observations: int  # disc observations in the final bundle adjustment
    n_rejected_views: int  # (frame, target) views dropped as not fitting
    scale_residual_m: float  # RMS of the card disc-distance residuals after scaling
    timing_s: dict[str, float] = field(default_factory=dict)
    intrinsics_std: np.ndarray | None = None  # (5,) 1 sigma of [f, cx, cy, k1, k2] (px, px, px, -, -); None: fixed
    map_warnings: list[MapWarning] = field(default_factory=list)  # the warnings that name cards, typed
    # Consecutive observations of a disc worth one independent one (`bundle.correlation_time`):
    # the covariance behind intrinsics_std and the discs' std_m is widened by it.
    correlation_time: float = 1.0
    # Joint covariance of every target's discs relative to the map (m^2), rows x, y, z of
    # each disc of each target in `targets` order; None without a covariance. The map
    # document carries only its diagonal blocks' traces (`std_m`).
    disc_covariance: np.ndarray | None = None

    @property
    def n_registered(self) -> int:
        """The number of frames registered."""
        return sum(p is not None for p in self.trajectory)

    def target(self, target_id: int) -> SurveyedTarget:
        """The surveyed target of id ``target_id``.

        Parameters
        ----------
        target_id : int
            The printed id.

        Returns
        -------
        SurveyedTarget
            The target; KeyError when it was not surveyed.
        """
        for t in self.targets:
            if t.id == target_id:
                return t
        raise KeyError(target_id)

    def to_map_document(self, frame: str = "survey", survey_job_id: str | None = None) -> dict[str, Any]:
        """The map document (docs/map-format.md).

        Parameters
        ----------
        frame : str
            The name of the map's frame.
        survey_job_id : str, optional
            The job that made the map.

        Returns
        -------
        dict
            ``frame``, ``units``, ``camera``, ``targets`` (by id), ``rms_px`` and
            ``survey_job_id``: plain JSON types.
        """
        return {
            "frame": frame,
            "units": "m",
            "camera": self.camera.to_dict(),
            "targets": [t.to_dict() for t in sorted(self.targets, key=lambda t: t.id)],
            "rms_px": float(round(self.rms_px, 4)),
            "survey_job_id": survey_job_id,
        }

    def summary(self) -> dict[str, Any]:
        """A small JSON-able digest for a job result.

        Returns
        -------
        dict
            Frames, registered frames, targets, RMS, the lens and its standard deviations
            (``intrinsics_std``: None when the intrinsics were given), the correlation time
            of the discs' errors the uncertainties are widened by, warnings (every one
            as text; ``card_warnings``: those about parts of the map, with their kind, the
            ids of the cards they name and, for a probable misread, the frames it was read
            in) and timing.
        """
        std = self.intrinsics_std

        def number(x: float) -> float | None:  # JSON has no NaN: a degenerate covariance gives None
            return float(x) if np.isfinite(x) else None

        return {
            "n_frames": len(self.frames_used),
            "n_registered": self.n_registered,
            "n_targets": len(self.targets),
            "rms_px": float(self.rms_px),
            "focal_px": self.camera.fx,
            "principal_point": [self.camera.cx, self.camera.cy],
            "dist": self.camera.dist.tolist(),
            "intrinsics_std": None if std is None else {
                "focal_px": number(std[0]), "principal_point_px": [number(std[1]), number(std[2])],
                "k1": number(std[3]), "k2": number(std[4])},
            "correlation_time": float(self.correlation_time),
            "warnings": list(self.warnings),
            "card_warnings": [{"kind": w.kind.value, "target_ids": list(w.target_ids), "message": w.message,
                               "frames": list(w.frames)} for w in self.map_warnings],
            "timing_s": dict(self.timing_s),
        }


@dataclass(frozen=True, eq=False)
class SurveyedViews:
    """The views the final map rests on, and the targets it surveys."""

    used: np.ndarray  # (V,) usable views of registered frames and placed targets
    n_rejected: int  # views of registered frames and placed targets set aside as not fitting
    n_views: np.ndarray  # (T,) used views of each target
    targets: np.ndarray  # target indices surveyed: placed and seen in 2+ used views


def surveyed_views(state: SurveyState) -> SurveyedViews:
    """The views and targets of the final map.

    Parameters
    ----------
    state : SurveyState
        The survey after its last bundle adjustment.

    Returns
    -------
    SurveyedViews
        The used and rejected views, and the surveyed targets.

    Raises
    ------
    SurveyError
        When no target was seen in 2 or more registered frames.
    """
    rec, views, usable = state.reconstruction, state.views, state.usable
    registered = rec.registered()
    used = usable & registered[views.frame] & rec.placed()[views.target * 4]
    n_rejected = int((~usable & registered[views.frame] & rec.placed()[views.target * 4]).sum())
    n_views = np.bincount(views.target[used], minlength=state.tracks.n_targets)
    targets = np.flatnonzero((n_views >= 2) & np.isfinite(rec.X[0::4, 0]))
    if len(targets) == 0:
        raise SurveyError("no target was seen in 2 or more registered frames")
    return SurveyedViews(used, n_rejected, n_views, targets)


def map_advice_of(results: list[SurveyedTarget], tracks: Tracks, views: Views, surveyed: SurveyedViews,
                  camera_centres: np.ndarray | None = None, frame_groups: np.ndarray | None = None
                  ) -> list[MapWarning]:
    """The typed warnings about weak parts of the map (`advice.map_advice`).

    Parameters
    ----------
    results : list of SurveyedTarget
        The surveyed targets, in the order of ``surveyed.targets``.
    tracks : Tracks
        The observations.
    views : Views
        Every view.
    surveyed : SurveyedViews
        The views the map rests on.
    camera_centres : (F, 3) ndarray, optional
        The registered cameras' centres; without them no pure pan is told.
    frame_groups : (F,) ndarray of int, optional
        Frames linked by feature points (`features.feature_groups`); default: none.

    Returns
    -------
    list of MapWarning
        Each with its kind, the cards it names and its text; a card placed too
        uncertainly (`verify.uncertain_cards`) and not named already gets one of its own;
        the ids left out as probable misreads last (`advice.misread_advice`).
    """
    targets = [TargetViews(r.id, r.discs.mean(axis=0), r.n_views, r.baseline_deg, r.distance_m) for r in results]
    centres = np.zeros((0, 3)) if camera_centres is None else camera_centres
    advice = map_advice(targets, tracks, views, surveyed.used, surveyed.targets, centres, MIN_VIEWS,
                        MIN_BASELINE_DEG, frame_groups)
    named = {card for w in advice for card in w.target_ids}
    uncertain = [(card, std) for card, std in uncertain_cards([r.id for r in results], [r.std_m for r in results])
                 if card not in named]
    return advice + uncertainty_advice(uncertain, targets) + misread_advice(tracks.misreads)


def survey_result(state: SurveyState, info: BundleInfo, surveyed: SurveyedViews, scale: MetricScale,
                  used_frames: list[int], n_input_frames: int) -> SurveyResult:
    """The result of a survey: the scaled map, its uncertainty, the trajectory, warnings.

    Parameters
    ----------
    state : SurveyState
        The survey after scaling; its warnings get the map's (`map_advice_of`).
    info : BundleInfo
        The last bundle adjustment, with its covariance.
    surveyed : SurveyedViews
        The views and targets of the map.
    scale : MetricScale
        The scale applied to the map after the bundle adjustment.
    used_frames : list of int
        The input frames the survey used.
    n_input_frames : int
        The number of frames of the input video.

    Returns
    -------
    SurveyResult
        The result.
    """
    rec, tracks, views = state.reconstruction, state.tracks, state.views
    registered = rec.registered()
    joint = info.disc_covariance(rec.X)  # projected once: the discs' std_m are its blocks
    std = info.disc_std(rec.X, joint) * scale.factor
    row_of = {int(point): k for k, point in enumerate(info.points)}
    err = rec.errors(tracks, info.obs)
    rms = float(np.sqrt(np.nanmean(err**2)))
    results: list[SurveyedTarget] = []
    for t in surveyed.targets:
        frames_t = np.unique(views.frame[views.of_target[t][surveyed.used[views.of_target[t]]]])
        centres = np.array([rec.pose(f).position for f in frames_t])
        X = rec.discs(t)
        angle = max_angle_deg(centres, X.mean(axis=0))
        distance = float(np.median(np.linalg.norm(centres - X.mean(axis=0), axis=1)))
        results.append(SurveyedTarget(int(tracks.ids[t]), X.copy(), std[4 * t : 4 * t + 4].copy(),
                                      len(frames_t), angle, distance))
    disc_covariance = None
    if joint is not None and all(4 * t + k in row_of for t in surveyed.targets for k in range(4)):
        rows = np.array([3 * row_of[4 * t + k] + axis for t in surveyed.targets for k in range(4) for axis in range(3)],
                        np.int64).reshape(-1)
        disc_covariance = joint[np.ix_(rows, rows)] * scale.factor**2
    camera_centres = np.array([rec.pose(f).position for f in np.flatnonzero(registered)]).reshape(-1, 3)
    advice = map_advice_of(results, tracks, views, surveyed, camera_centres, feature_groups(state))
    state.warnings += [w.message for w in advice]
    lens_std = info.intrinsics_std()
    for warning in (lens_warning(lens_std),
                    None if lens_std is None else focal_std_message(rec.camera.fx, float(lens_std[0])),
                    None if lens_std is None else few_frames_lens_message(rec.n_registered)):
        if warning is not None:
            state.warnings.append(warning)
    trajectory: list[Pose | None] = [None] * n_input_frames
    for fi, index in enumerate(used_frames):
        if registered[fi]:
            trajectory[index] = rec.pose(fi)
    return SurveyResult(
        camera=rec.camera, targets=results, rms_px=rms, trajectory=trajectory, warnings=state.warnings,
        intrinsics_fixed=state.settings.intrinsics_given, frames_used=used_frames,
        n_observations=len(info.obs), n_rejected_views=surveyed.n_rejected,
        scale_residual_m=scale.residual_m, timing_s=state.clock.timing_s, intrinsics_std=lens_std,
        map_warnings=advice, correlation_time=info.correlation_time, disc_covariance=disc_covariance,
    )
