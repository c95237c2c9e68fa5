"""Dark elliptical blobs as disc candidates, and the survey's detector that adds them to
the learned ones: cards seen at grazing angles are found, none as another card."""

from __future__ import annotations

import numpy as np

from app.core.detection import Detector, load_default_classifier
from app.core.detection.blobs import GRAZING_BLOBS, blob_candidates
from app.sim import scenes
from app.sim.truth import truth_cards


def _grazing_frames(n: int) -> list[tuple[np.ndarray, scenes.FrameTruth]]:
    rng = np.random.default_rng(21)
    return [scenes.scenario_frame("grazing", rng) for _ in range(n)]


def test_blobs_find_the_discs_of_cards_seen_edge_on() -> None:
    near = total = 0
    for image, truth in _grazing_frames(10):
        cand = blob_candidates(image, GRAZING_BLOBS)
        for t in truth.targets:
            if t.visible and t.facing_cos < 0.35:
                for disc in t.discs_px:
                    total += 1
                    near += bool(len(cand)) and np.hypot(*(cand[:, :2] - disc).T).min() < 1.0
    assert total >= 20 and near >= 0.7 * total, (near, total)


def test_the_survey_detector_finds_grazing_cards_the_live_one_misses() -> None:
    classifier = load_default_classifier()
    live, survey = Detector(classifier), Detector(classifier, thorough=True)
    found = {False: 0, True: 0}
    wrong = 0
    for image, truth in _grazing_frames(60):
        counted = {c.id for c in truth_cards(truth, None) if c.counted}
        for thorough, detector in ((False, live), (True, survey)):
            ids = [t.id for t in detector.detect(image).targets]
            found[thorough] += len(counted & set(ids))
            wrong += sum(i not in {t.id for t in truth.targets} for i in ids)
    assert found[True] >= found[False] + 8 and wrong == 0, (found, wrong)  # 76 against 64
