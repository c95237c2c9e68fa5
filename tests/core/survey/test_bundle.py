"""Bundle adjustment: the lens, every pose and every disc at once."""

from __future__ import annotations

import copy
import dataclasses

import cv2
import numpy as np
import pytest

from app.core.geometry.alignment import similarity_from_points
from app.core.survey.bundle import bundle_adjust, camera_from_intrinsics, correlation_time
from app.core.survey.cards import PAIR_UNITS, PAIRS
from app.core.survey.points import FeatureObservations, RobustLoss
from app.core.survey.state import Reconstruction, SurveyState, Tracks
from app.sim.examples import ExampleRoom

from .conftest import wall_points

PRIOR = (0.2, 1e-5)  # the printed card, 10 um


def _held(state: SurveyState) -> int:
    """The frame the bundle adjustment holds (the gauge)."""
    _, info = bundle_adjust(state.reconstruction, state.tracks, state.usable.repeat(4), False, PRIOR,
                            max_iterations=0)
    return info.held_frame


def _disturb(state: SurveyState, rng: np.random.Generator) -> None:
    """Every point by ~5 mm, every pose but the held one by ~0.3 degree and ~1 cm."""
    rec = state.reconstruction
    held = _held(state)
    moved = rec.registered()
    moved[held] = False
    rec.X += rng.normal(0, 0.005, rec.X.shape)
    rec.rvec[moved] += rng.normal(0, 0.005, (int(moved.sum()), 3))
    rec.tvec[moved] += rng.normal(0, 0.01, (int(moved.sum()), 3))


def test_bundle_adjustment_recovers_disturbed_poses_and_points(true_state: SurveyState) -> None:
    truth = copy.deepcopy(true_state.reconstruction)
    _disturb(true_state, np.random.default_rng(1))
    start = true_state.reconstruction
    out, info = bundle_adjust(start, true_state.tracks, true_state.usable.repeat(4), False, PRIOR)
    # The held frame and the card prior fix the gauge: the optimum is the truth.
    np.testing.assert_allclose(out.X, truth.X, atol=1e-9)
    np.testing.assert_allclose(out.rvec, truth.rvec, atol=1e-9)
    np.testing.assert_allclose(out.tvec, truth.tvec, atol=1e-9)
    assert info.rms_px < 1e-9 and 0 < info.iterations < 100
    assert info.n_intr == 0 and out.camera is start.camera
    assert start.X is not out.X  # the start is left as it was


def test_bundle_adjustment_finds_the_lens(true_state: SurveyState) -> None:
    camera = true_state.reconstruction.camera
    _disturb(true_state, np.random.default_rng(2))
    true_state.reconstruction.camera = camera_from_intrinsics(np.array([612.0, 324.0, 236.0, -0.08, 0.01]), 640, 480)
    out, info = bundle_adjust(true_state.reconstruction, true_state.tracks, true_state.usable.repeat(4), True, PRIOR)
    assert info.n_intr == 5 and info.rms_px < 1e-9
    np.testing.assert_allclose(out.camera.K, camera.K, atol=1e-6)
    np.testing.assert_allclose(out.camera.dist, camera.dist, atol=1e-9)


def test_the_card_prior_makes_the_map_metric(true_state: SurveyState) -> None:
    """Reprojection alone leaves the scale free; the card prior gives every card its
    printed size."""
    rec = true_state.reconstruction
    rec.X *= 1.1
    rec.tvec *= 1.1
    use = true_state.usable.repeat(4)
    free, _ = bundle_adjust(rec, true_state.tracks, use, False, None)
    metric, info = bundle_adjust(rec, true_state.tracks, use, False, PRIOR)
    assert info.rms_px < 1e-9

    def sides(X: np.ndarray) -> np.ndarray:
        cards = X.reshape(-1, 4, 3)
        return np.linalg.norm(cards[:, PAIRS[:, 0]] - cards[:, PAIRS[:, 1]], axis=2) / (PAIR_UNITS * 0.2)

    np.testing.assert_allclose(sides(free.X), 1.1, rtol=1e-9)
    np.testing.assert_allclose(sides(metric.X), 1.0, rtol=1e-7)


