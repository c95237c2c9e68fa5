"""Verification (app.core.detection.verification): quadrilaterals that are no card are
refused; the measurements read numpy's order statistics; and its compiled kernel against
the vectorised measurements, bit for bit."""

from __future__ import annotations

import numpy as np

from app.core.detection import verification as vf
from app.core.detection._frame import Pyramid
from app.core.detection.targets import assemble_targets
from app.core.geometry.homography import homographies
from app.core.markers import DEFAULT_FAMILY, get_family


def test_verification_rejects_quadrilaterals_of_non_discs(clean_frames: list) -> None:
    rng = np.random.default_rng(3)
    for image, truth in clean_frames:
        # the true quadrilateral moved off its card onto the background and other places
        t = next(t for t in truth.targets if t.visible)
        side = float(np.linalg.norm(t.discs_px[1] - t.discs_px[0]))
        quads = []
        for _ in range(20):
            shift = rng.uniform(-3, 3, 2) * side
            q = t.discs_px + shift
            if (q.min(axis=0) > 0).all() and (q[:, 0].max() < image.shape[1]) and (q[:, 1].max() < image.shape[0]):
                centre = q.mean(axis=0)
                if np.linalg.norm(centre - t.discs_px.mean(axis=0)) > 1.5 * side:
                    quads.append(q)
        if not quads:
            continue
        hs = homographies(np.array(quads))
        m = vf._measure(Pyramid(image), hs, get_family(DEFAULT_FAMILY).cells)
        assert not m.passed().any()
        # and as candidates, nothing comes out
        r = 0.125 / 0.6 * side
        cand = np.array([[u, v, r, 1.0] for q in quads[:1] for u, v in q])
        assert assemble_targets(image, cand) == []


def test_verification_rejects_four_dark_squares() -> None:
    # Four black squares where discs should be, on a white card: no disc pattern.
    img = np.full((200, 200), 220, np.uint8)
    centres = np.array([[60, 60], [140, 60], [140, 140], [60, 140]], np.float64)
    for x, y in centres.astype(int):
        img[y - 17 : y + 18, x - 17 : x + 18] = 20
    cand = np.column_stack([centres, np.full(4, 16.0), np.ones(4)])
    assert assemble_targets(img, cand) == []


def test_mean_is_numpys_mean() -> None:
    rng = np.random.default_rng(11)
    for shape, axis in (((50, 7), 1), ((30, 9, 5), 2), ((5, 40), 0)):
        x = rng.normal(size=shape).astype(np.float32) * 100
        assert np.array_equal(vf._mean(x, axis), x.mean(axis=axis))


