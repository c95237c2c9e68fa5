"""Targets from disc candidates (app.core.detection.targets): grouping, verification, subpixel
centres, identification and degenerate input, each on small simulator renders with
simulated candidates. Fast (a few seconds)."""

from __future__ import annotations

import numpy as np
import pytest

from app.sim import scenes
from app.core.detection import targets as tg
from app.core.geometry import homography as hg
from app.core.markers import DEFAULT_FAMILY, get_family, marker_layout, render_card
from bench.peers import truth_cards


def _frames(name: str, n: int, seed: int) -> list[tuple[np.ndarray, scenes.FrameTruth]]:
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        try:
            image, truth = scenes.scenario_frame(name, rng)
        except ValueError:  # the simulator could not place the cards: draw again
            continue
        if any(t.visible for t in truth.targets):
            out.append((image, truth))
    return out


@pytest.fixture(scope="module")
def clean_frames() -> list[tuple[np.ndarray, scenes.FrameTruth]]:
    return _frames("clean", 6, seed=11)


@pytest.fixture(scope="module")
def default_frames() -> list[tuple[np.ndarray, scenes.FrameTruth]]:
    return _frames("default", 6, seed=12)


def test_grouping_finds_the_true_quadrilateral_among_clutter(default_frames: list) -> None:
    rng = np.random.default_rng(0)
    n_cards = 0
    for image, truth in default_frames:
        cand = tg.simulate_candidates(image, truth.targets, rng, n_random=60, n_texture=40)
        quads = tg.group_candidates(cand)
        assert quads.ndim == 2 and quads.shape[1] == 4
        for t in truth.targets:
            if not t.visible:
                continue
            n_cards += 1
            # some proposal has a candidate on each disc, in the layout's cyclic order
            d = np.hypot(*(cand[quads, None, :2] - t.discs_px[None, None]).transpose(3, 0, 1, 2))  # (P, 4, 4)
            on = d <= 1.5  # jitter is 1 px
            hit = any(
                all(on[p, k, (k + s) % 4] for k in range(4)) for p in range(len(quads)) for s in range(4)
            )
            assert hit, f"card {t.id} not proposed"
        # proposals stay few: clutter must not explode the 4-cycles
        assert quads.shape[0] <= 20 * len(cand)
    assert n_cards >= 6


def test_grouping_orientation_is_the_layouts(clean_frames: list) -> None:
    rng = np.random.default_rng(1)
    image, truth = clean_frames[0]
    cand = tg.simulate_candidates(image, truth.targets, rng, n_random=0, n_texture=0, jitter_px=0.0)
    for q in tg.group_candidates(cand):
        p = cand[q, :2].astype(np.float64)
        a, b = p[1] - p[0], p[3] - p[0]
        cross = a[0] * b[1] - a[1] * b[0]
        assert cross > 0  # clockwise on screen (y down), as discs 0-1-2-3 printed


def test_detects_every_visible_card_with_simulated_candidates(default_frames: list) -> None:
    rng = np.random.default_rng(2)
    n = 0
    for image, truth in default_frames:
        cand = tg.simulate_candidates(image, truth.targets, rng)
        found = {t.id: t for t in tg.assemble_targets(image, cand)}
        ids = {t.id for t in truth.targets}
        assert set(found) <= ids  # no false targets, no wrong ids
        for t, card in zip(truth.targets, truth_cards(truth, None), strict=True):
            # (a card partly covered by a nearer one is not counted)
            if card.counted and t.disc_diameter_px >= 6:
                n += 1
                assert t.id in found, f"card {t.id} (discs {t.disc_diameter_px:.1f} px) missed"
                assert np.abs(found[t.id].discs - t.discs_px).max() < 1.0
    assert n >= 5


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
        hs = hg.homographies(np.array(quads))
        m = tg._measure(tg._Pyramid(image), hs, get_family(DEFAULT_FAMILY).cells)
        assert not m.passed().any()
        # and as candidates, nothing comes out
        r = 0.125 / 0.6 * side
        cand = np.array([[u, v, r, 1.0] for q in quads[:1] for u, v in q])
        assert tg.assemble_targets(image, cand) == []


