"""Each detected target carries its code's margin (`DetectedTarget.code_gap`): how much
worse the best other code fits the read, which the survey weighs when an id turns up in a
frame or two only (`survey.tracks.probable_misreads`)."""

from __future__ import annotations

import numpy as np

from app.core.detection import targets as tg
from app.core.detection.identification import CODE_GAP_MIN, MOTION_GAP_TIGHT
from app.sim.candidates import simulate_candidates


def test_every_target_carries_the_margin_its_code_was_accepted_with(default_frames: list) -> None:
    rng = np.random.default_rng(2)
    gaps = [t.code_gap for image, truth in default_frames
            for t in tg.assemble_targets(image, simulate_candidates(image, truth.targets, rng))]
    assert len(gaps) >= 5
    assert all(np.isfinite(g) and g >= min(CODE_GAP_MIN, MOTION_GAP_TIGHT) for g in gaps)
    assert max(gaps) > 2 * CODE_GAP_MIN  # a clear read stands well clear of the threshold
