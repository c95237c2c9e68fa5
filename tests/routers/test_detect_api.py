"""POST /detect: targets in a JPEG or PNG, candidates on request, clear 4xx on bad input."""

from __future__ import annotations

import struct
import time

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.sim import scenes
from app.settings import Settings


#: A rendered frame and what it shows.
Frame = tuple[np.ndarray, scenes.FrameTruth]


@pytest.fixture(scope="module")
def frame() -> Frame:
    return scenes.scenario_frame("clean", np.random.default_rng(11))


def _encode(image: np.ndarray, ext: str) -> bytes:
    ok, data = cv2.imencode(ext, image, [cv2.IMWRITE_JPEG_QUALITY, 95] if ext == ".jpg" else [])
    assert ok
    return data.tobytes()


def _check_found(body: dict, truth: scenes.FrameTruth) -> None:
    found = {t["id"]: np.array(t["discs"]) for t in body["targets"]}
    visible = truth.visible_targets()
    assert visible
    for target in visible:
        assert target.id in found, (target.id, list(found))
        assert np.abs(found[target.id] - target.discs_px).max() < 2.0
    assert set(found) <= {t.id for t in truth.targets}
    # every target says how clearly its code was read
    assert all(isinstance(t["read_margin"], float) and t["read_margin"] >= 0 for t in body["targets"])


@pytest.mark.parametrize("ext,content_type", [(".png", "image/png"), (".jpg", "image/jpeg")])
def test_detect_png_and_jpeg_bodies(client: TestClient, frame: Frame, ext: str, content_type: str) -> None:
    image, truth = frame
    reply = client.post("/detect", content=_encode(image, ext), headers={"content-type": content_type})
    assert reply.status_code == 200, reply.text
    body = reply.json()
    assert (body["width"], body["height"]) == (640, 480)
    assert body["candidates"] is None
    _check_found(body, truth)


def test_detect_multipart_with_candidates(client: TestClient, frame: Frame) -> None:
    image, truth = frame
    reply = client.post("/detect?candidates=true", files={"image": ("f.png", _encode(image, ".png"), "image/png")})
    assert reply.status_code == 200, reply.text
    body = reply.json()
    _check_found(body, truth)
    candidates = np.array(body["candidates"])
    assert candidates.ndim == 2 and candidates.shape[1] == 4
    # Every disc of every found target passed the classifier.
    for target in body["targets"]:
        for u, v in target["discs"]:
            assert np.hypot(candidates[:, 0] - u, candidates[:, 1] - v).min() < 2.0


def test_detect_accepts_grey_alpha_and_16_bit(client: TestClient, frame: Frame) -> None:
    image, truth = frame
    for variant in (cv2.cvtColor(image, cv2.COLOR_GRAY2BGRA), image.astype(np.uint16) * 257):
        reply = client.post("/detect", content=_encode(variant, ".png"), headers={"content-type": "image/png"})
        assert reply.status_code == 200, reply.text
        _check_found(reply.json(), truth)


def _giant_jpeg() -> bytes:
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 11, 8, 30000, 30000, 1) + b"\x01\x11\x00"
    return b"\xff\xd8" + sof + b"\xff\xda\x00\x08\x01\x01\x00\x00\x3f\x00" + b"\x00" * 600 + b"\xff\xd9"


@pytest.mark.parametrize(
    "body,status",
    [(b"", 422), (b"not an image at all", 415), (b"GIF89a\x01\x00\x01\x00", 415), (_giant_jpeg(), 413)],
)
def test_bad_images_get_a_clear_4xx(client: TestClient, body: bytes, status: int) -> None:
    reply = client.post("/detect", content=body, headers={"content-type": "image/jpeg"})
    assert reply.status_code == status, reply.text
    assert reply.json()["detail"]


def test_truncated_jpeg_is_422(client: TestClient, frame: Frame) -> None:
    data = _encode(frame[0], ".jpg")
    reply = client.post("/detect", content=data[: len(data) // 2], headers={"content-type": "image/jpeg"})
    assert reply.status_code == 422 and "truncated" in reply.json()["detail"]


def test_body_over_the_limit_is_413(settings: Settings) -> None:
    from app.main import create_app

    small = settings.model_copy(update={"max_image_bytes": 2048})
    with TestClient(create_app(small)) as client:
        reply = client.post("/detect", content=b"\xff\xd8\xff" + b"\x00" * 5000, headers={"content-type": "image/jpeg"})
        assert reply.status_code == 413
        assert client.get("/livez").status_code == 200


def test_multipart_without_image_field_is_422(client: TestClient) -> None:
    reply = client.post("/detect", files={"picture": ("f.png", b"x", "image/png")})
    assert reply.status_code == 422 and "image" in reply.json()["detail"]


def test_unknown_classifier_404_and_family_422(client: TestClient, frame: Frame) -> None:
    data = _encode(frame[0], ".png")
    reply = client.post("/detect?classifier_id=999", content=data, headers={"content-type": "image/png"})
    assert reply.status_code == 404
    reply = client.post("/detect?family=qr", content=data, headers={"content-type": "image/png"})
    assert reply.status_code == 422


def test_an_image_whose_decoding_would_overrun_the_memory_budget_is_413_at_once(client: TestClient) -> None:
    # 280 kB of PNG that decodes to 6000x6000 16-bit RGBA: 288 MB before the detector's
    # own pyramid, seconds of work. Its header says so: refused before decoding.
    data = _encode(np.zeros((6000, 6000, 4), np.uint16), ".png")
    assert len(data) < 400_000
    warm = client.post("/detect", content=_encode(np.zeros((48, 64), np.uint8), ".png"))  # the worker started
    assert warm.status_code == 200
    started = time.perf_counter()
    reply = client.post("/detect", content=data, headers={"Content-Type": "image/png"})
    assert reply.status_code == 413, reply.text
    assert "memory" in reply.json()["detail"]
    assert time.perf_counter() - started < 0.5


def test_a_jpeg_cut_short_and_closed_with_an_end_marker_is_422(client: TestClient, frame: Frame) -> None:
    data = _encode(frame[0], ".jpg")
    reply = client.post("/detect", content=data[: len(data) // 3] + b"\xff\xd9",
                        headers={"Content-Type": "image/jpeg"})
    assert reply.status_code == 422 and "premature end" in reply.json()["detail"]
