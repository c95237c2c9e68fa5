"""A survey's detection split into pieces reads, piece by piece, exactly the frames a
whole read gives: each piece enters the video at its own first frame."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from app.services.surveys import FRAMES_PER_PIECE, SurveyParams, frame_count, read_frames
from tests.routers.test_survey_api import room  # noqa: F401  (the fixture: a rendered room's MP4)


def _params(video: Path, max_frames: int) -> SurveyParams:
    return SurveyParams(upload_dir=str(video.parent), source="video", video=str(video), video_frames=90, width=640,
                        height=480, marker_size_m=0.25, intrinsics=None, max_frames=max_frames, classifier_id=1,
                        family="fido3x3", max_pixels=10**8)


def _as_h264(mp4: bytes, tmp_path: Path) -> bytes:
    """The video re-encoded as a phone does: H.264 with B-frames, a keyframe a second."""
    import av

    source = tmp_path / "source.mp4"
    source.write_bytes(mp4)
    capture = cv2.VideoCapture(str(source))
    out = tmp_path / "h264.mp4"
    with av.open(str(out), "w") as container:
        stream = container.add_stream("libx264", rate=30)
        stream.width, stream.height, stream.pix_fmt = 640, 480, "yuv420p"
        stream.options = {"g": "30", "bf": "2", "crf": "20"}
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            container.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="bgr24")))
        container.mux(stream.encode())
    capture.release()
    return out.read_bytes()


@pytest.mark.parametrize(("codec", "max_frames"), [("mp4v", 90), ("mp4v", 37), ("h264", 90), ("h264", 37)])
def test_pieces_of_a_video_read_the_frames_a_whole_read_does(room, tmp_path: Path, codec: str,  # noqa: F811
                                                             max_frames: int) -> None:
    video = tmp_path / "video"
    video.write_bytes(room[2] if codec == "mp4v" else _as_h264(room[2], tmp_path))
    params = _params(video, max_frames)
    whole = list(read_frames(params))
    count = frame_count(params)
    assert [p for p, _, _ in whole] == list(range(count)) and count == min(90, max_frames)
    pieces = [list(read_frames(params, range(a, min(a + FRAMES_PER_PIECE, count))))
              for a in range(0, count, FRAMES_PER_PIECE)]
    joined = [frame for piece in pieces for frame in piece]
    assert [p for p, _, _ in joined] == list(range(count))
    for (_, _, a), (_, _, b) in zip(whole, joined, strict=True):
        assert np.array_equal(a, b)
