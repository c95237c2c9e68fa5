"""Client images: bytes in, a greyscale frame out, or a clear 4xx (every route and job
that takes images decodes them here), within a memory budget shared by every route."""

from __future__ import annotations

import multiprocessing
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from app.core.detection import MIN_SIDE
from app.core.imagecodec import JPEG_REDUCTIONS, ImageError, ImageHeader, check_size, decode_gray, read_header
from app.services.errors import Busy, Invalid, TooLarge, UnsupportedMedia
from app.settings import Settings

#: What detecting targets in a decoded frame holds at its peak, bytes per pixel (the
#: pyramid, the classifier's windows, the blob masks: 10-13 measured on 4-36 MP photographs).
DETECT_BYTES_PER_PIXEL = 16
#: How long a request waits for its share of the budget before it is refused (503).
MEMORY_WAIT_S = 30.0

_MB = 1e6


class MemoryBudget:
    """Bytes that the client images being decoded and detected may hold at once, shared
    by every route (``/detect``, ``/locate``, ``/track`` frames, survey uploads) and by
    the web process and its image workers (the count lives in shared memory).

    Each image's cost is known from its header before anything is decoded: an image that
    alone needs more than the whole budget is refused (413), and the others wait until
    the images in hand leave room (503 after `MEMORY_WAIT_S`). A 333-byte file that
    declares 40 megapixels therefore holds memory only one at a time, however many
    clients send it."""

    def __init__(self, limit_bytes: int, wait_s: float = MEMORY_WAIT_S) -> None:
        self.limit = limit_bytes
        self.wait_s = wait_s
        spawn = multiprocessing.get_context("spawn")
        self._held = spawn.Value("q", 0, lock=False)  # every process's holdings; guarded by the condition's lock
        self._room = spawn.Condition()
        self._own = 0  # this process's share of `_held`

    def __getstate__(self) -> dict[str, object]:
        # A process that receives the budget starts holding nothing of it.
        return {**self.__dict__, "_own": 0}

    def release_others(self) -> None:
        """Give back what the other processes held: called when the image workers have
        died, holding their shares, which would otherwise be lost to the budget."""
        with self._room:
            self._held.value = self._own
            self._room.notify_all()

    @property
    def held(self) -> int:
        """Bytes held now."""
        with self._room:
            return int(self._held.value)

    @contextmanager
    def hold(self, nbytes: int, what: str) -> Iterator[None]:
        """Hold `nbytes` of the budget for the block (blocking the calling thread while
        there is no room)."""
        if nbytes > self.limit:
            raise TooLarge(f"{what} needs {nbytes / _MB:.0f} MB of memory to process; the server's image memory "
                           f"budget is {self.limit / _MB:.0f} MB")
        with self._room:
            if not self._room.wait_for(lambda: self._held.value + nbytes <= self.limit, timeout=self.wait_s):
                raise Busy(f"the server is busy with other images (its image memory budget of "
                           f"{self.limit / _MB:.0f} MB is in use); retry")
            self._held.value += nbytes
            self._own += nbytes
        try:
            yield
        finally:
            with self._room:
                self._held.value -= nbytes
                self._own -= nbytes
                self._room.notify_all()


def limit_compute_threads(threads: int) -> None:
    """OpenCV's and BLAS's own thread pools (process-wide): a frame is small work, and
    its pools' idle threads spin on the cores other frames and clients need."""
    cv2.setNumThreads(threads)
    threadpool_limits(limits=threads)


