"""Every frame a survey decodes is within the pixel limit: a Motion JPEG video whose first
frames are small and a later one declares a huge size is refused at upload (413) and, in
the job, fails the survey naming the frame, from the frame's header, before it is decoded."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import av
import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.core.survey import SurveyError
from app.main import create_app
from app.services import surveys
from app.services.surveys import FramePiece, SurveyParams, detect_piece, read_frames
from app.settings import Settings

SMALL = (96, 96)
#: A frame over `LIMIT` that costs a few kB of JPEG (one grey).
HUGE = (2000, 2000)
LIMIT = 10_000
HUGE_AT = 5


def solid_jpeg(width: int, height: int, value: int) -> bytes:
    ok, data = cv2.imencode(".jpg", np.full((height, width), value, np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 50])
    assert ok
    return data.tobytes()


def mjpeg_video(path: Path, sizes: list[tuple[int, int]]) -> Path:
    """An MJPEG AVI with one JPEG packet of each size, in order; its header says the first."""
    with av.open(str(path), "w", format="avi") as container:
        stream = container.add_stream("mjpeg", rate=25)
        stream.width, stream.height = sizes[0]
        stream.pix_fmt = "yuvj420p"
        for index, (width, height) in enumerate(sizes):
            packet = av.Packet(solid_jpeg(width, height, 20 + 20 * index))
            packet.stream, packet.pts, packet.dts = stream, index, index
            container.mux(packet)
    return path


def params_of(video: Path, frames: int) -> SurveyParams:
    return SurveyParams(upload_dir=str(video.parent), source="video", video=str(video), video_frames=frames,
                        width=SMALL[0], height=SMALL[1], marker_size_m=0.2, intrinsics=None, max_frames=frames,
                        classifier_id=1, family="fido3x3", max_pixels=40_000_000, max_video_pixels=LIMIT)


@pytest.fixture
def decoded_shapes(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, ...]]:
    """The shapes of the frames decoded from JPEG packets."""
    shapes: list[tuple[int, ...]] = []
    imdecode = cv2.imdecode

    def recording(data: np.ndarray, flags: int) -> np.ndarray | None:
        image = imdecode(data, flags)
        if image is not None:
            shapes.append(image.shape)
        return image

    monkeypatch.setattr(surveys.cv2, "imdecode", recording)
    return shapes


@dataclass
class _NoTargets:
    """A detector stand-in: finds nothing, counts the frames it saw."""

    seen: list[tuple[int, ...]] = field(default_factory=list)

    def detect(self, gray: np.ndarray) -> _NoTargets:
        self.seen.append(gray.shape)
        return self

    @property
    def targets(self) -> list[object]:
        return []


def test_a_huge_later_frame_fails_the_survey_naming_it_before_it_is_decoded(
        tmp_path: Path, decoded_shapes: list[tuple[int, ...]]) -> None:
    sizes = [SMALL] * HUGE_AT + [HUGE] + [SMALL] * 4
    params = params_of(mjpeg_video(tmp_path / "video.avi", sizes), len(sizes))
    read = []
    with pytest.raises(SurveyError, match=rf"frame {HUGE_AT} of the video is 2000x2000 pixels, over the limit "
                                          rf"of {LIMIT}") as refused:
        for position, _, gray in read_frames(params):
            read.append(position)
            assert gray.shape == (SMALL[1], SMALL[0])
    assert read == list(range(HUGE_AT)), refused.value
    assert decoded_shapes and max(h * w for h, w in decoded_shapes) <= LIMIT
    # The piece of a survey's detection that holds the frame fails alike; the one before does not.
    detector = _NoTargets()
    assert len(detect_piece(detector, FramePiece(params, range(0, HUGE_AT)))) == HUGE_AT  # type: ignore[arg-type]
    with pytest.raises(SurveyError, match=f"frame {HUGE_AT} "):
        detect_piece(detector, FramePiece(params, range(HUGE_AT - 1, HUGE_AT + 2)))  # type: ignore[arg-type]
    assert max(h * w for h, w in decoded_shapes) <= LIMIT


def test_motion_jpeg_frames_within_the_limit_read_as_the_video_decoder_gives_them(tmp_path: Path) -> None:
    sizes = [SMALL] * 8
    video = mjpeg_video(tmp_path / "video.avi", sizes)
    frames = [gray for _, _, gray in read_frames(params_of(video, len(sizes)))]
    capture = cv2.VideoCapture(str(video), cv2.CAP_FFMPEG)
    expected = []
    while (grabbed := capture.read())[0]:
        expected.append(cv2.cvtColor(grabbed[1], cv2.COLOR_BGR2GRAY))
    capture.release()
    assert len(frames) == len(expected) == len(sizes)
    for got, want in zip(frames, expected, strict=True):
        assert got.shape == want.shape and np.abs(got.astype(int) - want).max() <= 2
    # A piece entered at its first frame reads the frames a whole read gives.
    piece = [gray for _, _, gray in read_frames(params_of(video, len(sizes)), range(3, 6))]
    assert all(np.array_equal(a, b) for a, b in zip(piece, frames[3:6], strict=True))


def test_an_upload_with_a_huge_later_frame_is_refused_naming_it(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path / "data", max_video_pixels=LIMIT)
    video = mjpeg_video(tmp_path / "video.avi", [SMALL] * HUGE_AT + [HUGE] + [SMALL] * 4)
    with TestClient(create_app(settings)) as client:
        env = client.post("/environments", json={"name": "hall", "marker_size_m": 0.2}).json()["id"]
        reply = client.post(f"/environments/{env}/survey", files={"video": ("v.avi", video.read_bytes(), "video/avi")})
        assert reply.status_code == 413, reply.text
        assert reply.json()["detail"] == f"video: frame {HUGE_AT} is 2000x2000, over the limit of {LIMIT} pixels"
        assert client.get("/jobs").json() == []
    uploads = settings.data_dir / "uploads"
    assert not uploads.exists() or not any(uploads.iterdir())
