"""Fitting the disc classifier (app.learning.classifier): Hart's condensed nearest
neighbour and Gates' reduction on real windows."""

from __future__ import annotations

import numpy as np

from app.core.detection.candidates import normalise_windows
from app.learning import training
from app.learning.classifier import condense, dihedral, nn_predict, reduce_store
from app.sim import degrade, scenes


def test_hart_condensing_is_consistent_and_agrees_with_full_1nn() -> None:
    """Hart's rule on real windows: the condensed set classifies every training window
    as the full training set does (by construction) and mostly agrees on held-out ones;
    Gates' reduction keeps the training consistency."""
    rng = np.random.default_rng(5)
    image, truth = training.safe_scenario_frame("default", rng)
    blob = (0.25, 0.16, 0.16, 0.16)
    fw = training.frame_windows(image, training.visible_discs(truth), training.all_discs(truth), blob, None, rng)
    photo = degrade.to_uint8(scenes.builtin_photos()[0])
    fw2 = training.frame_windows(photo, np.zeros((0, 3)), np.zeros((0, 3)), blob, None, rng)
    pos = normalise_windows(dihedral(np.concatenate(fw.positives)))
    neg = normalise_windows(np.concatenate(fw.negatives + fw2.negatives))
    x = np.concatenate([pos, neg])
    y = np.concatenate([np.ones(len(pos), np.int8), np.zeros(len(neg), np.int8)])
    perm = rng.permutation(len(x))
    test, train = perm[: len(x) // 5], perm[len(x) // 5 :]
    store, passes = condense(x[train], y[train], rng)
    assert 1 <= passes < 50 and 0 < store.size < train.size
    full = nn_predict(x[train], x[train], y[train])
    assert np.array_equal(full, y[train])
    assert np.array_equal(nn_predict(x[train], x[train][store], y[train][store]), y[train])
    reduced = reduce_store(x[train], y[train], store)
    assert reduced.size <= store.size
    assert np.array_equal(nn_predict(x[train], x[train][reduced], y[train][reduced]), y[train])
    full_test = nn_predict(x[test], x[train], y[train])
    agree = np.mean(full_test == nn_predict(x[test], x[train][store], y[train][store]))
    assert agree > 0.85
