"""Fixtures of the /track tests: a room and a camera panning through it."""

from __future__ import annotations

import json
from typing import Any

import anyio
import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.testclient import WebSocketTestSession
from starlette.websockets import WebSocketDisconnect

from app.core.geometry.camera import Camera, Pose
from app.sim import degrade, scenes

#: A room, its camera, a pan's poses, their frames (JPEG) and the cards each frame shows.
Pan = tuple[scenes.Scene, Camera, list[Pose], list[bytes], list[set[int]]]


def pan_room(rng: np.random.Generator) -> tuple[Camera, scenes.Scene]:
    """The pans' camera and room: 24 cards of 0.2 m in a 6 x 5 x 3 m room."""
    camera = Camera.pinhole(820.0, 640, 480, dist=[-0.1, 0.0, 0.0, 0.0, 0.0])
    return camera, scenes.room_scene(rng, (6.0, 5.0, 3.0), n_targets=24, marker_size_m=0.2)


def pan_poses(first_deg: float, step_deg: float, n: int) -> list[Pose]:
    """A camera near the room's middle turning `step_deg` a frame from `first_deg`,
    drifting 1 cm a frame."""
    eye = np.array([3.0, 2.5, 1.5])
    poses = []
    for k in range(n):
        yaw = np.deg2rad(first_deg + step_deg * k)
        poses.append(Pose.look_at(eye + [0.01 * k, 0.0, 0.0], eye + [np.cos(yaw), np.sin(yaw), -0.05]))
    return poses


@pytest.fixture(scope="module")
def pan() -> Pan:
    """A camera turning 1.5 degrees a frame in a room: cards enter the view on the way."""
    rng = np.random.default_rng(1)
    camera, scene = pan_room(rng)
    poses = pan_poses(210.0, 1.5, 10)
    frames, visible = [], []
    for pose in poses:
        image, truth = scenes.render_frame(scene, camera, pose, rng, degrade.PRESETS["none"].sample(rng))
        frames.append(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes())
        visible.append({t.id for t in truth.visible_targets() if t.disc_diameter_px > 6})
    return scene, camera, poses, frames, visible


@pytest.fixture
def pan_environment(client: TestClient, pan: Pan) -> int:
    scene, camera, _, _, _ = pan
    env = client.post("/environments", json={"name": "pan", "marker_size_m": 0.2}).json()
    assert client.put(f"/environments/{env['id']}/map", json=scene.map_document(camera)).status_code == 200
    return int(env["id"])


def stream_frames(ws: WebSocketTestSession, frames: list[bytes], config: dict | None = None,
                  hello: bool = True) -> list[dict]:
    """Send `frames` in lock-step on an open /track connection, after reading its hello
    (unless `hello` is False) and sending `config`; the frame replies, in order."""
    if hello:
        assert ws.receive_json()["type"] == "hello"
    if config is not None:
        ws.send_text(json.dumps({"type": "config", **config}))
        assert ws.receive_json()["type"] == "config"
    replies = []
    for frame in frames:
        ws.send_bytes(frame)
        replies.append(ws.receive_json())
        assert replies[-1]["type"] == "frame", replies[-1]
    return replies


def receive(ws: WebSocketTestSession, timeout: float = 20.0) -> dict[str, Any]:
    """The next JSON message of a TestClient WebSocket; WebSocketDisconnect when the server
    closed it; a test failure after `timeout` s (never a hung test)."""

    async def next_message() -> dict[str, Any]:
        with anyio.fail_after(timeout):
            return await ws._send_rx.receive()  # noqa: SLF001 - TestClient has no timeout of its own

    message = ws.portal.call(next_message)
    if message["type"] == "websocket.close":
        raise WebSocketDisconnect(message.get("code", 1000), message.get("reason"))
    return json.loads(message["text"])
