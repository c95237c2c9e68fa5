"""Fitted disc centres (app.core.detection.disc_fit) on the bench room's walk: closer to the
truth than the detector's centroids, big discs and discs at the image's border left
alone, the detector's `fit_discs` option, and the compiled model against its numpy
reference."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.special import ndtr

from app.core.detection import _disc_fit_kernels as _kernels
from app.core.detection.candidates import load_default_classifier
from app.core.detection.detector import Detector
from app.core.detection.disc_fit import FIT_MAX_RADIUS_PX, fit_disc_centres
from app.core.geometry.homography import homographies
from app.sim.examples import BENCH_CAMERA, BENCH_ROOM
from app.sim.scenes import FrameTruth, render_walk


@pytest.fixture(scope="module")
def walk() -> list[tuple[np.ndarray, FrameTruth]]:
    """Every 25th frame of a 500-frame calibration walk through the bench room (seed 0)."""
    room = BENCH_ROOM.walk(0, 500)
    return list(render_walk(room.scene, BENCH_CAMERA, room.poses[::25], room.rng))


@pytest.fixture(scope="module")
def detector() -> Detector:
    return Detector(load_default_classifier())


def test_fitted_centres_are_closer_to_the_truth_than_centroids(walk: list, detector: Detector) -> None:
    centroid_err, fitted_err = [], []
    for image, truth in walk:
        by_id = {t.id: t for t in truth.targets}
        found = [t for t in detector.detect(image).targets if t.id in by_id]
        if not found:
            continue
        discs = np.array([t.discs for t in found])
        fit = fit_disc_centres(image, discs, homographies(discs))
        true = np.array([by_id[t.id].discs_px for t in found])
        centroid_err.append((discs - true)[fit.fitted])
        fitted_err.append((fit.centres - true)[fit.fitted])
        assert np.all(fit.centres[~fit.fitted] == discs[~fit.fitted])
        assert np.all(np.isfinite(fit.blur_px[fit.fitted])) and np.all(np.isnan(fit.blur_px[~fit.fitted]))
    c, f = np.concatenate(centroid_err), np.concatenate(fitted_err)
    assert len(f) >= 100
    rms_c, rms_f = float(np.sqrt(np.mean(c**2))), float(np.sqrt(np.mean(f**2)))
    # the fit removes at least a quarter of the centroids' error and stays near 0.01 px
    # on these discs of 3-7 px (0.014 with the blurred cards only the whole-card reader reads)
    assert rms_f < 0.75 * rms_c, (rms_f, rms_c)
    assert rms_f < 0.015


def test_big_discs_and_discs_at_the_border_keep_the_detectors_centres(walk: list) -> None:
    image, truth = next((im, tr) for im, tr in walk if any(t.visible for t in tr.targets))
    card = next(t for t in truth.targets if t.visible)
    discs = card.discs_px[None]
    fit = fit_disc_centres(image, discs, homographies(discs), max_radius_px=0.5)  # every disc "big"
    assert not fit.fitted.any() and np.all(fit.centres == discs)
    moved = discs - discs[0, 0] + [1.0, 1.0]  # the card's corner at the image's corner
    fit = fit_disc_centres(image, moved, homographies(moved))
    assert not fit.fitted[0, 0] and np.all(fit.centres[0, 0] == moved[0, 0])
    assert FIT_MAX_RADIUS_PX >= 6.0  # the walk's discs are 3-7 px: fitted by default


def test_no_cards_gives_an_empty_fit() -> None:
    fit = fit_disc_centres(np.zeros((48, 64), np.uint8), np.zeros((0, 4, 2)), np.zeros((0, 3, 3)))
    assert fit.centres.shape == (0, 4, 2) and fit.fitted.shape == (0, 4)


def test_detector_with_fit_discs_moves_only_centres(walk: list, detector: Detector) -> None:
    fitting = dataclasses.replace(detector, fit_discs=True)
    image = walk[0][0]
    plain, fitted = detector.detect(image), fitting.detect(image)
    assert [t.id for t in plain.targets] == [t.id for t in fitted.targets] and plain.targets
    shift = np.array([np.abs(a.discs - b.discs).max() for a, b in zip(plain.targets, fitted.targets, strict=True)])
    assert shift.max() > 0 and shift.max() < 0.5
    assert "targets.fit" in fitted.timing_ms and "targets.fit" not in plain.timing_ms


def _smeared_card(card_px: float, length_px: float, angle: float, supersample: int = 8
                  ) -> tuple[np.ndarray, np.ndarray]:
    """A card face-on on a dark wall, smeared straight over the exposure: the frame
    (uint8) and its true disc centres (4, 2)."""
    from app.core.markers import DEFAULT_FAMILY, DISC_CENTRES, marker_layout, render_card
    from app.sim import degrade

    side = int(card_px * 3)
    fine = np.full((side * supersample, side * supersample), 0.3)
    texture = render_card(marker_layout(DEFAULT_FAMILY, 7), int(card_px * supersample)) / 255.0
    x0, y0 = int((card_px + 0.3) * supersample), int((card_px + 0.45) * supersample)
    fine[y0:y0 + texture.shape[0], x0:x0 + texture.shape[1]] = texture
    image = fine.reshape(side, supersample, side, supersample).mean(axis=(1, 3)).astype(np.float32)
    image = degrade.motion_blur(image, length_px, angle)
    true = (np.array([x0, y0]) + DISC_CENTRES * texture.shape[0]) / supersample - 0.5
    return np.clip(image * 200 + 20, 0, 255).astype(np.uint8), true


def _radial(found: np.ndarray, true: np.ndarray) -> float:
    """The mean error of four discs away from the card's middle (px): the card's size."""
    outward = true - true.mean(axis=0)
    outward /= np.linalg.norm(outward, axis=1)[:, None]
    return float(((found - true) * outward).sum(axis=1).mean())


def test_a_smeared_card_keeps_its_size() -> None:
    # A 5 px smear of a card with 4 px discs on a darker wall, in 8 directions: an
    # isotropic blur's fit moved the discs 0.018 px toward the card's middle on average
    # (the card 0.1 % too small, so a survey of one-sided views puts it 0.1 % too far)
    # and one by 0.09 px; the smeared model finds the smear and keeps the card's size.
    radial, worst, lengths = [], 0.0, []
    for angle in np.linspace(0.0, np.pi, 8, endpoint=False):
        image, true = _smeared_card(32.0, 5.0, float(angle))
        fit = fit_disc_centres(image, true[None], homographies(true[None]))
        assert fit.fitted.all()
        radial.append(_radial(fit.centres[0], true))
        worst = max(worst, float(np.abs(fit.centres[0] - true).max()))
        lengths.extend(np.hypot(*fit.smear_px[0].T))
    assert abs(np.mean(radial)) < 0.008, radial
    assert worst < 0.04
    assert 4.0 < np.median(lengths) < 6.0, lengths


def test_a_sharp_card_is_fitted_as_sharp() -> None:
    image, true = _smeared_card(32.0, 0.0, 0.0)
    fit = fit_disc_centres(image, true[None], homographies(true[None]))
    assert fit.fitted.all()
    assert abs(_radial(fit.centres[0], true)) < 0.006
    assert np.hypot(*fit.smear_px[0].T).max() < 1.0


def _reference(px: np.ndarray, py: np.ndarray, du: np.ndarray, dv: np.ndarray, centres: np.ndarray,
               shapes: np.ndarray, nu: np.ndarray, nv: np.ndarray, theta: np.ndarray, ts: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """The smeared model and its Jacobian as numpy array operations: (n, K) and (n, K, 10)."""
    s, sm = theta[:, 5:6], theta[:, 8:10]
    white, contrast, back = theta[:, 2:3], theta[:, 3:4], theta[:, 4:5]
    step = white - back
    q00, q01, q11 = shapes[:, 0, 0, None], shapes[:, 0, 1, None], shapes[:, 1, 1, None]
    ink, card = np.zeros_like(px), np.zeros_like(px)
    jac = np.zeros(px.shape + (10,))
    for t in ts:
        x0 = px - (centres[:, 0] + theta[:, 0] + t * sm[:, 0])[:, None]
        x1 = py - (centres[:, 1] + theta[:, 1] + t * sm[:, 1])[:, None]
        g0, g1 = q00 * x0 + q01 * x1, q01 * x0 + q11 * x1
        qq = x0 * g0 + x1 * g1
        sq, gn = np.sqrt(qq) + 1e-12, np.hypot(g0, g1) + 1e-12
        d = (qq - sq) / gn
        h0, h1 = q00 * g0 + q01 * g1, q01 * g0 + q11 * g1
        a, b = (2.0 - 1.0 / sq) / gn, (qq - sq) / gn**3
        dd0, dd1 = -(a * g0 - b * h0), -(a * g1 - b * h1)
        zi = -d / s
        zu = -(du - t * (nu * sm).sum(1, keepdims=True) - theta[:, 6:7]) / s
        zv = -(dv - t * (nv * sm).sum(1, keepdims=True) - theta[:, 7:8]) / s
        pu, pv = ndtr(zu), ndtr(zv)
        ink += ndtr(zi) / len(ts)
        card += pu * pv / len(ts)
        gi, gu, gv = (np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi) for z in (zi, zu, zv))
        dink = -contrast * gi / len(ts)
        eu, ev = step * pv * gu / len(ts), step * pu * gv / len(ts)
        a0, a1 = dink * (-dd0 / s), dink * (-dd1 / s)
        jac[..., 0] += a0
        jac[..., 1] += a1
        jac[..., 5] += (dink * (-zi) + eu * (-zu) + ev * (-zv)) / s
        jac[..., 6] += eu / s
        jac[..., 7] += ev / s
        jac[..., 8] += t * (a0 + (eu * nu[:, 0:1] + ev * nv[:, 0:1]) / s)
        jac[..., 9] += t * (a1 + (eu * nu[:, 1:2] + ev * nv[:, 1:2]) / s)
    jac[..., 2], jac[..., 3], jac[..., 4] = card, -ink, 1.0 - card
    return back + card * step - contrast * ink, jac


def test_the_compiled_model_and_its_normal_equations_match_the_numpy_reference() -> None:
    rng = np.random.default_rng(3)
    n, k = 6, 200
    centres = rng.uniform(10, 20, (n, 2))
    px, py = centres[:, 0:1] + rng.uniform(-6, 6, (n, k)), centres[:, 1:2] + rng.uniform(-6, 6, (n, k))
    axes = rng.uniform(2, 5, (n, 2))
    angle = rng.uniform(0, np.pi, n)
    rot = np.stack([np.c_[np.cos(angle), -np.sin(angle)], np.c_[np.sin(angle), np.cos(angle)]], axis=1)
    shapes = rot @ (np.eye(2) / axes[:, None, :] ** 2) @ rot.transpose(0, 2, 1)
    normals = rng.normal(size=(n, 2, 2))
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    nu, nv = np.ascontiguousarray(normals[:, 0]), np.ascontiguousarray(normals[:, 1])
    du, dv = rng.uniform(-8, 1, (n, k)), rng.uniform(-8, 1, (n, k))
    theta = np.c_[rng.normal(0, 0.2, (n, 2)), rng.uniform(180, 230, n), rng.uniform(100, 150, n),
                  rng.uniform(20, 60, n), rng.uniform(0.4, 1.5, n), rng.normal(0, 0.3, (n, 2)),
                  rng.normal(0, 3, (n, 2))]
    vals = rng.uniform(0, 255, (n, k))
    wgt = (rng.random((n, k)) < 0.9).astype(np.float64)
    for ts in (np.zeros(1), (np.arange(5) + 0.5) / 5 - 0.5):
        pred, jac = _reference(px, py, du, dv, centres, shapes, nu, nv, theta, ts)
        r = vals - pred
        cost, normal, rhs = _kernels.normal_equations(px, py, wgt, vals, du, dv, centres, shapes, nu, nv, theta, ts,
                                                      True)
        np.testing.assert_allclose(cost, (wgt * r**2).sum(1), rtol=1e-6)
        jw = jac * wgt[..., None]
        np.testing.assert_allclose(normal, jw.transpose(0, 2, 1) @ jac, rtol=1e-5, atol=1e-6 * np.abs(normal).max())
        np.testing.assert_allclose(rhs, (jw * r[..., None]).sum(1), rtol=1e-5, atol=1e-6 * np.abs(rhs).max())
        only_cost = _kernels.normal_equations(px, py, wgt, vals, du, dv, centres, shapes, nu, nv, theta, ts, False)
        np.testing.assert_array_equal(only_cost[0], cost)