def test_huber_loss_lowers_the_pull_of_a_wild_observation(true_state: SurveyState) -> None:
    """A disc 1 px off (glare) weighs by its precision times Huber's weight: with the
    loss from 2.5 expected errors it moves the map far less than in least squares."""
    truth = true_state.reconstruction.X.copy()
    views = true_state.views
    v = views.of_target[4][5]
    views.uv[v, 0] += (0.8, -0.6)
    use = true_state.usable.repeat(4)
    robust, info = bundle_adjust(true_state.reconstruction, true_state.tracks, use, False, PRIOR, loss_scale=2.5)
    plain, _ = bundle_adjust(true_state.reconstruction, true_state.tracks, use, False, PRIOR, loss_scale=1e6)
    k = int(np.flatnonzero(info.obs == 4 * v)[0])
    assert info.weights[k] < 0.1 * true_state.tracks.precision[4 * v]
    others = np.delete(np.arange(len(info.obs)), k)
    np.testing.assert_allclose(info.weights[others], true_state.tracks.precision[info.obs[others]])
    error = np.nanmax(np.abs(robust.X - truth)), np.nanmax(np.abs(plain.X - truth))
    assert error[0] < 0.5 * error[1]


def test_only_used_observations_take_part(true_state: SurveyState) -> None:
    rec, views = true_state.reconstruction, true_state.views
    use = true_state.usable.copy()
    use[views.of_target[3]] = False  # target 3 left out: its points do not move
    rec.X[12:16] += 0.01
    out, info = bundle_adjust(rec, true_state.tracks, use.repeat(4), False, PRIOR, max_iterations=3)
    np.testing.assert_array_equal(out.X[12:16], rec.X[12:16])
    assert 12 not in info.points and len(info.obs) == 4 * int(use.sum())


def test_covariance_gives_each_disc_an_uncertainty(true_state: SurveyState) -> None:
    rng = np.random.default_rng(4)
    true_state.tracks.uv += rng.normal(0, 0.1, true_state.tracks.uv.shape)
    use = true_state.usable.repeat(4)
    rec, _ = bundle_adjust(true_state.reconstruction, true_state.tracks, use, False, PRIOR)
    again, info = bundle_adjust(rec, true_state.tracks, use, False, PRIOR, max_iterations=0, with_covariance=True)
    np.testing.assert_array_equal(again.X, rec.X)  # no iterations: the map stays
    assert info.covariance is not None and info.covariance.shape == (3 * len(info.points),) * 2
    std = info.disc_std(rec.X)
    assert np.isfinite(std).all() and 1e-4 < np.median(std) < 0.02  # 0.1 px at 1-3 m: mm
    # The joint covariance behind it: symmetric, no motion of the whole map in it, each
    # disc's block the std's square.
    joint = info.disc_covariance(rec.X)
    assert joint is not None and joint.shape == info.covariance.shape
    np.testing.assert_allclose(joint, joint.T)
    assert np.linalg.eigvalsh(joint).min() > -1e-9 * np.abs(joint).max()
    X = rec.X[info.points]
    shift = np.tile(np.eye(3), (len(X), 1))  # the whole map moved along x, y, z
    spin = np.cross(np.eye(3)[:, None, :], X - X.mean(axis=0)).transpose(1, 2, 0).reshape(-1, 3)  # turned
    for motion in (shift, spin):
        assert np.abs(motion.T @ joint @ motion).max() < 1e-9 * np.abs(motion.T @ info.covariance @ motion).max()
    np.testing.assert_allclose(np.sqrt(np.diag(joint).reshape(-1, 3).sum(axis=1)), std[info.points])
    # Without the covariance: no uncertainty.
    _, plain = bundle_adjust(rec, true_state.tracks, use, False, PRIOR, max_iterations=0)
    assert plain.covariance is None and np.isnan(plain.disc_std(rec.X)).all()


# --- feature points: the second kind of track ---------------------------------------------


