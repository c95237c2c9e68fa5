"""The frame as the target stages read it: uint8 grey and its image pyramid.

Shared by verification, refinement, identification, completion and the driver
(`targets.assemble_targets`), which all sample the same pyramid of one frame.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np


def as_gray(image: np.ndarray) -> np.ndarray:
    """The image as every detection stage reads it.

    Parameters
    ----------
    image : ndarray
        uint8 greyscale (H, W) or (H, W, 1), BGR or BGRA.

    Returns
    -------
    ndarray
        Contiguous uint8 greyscale (H, W); ValueError for any other input (another
        dtype, another shape).
    """
    a = np.asarray(image)
    if a.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {a.dtype}")
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    elif a.ndim == 3 and a.shape[2] in (3, 4):
        a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    elif a.ndim != 2:
        raise ValueError(f"expected a greyscale or BGR image, got shape {a.shape}")
    return np.ascontiguousarray(a)


class Pyramid:
    """Lazily built cv2.pyrDown levels of a uint8 image (level L pixel i is centred on
    full-resolution pixel i * 2**L)."""

    def __init__(self, gray: np.ndarray, levels: int = 4, built: Sequence[np.ndarray] = ()) -> None:
        # `built`: levels already made (the candidate stage's pyramid: the same pyrDown
        # chain of the same frame), reused rather than computed again.
        self.levels: list[np.ndarray] = [gray, *list(built)[1:levels]]
        self.max_level = levels - 1

    def get(self, level: int) -> np.ndarray:
        """Level `level` (the coarsest there is, if the image is too small for it)."""
        while len(self.levels) <= level:
            prev = self.levels[-1]
            if min(prev.shape) < 4:
                break
            self.levels.append(cv2.pyrDown(prev))
        return self.levels[min(level, len(self.levels) - 1)]
