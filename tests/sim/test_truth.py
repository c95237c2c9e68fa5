"""Which targets of a frame count (app.sim.truth): visible cards whose footprint lies in
the image and that no nearer card covers."""

from __future__ import annotations

import dataclasses

import numpy as np

from app.sim import scenes
from app.sim.truth import FOOTPRINT_UV, truth_cards


def test_counted_cards_are_visible_and_keep_their_points() -> None:
    rng = np.random.default_rng(7)
    n_counted = 0
    for _ in range(6):
        _, truth = scenes.scenario_frame("default", rng)
        cards = truth_cards(truth, None)
        assert [c.id for c in cards] == [t.id for t in truth.targets]
        for card, t in zip(cards, truth.targets, strict=True):
            assert card.points is t.discs_px
            assert not card.counted or t.visible
            n_counted += card.counted
    assert n_counted >= 1


def test_a_card_behind_a_nearer_one_is_not_counted() -> None:
    rng = np.random.default_rng(8)
    _, truth = next(f for f in (scenes.scenario_frame("clean", rng) for _ in range(20))
                    if any(c.counted for c in truth_cards(f[1], None)))
    front = next(t for t, c in zip(truth.targets, truth_cards(truth, None), strict=True) if c.counted)
    behind = dataclasses.replace(front, id=front.id + 1, discs_px=front.discs_px + 1.0,
                                 distance_m=front.distance_m + 1.0)
    cards = truth_cards(dataclasses.replace(truth, targets=[front, behind]), None)
    assert cards[0].counted and not cards[1].counted
    assert FOOTPRINT_UV.min() == 0.075 and FOOTPRINT_UV.max() == 0.925
