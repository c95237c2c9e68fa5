"""Each detected target carries the margins its code was read with: the nine-sample read's
(`DetectedTarget.code_gap`), which the survey weighs when an id turns up in a frame or two
only (`survey.tracks.probable_misreads`), and the whole card's (`read_margin`), which the
`/detect` and `/track` replies report."""

from __future__ import annotations

import numpy as np

from app.core.detection import targets as tg
from app.core.detection.code_reader import MIN_MARGIN
from app.core.detection.identification import CODE_GAP_MIN
from app.sim.candidates import simulate_candidates


def test_every_target_carries_the_margins_its_code_was_accepted_with(default_frames: list) -> None:
    rng = np.random.default_rng(2)
    found = [t for image, truth in default_frames
             for t in tg.assemble_targets(image, simulate_candidates(image, truth.targets, rng))]
    assert len(found) >= 5
    # a code stands on the nine samples and the whole card agreeing, or on a clear whole-card read
    assert all(np.isfinite(t.read_margin) and np.isfinite(t.code_gap) for t in found)
    assert all(t.code_gap >= CODE_GAP_MIN or t.read_margin >= MIN_MARGIN for t in found)
    assert max(t.read_margin for t in found) > 4 * MIN_MARGIN  # a clear read stands well clear of the threshold
