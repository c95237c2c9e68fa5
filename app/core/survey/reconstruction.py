"""The survey driver: structure from motion over the cards (paper §3 step 4, §5.1).

Input: the identified targets of every frame of a calibration video (the caller runs the
detector, so it can report progress and reuse detections). Output: the camera (focal
length, principal point, radial distortion), the 3D centre of every disc of every target
(the map) with its uncertainty, and the camera trajectory. The stages, in order, each a
function over one `SurveyState` (docs/survey.md walks through them):

1. `lens.initial_camera`: the lens from the cards alone;
2. `seed.bootstrap`: a metric start from two frames (essential matrix, triangulation,
   scale from the printed card);
3. `grow`: passes of `register.register_frames` (resection) and `place.place_targets`
   (triangulation), with `bundle.bundle_adjust` and `prune.prune` in between
   (`policy.ShouldBundle`);
4. `refine`: bundle adjustment over everything with a robust loss set by the video's own
   noise, outlier removal, and again, until nothing changes (through a rolling shutter,
   `shutter.undo_readout` moves each frame's observations to its middle row's moment
   before every bundle adjustment, and `refine` runs once more);
5. `scale.apply_metric_scale`: the scale of the printed cards;
6. `result.survey_result`: each disc's uncertainty, warnings about weak parts of the map.
7. `verify`: the lens against the cards' own (`verify.LensAgreement`: a map whose focal
   length the cards disagree with is refused), cards placed too uncertainly named.

numpy / OpenCV / SciPy only; no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from app.core.detection import DetectedTarget
from app.core.geometry import Camera, RollingShutter
from app.core.survey.bundle import GROWTH_LOSS_SCALE, BundleInfo, bundle_adjust
from app.core.survey.features import feature_supported, prune_features, register_by_features, triangulate_features
from app.core.survey.lens import cards_lens, initial_camera
from app.core.survey.place import place_targets
from app.core.survey.points import FeatureObservations
from app.core.survey.policy import ShouldBundle, ShouldFitLens
from app.core.survey.prune import HUBER_K, MIN_OUTLIER_PX, OUTLIER_K, drop_unsupported, prune, whitened_spread
from app.core.survey.register import register_frames
from app.core.survey.result import SurveyResult, survey_result, surveyed_views
from app.core.survey.scale import apply_metric_scale
from app.core.survey.seed import bootstrap
from app.core.survey.shutter import undo_readout
from app.core.survey.state import (
    Progress,
    Readout,
    StageClock,
    SurveyError,
    SurveySettings,
    SurveyStage,
    SurveyState,
)
from app.core.survey.tracks import collect_tracks, subsample_frames
from app.core.survey.verify import LensAgreement

#: With feature points, the bundle adjustment stops once an iteration gains less than this
#: fraction of the cost: Huber's reweighting then creeps on for a hundred iterations, each
#: worth less than rounding in the map.
FEATURE_TOLERANCE = 1e-6


def survey(
    frames: Sequence[Sequence[DetectedTarget]],
    width: int,
    height: int,
    marker_size_m: float,
    intrinsics: Camera | None = None,
    progress: Progress | None = None,
    max_frames: int | None = None,
    step: int = 1,
    card_prior_m: float | None = 1e-5,
    outlier_px: float = 3.0,
    features: FeatureObservations | None = None,
    shutter: RollingShutter | None = None,
    frame_numbers: Sequence[float] | None = None,
) -> SurveyResult:
    """Survey the targets seen in a calibration video.

    Parameters
    ----------
    frames : sequence of sequences of DetectedTarget
        The detected targets of each frame, in video order.
    width, height : int
        The image size, px.
    marker_size_m : float
        The printed card's side, metres.
    intrinsics : Camera, optional
        A known camera (K and dist held fixed); default: estimated.
    progress : callable, optional
        Called with a stage name (`SurveyStage`) and the fraction done.
    max_frames : int, optional
        Use at most this many frames, evenly over the video.
    step : int
        Use every ``step``-th frame.
    card_prior_m : float or None
        Sigma (metres) of a soft prior on each card's disc-to-disc distances inside the
        bundle adjustment (None: the scale is fitted afterwards only). On by default: a
        target linked to the rest only through frames from nearly one viewpoint can
        slide along the rays from that viewpoint, scaled, at no cost in reprojection
        error; its printed size is what pins it (bench room, 300 frames, detector
        output: disc RMS 44 mm without, 3.9 mm with). Tight (10 um, nearly a
        constraint): a printed card keeps its disc-to-disc distances, bent or not (a
        bend moves a disc along the card's normal, changing the distances only to second
        order), far better than the survey measures them (tests/core/survey's synthetic
        walk: discs 0.8-1.1 mm at 10 um, 2.1-3.7 mm at 1 mm).
    outlier_px : float
        How far (px) a view may be off while the map grows (the final bundle adjustment
        judges by the noise level instead).
    features : FeatureObservations, optional
        The scene's own points tracked through the video (frames numbered as
        ``frames``), a second kind of track: frames that see one card or none register
        through them, and cards never filmed together join through them. The map still
        holds the cards only.

    Returns
    -------
    SurveyResult
        The camera, the map, the trajectory and warnings.

    Raises
    ------
    SurveyError
        When the video does not allow a survey (the message says why, for a user).
    """
    clock = StageClock(progress)
    if not (marker_size_m > 0 and np.isfinite(marker_size_m)):
        raise SurveyError(f"marker_size_m must be a positive length in metres, got {marker_size_m}")
    if intrinsics is not None and (intrinsics.width, intrinsics.height) != (width, height):
        intrinsics = intrinsics.scaled_to(width, height)
    if len(frames) < 2:
        raise SurveyError(f"a survey needs a video of at least 2 frames, got {len(frames)}")
    used = subsample_frames(len(frames), max_frames, step)
    warnings: list[str] = []
    tracks = collect_tracks(frames, used, warnings)

    clock.report(SurveyStage.INTRINSICS, 0.0)
    card_lens = cards_lens(tracks, width, height) if intrinsics is None else None
    camera = initial_camera(tracks, width, height, intrinsics, warnings, card_lens)
    clock.lap(SurveyStage.INTRINSICS)

    clock.report(SurveyStage.INITIAL, 0.05)
    settings = SurveySettings(marker_size_m, outlier_px, card_prior_m, intrinsics_given=intrinsics is not None)
    if features is not None:
        features = features.in_frames(used)
    state = SurveyState.start(tracks, camera, settings, clock, warnings, features)
    if shutter is not None and shutter.readout > 0:
        numbers = np.arange(len(frames), dtype=np.float64) if frame_numbers is None else np.asarray(frame_numbers,
                                                                                                   np.float64)
        if len(numbers) != len(frames) or np.any(np.diff(numbers) <= 0):
            raise SurveyError("frame_numbers must give each frame's place in the video, increasing")
        state.readout = Readout.of(state, shutter, numbers[used])
    bootstrap(state)
    clock.lap(SurveyStage.INITIAL)

    grow(state)
    clock.lap(SurveyStage.REGISTER)
    if state.reconstruction.n_registered < 2:
        raise SurveyError("fewer than 2 frames could be registered: the targets must be seen from several "
                          "viewpoints, with at least two targets together in some frames")

    info = refine(state)
    if state.readout is not None:
        # The motion through the readout came from the poses of the map still growing:
        # once more with the refined trajectory.
        info = refine(state)
        if card_lens is not None:
            # The lens check judges the cards as the middle rows see them.
            card_lens = cards_lens(state.tracks, width, height)
    clock.lap(SurveyStage.BUNDLE)

    clock.report(SurveyStage.SCALE, 0.9)
    surveyed = surveyed_views(state)
    scale = apply_metric_scale(state.reconstruction, surveyed.targets, marker_size_m)
    clock.lap(SurveyStage.SCALE)

    clock.report(SurveyStage.COVARIANCE, 0.95)
    result = survey_result(state, info, surveyed, scale, used, len(frames))
    clock.lap(SurveyStage.COVARIANCE)
    if not np.isfinite(result.rms_px) or result.rms_px > 2 * outlier_px:
        raise SurveyError(f"the survey did not converge (reprojection RMS {result.rms_px:.1f} px): the video does "
                          "not show the targets from enough viewpoints, or many targets are misidentified")
    if card_lens is not None and card_lens.fitted is not None and not result.intrinsics_fixed:
        lens = LensAgreement(result.camera.fx, card_lens.fitted[0])
        if not lens.agrees:
            raise SurveyError(lens.message())
    clock.report(SurveyStage.DONE, 1.0)
    return result


def grow(state: SurveyState, should_bundle: ShouldBundle = ShouldBundle(),
         should_fit_lens: ShouldFitLens = ShouldFitLens()) -> None:
    """Grow the map from the start (step 3): register frames, place targets, in passes.

    Frames that see 2+ placed targets first, then frames resting on one. After a pass
    that changed the map the bundle adjustment refines it (``should_bundle``; the lens
    moves once ``should_fit_lens`` allows), and once the lens is fitted the map is
    judged by all its views (`prune.prune`): what does not fit is taken out, to be
    registered or placed again later from better views. New targets are placed only
    from poses the bundle has just refined.

    Parameters
    ----------
    state : SurveyState
        The survey after `seed.bootstrap`; grown in place.
    should_bundle : ShouldBundle
        When to bundle-adjust the growing map.
    should_fit_lens : ShouldFitLens
        When that bundle adjustment fits the intrinsics.
    """
    settings = state.settings
    placed = place_targets(state)
    passes = 0
    for min_targets in (2, 1):
        while passes < 100:  # a bound: pruning and re-registering must not cycle forever
            passes += 1
            added = register_frames(state, min_targets) + register_by_features(state)
            n_registered = state.reconstruction.n_registered
            state.clock.report(SurveyStage.REGISTER, 0.05 + 0.45 * n_registered / state.tracks.n_frames)
            if should_bundle(state, bool(added or placed)):
                lens_free = should_fit_lens.while_growing(state)
                # The card prior here too: a card linked to the rest only through frames
                # from nearly one viewpoint slides along their rays at no cost, and frames
                # registered against it inherit the error (noise-free walks end 20 mm off).
                adjust(state, lens_free, GROWTH_LOSS_SCALE, should_bundle.max_iterations)
                # Until the lens is fitted the initial focal length may be ~10 % off: views
                # are not judged by their fit yet.
                state.lens_refined = state.lens_refined or lens_free
                if state.lens_refined and (prune(state, 2 * settings.outlier_px)
                                           | prune_features(state, 2 * settings.outlier_px)):
                    state.attempted.clear()  # the map changed: frames refused before may fit now
                    state.feature_tried.clear()
            placed = place_targets(state) + triangulate_features(state)
            if added == 0 and placed == 0:
                break


def refine(state: SurveyState, should_fit_lens: ShouldFitLens = ShouldFitLens(), rounds: int = 5) -> BundleInfo:
    """Bundle-adjust the whole map and remove its outliers, until nothing changes (step 4).

    Every view set aside while the map grew, in a frame carried by feature points, gets a
    new chance first. Each round: a bundle
    adjustment with Huber's loss from ``HUBER_K`` robust spreads of
    the whitened errors (`prune.whitened_spread`: the video's own noise level); frames
    that failed before are registered and targets placed if they fit now; then every
    view is judged, also those set aside: a view with a disc beyond ``OUTLIER_K`` spreads
    (and ``MIN_OUTLIER_PX``) is set aside, one set aside is taken back only well inside
    (half the threshold), else a view near it goes in and out every round. A frame or a
    target left with no usable view is taken out. Stops when a round changes nothing;
    else a last adjustment follows. Then the covariance at the optimum.

    Parameters
    ----------
    state : SurveyState
        The grown survey; refined in place (the lens is held when ``should_fit_lens``
        refuses, with a warning).
    should_fit_lens : ShouldFitLens
        Whether the intrinsics are fitted.
    rounds : int
        At most this many rounds.

    Returns
    -------
    BundleInfo
        The last bundle adjustment, with the marginal covariance of the intrinsics and
        points.
    """
    if not state.lens_fixed and not should_fit_lens.at_the_end(state):
        state.lens_fixed = True
        state.warnings.append("too few frames could be registered to calibrate the lens: the initial focal length "
                              "estimate was kept and no distortion was fitted")
    expected_px = state.tracks.expected_px
    # Views set aside while the map grew were judged against a map whose loops were not
    # closed yet: a card seen again after a stretch carried by feature points is off by
    # the drift, and leaving it out keeps the drift (centre loop, room 0: discs 16 mm off
    # against 3.6 mm with those views judged again here; the optimum is 3.1 mm). Only
    # frames that rest on feature points drift so: elsewhere a view set aside stays
    # aside until it fits.
    carried = feature_supported(state)
    state.usable |= carried[state.views.frame]
    state.feature_usable |= carried[state.features.frame]
    clean = False
    for round_ in range(rounds):
        state.clock.report(SurveyStage.BUNDLE, 0.5 + 0.1 * round_)
        adjust(state, not state.lens_fixed, HUBER_K * whitened_spread(state))
        before = state.reconstruction.n_registered
        state.attempted.clear()
        state.feature_tried.clear()
        register_frames(state, 1)
        register_by_features(state)
        grew = place_targets(state) + triangulate_features(state) > 0 or state.reconstruction.n_registered > before
        threshold_px = np.maximum(OUTLIER_K * whitened_spread(state) * expected_px, MIN_OUTLIER_PX)
        feature_px = OUTLIER_K * state.features.sigma_px
        if not (prune(state, 1.0, threshold_px, 0.5) | prune_features(state, feature_px, 0.5 * feature_px)) and not grew:
            clean = True
            break
        drop_unsupported(state)
    loss_scale = HUBER_K * whitened_spread(state)
    if not clean:
        adjust(state, not state.lens_fixed, loss_scale)
    # The covariance at the optimum (no iterations: the map stays as it is).
    return adjust(state, not state.lens_fixed, loss_scale, max_iterations=0, with_covariance=True)


def adjust(state: SurveyState, free_intrinsics: bool, loss_scale: float, max_iterations: int = 100,
           with_covariance: bool = False) -> BundleInfo:
    """Bundle-adjust every usable view of both kinds of track; the state takes the result.

    Parameters
    ----------
    state : SurveyState
        The survey: its reconstruction and feature points are replaced by the adjusted ones.
    free_intrinsics : bool
        Whether the lens moves.
    loss_scale : float
        Huber's threshold on the discs' whitened errors (the feature points have their own).
    max_iterations : int
        At most this many iterations (0: only measure).
    with_covariance : bool
        Also compute the marginal covariance of the intrinsics and discs.

    Returns
    -------
    BundleInfo
        What the adjustment did.
    """
    undo_readout(state)
    features = state.features if len(state.features) else None
    state.reconstruction, info = bundle_adjust(
        state.reconstruction, state.tracks, state.usable.repeat(4), free_intrinsics=free_intrinsics,
        card_prior=state.settings.card_prior, max_iterations=max_iterations, loss_scale=loss_scale,
        with_covariance=with_covariance, features=features, feature_X=state.feature_X if features else None,
        feature_use=state.feature_usable if features else None, tolerance=FEATURE_TOLERANCE if features else 1e-12)
    if info.feature_X is not None:
        state.feature_X = info.feature_X
    return info
