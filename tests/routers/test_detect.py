"""POST /detect: targets in a JPEG or PNG, candidates on request, clear 4xx on bad
input; with ``draw=true`` the image back as a PNG of its size, with each target's
quadrilateral, discs and id and every candidate disc drawn over it."""

from __future__ import annotations

import struct
import time

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.core.detection import DetectedTarget, draw_detections
from app.settings import Settings
from app.sim import scenes

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


Frame = tuple[np.ndarray, scenes.FrameTruth]


@pytest.fixture(scope="module")
def default_frame() -> Frame:
    return scenes.scenario_frame("default", np.random.default_rng(2))


def _png(image: np.ndarray) -> bytes:
    return cv2.imencode(".png", image)[1].tobytes()


def _quad_mask(shape: tuple[int, ...], discs: np.ndarray, grow: float) -> np.ndarray:
    """The pixels of a target's disc quadrilateral, grown by `grow` of its size about its centre."""
    centre = discs.mean(axis=0)
    corners = np.round(centre + (discs - centre) * (1 + grow)).astype(np.int32)
    mask = np.zeros(shape[:2], np.uint8)
    cv2.fillConvexPoly(mask, corners, 1)
    return mask.astype(bool)


def test_draw_returns_the_image_with_the_targets_drawn(client: TestClient, default_frame: Frame) -> None:
    image, truth = default_frame
    body = _png(image)
    found = client.post("/detect?candidates=true", content=body, headers={"content-type": "image/png"})
    assert found.status_code == 200, found.text
    targets = found.json()["targets"]
    assert {t["id"] for t in targets} >= {t.id for t in truth.visible_targets()} and targets

    reply = client.post("/detect?draw=true", content=body, headers={"content-type": "image/png"})
    assert reply.status_code == 200, reply.text
    assert reply.headers["content-type"] == "image/png"
    drawn = cv2.imdecode(np.frombuffer(reply.content, np.uint8), cv2.IMREAD_COLOR)
    assert drawn is not None and drawn.shape == (image.shape[0], image.shape[1], 3)

    grey = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image
    changed = np.abs(drawn.astype(int) - grey.astype(int)).max(axis=2) > 40
    coloured = np.ptp(drawn.astype(int), axis=2) > 60  # the input is grey: colour is the drawing
    anywhere = np.zeros(changed.shape, bool)
    for target in targets:
        discs = np.array(target["discs"])
        near = _quad_mask(drawn.shape, discs, 0.6)
        anywhere |= near
        # Lines along the quadrilateral and circles on the discs, in colour.
        assert (changed & coloured & near).sum() > 4 * np.linalg.norm(discs[1] - discs[0]), target["id"]
        for u, v in discs:
            ring = (slice(max(int(v) - 12, 0), int(v) + 13), slice(max(int(u) - 12, 0), int(u) + 13))
            assert changed[ring].any(), (target["id"], u, v)
    # Away from the targets only the candidates are drawn: most of the image is as it was.
    assert changed[~anywhere].mean() < 0.05


def test_draw_works_on_a_jpeg_and_a_multipart_body(client: TestClient, default_frame: Frame) -> None:
    image, _ = default_frame
    jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    for kwargs in ({"content": jpeg, "headers": {"content-type": "image/jpeg"}},
                   {"files": {"image": ("f.jpg", jpeg, "image/jpeg")}}):
        reply = client.post("/detect?draw=true", **kwargs)  # type: ignore[arg-type]
        assert reply.status_code == 200 and reply.headers["content-type"] == "image/png"
        drawn = cv2.imdecode(np.frombuffer(reply.content, np.uint8), cv2.IMREAD_UNCHANGED)
        assert drawn.shape == (image.shape[0], image.shape[1], 3)


def test_without_draw_the_reply_is_json_as_before(client: TestClient, default_frame: Frame) -> None:
    image, _ = default_frame
    for query in ("", "?draw=false"):
        reply = client.post(f"/detect{query}", content=_png(image), headers={"content-type": "image/png"})
        assert reply.status_code == 200 and reply.headers["content-type"] == "application/json"
        body = reply.json()
        assert set(body) == {"width", "height", "targets", "candidates", "classifier_id", "timing_ms"}
        assert (body["width"], body["height"]) == (640, 480) and body["candidates"] is None and body["targets"]


def test_draw_refuses_what_detect_refuses(client: TestClient) -> None:
    assert client.post("/detect?draw=true", content=b"not an image",
                       headers={"content-type": "image/png"}).status_code == 415
    image, _ = scenes.scenario_frame("clean", np.random.default_rng(1))
    assert client.post("/detect?draw=true&classifier_id=999", content=_png(image),
                       headers={"content-type": "image/png"}).status_code == 404
    assert client.post("/detect?draw=true&family=nope", content=_png(image),
                       headers={"content-type": "image/png"}).status_code == 422


def test_drawing_leaves_its_input_alone_and_takes_colour_frames() -> None:
    gray = np.full((120, 160), 200, np.uint8)
    target = DetectedTarget(5, np.array([[40.0, 30.0], [100.0, 32.0], [98.0, 90.0], [42.0, 88.0]]), 0.9)
    candidates = np.array([[20.5, 100.25, 4.0, 0.3]])
    drawn = draw_detections(gray, [target], candidates)
    assert drawn.shape == (120, 160, 3) and drawn.dtype == np.uint8 and (gray == 200).all()
    assert (drawn[100, 14:27] != 200).any()  # the candidate's circle
    assert (drawn[31, 50:90] != 200).any()  # the quadrilateral's top side
    again = draw_detections(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR), [target], np.zeros((0, 4)))
    assert again.shape == (120, 160, 3) and (again[100, 14:27] == 200).all()
    with pytest.raises(ValueError):
        draw_detections(gray.astype(np.float32), [target], candidates)
