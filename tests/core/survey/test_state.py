"""The survey's state: settings, the reconstruction, the progress clock."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.geometry import Camera, Pose
from app.core.markers import DISC_CENTRES
from app.core.survey.state import Reconstruction, StageClock, SurveySettings, SurveyStage, SurveyState


def test_settings() -> None:
    given = SurveySettings(0.2, outlier_px=3.0, card_prior_m=1e-5, intrinsics_given=True)
    estimated = SurveySettings(0.2, outlier_px=3.0, card_prior_m=None)
    # Before the lens is fitted the image is off by its distortion: judged more loosely
    # when the lens is estimated than when it is given.
    assert given.loose_px == 6.0 and estimated.loose_px == 12.0
    assert given.card_prior == (0.2, 1e-5) and estimated.card_prior is None
    np.testing.assert_allclose(given.card_model[:, :2], DISC_CENTRES * 0.2)
    assert (given.card_model[:, 2] == 0).all()


def test_reconstruction_registers_and_places() -> None:
    rec = Reconstruction.empty(Camera.pinhole(600.0, 640, 480), n_frames=3, n_targets=2)
    assert rec.n_registered == 0 and not rec.placed().any() and rec.X.shape == (8, 3)
    pose = Pose.look_at([0.0, 0.0, 0.0], [0.0, 3.0, 0.2])
    rec.set_pose(1, pose)
    assert rec.registered().tolist() == [False, True, False]
    np.testing.assert_allclose(rec.pose(1).R, pose.R, atol=1e-12)
    np.testing.assert_allclose(rec.pose(1).t, pose.t, atol=1e-12)
    discs = np.arange(12.0).reshape(4, 3)
    rec.place(1, discs)
    assert rec.placed().tolist() == [False] * 4 + [True] * 4
    np.testing.assert_array_equal(rec.discs(1), discs)
    rec.unplace(1)
    rec.unregister(1)
    assert rec.n_registered == 0 and not rec.placed().any()


def test_reconstruction_errors(true_state: SurveyState) -> None:
    """Reprojection errors: ~0 at the truth, the offset where a view is off, nan where
    nothing is placed, inf for a point behind the camera."""
    rec, tracks, views = true_state.reconstruction, true_state.tracks, true_state.views
    obs = np.arange(len(tracks.frame))
    assert np.nanmax(rec.errors(tracks, obs)) < 1e-9
    v = views.of_target[4][0]
    views.uv[v, 1] += (3.0, 4.0)
    err = rec.errors(tracks, obs)
    assert err[4 * v + 1] == pytest.approx(5.0, abs=1e-9) and np.delete(err, 4 * v + 1).max() < 1e-9
    rec.unplace(4)
    assert np.isnan(rec.errors(tracks, np.array([4 * v]))).all()
    f = int(views.frame[views.of_target[5][0]])
    pose = rec.pose(f)
    rec.set_pose(f, Pose(pose.R, pose.t - np.array([0.0, 0.0, 50.0])))  # the map behind the camera
    assert np.isinf(rec.errors(tracks, np.flatnonzero(tracks.frame == f))).all()


def test_stage_clock_reports_and_times() -> None:
    calls: list[tuple[str, float]] = []
    clock = StageClock(lambda stage, fraction: calls.append((stage, fraction)))
    clock.report(SurveyStage.INTRINSICS, -0.5)
    clock.report(SurveyStage.REGISTER, 0.4)
    clock.report(SurveyStage.REGISTER, 0.3)  # frames taken out again: the bar does not go back
    clock.report(SurveyStage.DONE, 1.5)
    assert calls == [("intrinsics", 0.0), ("register", 0.4), ("register", 0.4), ("done", 1.0)]
    assert all(type(stage) is str for stage, _ in calls)  # plain names for the caller
    clock.lap(SurveyStage.BUNDLE)
    clock.lap(SurveyStage.BUNDLE)
    clock.lap(SurveyStage.SCALE)
    assert set(clock.timing_s) == {"bundle", "scale"} and all(t >= 0 for t in clock.timing_s.values())
    StageClock().report(SurveyStage.DONE, 1.0)  # no callback: nothing to do


def test_state_starts_empty_and_judges_loosely_until_the_lens_is_fitted(true_state: SurveyState) -> None:
    settings = SurveySettings(0.2, outlier_px=3.0)
    state = SurveyState.start(true_state.tracks, true_state.reconstruction.camera, settings, StageClock(), [])
    assert state.reconstruction.n_registered == 0 and not state.reconstruction.placed().any()
    assert state.usable.all() and len(state.usable) == len(state.views)
    assert not state.lens_fixed and not state.lens_refined
    assert state.tolerance_px == settings.loose_px and state.pose_fit_px == 30.0
    state.lens_refined = True
    assert state.tolerance_px == 3.0 and state.pose_fit_px == 6.0