def _wall_features(state: SurveyState, room: ExampleRoom, rng: np.random.Generator, n: int, sigma_px: float = 0.5,
                   loss: RobustLoss = RobustLoss.CAUCHY) -> tuple[FeatureObservations, np.ndarray]:
    """Points on the small room's walls (from its geometry, not from the survey) and their
    exact images in a run of up to 6 registered frames that see them (in the lens's field,
    2 px inside the image, on a wall facing the camera), kept when those views are 2
    degrees apart at least: (observations, true points)."""
    rec, camera = state.reconstruction, state.reconstruction.camera
    frames = np.flatnonzero(rec.registered())
    m = 20 * n
    X, inward = wall_points(rng, m, (0.1, 0.2), room.size)
    seen = np.zeros((len(frames), m), bool)
    uv = np.zeros((len(frames), m, 2))
    for i, f in enumerate(frames):
        pose = rec.pose(f)
        ray = pose.position - X
        uv[i] = cv2.projectPoints(X.reshape(-1, 1, 3), rec.rvec[f], rec.tvec[f], camera.K, camera.dist)[0][:, 0]
        facing = (ray * inward).sum(axis=1) > 0.2 * np.linalg.norm(ray, axis=1)
        inside = ((uv[i] >= 2) & (uv[i] <= [camera.width - 3, camera.height - 3])).all(axis=1)
        seen[i] = camera.in_field(pose.transform(X)) & facing & inside
    rows, points = [], []
    for j in range(m):
        views = np.flatnonzero(seen[:, j])
        start = int(rng.integers(0, max(len(views) - 5, 1)))
        views = views[start : start + 6]
        rays = X[j] - np.array([rec.pose(f).position for f in frames[views]]).reshape(-1, 3)
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        if len(views) < 2 or np.degrees(np.arccos(np.clip((rays @ rays.T).min(), -1, 1))) < 2.0:
            continue
        rows += [(frames[i], len(points), uv[i, j]) for i in views]
        points.append(X[j])
        if len(points) == n:
            break
    assert len(points) == n
    rows.sort(key=lambda row: (row[0], row[1]))
    features = FeatureObservations(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]),
                                   np.array([r[2] for r in rows]), sigma_px=sigma_px, loss=loss)
    return features, np.array(points)


def test_feature_points_join_the_adjustment_and_it_recovers_poses_and_points(true_state: SurveyState,
                                                                             room: ExampleRoom) -> None:
    truth = copy.deepcopy(true_state.reconstruction)
    rng = np.random.default_rng(11)
    features, points = _wall_features(true_state, room, rng, 150)
    _disturb(true_state, rng)
    start_points = points + rng.normal(0, 0.02, points.shape)
    given = start_points.copy()
    use = true_state.usable.repeat(4)
    out, info = bundle_adjust(true_state.reconstruction, true_state.tracks, use, False, PRIOR, features=features,
                              feature_X=start_points)
    np.testing.assert_array_equal(start_points, given)  # the start is left as it was
    # The held frame and the card prior fix the gauge: the optimum is the truth, feature
    # points included.
    np.testing.assert_allclose(out.X, truth.X, atol=1e-9)
    np.testing.assert_allclose(out.rvec, truth.rvec, atol=1e-9)
    np.testing.assert_allclose(out.tvec, truth.tvec, atol=1e-9)
    assert info.feature_X is not None
    np.testing.assert_allclose(info.feature_X, points, atol=1e-7)
    assert len(info.feature_obs) == len(features) and len(info.feature_points) == len(points)
    assert info.rms_px < 1e-9 and info.feature_rms_px < 1e-7 and 0 < info.iterations < 100
    assert info.held_frame == _held(true_state)  # the same gauge as the discs alone


def test_feature_points_and_the_lens(true_state: SurveyState, room: ExampleRoom) -> None:
    """The intrinsics move with feature points too, and the covariance is that of the
    discs given everything else."""
    camera = true_state.reconstruction.camera
    rng = np.random.default_rng(12)
    features, points = _wall_features(true_state, room, rng, 100)
    _disturb(true_state, rng)
    true_state.reconstruction.camera = camera_from_intrinsics(np.array([612.0, 324.0, 236.0, -0.08, 0.01]), 640, 480)
    use = true_state.usable.repeat(4)
    out, info = bundle_adjust(true_state.reconstruction, true_state.tracks, use, True, PRIOR, features=features,
                              feature_X=points + rng.normal(0, 0.02, points.shape), with_covariance=True)
    assert info.n_intr == 5 and info.rms_px < 1e-9
    np.testing.assert_allclose(out.camera.K, camera.K, atol=1e-6)
    np.testing.assert_allclose(out.camera.dist, camera.dist, atol=1e-9)
    assert info.covariance is not None and info.covariance.shape == (5 + 3 * len(info.points),) * 2
    assert np.isfinite(info.disc_std(out.X)).all()