def test_measures_read_the_same_order_statistics_as_numpy() -> None:
    rng = np.random.default_rng(12)
    plan = vf._plan(get_family(DEFAULT_FAMILY).cells)
    m_pts = plan.points.shape[0]
    vals = rng.integers(0, 256, (60, m_pts)).astype(np.float32)  # whole grey levels, as cv2.remap reads them
    inside = rng.uniform(size=vals.shape) < 0.97
    inside[:20] = True
    m = vf._measures_from(vals, inside, plan)
    disc = vals[:, plan.disc.ravel()]
    white = vals[:, plan.white]
    inner = vals[:, np.concatenate([plan.between, plan.gap])]
    black = np.median(disc, axis=1)
    c = np.maximum(np.median(white, axis=1) - black, 1e-3)
    assert np.array_equal(m.black, black)
    assert np.array_equal(m.white, np.median(white, axis=1))
    close = {"rtol": 1e-5, "atol": 1e-5}
    assert np.allclose(m.uniformity, (np.percentile(inner, 90, axis=1) - np.percentile(inner, 10, axis=1)) / c, **close)
    assert np.allclose(m.white_low, (np.percentile(white, vf.WHITE_LOW_PERCENTILE, axis=1) - black) / c, **close)
    assert np.allclose(m.gap_low, (np.sort(vals[:, plan.gap], axis=1)[:, 1] - black) / c, **close)
    assert np.allclose(m.disc_max, (disc.max(axis=1) - black) / c, **close)
    assert np.allclose(m.disc_level, ((vals[:, plan.disc].mean(axis=2) - black[:, None]) / c[:, None]).max(axis=1),
                       **close)
    for r in range(60):
        edge = np.sort(vals[r, plan.edge][inside[r, plan.edge]])
        want = (edge[edge.size // 2] - black[r]) / c[r] if edge.size >= 4 else 1.0
        assert np.isclose(m.edge_level[r], want, **close)
    core_in = inside[:, plan.core].all(axis=1)
    assert np.array_equal(m.valid, np.where(core_in, inside.mean(axis=1), 0.0))


# --------------------------------------------------------------------------------------
# The compiled kernel (`_verification_kernels.measure_stats`) against the vectorised
# measurements (one sort of the groups, each lifted by its own multiple of 1024: whole
# grey levels sort apart)
# --------------------------------------------------------------------------------------


def _reference_measures_from(vals: np.ndarray, inside: np.ndarray, plan: vf._SamplePlan, cells: bool = True
                             ) -> vf._Measures:
    lift = np.repeat(1024.0 * np.arange(5), np.diff(plan.sorted_bounds)).astype(np.float32)
    p = vals.shape[0]
    s = vals.take(plan.sorted_index, axis=1)  # (ndarray.take: several times cheaper than fancy indexing)
    s += lift
    inside_edge = inside.take(plan.edge, axis=1)
    s[:, plan.sorted_bounds[4]:][~inside_edge] = np.inf  # outside the image: no evidence
    s.sort(axis=1)
    s -= lift
    # every order statistic at once (`_SamplePlan.stats_lo`), as `_quantile_sorted` would
    lo = s.take(plan.stats_lo, axis=1)
    q = lo + plan.stats_frac * (s.take(plan.stats_hi, axis=1) - lo)
    black, white = q[:, 0], q[:, 1]
    contrast = white - black
    c = np.maximum(contrast, 1e-3)
    uniformity = (q[:, 2] - q[:, 3]) / c
    white_low, gap_low, disc_max = ((q[:, 4:] - black[:, None]) / c[:, None]).T
    disc_means = (vf._mean(vals.take(plan.disc, axis=1), 2) - black[:, None]) / c[:, None]
    n_in = np.count_nonzero(inside_edge, axis=1)
    edge_med = s[np.arange(p), plan.sorted_bounds[4] + n_in // 2]
    edge_level = np.where(n_in >= 4, (edge_med - black) / c, 1.0)
    # Discs and code must be wholly in the image; the white margin mostly.
    valid = np.where(inside.take(plan.core, axis=1).all(axis=1), np.count_nonzero(inside, axis=1) / inside.shape[1],
                     0.0)
    dmax, dmin = disc_means.max(axis=1), disc_means.min(axis=1)
    cell_means = None
    if cells:
        # (P, n*n, S); fancy indexing, not take: its (n*n, S, P) memory layout carries into
        # the template fit, whose float32 sums depend on it
        cell_vals = (vals[:, plan.cells] - black[:, None, None]) / c[:, None, None]
        cell_means = vf._mean(cell_vals, 2)
    return vf._Measures(
        black=black, white=white, contrast=contrast, uniformity=uniformity,
        disc_level=dmax, disc_spread=dmax - dmin, disc_max=disc_max, white_low=white_low, gap_low=gap_low,
        edge_level=edge_level, valid=valid, cells=cell_means,
    )


def test_measure_stats_match_numpy() -> None:
    """`verification._measures_from` (`_verification_kernels.measure_stats`) against the vectorised
    measurements: every field, bit for bit, with samples outside the image (edge
    groups partly or wholly outside, core samples outside) and ties."""
    rng = np.random.default_rng(18)
    for n in (3, 4):
        plan = vf._plan(n)
        m = plan.points.shape[0]
        for trial in range(200):
            p = int(rng.integers(0, 6))
            levels = rng.integers(0, 256, 2)
            vals = rng.integers(min(levels), max(levels) + 1, (p, m)).astype(np.float32)
            inside = rng.random((p, m)) > rng.choice([0.0, 0.05, 0.5, 1.0])
            got = vf._measures_from(vals, inside, plan, cells=trial % 2 == 0)
            expected = _reference_measures_from(vals, inside, plan, cells=trial % 2 == 0)
            for name in expected.__dataclass_fields__:
                g, e = getattr(got, name), getattr(expected, name)
                if e is None:
                    assert g is None
                    continue
                assert g.dtype == e.dtype and g.shape == e.shape, name
                np.testing.assert_array_equal(g, e, err_msg=name)
