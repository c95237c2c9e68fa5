"""Client images: bytes in, a greyscale frame out, or a clear 4xx (every route and job
that takes images decodes them here)."""

from __future__ import annotations

import numpy as np

from app.core.detection import MIN_SIDE
from app.core.imagecodec import ImageError, decode_gray
from app.services.errors import Invalid, TooLarge, UnsupportedMedia
from app.settings import Settings


def decode(data: bytes, settings: Settings) -> np.ndarray:
    """Client bytes to a greyscale frame within ``max_image_bytes`` and ``max_image_pixels``.

    Raises TooLarge (413), UnsupportedMedia (415) or Invalid (422)."""
    if len(data) > settings.max_image_bytes:
        raise TooLarge(f"image of {len(data)} bytes exceeds the limit of {settings.max_image_bytes} bytes")
    try:
        gray = decode_gray(data, settings.max_image_pixels)
    except ImageError as exc:
        if exc.kind == "too_large":
            raise TooLarge(str(exc)) from None
        if exc.kind == "unsupported":
            raise UnsupportedMedia(str(exc)) from None
        raise Invalid(str(exc)) from None
    if min(gray.shape) < MIN_SIDE:
        # The detector looks through a window of this size: a smaller frame is the
        # client's error, not the detector's.
        raise Invalid(
            f"the image is {gray.shape[1]}x{gray.shape[0]} pixels; both sides must be at least {MIN_SIDE}"
        )
    return gray
