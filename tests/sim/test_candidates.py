"""Simulated disc candidates (app.sim.candidates): a candidate on every visible disc, as
close and as sized as asked, false ones besides, the same from the same seed."""

from __future__ import annotations

import numpy as np

from app.sim import scenes
from app.sim.candidates import simulate_candidates


def _frame(seed: int) -> tuple[np.ndarray, scenes.FrameTruth]:
    rng = np.random.default_rng(seed)
    while True:
        try:
            image, truth = scenes.scenario_frame("default", rng)
        except ValueError:  # the simulator could not place the cards: draw again
            continue
        if any(t.visible for t in truth.targets):
            return image, truth


def test_every_visible_disc_has_a_candidate_within_the_jitter() -> None:
    image, truth = _frame(3)
    cand = simulate_candidates(image, truth.targets, np.random.default_rng(0), jitter_px=0.5,
                               radius_factor=(0.8, 1.2))
    assert cand.dtype == np.float32 and cand.shape[1] == 4
    for t in truth.targets:
        for k in np.flatnonzero(t.disc_visible):
            off = np.abs(cand[:, :2] - t.discs_px[k]).max(axis=1)
            near = cand[off <= 0.5 + 1e-3]
            assert near.size, f"disc {k} of card {t.id} has no candidate"
            ratio = near[:, 2] / (0.5 * t.disc_diameter_px)
            assert ((ratio >= 0.8 - 1e-5) & (ratio <= 1.2 + 1e-5)).any()


def test_false_candidates_come_on_top_and_the_seed_fixes_them() -> None:
    image, truth = _frame(4)
    n_discs = int(sum(t.disc_visible.sum() for t in truth.targets))
    plain = simulate_candidates(image, truth.targets, np.random.default_rng(1), n_random=0, n_texture=0,
                                code_cells=False, card_corners=False)
    assert plain.shape[0] == n_discs
    full = simulate_candidates(image, truth.targets, np.random.default_rng(1), n_random=25, n_texture=0)
    assert full.shape[0] >= n_discs + 25
    again = simulate_candidates(image, truth.targets, np.random.default_rng(1), n_random=25, n_texture=0)
    np.testing.assert_array_equal(full, again)
