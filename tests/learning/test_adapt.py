"""Self-labelled adaptation of the disc classifier to a site's own images."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.detection import candidates as cand
from app.core.detection.candidates import load_default_classifier
from app.learning.adapt import adapt_classifier, label_site_image
from app.sim import scenes


@pytest.fixture(scope="module")
def site_frames() -> list[tuple[np.ndarray, scenes.FrameTruth]]:
    rng = np.random.default_rng(5)
    return [scenes.scenario_frame(name, rng) for name in ("default", "dark", "blur", "clean")]


def test_positive_windows_sit_on_true_discs_and_negatives_away_from_them(site_frames) -> None:
    base = load_default_classifier()
    image, truth = site_frames[3]
    site = label_site_image(image, base)
    assert site.targets >= 1 and site.positives.shape[0] >= 4 * site.targets
    # Every positive window, found again among the stage-1 windows, is centred on a true disc.
    s1 = cand.stage1_windows(image, base)
    centres = s1.full_resolution_centres()
    true_discs = np.concatenate([t.discs_px for t in truth.targets])
    as_rows = s1.windows.reshape(len(s1), -1)
    for window in site.positives.reshape(site.positives.shape[0], -1):
        k = int(np.flatnonzero((as_rows == window).all(axis=1))[0])
        scale = 2.0 ** int(s1.level[k])
        assert np.hypot(*(true_discs - centres[k]).T).min() <= 2.0 * scale
    assert site.negatives.shape[0] > 0


def test_adapted_classifier_extends_the_base_and_accepts_the_site_discs(site_frames) -> None:
    base = load_default_classifier()
    adapted = adapt_classifier(base, [image for image, _ in site_frames])
    n = base.prototypes.shape[0]
    # Hart's rule started from the base prototypes: they are all still there, first.
    np.testing.assert_array_equal(adapted.prototypes[:n], base.prototypes)
    np.testing.assert_array_equal(adapted.labels[:n], base.labels)
    stats = adapted.stats
    assert stats["site_images"] == 4 and stats["site_targets_verified"] >= 3
    assert stats["condensation_prototypes"] == adapted.prototypes.shape[0] >= n
    assert stats["site_stage2_disc_window_accept_after"] >= stats["site_stage2_disc_window_accept_before"]
    assert stats["site_stage2_false_window_accept_after"] <= stats["site_stage2_false_window_accept_before"]
    # It still finds what the base found on the site images, and stores like any classifier.
    assert stats["site_targets_after"] >= stats["site_targets_before"]
    again = cand.DiscClassifier.from_arrays(adapted.to_arrays())
    np.testing.assert_array_equal(again.prototypes, adapted.prototypes)


def test_images_without_targets_are_refused() -> None:
    empty, _ = scenes.scenario_frame("empty", np.random.default_rng(2))
    with pytest.raises(ValueError, match="no target"):
        adapt_classifier(load_default_classifier(), [empty])
    with pytest.raises(ValueError, match="no images"):
        adapt_classifier(load_default_classifier(), [])