def test_the_robust_loss_keeps_wrong_matches_from_moving_the_map(true_state: SurveyState, room: ExampleRoom) -> None:
    """A handful of feature observations 20-40 px off (wrong matches) among 0.5 px noisy
    ones barely move the map under either robust loss, and pull it off in least squares."""
    rng = np.random.default_rng(13)
    features, points = _wall_features(true_state, room, rng, 150)
    noisy = features.uv + rng.normal(0, 0.5, features.uv.shape)
    wrong = rng.choice(len(features), 5, replace=False)
    angle = rng.uniform(0, 2 * np.pi, 5)
    bad = noisy.copy()
    bad[wrong] += rng.uniform(20, 40, 5)[:, None] * np.c_[np.cos(angle), np.sin(angle)]
    rec, tracks, use = true_state.reconstruction, true_state.tracks, true_state.usable.repeat(4)
    frames = np.flatnonzero(rec.registered())

    def moved(loss: RobustLoss, scale: float) -> tuple[float, float, np.ndarray]:
        """How far the wrong matches move the discs and the camera positions (m), and
        their weights relative to a good observation's."""
        clean = dataclasses.replace(features, uv=noisy, loss=loss, loss_scale=scale)
        a, _ = bundle_adjust(rec, tracks, use, False, PRIOR, features=clean, feature_X=points, tolerance=1e-9)
        b, info = bundle_adjust(rec, tracks, use, False, PRIOR, features=dataclasses.replace(clean, uv=bad),
                                feature_X=points, tolerance=1e-9)
        centres = [np.linalg.norm(a.pose(f).position - b.pose(f).position) for f in frames]
        relative = info.feature_weights[np.isin(info.feature_obs, wrong)] * features.sigma_px**2
        return float(np.abs(a.X - b.X).max()), float(max(centres)), relative

    plain = moved(RobustLoss.HUBER, 1e6)
    assert plain[0] > 2e-4 and plain[1] > 5e-3  # least squares: discs 0.2 mm off and more, cameras 5 mm
    huber, cauchy = moved(RobustLoss.HUBER, 2.5), moved(RobustLoss.CAUCHY, 2.5)
    assert huber[0] < 0.2 * plain[0] and huber[1] < 0.2 * plain[1] and (huber[2] < 0.1).all()
    assert cauchy[0] < 0.1 * plain[0] and cauchy[1] < 0.1 * plain[1] and (cauchy[2] < 0.005).all()


def test_without_feature_points_the_result_is_the_discs_alone(true_state: SurveyState, room: ExampleRoom) -> None:
    """No feature points, an empty set, or none usable: the same arrays, to the bit."""
    rng = np.random.default_rng(14)
    features, points = _wall_features(true_state, room, rng, 20)
    _disturb(true_state, rng)
    true_state.reconstruction.camera = camera_from_intrinsics(np.array([612.0, 324.0, 236.0, -0.08, 0.01]), 640, 480)
    rec, tracks, use = true_state.reconstruction, true_state.tracks, true_state.usable.repeat(4)
    runs = [
        bundle_adjust(rec, tracks, use, True, PRIOR, max_iterations=20, with_covariance=True),
        bundle_adjust(rec, tracks, use, True, PRIOR, max_iterations=20, with_covariance=True,
                      features=FeatureObservations.empty(), feature_X=np.zeros((0, 3))),
        bundle_adjust(rec, tracks, use, True, PRIOR, max_iterations=20, with_covariance=True,
                      features=features, feature_X=points, feature_use=np.zeros(len(features), bool)),
    ]
    (ref, ref_info), others = runs[0], runs[1:]
    for out, info in others:
        np.testing.assert_array_equal(out.X, ref.X)
        np.testing.assert_array_equal(out.rvec, ref.rvec)
        np.testing.assert_array_equal(out.tvec, ref.tvec)
        np.testing.assert_array_equal(out.camera.K, ref.camera.K)
        np.testing.assert_array_equal(out.camera.dist, ref.camera.dist)
        np.testing.assert_array_equal(info.residuals, ref_info.residuals)
        np.testing.assert_array_equal(info.weights, ref_info.weights)
        np.testing.assert_array_equal(info.covariance, ref_info.covariance)
        assert (info.cost, info.iterations, info.held_frame) == (ref_info.cost, ref_info.iterations,
                                                                 ref_info.held_frame)
        assert len(info.feature_obs) == 0
    assert ref_info.feature_X is None
    np.testing.assert_array_equal(others[1][1].feature_X, points)  # given back as they were


