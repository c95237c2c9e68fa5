"""The targets stage as a whole (app.core.detection.targets): every visible card found from
simulated candidates, degenerate input, the timings and counts it reports; and the
detector's warm-up, after which a detection compiles no kernel."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from app.core.detection import (
    _candidates_kernels,
    _completion_kernels,
    _grouping_kernels,
    _refinement_kernels,
    _verification_kernels,
    warm_up,
)
from app.core.detection import targets as tg
from app.core.detection.candidates import load_default_classifier
from app.core.detection.detector import Detector
from app.core.detection.grouping import group_candidates
from app.core.geometry import _kernels as geometry_kernels
from app.sim.candidates import simulate_candidates
from app.sim.truth import truth_cards


def test_detects_every_visible_card_with_simulated_candidates(default_frames: list) -> None:
    rng = np.random.default_rng(2)
    n = 0
    for image, truth in default_frames:
        cand = simulate_candidates(image, truth.targets, rng)
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
    assert group_candidates(cand).shape == (0, 4) or cand.shape[1] < 3


def test_timing_and_counts(default_frames: list) -> None:
    image, truth = default_frames[0]
    cand = simulate_candidates(image, truth.targets, np.random.default_rng(6))
    timing: dict[str, float] = {}
    counts: dict[str, int] = {}
    out = tg.assemble_targets(image, cand, timing=timing, counts=counts)
    assert set(timing) == {"group", "verify", "refine", "identify", "complete"}
    assert counts["proposals"] >= counts["quick"] >= counts["verified"]
    assert counts["identified"] == len(out) >= counts["completed"] >= 0


#: Every module of compiled kernels the detector calls.
KERNEL_MODULES = (_candidates_kernels, _grouping_kernels, _verification_kernels, _refinement_kernels,
                  _completion_kernels, geometry_kernels)


def test_warm_up_compiles_what_the_detector_calls(texture: Callable[[np.random.Generator, int, int], np.ndarray]
                                                  ) -> None:
    """After `warm_up` a detection compiles nothing more (its argument types, read-only
    and non-contiguous arrays included, were all seen), in any stage's kernels."""
    warm_up()
    # the kernels each module defines (not those it imports: `_numba.pairwise_sum` is
    # called from compiled code only)
    dispatchers = {f"{m.__name__}.{name}": getattr(m, name) for m in KERNEL_MODULES for name in dir(m)
                   if hasattr(getattr(m, name), "signatures") and not name.startswith("_")
                   and getattr(m, name).py_func.__module__ == m.__name__}
    assert {d.py_func.__module__ for d in dispatchers.values()} == {m.__name__ for m in KERNEL_MODULES}
    before = {name: set(d.signatures) for name, d in dispatchers.items()}
    rng = np.random.default_rng(15)
    Detector(load_default_classifier()).detect(texture(rng, 240, 320))
    assert {name: set(d.signatures) for name, d in dispatchers.items()} == before
