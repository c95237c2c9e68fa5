"""The /track WebSocket and POST /environments/{id}/locate."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from app.core import degrade, scenes
from app.core.camera import Camera, Pose


@pytest.fixture(scope="module")
def world() -> tuple[scenes.Scene, Camera, list[Pose], list[bytes]]:
    rng = np.random.default_rng(21)
    camera = Camera.pinhole(820.0, 640, 480, dist=[-0.1, 0.0, 0.0, 0.0, 0.0])
    scene = scenes.single_frame_scene(rng, camera, n_targets=3, distance_m=(1.2, 2.0), tilt_deg=(0, 30))
    poses = [Pose.look_at([x, 0.05 * x, 0.0], [0.0, 0.0, 1.6], up=(0.0, -1.0, 0.0)) for x in (-0.1, 0.0, 0.1)]
    frames = []
    for pose in poses:
        image, _ = scenes.render_frame(scene, camera, pose, rng, degrade.PRESETS["none"].sample(rng))
        frames.append(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes())
    return scene, camera, poses, frames


@pytest.fixture
def environment(client: TestClient, world) -> int:  # type: ignore[no-untyped-def]
    scene, camera, _, _ = world
    env = client.post("/environments", json={"name": "bench", "marker_size_m": 0.2}).json()
    assert client.put(f"/environments/{env['id']}/map", json=scene.map_document(camera)).status_code == 200
    return int(env["id"])


def test_hello_frames_and_poses_in_order(client: TestClient, world, environment: int) -> None:  # type: ignore[no-untyped-def]
    _, _, poses, frames = world
    with client.websocket_connect(f"/track?environment_id={environment}") as ws:
        hello = ws.receive_json()
        assert hello["type"] == "hello" and hello["environment_id"] == environment and hello["targets"] == 3
        assert hello["camera"]["width"] == 640
        for seq, (pose, frame) in enumerate(zip(poses, frames, strict=True)):
            ws.send_bytes(frame)
            reply = ws.receive_json()
            assert reply["type"] == "frame" and reply["seq"] == seq and reply["dropped"] == 0
            assert len(reply["targets"]) == 3
            assert reply["pose"]["n_targets"] == 3 and reply["pose"]["n_points"] == 12
            assert np.linalg.norm(np.array(reply["pose"]["position"]) - pose.position) < 0.01
            assert set(reply["timing_ms"]) >= {"decode", "detect", "pose", "total"}


def test_config_and_bad_messages(client: TestClient, world, environment: int) -> None:  # type: ignore[no-untyped-def]
    _, _, poses, frames = world
    with client.websocket_connect(f"/track?environment_id={environment}") as ws:
        ws.receive_json()
        ws.send_text(json.dumps({"type": "config", "method": "posit"}))
        assert ws.receive_json() == {"type": "config", "method": "posit", "estimate_focal": False,
                                     "intrinsics": None}
        ws.send_text(json.dumps({"type": "config", "method": "magic"}))
        assert ws.receive_json()["code"] == "bad_config"
        ws.send_text("hello")
        assert ws.receive_json()["code"] == "bad_message"
        ws.send_bytes(b"definitely not a jpeg")
        error = ws.receive_json()
        assert error["type"] == "error" and error["code"] == "bad_frame" and error["seq"] == 0
        ws.send_bytes(frames[0][: len(frames[0]) // 2])
        assert ws.receive_json()["seq"] == 1
        ws.send_bytes(frames[1])
        reply = ws.receive_json()
        assert reply["seq"] == 2 and reply["pose"]["method"] == "posit"
        assert np.linalg.norm(np.array(reply["pose"]["position"]) - poses[1].position) < 0.05


def test_focal_estimation_on_request(client: TestClient, world, environment: int) -> None:  # type: ignore[no-untyped-def]
    _, _, _, frames = world
    with client.websocket_connect(f"/track?environment_id={environment}") as ws:
        ws.receive_json()
        ws.send_text(json.dumps({"type": "config", "estimate_focal": True}))
        ws.receive_json()
        ws.send_bytes(frames[2])
        pose = ws.receive_json()["pose"]
        assert abs(pose["focal_px"] - 820.0) < 15.0


@pytest.mark.parametrize("query,code", [("environment_id=999", "unknown_environment"), ("", "bad_request")])
def test_unknown_environment_is_refused(client: TestClient, query: str, code: str) -> None:
    with client.websocket_connect(f"/track?{query}") as ws:
        message = ws.receive_json()
        assert message["type"] == "error" and message["code"] == code
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
        assert closed.value.code == 1008


def test_environment_without_map_is_refused(client: TestClient) -> None:
    env = client.post("/environments", json={"name": "empty", "marker_size_m": 0.2}).json()
    with client.websocket_connect(f"/track?environment_id={env['id']}") as ws:
        message = ws.receive_json()
        assert message["code"] == "no_map" and "no map" in message["message"]


def test_flooding_client_loses_old_frames_never_the_newest(client: TestClient, world, environment: int) -> None:  # type: ignore[no-untyped-def]
    _, _, _, frames = world
    sent = 40
    with client.websocket_connect(f"/track?environment_id={environment}") as ws:
        ws.receive_json()
        for k in range(sent):
            ws.send_bytes(frames[k % 3])
        replies = []
        while not replies or replies[-1]["seq"] != sent - 1:
            replies.append(ws.receive_json())
        assert all(r["type"] == "frame" for r in replies)
        assert sum(r["dropped"] for r in replies) + len(replies) == sent
        assert len(replies) < sent  # the server did drop frames
        seqs = [r["seq"] for r in replies]
        assert seqs == sorted(seqs)
    # The server keeps serving others.
    with client.websocket_connect(f"/track?environment_id={environment}") as other:
        other.receive_json()
        other.send_bytes(frames[0])
        assert other.receive_json()["pose"] is not None


def test_garbage_from_one_client_does_not_disturb_another(client: TestClient, world, environment: int) -> None:  # type: ignore[no-untyped-def]
    _, _, _, frames = world
    with client.websocket_connect(f"/track?environment_id={environment}") as good, \
         client.websocket_connect(f"/track?environment_id={environment}") as bad:
        good.receive_json()
        bad.receive_json()
        for junk in (b"", b"\xff\xd8\xff", b"\x00" * 10):
            bad.send_bytes(junk)
            assert bad.receive_json()["type"] == "error"
            good.send_bytes(frames[1])
            assert good.receive_json()["pose"] is not None


def test_locate_one_image(client: TestClient, world, environment: int) -> None:  # type: ignore[no-untyped-def]
    _, _, poses, frames = world
    reply = client.post(f"/environments/{environment}/locate", content=frames[0],
                        headers={"content-type": "image/jpeg"})
    assert reply.status_code == 200, reply.text
    body = reply.json()
    assert len(body["targets"]) == 3
    assert np.linalg.norm(np.array(body["pose"]["position"]) - poses[0].position) < 0.01
    blank = cv2.imencode(".png", np.full((480, 640), 200, np.uint8))[1].tobytes()
    body = client.post(f"/environments/{environment}/locate", content=blank,
                       headers={"content-type": "image/png"}).json()
    assert body["pose"] is None and "no identified target" in body["pose_error"]
    assert client.post("/environments/999/locate", content=frames[0],
                       headers={"content-type": "image/jpeg"}).status_code == 404