def test_the_step_is_that_of_the_whole_problem(true_state: SurveyState, room: ExampleRoom) -> None:
    """Eliminating the feature points gives the step of the damped normal equations of
    every parameter at once, built here from finite differences of the whitened
    residuals (a few frames; intrinsics free; no robust loss in play)."""
    rng = np.random.default_rng(15)
    features, points = _wall_features(true_state, room, rng, 100, loss=RobustLoss.HUBER)
    features = dataclasses.replace(features, loss_scale=1e9)
    _disturb(true_state, rng)
    rec, tracks = true_state.reconstruction, true_state.tracks
    frames = np.flatnonzero(rec.registered())[10:18]
    use = np.isin(tracks.frame, frames)
    f_use = np.isin(features.frame, frames)
    f_use &= np.bincount(features.track[f_use], minlength=len(points))[features.track] >= 2
    start_points = points + rng.normal(0, 0.01, points.shape)
    out, info = bundle_adjust(rec, tracks, use, True, PRIOR, loss_scale=1e9, max_iterations=1, features=features,
                              feature_X=start_points, feature_use=f_use)
    free = frames[frames != info.held_frame]
    d_points, f_points = info.points, info.feature_points
    intr0 = np.array([rec.camera.fx, rec.camera.cx, rec.camera.cy, rec.camera.dist[0], rec.camera.dist[1]])
    whole = [t for t in np.unique(d_points // 4) if np.isin(4 * t + np.arange(4), d_points).all()]
    n_d, n_c = 3 * len(d_points), 6 * len(free)

    def unpack(x: np.ndarray) -> tuple[Reconstruction, np.ndarray]:
        r = copy.deepcopy(rec)
        r.camera = camera_from_intrinsics(intr0 + x[:5], 640, 480)
        r.X[d_points] += x[5 : 5 + n_d].reshape(-1, 3)
        r.rvec[free] += x[5 + n_d : 5 + n_d + n_c].reshape(-1, 6)[:, :3]
        r.tvec[free] += x[5 + n_d : 5 + n_d + n_c].reshape(-1, 6)[:, 3:]
        fX = start_points.copy()
        fX[f_points] += x[5 + n_d + n_c :].reshape(-1, 3)
        return r, fX

    def whitened(x: np.ndarray) -> np.ndarray:
        r, fX = unpack(x)
        out = []
        for f in frames:
            i = np.flatnonzero(use & (tracks.frame == f))
            p, _ = cv2.projectPoints(r.X[tracks.point[i]].reshape(-1, 1, 3), r.rvec[f], r.tvec[f], r.camera.K,
                                     r.camera.dist)
            out.append(((p.reshape(-1, 2) - tracks.uv[i]) * np.sqrt(tracks.precision[i])[:, None]).ravel())
            k = np.flatnonzero(f_use & (features.frame == f))
            p, _ = cv2.projectPoints(fX[features.track[k]].reshape(-1, 1, 3), r.rvec[f], r.tvec[f], r.camera.K,
                                     r.camera.dist)
            out.append(((p.reshape(-1, 2) - features.uv[k]) / features.sigma_px).ravel())
        for t in whole:
            d = np.linalg.norm(r.X[4 * t + PAIRS[:, 0]] - r.X[4 * t + PAIRS[:, 1]], axis=1)
            out.append((d - PAIR_UNITS * PRIOR[0]) / PRIOR[1])
        return np.concatenate(out)

    n = 5 + n_d + n_c + 3 * len(f_points)
    e = whitened(np.zeros(n))
    J = np.empty((len(e), n))
    for j in range(n):
        h = np.zeros(n)
        h[j] = 1e-4 if j < 3 else 1e-7  # f, cx, cy in pixels
        J[:, j] = (whitened(h) - whitened(-h)) / (2 * h[j])
    H = J.T @ J
    step = -np.linalg.solve(H + 1e-4 * np.diag(np.diag(H) + 1e-12), J.T @ e)  # the first iteration's damping
    expected, expected_points = unpack(step)
    scale = np.abs(step).max()
    np.testing.assert_allclose(out.X[d_points], expected.X[d_points], atol=1e-6 * scale)
    np.testing.assert_allclose(out.rvec[free], expected.rvec[free], atol=1e-6 * scale)
    np.testing.assert_allclose(out.tvec[free], expected.tvec[free], atol=1e-6 * scale)
    np.testing.assert_allclose(info.feature_X[f_points], expected_points[f_points], atol=1e-6 * scale)
    np.testing.assert_allclose(out.camera.fx, intr0[0] + step[0], atol=1e-6 * abs(step[0]))


# --- errors shared by consecutive frames -------------------------------------------------


def _drifting_errors(tracks: Tracks, rng: np.random.Generator, sigma_px: float, rho: float) -> np.ndarray:
    """(M, 2) errors of ``sigma_px`` per axis that each disc carries from one frame to the
    next with correlation ``rho`` (as a video's blur and compression do)."""
    err = rng.normal(0, sigma_px, tracks.uv.shape)
    order = np.lexsort((tracks.frame, tracks.point))
    point = tracks.point[order]
    for i in range(1, len(order)):
        if point[i] == point[i - 1]:
            err[order[i]] = rho * err[order[i - 1]] + np.sqrt(1 - rho**2) * err[order[i]]
    return err


def test_the_correlation_time_of_a_drifting_error() -> None:
    rng = np.random.default_rng(0)
    point = np.repeat(np.arange(40), 200)
    frame = np.tile(np.arange(200), 40)
    white = rng.normal(size=(len(point), 2))
    assert 0.9 < correlation_time(point, frame, white) < 1.2
    for rho in (0.5, 0.8):
        drift = white.copy().reshape(40, 200, 2)
        for k in range(1, 200):
            drift[:, k] = rho * drift[:, k - 1] + np.sqrt(1 - rho**2) * drift[:, k]
        expected = (1 + rho) / (1 - rho)
        assert 0.75 * expected < correlation_time(point, frame, drift.reshape(-1, 2)) < 1.25 * expected
    # The order of the observations does not matter: each point's are taken in frame order.
    shuffled = rng.permutation(len(point))
    assert correlation_time(point[shuffled], frame[shuffled], drift.reshape(-1, 2)[shuffled]) == pytest.approx(
        correlation_time(point, frame, drift.reshape(-1, 2)))


def test_errors_shared_by_consecutive_frames_widen_the_covariance_to_cover_them(true_state: SurveyState) -> None:
    exact = true_state.tracks.uv.copy()
    truth = true_state.reconstruction.X.copy()
    use = true_state.usable.repeat(4)
    found = {}
    for rho in (0.0, 0.9):
        errors, stds, taus = [], [], []
        for seed in range(3):
            true_state.tracks.uv[:] = exact + _drifting_errors(true_state.tracks, np.random.default_rng(seed), 0.1, rho)
            rec, _ = bundle_adjust(true_state.reconstruction, true_state.tracks, use, False, PRIOR)
            _, info = bundle_adjust(rec, true_state.tracks, use, False, PRIOR, max_iterations=0, with_covariance=True)
            adjusted = rec.X[info.points]
            fit = similarity_from_points(adjusted, truth[info.points], with_scale=False)
            errors.append(np.linalg.norm(fit.apply(adjusted) - truth[info.points], axis=1))
            stds.append(info.disc_std(rec.X)[info.points])
            taus.append(info.correlation_time)
        ratio = np.sqrt(np.mean(np.concatenate(errors) ** 2) / np.mean(np.concatenate(stds) ** 2))
        found[rho] = (float(np.median(taus)), ratio)
    # The bundle sees the errors' correlation in its own residuals ...
    assert found[0.0][0] < 1.5 and found[0.9][0] > 4.0, found
    # ... and the uncertainty it reports covers the map's error either way.
    assert found[0.0][1] < 1.5 and found[0.9][1] < 1.5, found
