"""POST /detect?draw=true: the image back as a PNG of its size, with each target's
quadrilateral, discs and id and every candidate disc drawn over it; without draw the
JSON reply is as it was."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.core.detection import DetectedTarget, draw_detections
from app.sim import scenes

Frame = tuple[np.ndarray, scenes.FrameTruth]


@pytest.fixture(scope="module")
def frame() -> Frame:
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


def test_draw_returns_the_image_with_the_targets_drawn(client: TestClient, frame: Frame) -> None:
    image, truth = frame
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


def test_draw_works_on_a_jpeg_and_a_multipart_body(client: TestClient, frame: Frame) -> None:
    image, _ = frame
    jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    for kwargs in ({"content": jpeg, "headers": {"content-type": "image/jpeg"}},
                   {"files": {"image": ("f.jpg", jpeg, "image/jpeg")}}):
        reply = client.post("/detect?draw=true", **kwargs)  # type: ignore[arg-type]
        assert reply.status_code == 200 and reply.headers["content-type"] == "image/png"
        drawn = cv2.imdecode(np.frombuffer(reply.content, np.uint8), cv2.IMREAD_UNCHANGED)
        assert drawn.shape == (image.shape[0], image.shape[1], 3)


def test_without_draw_the_reply_is_json_as_before(client: TestClient, frame: Frame) -> None:
    image, _ = frame
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