def test_verification_rejects_four_dark_squares() -> None:
    # Four black squares where discs should be, on a white card: no disc pattern.
    img = np.full((200, 200), 220, np.uint8)
    centres = np.array([[60, 60], [140, 60], [140, 140], [60, 140]], np.float64)
    for x, y in centres.astype(int):
        img[y - 17 : y + 18, x - 17 : x + 18] = 20
    cand = np.column_stack([centres, np.full(4, 16.0), np.ones(4)])
    assert tg.assemble_targets(img, cand) == []


def test_subpixel_centres_on_clean_frames(clean_frames: list) -> None:
    rng = np.random.default_rng(4)
    errs = []
    for image, truth in clean_frames:
        for t in truth.targets:
            if not t.visible or t.disc_diameter_px < 8:
                continue
            start = t.discs_px + rng.uniform(-1.0, 1.0, (4, 2))
            start = np.roll(start, int(rng.integers(4)), axis=0)  # any starting disc
            refined, radii = tg.refine_centres(image, start[None])
            truth_rolled = np.roll(t.discs_px, 0, axis=0)
            # match each refined centre to its true disc
            d = np.hypot(*(refined[0][:, None, :] - truth_rolled[None]).transpose(2, 0, 1))
            errs.extend(d.min(axis=1).tolist())
            assert np.allclose(radii[0], t.disc_diameter_px / 2, rtol=0.15)
    errs = np.array(errs)
    assert errs.size >= 16
    rms = float(np.sqrt(np.mean(errs**2)))
    # measured ~0.003 px on this simulator; the bound is 0.1 px
    assert rms <= 0.05, f"disc centre RMS {rms:.3f} px"


def test_identification_in_every_rotation_gives_the_design_order(clean_frames: list) -> None:
    n = 0
    for image, truth in clean_frames:
        for t in truth.targets:
            if not t.visible:
                continue
            for s in range(4):  # the quadrilateral may start at any disc
                got = tg.identify(image, np.roll(t.discs_px, s, axis=0))
                assert got is not None
                tid, discs, match = got
                assert tid == t.id
                assert np.allclose(discs, t.discs_px)  # DESIGN.md order: 0 TL, 1 TR, 2 BR, 3 BL
                assert match.gap >= tg.CODE_GAP_MIN
                n += 1
    assert n >= 16


def test_identification_of_rotated_cards() -> None:
    # A printed card rolled by 0, 90, 180 and 270 degrees in the image (fronto-parallel):
    # the id and the printed disc order come out whatever the roll.
    fam = get_family(DEFAULT_FAMILY)
    for marker_id in (0, 7, len(fam) - 1):
        card = render_card(marker_layout(DEFAULT_FAMILY, marker_id), 240)
        canvas = np.full((320, 320), 128, np.uint8)
        canvas[40:280, 40:280] = card
        # printed disc centres (DESIGN order) in canvas pixels (pixel centres at integers)
        base = 40 + np.array([[0.2, 0.2], [0.8, 0.2], [0.8, 0.8], [0.2, 0.8]]) * 240 - 0.5
        for k in range(4):
            img = np.ascontiguousarray(np.rot90(canvas, k))  # counter-clockwise by 90 k
            pts = base.copy()
            for _ in range(k):  # where np.rot90 moves pixel (x, y): (y, 319 - x)
                pts = np.stack([pts[:, 1], 319 - pts[:, 0]], axis=1)
            for s in range(4):
                got = tg.identify(img, np.roll(pts, s, axis=0))
                assert got is not None, f"id {marker_id} rotated {90 * k}"
                tid, discs, _ = got
                assert tid == marker_id
                assert np.allclose(discs, pts, atol=1e-6)


