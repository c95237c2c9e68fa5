"""The survey driver's stages in order: start, growth, refinement."""

from __future__ import annotations

import numpy as np

from app.core.geometry.alignment import alignment_residuals, similarity_from_points
from app.core.survey.features import feature_supported, triangulate_features
from app.core.survey.reconstruction import grow, refine
from app.core.survey.seed import bootstrap
from app.core.survey.state import StageClock, SurveySettings, SurveyState

from .conftest import wall_features


def _started(true_state: SurveyState, intrinsics_given: bool = True) -> tuple[SurveyState, np.ndarray]:
    """A fresh state on the true state's views, bootstrapped; and the true discs."""
    truth = true_state.reconstruction.X.copy()
    settings = SurveySettings(0.2, intrinsics_given=intrinsics_given)
    state = SurveyState.start(true_state.tracks, true_state.reconstruction.camera, settings, StageClock(), [])
    bootstrap(state)
    return state, truth


def _map_error(state: SurveyState, truth: np.ndarray) -> float:
    placed = state.reconstruction.placed()
    src, dst = state.reconstruction.X[placed], truth[placed]
    return float(alignment_residuals(similarity_from_points(src, dst, with_scale=False), src, dst).max())


def test_growth_registers_every_frame_and_places_every_target(true_state: SurveyState) -> None:
    state, truth = _started(true_state)
    calls: list[tuple[str, float]] = []
    state.clock.progress = lambda stage, fraction: calls.append((stage, fraction))
    grow(state)
    rec = state.reconstruction
    # Every frame that sees 2+ targets; frames that see one only where the camera's
    # motion confirms the card's tilt.
    several = [f for f, v in enumerate(state.views.of_frame) if len(v) >= 2]
    assert rec.registered()[several].all()
    assert rec.n_registered >= 0.95 * sum(len(v) > 0 for v in state.views.of_frame)
    assert rec.placed().all()
    assert _map_error(state, truth) < 1e-6  # exact views: the map up to a rigid motion
    assert calls and all(stage == "register" for stage, _ in calls)
    assert calls[-1][1] == 0.05 + 0.45 * rec.n_registered / state.tracks.n_frames


def test_refinement_sets_aside_a_view_off_by_more_than_the_noise(true_state: SurveyState) -> None:
    """After growth on views with a little noise, the final rounds find the one disc
    that is 0.5 px off (glare), set its view aside, and reach the noise."""
    rng = np.random.default_rng(6)
    tracks, views = true_state.tracks, true_state.views
    tracks.uv += rng.normal(0, 0.01, tracks.uv.shape)
    v = views.of_target[4][7]
    views.uv[v, 1] += (0.4, 0.3)
    state, truth = _started(true_state, intrinsics_given=False)
    grow(state)
    assert not state.lens_fixed and state.lens_refined
    info = refine(state)
    assert not state.usable[v] and int((~state.usable).sum()) == 1
    assert info.covariance is not None and info.n_intr == 5
    assert info.rms_px < 0.02
    assert _map_error(state, truth) < 1e-3


def test_refinement_keeps_the_lens_from_too_few_frames(true_state: SurveyState) -> None:
    """Five lens parameters from 9 frames are not determined: the lens is held, with a
    warning."""
    rec = true_state.reconstruction
    true_state.lens_fixed = False
    keep = [f for f, v in enumerate(true_state.views.of_frame) if len(v)][:9]
    for f in np.flatnonzero(rec.registered()):
        if f not in keep:
            rec.unregister(int(f))
    camera = rec.camera
    refine(true_state)
    assert true_state.lens_fixed and true_state.reconstruction.camera is camera
    assert any("too few frames could be registered to calibrate the lens" in w for w in true_state.warnings)


def _with_wall_features(true_state: SurveyState) -> SurveyState:
    """The true state with the walls' feature tracks beside the cards, triangulated from the
    true poses."""
    state = SurveyState.start(true_state.tracks, true_state.reconstruction.camera, true_state.settings, StageClock(),
                              [], wall_features(sigma_px=0.05))
    state.reconstruction, state.seed_frame = true_state.reconstruction, true_state.seed_frame
    state.lens_fixed = state.lens_refined = True
    triangulate_features(state)
    return state


def test_refinement_judges_again_the_views_set_aside_in_frames_carried_by_feature_points(
        true_state: SurveyState) -> None:
    """A card seen again after a stretch carried by the walls' points is off by the drift
    while the map grows, and its views are set aside then; once the refinement closes the
    loop they fit, and the card is mapped where it is."""
    state = _with_wall_features(true_state)
    truth = state.reconstruction.X.copy()
    k = int(np.argmax([len(v) for v in state.views.of_target]))
    carried = feature_supported(state)
    views = state.views.of_target[k]
    views = views[carried[state.views.frame[views]]]
    assert len(views) >= 5
    # Where growth left the card: 3 cm off, every view of it in those frames set aside.
    state.reconstruction.place(k, state.reconstruction.discs(k) + [0.03, -0.02, 0.01])
    state.usable[views] = False
    refine(state)
    assert state.reconstruction.placed()[4 * k]
    assert state.usable[views].all()
    assert _map_error(state, truth) < 1e-3

