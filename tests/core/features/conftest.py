"""Synthetic videos with known motion for the feature tracker's tests: a textured plane
(smoothed noise at several scales, no simulator needed) filmed through known
homographies, so every point's true place in every frame is exact."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
import pytest


def texture(seed: int, height: int, width: int) -> np.ndarray:
    """A plane's texture: noise smoothed at scales of 32, 8 and 4 px, grey levels 0..255."""
    rng = np.random.default_rng(seed)
    t = np.zeros((height, width), np.float32)
    for scale, amplitude in ((32, 1.0), (8, 0.6), (4, 0.3)):
        small = rng.normal(0.0, 1.0, (height // scale + 3, width // scale + 3)).astype(np.float32)
        big = cv2.resize(small, ((width // scale + 3) * scale, (height // scale + 3) * scale),
                         interpolation=cv2.INTER_CUBIC)
        t += amplitude * big[scale : scale + height, scale : scale + width]
    t = (t - t.mean()) / t.std()
    return np.clip(np.rint(128 + 45 * t), 0, 255).astype(np.uint8)


def view(offset_x: float, offset_y: float, k: float) -> np.ndarray:
    """The homography from a frame's pixels to the texture's: the camera looks at
    (offset_x, offset_y), turned by 0.3 degrees, scaled by 0.4 % and tilted a little per
    unit of k."""
    a, s = np.radians(0.3 * k), 1.0 + 0.004 * k
    return np.array([[s * np.cos(a), -s * np.sin(a), offset_x],
                     [s * np.sin(a), s * np.cos(a), offset_y],
                     [1e-6 * k, 2e-6 * k, 1.0]])


def film(plane: np.ndarray, views: Sequence[np.ndarray], size: tuple[int, int] = (640, 480)) -> list[np.ndarray]:
    """The frames that see the plane through each view (frame pixel -> texture pixel)."""
    return [cv2.warpPerspective(plane, H, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP) for H in views]


def transfer(views: Sequence[np.ndarray], frame_a: int, frame_b: int, uv: np.ndarray) -> np.ndarray:
    """Where points seen at uv in frame a appear in frame b (the truth)."""
    H = np.linalg.inv(views[frame_b]) @ views[frame_a]
    p = np.c_[uv, np.ones(len(uv))] @ H.T
    return p[:, :2] / p[:, 2:]


@pytest.fixture(scope="session")
def plane() -> np.ndarray:
    """A 900 x 2400 px textured plane."""
    return texture(1, 900, 2400)


@pytest.fixture(scope="session")
def gliding(plane: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """20 frames gliding over the plane (4 px right and 2.5 px down a frame, turning,
    zooming and tilting): the views and the frames."""
    views = [view(100 + 4.0 * k, 80 + 2.5 * k, k) for k in range(20)]
    return views, film(plane, views)
