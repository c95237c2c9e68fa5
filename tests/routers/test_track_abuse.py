"""Abuse of WebSocket /track: garbage of every kind gets an error message (never a dead
connection or server) while another client on the same environment keeps tracking;
refused connections; the per-client frame rate limit and the connection limit."""

from __future__ import annotations

import json
import random
import struct
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from app.core.geometry.camera import Camera, Pose
from app.main import create_app
from app.schemas import TrackConfig
from app.services.tracking import FrameResult, StreamFrame, TrackingContext
from app.settings import Settings
from app.sim import degrade, scenes
from tests.routers.conftest import receive

MAX_FRAME_BYTES = 256 * 1024


#: A scene of three cards, its camera and three frames of it (JPEG).
World = tuple[scenes.Scene, Camera, list[bytes]]


@pytest.fixture(scope="module")
def world() -> World:
    rng = np.random.default_rng(21)
    camera = Camera.pinhole(820.0, 640, 480, dist=[-0.1, 0.0, 0.0, 0.0, 0.0])
    scene = scenes.single_frame_scene(rng, camera, n_targets=3, distance_m=(1.2, 2.0), tilt_deg=(0, 30))
    frames = []
    for x in (-0.1, 0.0, 0.1):
        pose = Pose.look_at([x, 0.05 * x, 0.0], [0.0, 0.0, 1.6], up=(0.0, -1.0, 0.0))
        image, _ = scenes.render_frame(scene, camera, pose, rng, degrade.PRESETS["none"].sample(rng))
        frames.append(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes())
    assert max(map(len, frames)) < MAX_FRAME_BYTES
    return scene, camera, frames


def _app_client(tmp_path: Path, world: World, **limits: Any) -> Iterator[tuple[TestClient, int]]:
    scene, camera, _ = world
    settings = Settings(data_dir=tmp_path / "data", max_frame_bytes=MAX_FRAME_BYTES, **limits)
    with TestClient(create_app(settings)) as client:
        env = client.post("/environments", json={"name": "abuse", "marker_size_m": 0.2}).json()
        assert client.put(f"/environments/{env['id']}/map", json=scene.map_document(camera)).status_code == 200
        yield client, int(env["id"])


@pytest.fixture
def served(tmp_path: Path, world: World) -> Iterator[tuple[TestClient, int]]:
    yield from _app_client(tmp_path, world)


def _png(image: np.ndarray) -> bytes:
    return cv2.imencode(".png", image)[1].tobytes()