def cost_bytes(header: ImageHeader, detect: bool, reduction: int = 1) -> int:
    """Memory that decoding the image (and detecting in it, `detect`) holds at its peak,
    decoded at 1 / `reduction` of its size."""
    pixels = -(-header.width // reduction) * -(-header.height // reduction)
    return header.reduced_decode_bytes(reduction) + (DETECT_BYTES_PER_PIXEL * pixels if detect else 0)


@dataclass(frozen=True)
class Frame:
    """A decoded client image.

    Attributes
    ----------
    gray : (rows, columns) ndarray of uint8
        The image, or the image decoded smaller (`reduction`).
    width, height : int
        The image's own size, pixels.
    reduction : int
        `gray` is the image at 1 / `reduction`: its pixel ``i`` is centred on the image's
        pixel ``(i + 0.5) * reduction - 0.5``; 1 for an image decoded whole.
    """

    gray: np.ndarray
    width: int
    height: int
    reduction: int = 1


@contextmanager
def decoded(data: bytes, settings: Settings, memory: MemoryBudget, *, detect: bool = True) -> Iterator[np.ndarray]:
    """Client bytes as a greyscale frame, within ``max_image_bytes`` and
    ``max_image_pixels``, holding the image's share of `memory` while the block runs
    (`detect`: the block detects targets in it, which costs more than decoding).

    Raises TooLarge (413), UnsupportedMedia (415), Invalid (422) or Busy (503)."""
    with decoded_frame(data, settings, memory, detect=detect) as frame:
        yield frame.gray


def frame_header(data: bytes, settings: Settings) -> ImageHeader:
    """The client image's header (format and size), read before any pixel is decoded,
    within ``max_image_bytes`` and ``max_image_pixels``.

    Raises TooLarge (413), UnsupportedMedia (415) or Invalid (422)."""
    if len(data) > settings.max_image_bytes:
        raise TooLarge(f"image of {len(data)} bytes exceeds the limit of {settings.max_image_bytes} bytes")
    try:
        header = read_header(data)
        check_size(header, settings.max_image_pixels)
    except ImageError as exc:
        raise _refusal(exc) from None
    return header


@contextmanager
def decoded_frame(data: bytes, settings: Settings, memory: MemoryBudget, *, header: ImageHeader | None = None,
                  detect: bool = True, reduction: int = 1) -> Iterator[Frame]:
    """`decoded`, with the image's size, and a JPEG decoded smaller when the caller says so.

    `header` is the image's (`frame_header`), when the caller read it to decide the
    `reduction`: the factor to decode a JPEG smaller by (1, 2, 4 or 8, the decoder's DCT
    scaling: less time and memory than decoding the whole and resampling). A PNG is
    decoded whole whatever it says, and so is a JPEG that the factor would make smaller
    than the detector's window.

    Raises TooLarge (413), UnsupportedMedia (415), Invalid (422) or Busy (503)."""
    if header is None:
        header = frame_header(data, settings)
    if reduction not in JPEG_REDUCTIONS:
        raise ValueError(f"a JPEG is decoded at 1/{JPEG_REDUCTIONS} of its size, not 1/{reduction}")
    factor = reduction if header.format == "jpeg" else 1
    if min(-(-header.width // factor), -(-header.height // factor)) < MIN_SIDE:
        factor = 1  # too small for the detector reduced: whole (or refused below, as ever)
    with memory.hold(cost_bytes(header, detect, factor), f"a {header.width}x{header.height} {header.format.upper()}"):
        try:
            gray = decode_gray(data, settings.max_image_pixels, header=header, reduction=factor)
        except ImageError as exc:
            raise _refusal(exc) from None
        if min(gray.shape) < MIN_SIDE:
            # The detector looks through a window of this size: a smaller frame is the
            # client's error, not the detector's.
            raise Invalid(
                f"the image is {gray.shape[1]}x{gray.shape[0]} pixels; both sides must be at least {MIN_SIDE}"
            )
        yield Frame(gray, header.width, header.height, factor)


def _refusal(exc: ImageError) -> TooLarge | UnsupportedMedia | Invalid:
    if exc.kind == "too_large":
        return TooLarge(str(exc))
    if exc.kind == "unsupported":
        return UnsupportedMedia(str(exc))
    return Invalid(str(exc))
