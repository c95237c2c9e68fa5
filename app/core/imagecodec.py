"""Safe decoding of client images (JPEG, PNG) to 8-bit greyscale.

A small file can declare an enormous image (a 631-byte JPEG can claim 30000x30000 and
make a decoder allocate gigabytes), so the size is read from the header and checked
before anything is decoded. Truncated files are refused rather than decoded into a
half-grey frame: JPEGs are decoded by libjpeg-turbo through simplejpeg, which reports
the decoder's warnings (OpenCV swallows them, so that a file cut short and given an
end-of-image marker decodes into grey rows without a word). Two more cheap-file,
expensive-decode tricks are refused from the structure alone: a PNG chunk that declares
more bytes than the file holds (libpng spends seconds per gigabyte declared before
failing) and a progressive JPEG with thousands of scans (each scan is one more pass over
the whole image: 125 kB took 20 s).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np
import simplejpeg

__all__ = ["JPEG_MAGIC", "JPEG_REDUCTIONS", "MAX_JPEG_SCANS", "PNG_MAGIC", "ImageError", "ImageHeader", "check_size",
           "decode_gray", "peek_size", "read_header", "reduced_size"]

JPEG_MAGIC = b"\xff\xd8\xff"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# Most scans a JPEG may have. Baseline files have 1 (or one per component), the standard
# progressive scripts 6-10, optimising encoders a few more.
MAX_JPEG_SCANS = 64
# Start-of-frame markers carry the image size (all SOFn except DHT, JPG and DAC).
_SOF_MARKERS = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
# Those of progressive JPEGs: the decoder holds every coefficient of the image at once.
_PROGRESSIVE_SOF = {0xC2, 0xC6, 0xCA, 0xCE}
# Those of Huffman-coded JPEGs (see `check_size`).
_HUFFMAN_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7}
# Channels of each PNG colour type (a palette is decoded to BGR).
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}
#: Factors a JPEG can be decoded smaller by, through the decoder's DCT scaling: each 8x8
#: block is inverse-transformed straight to (8 / factor)^2 pixels, so a reduced frame
#: costs less than a whole one and no resampling after it (the entropy decoding, a
#: large share of the time at q90, is the same at every factor).
JPEG_REDUCTIONS = (1, 2, 4, 8)
# libjpeg's warnings about bytes a file has to spare, not about missing ones: some
# cameras' encoders write them, and the image is whole.
_HARMLESS_JPEG_WARNINGS = ("extraneous bytes before marker",)


class ImageError(ValueError):
    """The bytes are not an image this service decodes.

    Parameters
    ----------
    kind : str
        Why: "unsupported", "corrupt", "too_large" or "empty".
    message : str
        A message for the user.
    """

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind  # "unsupported", "corrupt", "too_large", "empty"


@dataclass(frozen=True)
class ImageHeader:
    """What an image's header declares.

    Attributes
    ----------
    format : str
        "jpeg" or "png".
    width, height : int
        Declared size, pixels.
    channels : int
        Colour components (JPEG) or decoded channels (PNG).
    sample_bytes : int
        Bytes per sample once decoded: 1, or 2 for 16-bit PNGs and 12-bit JPEGs.
    progressive : bool
        A progressive JPEG (decoded from whole-image coefficient buffers).
    huffman_bytes : int or None
        A Huffman-coded JPEG's bytes from its first scan on (None for other images).
    """

    format: str  # "jpeg" or "png"
    width: int
    height: int
    channels: int = 1
    sample_bytes: int = 1
    progressive: bool = False
    huffman_bytes: int | None = None

    @property
    def decode_bytes(self) -> int:
        """The most memory decoding this image to greyscale holds at once, bytes (an
        upper bound: the decoder's output and working buffers, and the conversions)."""
        return self.reduced_decode_bytes(1)

    def reduced_decode_bytes(self, reduction: int) -> int:
        """`decode_bytes` of the image decoded at 1 / `reduction` of its size.

        Parameters
        ----------
        reduction : int
            One of `JPEG_REDUCTIONS` (a JPEG's; other formats are always decoded whole).

        Returns
        -------
        int
            Bytes.
        """
        pixels = self.width * self.height
        if self.format == "jpeg":
            # 16-bit coefficients of every component, unless decoded a band at a time.
            coefficients = 2 * self.channels * pixels if self.progressive else 0
            width, height = reduced_size(self.width, self.height, reduction)
            return width * height + coefficients
        # The decoded image, a converted copy of it, and the grey result.
        return 2 * pixels * self.channels * self.sample_bytes + pixels


def read_header(data: bytes) -> ImageHeader:
    """Format and size from the header alone, without decoding pixels.

    The structure is checked on the way: a PNG's chunks must fit in the file and end
    with IEND; a JPEG must end with its end-of-image marker and have at most
    `MAX_JPEG_SCANS` scans.

    Parameters
    ----------
    data : bytes
        The file's bytes.

    Returns
    -------
    ImageHeader

    Raises
    ------
    ImageError
        If the data is empty, not a JPEG or PNG, truncated or corrupt.
    """
    if not data:
        raise ImageError("empty", "the image is empty (0 bytes)")
    if data.startswith(PNG_MAGIC):
        return _png_header(data)
    if data.startswith(JPEG_MAGIC):
        return _jpeg_header(data)
    raise ImageError("unsupported", "not a JPEG or PNG image (unknown file signature)")


def peek_size(head: bytes) -> tuple[int, int] | None:
    """The (width, height) an image declares, from its first bytes alone: for checking
    a file against the limits while it is still arriving.

    Parameters
    ----------
    head : bytes
        The first bytes of a file (any number).

    Returns
    -------
    (width, height) : tuple of int, or None
        None while `head` does not reach the size yet (a JPEG's start-of-frame may come
        after application segments of up to 64 KiB each).

    Raises
    ------
    ImageError
        If the bytes already show that the file is not a JPEG or PNG, or a corrupt one.
    """
    if head.startswith(PNG_MAGIC):
        if len(head) < 24:
            return None
        if head[12:16] != b"IHDR":
            raise ImageError("corrupt", "PNG header has no IHDR chunk")
        width, height = struct.unpack(">II", head[16:24])
        return int(width), int(height)
    if head.startswith(JPEG_MAGIC):
        for marker, i, _ in _jpeg_segments(head, 2):
            if marker in _SOF_MARKERS and i + 9 <= len(head):
                height, width = struct.unpack(">HH", head[i + 5 : i + 9])
                return int(width), int(height)
        return None
    if PNG_MAGIC.startswith(head[:8]) or JPEG_MAGIC.startswith(head[:3]):
        return None  # too short to tell
    raise ImageError("unsupported", "not a JPEG or PNG image (unknown file signature)")


def _png_header(data: bytes) -> ImageHeader:
    if len(data) < 33 or data[12:16] != b"IHDR":
        raise ImageError("corrupt", "PNG header is truncated or has no IHDR chunk")
    width, height = struct.unpack(">II", data[16:24])
    depth, colour = data[24], data[25]
    # Walk the chunks: each must fit in the file, and the last one is IEND.
    i, n = 8, len(data)
    while i + 12 <= n:
        (length,) = struct.unpack(">I", data[i : i + 4])
        if length > n - i - 12:
            kind = data[i + 4 : i + 8].decode("latin-1")
            raise ImageError("corrupt", f"PNG chunk {kind!r} at byte {i} declares {length} bytes; "
                             f"the file has {max(n - i - 12, 0)} left (truncated or corrupt)")
        if data[i + 4 : i + 8] == b"IEND":
            return ImageHeader("png", int(width), int(height), channels=_PNG_CHANNELS.get(colour, 4),
                               sample_bytes=2 if depth == 16 else 1)
        i += 12 + length
    raise ImageError("corrupt", "PNG is truncated (no IEND chunk at the end)")


def _jpeg_header(data: bytes) -> ImageHeader:
    for marker, i, _ in _jpeg_segments(data, 2):
        if marker in _SOF_MARKERS:
            if i + 9 > len(data):
                break
            height, width = struct.unpack(">HH", data[i + 5 : i + 9])
            precision, components = data[i + 4], data[i + 9] if i + 9 < len(data) else 1
            if not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
                raise ImageError("corrupt", "JPEG is truncated (no end-of-image marker)")
            scans, first_scan = _jpeg_scans(data, i)
            if scans > MAX_JPEG_SCANS:
                raise ImageError("corrupt", f"JPEG has {scans} scans; at most {MAX_JPEG_SCANS} are accepted")
            coded = len(data) - first_scan if marker in _HUFFMAN_SOF and first_scan is not None else None
            return ImageHeader("jpeg", int(width), int(height), channels=max(int(components), 1),
                               sample_bytes=2 if precision > 8 else 1, progressive=marker in _PROGRESSIVE_SOF,
                               huffman_bytes=coded)
    raise ImageError("corrupt", "JPEG header is truncated (no frame header found)")


def _jpeg_segments(data: bytes, i: int) -> Iterator[tuple[int, int, int]]:
    """``(marker, position, length)`` of each JPEG marker from byte `i` on (length 0 for
    the markers that have none), while a segment header fits in the data; each segment
    is skipped whole, so a comment or an APPn block may hold any bytes."""
    n = len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            raise ImageError("corrupt", f"JPEG marker expected at byte {i}")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            yield marker, i, 0
            i += 2
            continue
        (length,) = struct.unpack(">H", data[i + 2 : i + 4])
        if length < 2:
            raise ImageError("corrupt", "JPEG segment with an impossible length")
        yield marker, i, length
        i += 2 + length


def _jpeg_scans(data: bytes, i: int) -> tuple[int, int | None]:
    """The scans of a JPEG from byte `i` on, and where the first begins: segment by
    segment up to the first scan, then every FF DA, since 0xFF is stuffed as FF 00 inside
    entropy-coded data."""
    for marker, j, _ in _jpeg_segments(data, i):
        if marker == 0xDA:
            return 1 + _count_sos(data, j + 2), j
    return 0, None


def _count_sos(data: bytes, start: int) -> int:
    """``data.count(b"\\xff\\xda", start)`` at a third of its cost (0.13 instead of 0.35
    ms on a 1920x1080 frame): a DA byte is rare in entropy-coded data, so only those are
    checked for the FF before them."""
    a = np.frombuffer(data, np.uint8)[start:]
    if a.size < 2:
        return 0
    at = np.flatnonzero(a[1:] == 0xDA)
    return int(np.count_nonzero(a[at] == 0xFF))


def check_size(header: ImageHeader, max_pixels: int, max_side: int = 30000) -> None:
    """Refuse a declared size of zero, over the limits, or more than the file's data can
    hold.

    Parameters
    ----------
    header : ImageHeader
        What the image declares.
    max_pixels : int
        Largest width * height accepted.
    max_side : int, optional
        Largest width or height accepted.

    Raises
    ------
    ImageError
        "empty", "too_large", or "corrupt" (a JPEG too short for its size).
    """
    if header.width <= 0 or header.height <= 0:
        raise ImageError("empty", f"the image declares a zero size ({header.width}x{header.height})")
    if header.width > max_side or header.height > max_side or header.width * header.height > max_pixels:
        raise ImageError(
            "too_large",
            f"the image declares {header.width}x{header.height} pixels; the limit is {max_pixels} pixels",
        )
    # Each 8x8 block of a Huffman-coded JPEG's first component costs at least a bit (its DC
    # code): 344 bytes that declare 6324x6324 pixels, which cost the decoder 23 ms before
    # it finds the data missing, are refused from the sizes alone. (Arithmetic coding can
    # spend less than a bit on a block.)
    needed = -(-header.width // 8) * -(-header.height // 8) // 8
    if header.huffman_bytes is not None and header.huffman_bytes < needed:
        raise ImageError("corrupt", f"the JPEG holds {header.huffman_bytes} bytes of image data; a "
                         f"{header.width}x{header.height} image needs at least {needed} (truncated or corrupt)")


def reduced_size(width: int, height: int, reduction: int) -> tuple[int, int]:
    """The size of a `width` x `height` JPEG decoded at 1 / `reduction`: the decoder
    rounds up.

    Parameters
    ----------
    width, height : int
        The image's size, pixels.
    reduction : int
        One of `JPEG_REDUCTIONS`; ValueError otherwise.

    Returns
    -------
    (width, height) : tuple of int
    """
    if reduction not in JPEG_REDUCTIONS:
        raise ValueError(f"a JPEG is decoded at 1/{JPEG_REDUCTIONS} of its size, not 1/{reduction}")
    return -(-width // reduction), -(-height // reduction)


def decode_gray(data: bytes, max_pixels: int, max_side: int = 30000, header: ImageHeader | None = None,
                reduction: int = 1) -> np.ndarray:
    """Decode a JPEG or PNG to 8-bit greyscale.

    Greyscale, colour, 4-channel and 16-bit images are accepted and converted; EXIF
    orientation is ignored. A JPEG may be decoded smaller (`reduction`): pixel ``i`` of
    the result covers pixels ``i * reduction`` to ``(i + 1) * reduction - 1`` of the
    image, so its centre is at ``(i + 0.5) * reduction - 0.5`` in the image's pixels
    (the convention of `app.core.geometry.Camera.scaled_to`).

    Parameters
    ----------
    data : bytes
        The file's bytes.
    max_pixels : int
        Largest width * height accepted, checked on the header before decoding.
    max_side : int, optional
        Largest width or height accepted.
    header : ImageHeader, optional
        `read_header` of `data`, when the caller has read it already.
    reduction : int, optional
        Decode a JPEG at 1 / `reduction` of its size (one of `JPEG_REDUCTIONS`), through
        the decoder's DCT scaling; other formats are decoded whole whatever it says.

    Returns
    -------
    (height, width) ndarray of uint8
        The image, or a JPEG's reduced size (`reduced_size`).

    Raises
    ------
    ImageError
        For anything else, and for images over the limits (before decoding).
    """
    header = header or read_header(data)
    check_size(header, max_pixels, max_side)
    if header.format == "jpeg":
        return _decode_jpeg_gray(data, header, reduction)
    # 16-bit and 4-channel PNGs are converted below.
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None or image.size == 0:
        raise ImageError("corrupt", f"the {header.format.upper()} data could not be decoded")
    if image.shape[0] != header.height or image.shape[1] != header.width:
        raise ImageError("corrupt", "decoded size differs from the header")
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise ImageError("unsupported", f"{image.dtype} pixels are not supported")
    if image.ndim == 3:
        code = {3: cv2.COLOR_BGR2GRAY, 4: cv2.COLOR_BGRA2GRAY}.get(image.shape[2])
        if code is None:
            raise ImageError("unsupported", f"{image.shape[2]}-channel images are not supported")
        image = cv2.cvtColor(image, code)
    return np.ascontiguousarray(image)


def _decode_jpeg_gray(data: bytes, header: ImageHeader, reduction: int = 1) -> np.ndarray:
    """Luma straight from the decoder: a colour JPEG's chroma is never upsampled or
    converted (0.6 instead of 0.9 ms at 640x480). EXIF orientation is ignored, as for
    every format: pixels must stay where the camera's intrinsics put them. A warning of
    the decoder (data cut short, a corrupt segment) refuses the file. The decoder writes
    into a 2-D array of its own, so the frame needs no copy to be contiguous."""
    width, height = reduced_size(header.width, header.height, reduction)
    # The decoder picks the smallest of its scales that is at least this big and reduces
    # by at least `reduction`: exactly 1 / reduction.
    scale = {"min_height": height, "min_width": width, "min_factor": float(reduction)} if reduction > 1 else {}
    out = np.empty((height, width), np.uint8)
    try:
        image = simplejpeg.decode_jpeg(data, colorspace="GRAY", strict=True, buffer=out, **scale)
    except ValueError as exc:
        message = str(exc)
        if not any(harmless in message for harmless in _HARMLESS_JPEG_WARNINGS):
            kind = "unsupported" if "Unsupported color conversion" in message else "corrupt"
            raise ImageError(kind, f"the JPEG could not be decoded: {message}") from None
        image = simplejpeg.decode_jpeg(data, colorspace="GRAY", strict=False, buffer=out, **scale)
    if image.shape[0] != height or image.shape[1] != width:
        raise ImageError("corrupt", "decoded size differs from the header")
    return out
