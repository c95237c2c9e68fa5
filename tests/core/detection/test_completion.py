"""Completion (app.core.detection.completion): a card with a disc missing from the
candidates is found from the other three, three discs of no card are not; and its
compiled kernel (`_completion_kernels.affine_points`) against numpy, bit for bit."""

from __future__ import annotations

import numpy as np

from app.core.detection import _completion_kernels as kernels
from app.core.detection import completion as cp
from app.core.detection.targets import assemble_targets
from app.core.markers import DEFAULT_FAMILY, marker_layout, render_card
from app.sim.candidates import simulate_candidates
from app.sim.truth import truth_cards


def _card_image(marker_id: int, px: int = 120, pad: int = 60, bg: int = 90) -> tuple[np.ndarray, np.ndarray]:
    """One upright card on a grey background, and its disc centres (printed order)."""
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
        cand = simulate_candidates(image, truth.targets, rng)
        for t, card in zip(truth.targets, truth_cards(truth, None), strict=True):
            if not (card.counted and t.disc_diameter_px >= 8):
                continue
            k = int(rng.integers(4))
            gone = np.hypot(*(cand[:, :2] - t.discs_px[k]).T) <= t.disc_diameter_px
            counts: dict[str, int] = {}
            found = {x.id: x for x in assemble_targets(image, cand[~gone], counts=counts)}
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
            out = assemble_targets(img, cand)
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
        assert assemble_targets(img, cand) == []
    # a real card, its fourth disc covered by white paper / by a grey object
    for cover in (235, 90):
        img, discs = _card_image(21)
        x, y = np.rint(discs[2]).astype(int)
        img[y - 20 : y + 21, x - 20 : x + 21] = cover
        cand = np.column_stack([discs[[0, 1, 3]], np.full(3, 15.0), np.ones(3)])
        assert assemble_targets(img, cand) == []


def test_affine_points_match_numpy() -> None:
    rng = np.random.default_rng(17)
    for coef in (cp._corner_look_points(), cp._plan_affine(3), cp._plan_affine(4)):
        for s in (0, 1, 7, 40):
            pi, pj, pl = (rng.uniform(-50, 700, (s, 2)) for _ in range(3))
            xy = pi[:, None, :] + coef[None, :, :1] * (pj - pi)[:, None, :] + coef[None, :, 1:] * (pl - pi)[:, None, :]
            inside = ((xy >= -0.5) & (xy <= np.array([640 - 0.5, 480 - 0.5]))).all(axis=-1)
            got_xy, got_inside = kernels.affine_points(pi, pj, pl, coef, 640, 480)
            np.testing.assert_array_equal(got_xy, xy.astype(np.float32))
            np.testing.assert_array_equal(got_inside, inside)
            assert got_xy.dtype == np.float32 and got_xy.shape == xy.shape