def test_ambiguous_or_unreadable_codes_are_refused() -> None:
    tmpl, ids, shifts = tg._templates(DEFAULT_FAMILY)
    # a clean code is read, with its id and rotation
    for row in (0, 5, len(tmpl) - 1):
        m = tg.decode_cells(tmpl[row])
        assert m is not None and m.id == ids[row] and m.shift == shifts[row]
    # every cell grey: unreadable
    assert tg.decode_cells(np.full(9, 0.5)) is None
    # halfway between two codes (or rotations) at the family's distance: ambiguous
    dist = (tmpl[:, None, :] != tmpl[None, :, :]).sum(axis=2)
    np.fill_diagonal(dist, 99)
    a, b = np.unravel_index(np.argmin(dist), dist.shape)
    assert tg.decode_cells(0.5 * (tmpl[a] + tmpl[b])) is None
    # noise far beyond any blur: refused
    rng = np.random.default_rng(5)
    refused = sum(tg.decode_cells(rng.uniform(-0.5, 1.5, 9)) is None for _ in range(200))
    assert refused >= 190


@pytest.mark.parametrize(
    "cand",
    [
        np.zeros((0, 4)),
        np.array([[10.0, 10.0, 3.0, 1.0]]),
        np.array([[10.0, 10.0, 3.0, 1.0], [30.0, 10.0, 3.0, 1.0], [30.0, 30.0, 3.0, 1.0]]),
        np.array([[10.0 * k, 50.0, 3.0, 1.0] for k in range(1, 9)]),  # collinear
        np.array([[np.nan, 10.0, 3.0, 1.0], [30.0, np.nan, 3.0, 1.0], [30.0, 30.0, np.inf, 1.0],
                  [10.0, 30.0, 3.0, np.nan]]),
        np.full((6, 4), np.nan),
        np.array([[20.0, 20.0, 3.0, 1.0]] * 6),  # all on one spot
        np.zeros((5, 2)),  # no radius column
    ],
)
def test_degenerate_input_gives_nothing(cand: np.ndarray) -> None:
    img = np.full((100, 100), 200, np.uint8)
    assert tg.assemble_targets(img, cand) == []
    assert tg.group_candidates(cand).shape == (0, 4) or cand.shape[1] < 3


def test_timing_and_counts(default_frames: list) -> None:
    image, truth = default_frames[0]
    cand = tg.simulate_candidates(image, truth.targets, np.random.default_rng(6))
    timing: dict[str, float] = {}
    counts: dict[str, int] = {}
    out = tg.assemble_targets(image, cand, timing=timing, counts=counts)
    assert set(timing) == {"group", "verify", "refine", "identify", "complete"}
    assert counts["proposals"] >= counts["quick"] >= counts["verified"]
    assert counts["identified"] == len(out) >= counts["completed"] >= 0


def _smeared_card(marker_id: int, px: int, length: float, angle: float) -> tuple[np.ndarray, np.ndarray]:
    from app.sim import degrade

    img = np.full((px + 80, px + 80), 90, np.uint8)
    img[40 : 40 + px, 40 : 40 + px] = render_card(marker_layout(DEFAULT_FAMILY, marker_id), px)
    discs = np.asarray(marker_layout(DEFAULT_FAMILY, marker_id).discs, np.float64) * px - 0.5 + 40
    return degrade.motion_blur(img, length, angle), discs


def test_motion_blurred_codes_are_read_by_the_smear_templates(monkeypatch: pytest.MonkeyPatch) -> None:
    """A small card smeared by two cell widths: the motion fallback reads codes the
    isotropic templates refuse, and never reads a wrong one."""
    found = {True: 0, False: 0}
    for marker_id in range(0, 60, 5):
        for angle in (0.3, 1.1, 2.0, 2.7):
            img, discs = _smeared_card(marker_id, 48, 12.0, angle)
            cand = np.column_stack([discs, np.full(4, 0.125 * 48), np.ones(4)])
            for on in (True, False):
                monkeypatch.setattr(tg, "MOTION_MAX_READS", 4 if on else 0)
                out = tg.assemble_targets(img, cand)
                assert all(t.id == marker_id for t in out)
                found[on] += any(t.id == marker_id for t in out)
    assert found[True] > found[False]