def _garbage(frames: list[bytes]) -> list[tuple[str, str | bytes, str]]:
    """(name, message, expected error code): text goes as text, bytes as binary."""
    rng = random.Random(5)
    jpeg = frames[0]
    sof = jpeg.index(b"\xff\xc0")
    giant_sof = jpeg[: sof + 5] + struct.pack(">HH", 30000, 30000) + jpeg[sof + 9 :]
    zero_sof = jpeg[: sof + 5] + struct.pack(">HH", 0, 0) + jpeg[sof + 9 :]
    png = _png(np.full((480, 640), 90, np.uint8))
    return [
        ("plain text", "hello", "bad_message"),
        ("empty text", "", "bad_message"),
        ("broken JSON", '{"type": "config", ', "bad_message"),
        ("JSON list", "[1, 2, 3]", "bad_message"),
        ("JSON number", "42", "bad_message"),
        ("JSON null", "null", "bad_message"),
        ("JSON string", '"config"', "bad_message"),
        ("JSON, not a config", '{"type": "frame", "seq": 3}', "bad_message"),
        ("JSON without type", '{"method": "posit"}', "bad_message"),
        ("deep JSON", "[" * 50_000 + "]" * 50_000, "bad_message"),
        ("NaN JSON", '{"type": "config", "method": NaN}', "bad_config"),
        ("unknown method", '{"type": "config", "method": "magic"}', "bad_config"),
        ("unknown field", '{"type": "config", "zoom": 3}', "bad_config"),
        ("estimate_focal list", '{"type": "config", "estimate_focal": [1]}', "bad_config"),
        ("intrinsics junk", '{"type": "config", "intrinsics": {"width": -1}}', "bad_config"),
        ("intrinsics NaN", json.dumps({"type": "config", "intrinsics": {
            "width": 640, "height": 480, "K": [[float("nan"), 0, 320], [0, 800, 240], [0, 0, 1]],
            "dist": [0, 0, 0, 0, 0]}}), "bad_config"),
        ("empty binary", b"", "bad_frame"),
        ("giant binary", rng.randbytes(MAX_FRAME_BYTES + 1), "frame_too_large"),
        ("giant JPEG", jpeg + bytes(MAX_FRAME_BYTES), "frame_too_large"),
        ("half a JPEG", jpeg[: len(jpeg) // 2], "bad_frame"),
        ("JPEG head only", jpeg[:3], "bad_frame"),
        ("JPEG declaring 30000x30000", giant_sof, "bad_frame"),
        ("JPEG declaring 0x0", zero_sof, "bad_frame"),
        ("half a PNG", png[: len(png) // 2], "bad_frame"),
        ("PNG chunk length 0xFFFFFFFF", png[:33] + b"\xff\xff\xff\xff" + png[37:], "bad_frame"),
        ("1x1 PNG", _png(np.zeros((1, 1), np.uint8)), "bad_frame"),
        ("GIF", b"GIF89a\x01\x00\x01\x00\x00\x00\x00;", "bad_frame"),
        ("random bytes", rng.randbytes(5000), "bad_frame"),
        ("text as binary", b'{"type": "config"}', "bad_frame"),
        ("a config of 20 unknown keys", json.dumps({"type": "config", **{f"e{i}": 0 for i in range(20)}}),
         "bad_message"),
        ("a config of 1 MB", json.dumps({"type": "config", **{f"e{i}": 0 for i in range(100_000)}}), "bad_message"),
        ("a 6324x6324 JPEG of 333 bytes", jpeg[: sof + 5] + struct.pack(">HH", 6324, 6324) + jpeg[sof + 9 : sof + 300]
         + b"\xff\xd9", "bad_frame"),
        ("a JPEG cut short with an end marker", jpeg[: len(jpeg) // 2] + b"\xff\xd9", "bad_frame"),
    ]


def test_garbage_gets_errors_while_another_client_keeps_tracking(
    served: tuple[TestClient, int], world: World, caplog: pytest.LogCaptureFixture
) -> None:
    import logging

    caplog.set_level(logging.WARNING)
    client, environment = served
    _, _, frames = world
    garbage = _garbage(frames)
    stop = threading.Event()
    good_replies: list[dict[str, Any]] = []
    good_errors: list[BaseException] = []

    def good_client() -> None:
        try:
            with client.websocket_connect(f"/track?environment_id={environment}") as ws:
                assert receive(ws)["type"] == "hello"
                k = 0
                while not stop.is_set() or len(good_replies) < 3:
                    ws.send_bytes(frames[k % 3])
                    good_replies.append(receive(ws))
                    k += 1
        except BaseException as exc:  # reported by the main thread
            good_errors.append(exc)

    thread = threading.Thread(target=good_client, daemon=True)
    thread.start()
    try:
        with client.websocket_connect(f"/track?environment_id={environment}") as bad:
            assert receive(bad)["type"] == "hello"
            seq = 0
            for name, message, code in garbage:
                if isinstance(message, str):
                    bad.send_text(message)
                else:
                    bad.send_bytes(message)
                reply = receive(bad)
                assert reply["type"] == "error", (name, reply)
                assert reply["code"] == code, (name, reply)
                assert isinstance(reply["message"], str) and reply["message"], name
                # Short, whatever came in: the input is never echoed, nor each of its errors.
                assert len(reply["message"]) < 1500, (name, len(reply["message"]))
                if isinstance(message, bytes):
                    assert reply["seq"] == seq, (name, reply)
                    seq += 1
                # Interleave: the good client gets a reply between any two pieces of garbage.
                seen, deadline = len(good_replies), time.monotonic() + 20
                while len(good_replies) == seen and not good_errors:
                    assert time.monotonic() < deadline, f"the good client stalled after {name}"
                    time.sleep(0.002)
            # The abused connection itself still tracks.
            bad.send_bytes(frames[1])
            reply = receive(bad)
            assert reply["type"] == "frame" and reply["seq"] == seq and reply["pose"] is not None
            assert reply["dropped"] == 0
    finally:
        stop.set()
        thread.join(timeout=60)
    assert not thread.is_alive()
    assert not good_errors, good_errors
    assert len(good_replies) >= 3
    assert all(r["type"] == "frame" and r["pose"] is not None for r in good_replies), good_replies[:3]
    assert [r["seq"] for r in good_replies] == list(range(len(good_replies)))
    assert len(good_replies) > len(garbage)
    assert client.get("/livez").status_code == 200
    problems = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert not problems, problems


def test_a_valid_png_frame_is_accepted(served: tuple[TestClient, int]) -> None:
    """Frames are meant to be JPEGs, but the decoder is the one of /detect: a PNG works."""
    client, environment = served
    with client.websocket_connect(f"/track?environment_id={environment}") as ws:
        receive(ws)
        ws.send_bytes(_png(np.full((480, 640), 200, np.uint8)))
        reply = receive(ws)
        assert reply["type"] == "frame" and reply["pose"] is None and reply["pose_error"]


def test_a_server_bug_on_one_frame_is_an_error_message_not_a_dead_connection(
    served: tuple[TestClient, int], world: World, monkeypatch: pytest.MonkeyPatch
) -> None:
    client, environment = served
    _, _, frames = world
    tracking = client.app.state.tracking
    real = tracking.locate_frame

    def flaky(context: TrackingContext, data: bytes, config: TrackConfig | StreamFrame) -> FrameResult:
        if data == b"boom" * 10:
            raise ZeroDivisionError("a bug")
        return real(context, data, config)

    monkeypatch.setattr(tracking, "locate_frame", flaky)
    with client.websocket_connect(f"/track?environment_id={environment}") as ws:
        receive(ws)
        ws.send_bytes(b"boom" * 10)
        error = receive(ws)
        assert error["type"] == "error" and error["code"] == "internal_error" and error["seq"] == 0
        ws.send_bytes(frames[0])
        reply = receive(ws)
        assert reply["type"] == "frame" and reply["seq"] == 1 and reply["pose"] is not None


@pytest.mark.parametrize(
    "query,code",
    [("environment_id=999", "unknown_environment"), ("", "bad_request"), ("environment_id=", "bad_request"),
     ("environment_id=abc", "bad_request"), ("environment_id=1.5", "bad_request"),
     ("environment_id=99999999999999999999999", "unknown_environment"),
     ("environment_id=-1", "unknown_environment")],
)
def test_refused_connections_say_why_then_close_1008(served: tuple[TestClient, int], query: str, code: str) -> None:
    client, _ = served
    with client.websocket_connect(f"/track?{query}") as ws:
        message = receive(ws)
        assert message["type"] == "error" and message["code"] == code and message["message"]
        with pytest.raises(WebSocketDisconnect) as closed:
            receive(ws)
        assert closed.value.code == 1008
    assert client.get("/livez").status_code == 200


def test_environment_without_map_is_refused_with_1008(served: tuple[TestClient, int]) -> None:
    client, _ = served
    env = client.post("/environments", json={"name": "empty", "marker_size_m": 0.2}).json()
    with client.websocket_connect(f"/track?environment_id={env['id']}") as ws:
        message = receive(ws)
        assert message["type"] == "error" and message["code"] == "no_map" and "no map" in message["message"]
        with pytest.raises(WebSocketDisconnect) as closed:
            receive(ws)
        assert closed.value.code == 1008


# --- limits -------------------------------------------------------------------------------


def test_rate_limit_lock_step(tmp_path: Path, world: World) -> None:
    """A client that waits for each reply but sends faster than max_track_fps: every frame
    is processed (nothing newer replaces it), at the limited rate, with at most one
    rate_limited message a second."""
    fps, n = 4.0, 12  # slow enough that the rate, not the CPU, limits even on a loaded machine
    _, _, frames = world
    for client, environment in _app_client(tmp_path, world, max_track_fps=fps):
        with client.websocket_connect(f"/track?environment_id={environment}") as ws:
            receive(ws)
            started = time.monotonic()
            notices, replies = [], []
            for k in range(n):
                ws.send_bytes(frames[k % 3])
                while True:
                    message = receive(ws)
                    if message["type"] == "error":
                        assert message["code"] == "rate_limited" and message["message"], message
                        notices.append(time.monotonic())
                        continue
                    replies.append(message)
                    break
            elapsed = time.monotonic() - started
    assert [r["seq"] for r in replies] == list(range(n))
    assert all(r["dropped"] == 0 and r["pose"] is not None for r in replies)
    # The first `fps` frames are the burst; the rest come at `fps` a second.
    assert elapsed >= (n - fps - 1) / fps * 0.9, elapsed
    assert 1 <= len(notices) <= elapsed / 1.0 + 1
    assert all(b - a >= 0.95 for a, b in zip(notices, notices[1:]))


def test_rate_limit_flood_drops_old_frames_never_the_newest(tmp_path: Path, world: World) -> None:
    fps, sent = 5.0, 60
    small = _png(np.full((64, 64), 200, np.uint8))  # fast to process: the rate, not the CPU, limits
    for client, environment in _app_client(tmp_path, world, max_track_fps=fps):
        with client.websocket_connect(f"/track?environment_id={environment}") as ws:
            receive(ws)
            started = time.monotonic()
            replies, notices = [], 0
            for _ in range(sent):  # ~100 frames a second: the server could process them all
                ws.send_bytes(small)
                time.sleep(0.01)
            while not replies or replies[-1]["seq"] != sent - 1:
                message = receive(ws)
                if message["type"] == "error":
                    assert message["code"] == "rate_limited", message
                    notices += 1
                else:
                    replies.append(message)
            elapsed = time.monotonic() - started
            # The connection is fine afterwards.
            ws.send_text(json.dumps({"type": "config", "method": "posit"}))
            assert receive(ws)["type"] == "config"
    assert all(r["type"] == "frame" for r in replies)
    assert sum(r["dropped"] for r in replies) + len(replies) == sent
    assert len(replies) <= fps + 1 + fps * elapsed
    assert len(replies) < sent / 2 and 1 <= notices <= elapsed + 1
    seqs = [r["seq"] for r in replies]
    assert seqs == sorted(seqs) and seqs[-1] == sent - 1


def test_connection_limit_refuses_with_1013_and_frees_slots(tmp_path: Path, world: World) -> None:
    _, _, frames = world
    for client, environment in _app_client(tmp_path, world, max_track_connections=2):
        url = f"/track?environment_id={environment}"
        # Connections refused for other reasons give their slot back.
        for _ in range(3):
            with client.websocket_connect("/track?environment_id=999") as ws:
                assert receive(ws)["code"] == "unknown_environment"
        with client.websocket_connect(url) as first, client.websocket_connect(url) as second:
            assert receive(first)["type"] == "hello" and receive(second)["type"] == "hello"
            with client.websocket_connect(url) as third:
                message = receive(third)
                assert message["type"] == "error" and message["code"] == "too_many_connections"
                assert message["message"]
                with pytest.raises(WebSocketDisconnect) as closed:
                    receive(third)
                assert closed.value.code == 1013
            # The two admitted connections are unaffected.
            first.send_bytes(frames[0])
            assert receive(first)["pose"] is not None
        # Once they close, there is room again (the server notices the close a moment later).
        deadline = time.monotonic() + 10
        while True:
            with client.websocket_connect(url) as again:
                message = receive(again)
                if message["type"] == "hello":
                    again.send_bytes(frames[1])
                    assert receive(again)["pose"] is not None
                    break
                assert message["code"] == "too_many_connections"
            assert time.monotonic() < deadline, "slots were never released"
            time.sleep(0.05)
        assert client.get("/livez").status_code == 200


def test_an_idle_connection_is_closed_and_gives_its_slot_back(tmp_path: Path, world: World) -> None:
    _, _, frames = world
    for client, environment in _app_client(tmp_path, world, max_track_connections=1, track_idle_timeout_s=0.5):
        url = f"/track?environment_id={environment}"
        with client.websocket_connect(url) as idle:
            assert receive(idle)["type"] == "hello"
            idle.send_bytes(frames[0])
            assert receive(idle)["type"] == "frame"  # a client that sends stays open ...
            started = time.monotonic()
            message = receive(idle)  # ... until it sends nothing for the timeout
            assert message["type"] == "error" and message["code"] == "idle" and message["message"]
            assert 0.4 < time.monotonic() - started < 5
            with pytest.raises(WebSocketDisconnect) as closed:
                receive(idle)
            assert closed.value.code == 1001
        with client.websocket_connect(url) as next_client:  # the one slot is free again
            assert receive(next_client)["type"] == "hello"
            next_client.send_bytes(frames[1])
            assert receive(next_client)["pose"] is not None
