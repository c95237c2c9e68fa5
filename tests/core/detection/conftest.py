"""Shared fixtures of the detector's tests: small simulator frames of named scenarios
(a few clean and default frames, each with at least one visible card) and a random
textured image for the kernels' bit-for-bit tests."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import pytest

from app.sim import scenes

Frames = list[tuple[np.ndarray, scenes.FrameTruth]]


def _frames(name: str, n: int, seed: int) -> Frames:
    """`n` frames of scenario `name` from `seed`, each with a visible card."""
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


@pytest.fixture(scope="session")
def clean_frames() -> Frames:
    """Six frames of the "clean" scenario (no degradation)."""
    return _frames("clean", 6, seed=11)


@pytest.fixture(scope="session")
def default_frames() -> Frames:
    """Six frames of the "default" scenario (the usual degradations)."""
    return _frames("default", 6, seed=12)


def _texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A random image with dark blobs of every size (plenty of maxima and ties)."""
    img = cv2.GaussianBlur(rng.integers(0, 256, (h, w)).astype(np.uint8), (0, 0), float(rng.uniform(0.3, 3)))
    for _ in range(int(rng.integers(0, 12))):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        cv2.circle(img, c, int(rng.integers(1, 20)), int(rng.integers(0, 60)), -1)
    if rng.random() < 0.3:
        img[: h // 3] = 128  # flat: equal scores, plateaus of maxima
    return img


@pytest.fixture(scope="session")
def texture() -> Callable[[np.random.Generator, int, int], np.ndarray]:
    """``texture(rng, h, w)``: a random uint8 image with dark blobs of every size."""
    return _texture