def _card_image(marker_id: int, px: int = 120, pad: int = 60, bg: int = 90) -> tuple[np.ndarray, np.ndarray]:
    """One upright card on a grey background, and its disc centres (DESIGN order)."""
    layout = marker_layout(DEFAULT_FAMILY, marker_id)
    img = np.full((px + 2 * pad, px + 2 * pad), bg, np.uint8)
    img[pad : pad + px, pad : pad + px] = render_card(layout, px)
    return img, np.asarray(layout.discs, np.float64) * px - 0.5 + pad


def test_card_with_a_disc_missing_from_the_candidates_is_completed(default_frames: list) -> None:
    """A card whose fourth disc has no candidate (blur, the candidate stage's miss) is
    found from the other three: the fourth is predicted, refined and verified."""
    rng = np.random.default_rng(8)
    n = 0
    for image, truth in default_frames:
        cand = tg.simulate_candidates(image, truth.targets, rng)
        for t, card in zip(truth.targets, truth_cards(truth, None), strict=True):
            if not (card.counted and t.disc_diameter_px >= 8):
                continue
            k = int(rng.integers(4))
            gone = np.hypot(*(cand[:, :2] - t.discs_px[k]).T) <= t.disc_diameter_px
            counts: dict[str, int] = {}
            found = {x.id: x for x in tg.assemble_targets(image, cand[~gone], counts=counts)}
            assert set(found) <= {x.id for x in truth.targets}
            assert t.id in found, f"card {t.id} without disc {k} not completed"
            assert np.abs(found[t.id].discs - t.discs_px).max() < 1.0
            assert counts["completed"] >= 1
            n += 1
    assert n >= 5
    # a single card, each disc in turn, every rotation of the code
    for marker_id in (3, 17, 40):
        img, discs = _card_image(marker_id)
        for k in range(4):
            keep = [m for m in range(4) if m != k]
            cand = np.column_stack([discs[keep], np.full(3, 0.125 * 120), np.ones(3)])
            out = tg.assemble_targets(img, cand)
            assert [x.id for x in out] == [marker_id]
            assert np.abs(out[0].discs - discs).max() < 0.3


def test_three_disc_corner_of_nothing_is_not_a_target() -> None:
    """Three dark discs at the corners of a card-like square but no fourth disc: no
    target, however the candidates sit (and neither from a card whose fourth disc is
    covered)."""
    img = np.full((240, 240), 225, np.uint8)
    yy, xx = np.mgrid[:240, :240]
    centres = np.array([[60.0, 60.0], [180.0, 60.0], [180.0, 180.0], [60.0, 180.0]])
    for x, y in centres[:3]:
        img[(xx - x) ** 2 + (yy - y) ** 2 <= 25.0**2] = 20
    rng = np.random.default_rng(4)
    for _ in range(10):
        cand = np.column_stack([centres[:3] + rng.uniform(-2, 2, (3, 2)), rng.uniform(18, 30, 3), np.ones(3)])
        assert tg.assemble_targets(img, cand) == []
    # a real card, its fourth disc covered by white paper / by a grey object
    for cover in (235, 90):
        img, discs = _card_image(21)
        x, y = np.rint(discs[2]).astype(int)
        img[y - 20 : y + 21, x - 20 : x + 21] = cover
        cand = np.column_stack([discs[[0, 1, 3]], np.full(3, 15.0), np.ones(3)])
        assert tg.assemble_targets(img, cand) == []


# --------------------------------------------------------------------------------------
# The fast paths of the stage give exactly what the plain numpy expressions give
# --------------------------------------------------------------------------------------


