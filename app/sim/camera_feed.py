"""A rendered walk as a camera a browser can open: Chromium's fake video capture device
plays a YUV4MPEG2 (``.y4m``) file (``--use-fake-device-for-media-stream
--use-file-for-fake-video-capture=FILE``) as if it were a webcam, in a loop.

A page grabs whichever picture the camera shows when it is ready for the next frame, so
the frames it sends are not the file's frames one for one. Each frame therefore carries
its index, stamped in a strip of blocks along its top-left edge, which survives the
browser's scaling and JPEG encoding: whoever receives a frame reads the index
(`read_frame_index`) and finds its ground truth.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

__all__ = ["INDEX_BITS", "read_frame_index", "stamp_frame_index", "write_y4m"]

#: Bits of the stamped index: walks of up to 4095 frames.
INDEX_BITS = 12
#: Side of one block of the stamp as a fraction of the image width (16 px at 640 px).
BLOCK_FRACTION = 1 / 40
_DARK, _LIGHT = 24, 232


def _block_px(width: int) -> int:
    return max(4, round(width * BLOCK_FRACTION))


def stamp_frame_index(image: np.ndarray, index: int) -> np.ndarray:
    """The image with `index` written in its top-left corner: a start block (light),
    then `INDEX_BITS` blocks, most significant first, light for 1 and dark for 0.

    Parameters
    ----------
    image : (H, W) uint8 ndarray
        A grey frame.
    index : int
        0 .. 2**INDEX_BITS - 1.

    Returns
    -------
    (H, W) uint8 ndarray
        A copy with the stamp.
    """
    if not 0 <= index < 2**INDEX_BITS:
        raise ValueError(f"frame index {index} does not fit in {INDEX_BITS} bits")
    out = np.array(image, dtype=np.uint8, copy=True)
    block = _block_px(out.shape[1])
    bits = [1] + [(index >> (INDEX_BITS - 1 - k)) & 1 for k in range(INDEX_BITS)]
    for k, bit in enumerate(bits):
        out[:block, k * block:(k + 1) * block] = _LIGHT if bit else _DARK
    return out


def read_frame_index(image: np.ndarray) -> int | None:
    """The index stamped by `stamp_frame_index`, read from a frame of any scale.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8 ndarray
        A frame as received (decoded JPEG), possibly resized.

    Returns
    -------
    int or None
        The index; None when the start block is not there (not a stamped frame).
    """
    gray = image if image.ndim == 2 else image.mean(axis=2)
    block = _block_px(gray.shape[1])
    inner = max(1, block // 4)  # the middle of each block: clear of JPEG's ringing at its edges

    def level(k: int) -> float:
        centre = k * block + block // 2
        return float(gray[block // 2 - inner:block // 2 + inner, centre - inner:centre + inner].mean())

    if level(0) < 128:
        return None
    index = 0
    for k in range(1, INDEX_BITS + 1):
        index = (index << 1) | int(level(k) >= 128)
    return index


def write_y4m(path: Path, frames: Iterable[np.ndarray], fps: int = 30) -> int:
    """Write grey frames as a YUV4MPEG2 4:2:0 file (the chroma planes neutral).

    Parameters
    ----------
    path : Path
        The file to write.
    frames : iterable of (H, W) uint8 ndarray
        Frames of one size, even width and height.
    fps : int
        The frame rate the player shows them at.

    Returns
    -------
    int
        The number of frames written.
    """
    count = 0
    with open(path, "wb") as out:
        for frame in frames:
            frame = np.ascontiguousarray(frame, dtype=np.uint8)
            h, w = frame.shape
            if count == 0:
                if w % 2 or h % 2:
                    raise ValueError(f"4:2:0 needs an even frame size, got {w}x{h}")
                size = (w, h)
                chroma = np.full((h // 2) * (w // 2), 128, np.uint8).tobytes()
                out.write(f"YUV4MPEG2 W{w} H{h} F{fps}:1 Ip A1:1 C420jpeg\n".encode())
            elif (w, h) != size:
                raise ValueError(f"frame {count} is {w}x{h}, the first was {size[0]}x{size[1]}")
            out.write(b"FRAME\n")
            out.write(frame.tobytes())
            out.write(chroma)
            out.write(chroma)
            count += 1
    return count
