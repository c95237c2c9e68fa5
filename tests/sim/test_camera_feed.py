"""The fake camera's file and the frame stamp that lets a receiver find each frame's truth."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from app.sim.camera_feed import INDEX_BITS, read_frame_index, stamp_frame_index, write_y4m


@pytest.mark.parametrize("size", [(640, 480), (1280, 720)])
def test_the_stamped_index_survives_scaling_and_jpeg(size: tuple[int, int]) -> None:
    rng = np.random.default_rng(0)
    for index in (0, 1, 777, 2**INDEX_BITS - 1):
        frame = rng.integers(0, 256, (size[1], size[0]), dtype=np.uint8)  # the worst background: noise
        stamped = stamp_frame_index(frame, index)
        for width in (size[0], 640, 320):
            scaled = cv2.resize(stamped, (width, width * size[1] // size[0]), interpolation=cv2.INTER_AREA)
            data = cv2.imencode(".jpg", scaled, [cv2.IMWRITE_JPEG_QUALITY, 50])[1]
            assert read_frame_index(cv2.imdecode(data, cv2.IMREAD_COLOR)) == index


def test_an_unstamped_frame_has_no_index() -> None:
    assert read_frame_index(np.zeros((480, 640), np.uint8)) is None


def test_y4m_holds_the_frames_with_neutral_chroma(tmp_path: Path) -> None:
    frames = [np.full((4, 6), k * 10, np.uint8) for k in range(3)]
    path = tmp_path / "walk.y4m"
    assert write_y4m(path, frames, fps=25) == 3
    data = path.read_bytes()
    header, rest = data.split(b"\n", 1)
    assert header == b"YUV4MPEG2 W6 H4 F25:1 Ip A1:1 C420jpeg"
    chunks = rest.split(b"FRAME\n")[1:]
    assert [c[:24] for c in chunks] == [f.tobytes() for f in frames]
    assert all(c[24:] == bytes([128]) * 12 for c in chunks)
    with pytest.raises(ValueError, match="even"):
        write_y4m(tmp_path / "odd.y4m", [np.zeros((3, 5), np.uint8)])