def test_homographies_of_a_few_quadrilaterals_match_the_vectorised_path() -> None:
    rng = np.random.default_rng(9)
    q = rng.uniform(-50, 700, (4 * hg._FEW, 4, 2))
    q[0] = [[0, 0], [1, 0], [2, 0], [3, 0]]  # collinear: the guarded denominator
    q[1, 2] = np.nan
    q[2] = q[2, :1]  # all on one spot
    with np.errstate(invalid="ignore"):
        many = hg.homographies(q)  # more than _FEW: vectorised
        for start in range(0, q.shape[0], hg._FEW):
            few = hg.homographies(q[start : start + hg._FEW])  # Python floats
            assert np.array_equal(few, many[start : start + hg._FEW], equal_nan=True)


def test_masked_median_u8_matches_numpy() -> None:
    rng = np.random.default_rng(10)
    values = rng.integers(0, 256, (40, 90)).astype(np.uint8)
    mask = rng.uniform(size=values.shape) < rng.uniform(0, 1, (40, 1))
    mask[0] = False
    got = tg._masked_median_u8(values, mask)
    assert np.isnan(got[0])
    for r in range(1, 40):
        if mask[r].any():
            assert got[r] == np.median(values[r][mask[r]])


def test_mean_is_numpys_mean() -> None:
    rng = np.random.default_rng(11)
    for shape, axis in (((50, 7), 1), ((30, 9, 5), 2), ((5, 40), 0)):
        x = rng.normal(size=shape).astype(np.float32) * 100
        assert np.array_equal(tg._mean(x, axis), x.mean(axis=axis))


def test_measures_read_the_same_order_statistics_as_numpy() -> None:
    rng = np.random.default_rng(12)
    plan = tg._plan(get_family(DEFAULT_FAMILY).cells)
    m_pts = plan.points.shape[0]
    vals = rng.integers(0, 256, (60, m_pts)).astype(np.float32)  # whole grey levels, as cv2.remap reads them
    inside = rng.uniform(size=vals.shape) < 0.97
    inside[:20] = True
    m = tg._measures_from(vals, inside, plan)
    disc = vals[:, plan.disc.ravel()]
    white = vals[:, plan.white]
    inner = vals[:, np.concatenate([plan.between, plan.gap])]
    black = np.median(disc, axis=1)
    c = np.maximum(np.median(white, axis=1) - black, 1e-3)
    assert np.array_equal(m.black, black)
    assert np.array_equal(m.white, np.median(white, axis=1))
    close = {"rtol": 1e-5, "atol": 1e-5}
    assert np.allclose(m.uniformity, (np.percentile(inner, 90, axis=1) - np.percentile(inner, 10, axis=1)) / c, **close)
    assert np.allclose(m.white_low, (np.percentile(white, tg.WHITE_LOW_PERCENTILE, axis=1) - black) / c, **close)
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


def test_windows_inside_and_overhanging_the_image_read_the_same_pixels() -> None:
    rng = np.random.default_rng(13)
    img = rng.integers(0, 256, (60, 80)).astype(np.uint8)
    size = 9
    for x0, y0 in ((np.array([0, 10, 71]), np.array([0, 20, 51])), (np.array([-3, 40, 75]), np.array([5, -2, 58]))):
        got, valid = tg._windows_u8(img, x0, y0, size)
        offs = np.arange(size)
        xi, yi = x0[:, None, None] + offs[None, None, :], y0[:, None, None] + offs[None, :, None]
        assert np.array_equal(got, img[np.clip(yi, 0, 59), np.clip(xi, 0, 79)])
        inside = (xi >= 0) & (xi < 80) & (yi >= 0) & (yi < 60)
        assert (valid is None and inside.all()) or np.array_equal(valid, inside)


def test_refinement_given_its_homographies_is_the_same(clean_frames: list) -> None:
    image, truth = clean_frames[0]
    t = next(t for t in truth.targets if t.visible)
    start = t.discs_px[None] + np.random.default_rng(14).uniform(-1, 1, (1, 4, 2))
    a = tg.refine_centres(image, start)
    b = tg.refine_centres(image, start, _homographies=hg.homographies(start))
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
