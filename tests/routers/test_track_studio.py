"""/track for studios and AR apps: FreeD packets caught by a real UDP receiver, poses in
client conventions, smoothing and prediction, and the environment's FreeD output API."""

from __future__ import annotations

import json
import socket
from collections.abc import Iterator
from ipaddress import ip_network
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.core.geometry import from_convention
from app.main import create_app
from app.settings import Settings
from tests.routers.conftest import Pan, stream_frames


#: The receivers of these tests are on 127.0.0.1, as with a renderer on the server's machine.
LOOPBACK_RECEIVERS = {"freed_connection_receivers": True, "freed_allowed_networks": [ip_network("127.0.0.1/32")]}


@pytest.fixture
def settings(settings: Settings) -> Settings:
    return settings.model_copy(update=LOOPBACK_RECEIVERS)


@pytest.fixture
def receiver() -> Iterator[socket.socket]:
    """A UDP socket on 127.0.0.1, as a studio's FreeD receiver listens."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(5.0)
    yield sock
    sock.close()


def _port(sock: socket.socket) -> int:
    return int(sock.getsockname()[1])


def _decode(data: bytes) -> dict[str, float]:
    """The reference receiver: a FreeD D1 packet read byte by byte, as the protocol
    defines it (big-endian 24-bit fields; checksum 0x40 minus the sum of bytes 0..27)."""
    assert len(data) == 29 and data[0] == 0xD1
    assert (0x40 - sum(data[:28])) % 256 == data[28]

    def signed(i: int) -> int:
        value = (data[i] << 16) | (data[i + 1] << 8) | data[i + 2]
        return value - (1 << 24) if value & 0x800000 else value

    def unsigned(i: int) -> int:
        return (data[i] << 16) | (data[i + 1] << 8) | data[i + 2]

    return {"camera": data[1], "pan": signed(2) / 32768, "tilt": signed(5) / 32768, "roll": signed(8) / 32768,
            "x": signed(11) / 64, "y": signed(14) / 64, "z": signed(17) / 64, "zoom": unsigned(20),
            "focus": unsigned(23), "user": (data[26] << 8) | data[27]}


def _packets(sock: socket.socket, n: int) -> list[dict[str, float]]:
    return [_decode(sock.recv(64)) for _ in range(n)]


def _nothing_more(sock: socket.socket) -> bool:
    sock.settimeout(0.3)
    try:
        sock.recv(64)
    except TimeoutError:
        return True
    finally:
        sock.settimeout(5.0)
    return False


def _check_packet(packet: dict[str, float], pose: dict) -> None:
    """The packet carries the reply's pose as docs/freed.md says: X, Y, Z the camera's map
    position in mm; pan from +y clockwise seen from above (towards +x), tilt up, roll
    clockwise seen from behind; the map's z up."""
    R = np.array(pose["R"])
    np.testing.assert_allclose([packet["x"], packet["y"], packet["z"]], np.array(pose["position"]) * 1e3, atol=0.02)
    pan, tilt, roll = np.radians([packet["pan"], packet["tilt"], packet["roll"]])
    optical_axis = R[2]  # the camera's +z in map coordinates
    np.testing.assert_allclose(optical_axis, [np.sin(pan) * np.cos(tilt), np.cos(pan) * np.cos(tilt), np.sin(tilt)],
                               atol=1e-4)
    right = R[0]  # the camera's +x (image right) in map coordinates: it drops as the camera rolls clockwise
    assert -right[2] == pytest.approx(np.sin(roll) * np.cos(tilt), abs=1e-4)
    assert packet["zoom"] == 0 and packet["focus"] == 0 and packet["user"] == 0


def test_the_environments_freed_output_sends_every_pose(client: TestClient, pan: Pan, pan_environment: int,
                                                       receiver: socket.socket) -> None:
    _, _, _, frames, _ = pan
    put = client.put(f"/environments/{pan_environment}/freed",
                     json={"host": "127.0.0.1", "port": _port(receiver), "camera_id": 9})
    assert put.status_code == 200, put.text
    blank = cv2.imencode(".jpg", np.full((480, 640), 128, np.uint8))[1].tobytes()
    with client.websocket_connect(f"/track?environment_id={pan_environment}") as ws:
        replies = stream_frames(ws, [*frames[:4], blank, frames[4]])
    assert replies[4]["pose"] is None  # no pose: no packet
    posed = [r for r in replies if r["pose"] is not None]
    assert len(posed) == 5
    for packet, reply in zip(_packets(receiver, len(posed)), posed, strict=True):
        assert packet["camera"] == 9
        _check_packet(packet, reply["pose"])
        assert 0 < reply["timing_ms"]["freed"] < 10_000
    assert _nothing_more(receiver)
    assert "freed" not in replies[4]["timing_ms"]


def test_a_connection_chooses_its_receiver_camera_id_or_none(client: TestClient, pan: Pan, pan_environment: int,
                                                            receiver: socket.socket) -> None:
    _, _, _, frames, _ = pan
    url = f"/track?environment_id={pan_environment}"
    with client.websocket_connect(url) as ws:  # no output in the environment: nothing unless asked
        stream_frames(ws, frames[:2])
    assert _nothing_more(receiver)
    own = {"freed": {"host": "127.0.0.1", "port": _port(receiver), "camera_id": 3}}
    with client.websocket_connect(url) as ws:
        replies = stream_frames(ws, frames[:3], own)
    for packet, reply in zip(_packets(receiver, 3), replies, strict=True):
        assert packet["camera"] == 3
        _check_packet(packet, reply["pose"])
    client.put(f"/environments/{pan_environment}/freed", json={"host": "127.0.0.1", "port": _port(receiver)})
    with client.websocket_connect(url) as ws:  # a preview beside the studio camera opts out
        stream_frames(ws, frames[:2], {"freed": {"enabled": False}})
    assert _nothing_more(receiver)
    with client.websocket_connect(url) as ws:  # the environment's receiver, its own camera id
        stream_frames(ws, frames[:2], {"freed": {"camera_id": 200}})
    assert [p["camera"] for p in _packets(receiver, 2)] == [200, 200]


def test_an_unusable_freed_config_is_refused_and_changes_nothing(client: TestClient, pan: Pan, pan_environment: int,
                                                                receiver: socket.socket) -> None:
    _, _, _, frames, _ = pan
    with client.websocket_connect(f"/track?environment_id={pan_environment}") as ws:
        assert ws.receive_json()["type"] == "hello"
        ws.send_text(json.dumps({"type": "config", "frame": "unity", "freed": {"camera_id": 2}}))
        error = ws.receive_json()
        assert error["type"] == "error" and error["code"] == "freed" and "host and port" in error["message"]
        ws.send_text(json.dumps({"type": "config", "freed": {"host": "no-such-host.invalid", "port": 40000}}))
        error = ws.receive_json()
        assert error["code"] == "freed" and "resolve" in error["message"]
        ws.send_text(json.dumps({"type": "config", "freed": {"host": "127.0.0.1", "port": 70000}}))
        assert ws.receive_json()["code"] == "bad_config"
        ws.send_bytes(frames[0])
        reply = ws.receive_json()
        assert reply["type"] == "frame" and reply["pose"]["frame_pose"]["frame"] == "opencv"  # config unchanged
    assert _nothing_more(receiver)


def test_a_server_can_keep_connections_to_the_environments_receiver(tmp_path: Path, pan: Pan,
                                                                    receiver: socket.socket) -> None:
    scene, camera, _, frames, _ = pan
    settings = Settings(data_dir=tmp_path / "data", **{**LOOPBACK_RECEIVERS, "freed_connection_receivers": False})
    with TestClient(create_app(settings)) as client:
        env = client.post("/environments", json={"name": "studio", "marker_size_m": 0.2}).json()["id"]
        client.put(f"/environments/{env}/map", json=scene.map_document(camera))
        client.put(f"/environments/{env}/freed", json={"host": "127.0.0.1", "port": _port(receiver)})
        with client.websocket_connect(f"/track?environment_id={env}") as ws:
            assert ws.receive_json()["type"] == "hello"
            ws.send_text(json.dumps({"type": "config", "freed": {"host": "127.0.0.1", "port": 9}}))
            error = ws.receive_json()
            assert error["code"] == "freed" and "leave out host and port" in error["message"]
            replies = stream_frames(ws, frames[:2], {"freed": {"camera_id": 4}}, hello=False)
        assert [p["camera"] for p in _packets(receiver, 2)] == [4, 4]
        assert all(r["pose"] is not None for r in replies)


def test_the_freed_output_api(client: TestClient, pan_environment: int) -> None:
    url = f"/environments/{pan_environment}/freed"
    assert client.get(url).status_code == 404
    assert client.delete(url).status_code == 404
    assert client.get("/environments/999999/freed").status_code == 404
    assert client.put("/environments/999999/freed", json={"host": "a", "port": 1}).status_code == 404
    for bad in ({"host": "studio", "port": 0}, {"host": "studio", "port": 40000, "camera_id": 256},
                {"host": "bad host!", "port": 40000}, {"port": 40000}, {"host": "a", "port": 1, "extra": 1}):
        assert client.put(url, json=bad).status_code == 422, bad
    assert client.get(url).status_code == 404  # nothing half-written
    body = {"host": "192.168.1.40", "port": 40000, "camera_id": 2, "enabled": False}
    assert client.put(url, json=body).json() == body
    assert client.get(url).json() == body
    assert client.put(url, json={"host": "unreal.local", "port": 6301}).json()["camera_id"] == 1
    assert client.delete(url).status_code == 204
    assert client.get(url).status_code == 404
    created = client.put(url, json=body)
    assert created.status_code == 200
    assert client.delete(f"/environments/{pan_environment}").status_code == 204
    assert client.get(url).status_code == 404


#: Where each convention puts the map point (x, y, z) (docs/conventions.md), and its unit.
WORLD = {"opencv": (lambda p: p, 1.0), "opengl": (lambda p: [p[0], p[2], -p[1]], 1.0),
         "unity": (lambda p: [p[0], p[2], p[1]], 1.0), "unreal": (lambda p: [p[0], -p[1], p[2]], 100.0)}
#: The camera's optical axis as a column of each convention's camera-to-world matrix (sign, column).
FORWARD = {"opencv": (1, 2), "opengl": (-1, 2), "unity": (1, 2), "unreal": (1, 0)}


@pytest.mark.parametrize("frame", ["opencv", "opengl", "unity", "unreal"])
def test_poses_in_client_conventions(client: TestClient, pan: Pan, pan_environment: int, frame: str) -> None:
    _, _, truth, frames, _ = pan
    with client.websocket_connect(f"/track?environment_id={pan_environment}") as ws:
        replies = stream_frames(ws, frames[:3], {"frame": frame})
    to_world, scale = WORLD[frame]
    for reply, true_pose in zip(replies, truth[:3], strict=True):
        got = reply["pose"]["frame_pose"]
        assert got["frame"] == frame and got["unit"] == ("cm" if frame == "unreal" else "m")
        matrix = np.array(got["matrix"])
        # The truth's camera, moved into the convention's world by the documented axis map.
        np.testing.assert_allclose(got["position"], scale * np.array(to_world(true_pose.position)), atol=0.02 * scale)
        np.testing.assert_allclose(matrix[:3, 3], got["position"])
        sign, column = FORWARD[frame]
        np.testing.assert_allclose(sign * matrix[:3, column], to_world(true_pose.R[2]), atol=0.01)
        x, y, z, w = got["quaternion_xyzw"]
        assert w >= 0 and np.hypot(np.hypot(x, y), np.hypot(z, w)) == pytest.approx(1.0)
        # Round trip: the convention's matrix back to the reply's own map-frame pose.
        R, t = from_convention(matrix, frame)
        np.testing.assert_allclose(R, reply["pose"]["R"], atol=1e-9)
        np.testing.assert_allclose(t, reply["pose"]["t"], atol=1e-9)


def test_smoothed_and_predicted_poses_come_when_asked(client: TestClient, pan: Pan, pan_environment: int) -> None:
    """The pan turns 1.5 degrees a frame and moves 1 cm a frame along x: the pose predicted
    half a second ahead has turned and moved further the same way; without smoothing
    or prediction there is no `filtered`."""
    _, _, _, frames, _ = pan
    url = f"/track?environment_id={pan_environment}"
    with client.websocket_connect(url) as ws:
        plain = stream_frames(ws, frames)
    assert all(r["filtered"] is None for r in plain)
    with client.websocket_connect(url) as ws:
        smoothed = stream_frames(ws, frames, {"smoothing": {"min_cutoff_hz": 0.5}, "frame": "unreal"})
    for reply in smoothed:
        assert reply["filtered"]["smoothed"] and reply["filtered"]["predict_ms"] == 0
        assert reply["filtered"]["frame_pose"]["frame"] == "unreal"
    assert smoothed[0]["filtered"]["position"] == pytest.approx(smoothed[0]["pose"]["position"])
    with client.websocket_connect(url) as ws:
        predicted = stream_frames(ws, frames, {"predict_ms": 500})
    last, before = predicted[-1], predicted[-2]
    assert not last["filtered"]["smoothed"] and last["filtered"]["predict_ms"] == 500
    motion = np.array(last["pose"]["position"]) - np.array(before["pose"]["position"])
    ahead = np.array(last["filtered"]["position"]) - np.array(last["pose"]["position"])
    assert ahead @ motion > 0  # further along the way the camera moves

    def heading(R: list[list[float]]) -> float:  # the optical axis' direction in the map's x-y plane
        return float(np.arctan2(R[2][1], R[2][0]))

    turn = heading(last["pose"]["R"]) - heading(before["pose"]["R"])
    assert turn > 0 and heading(last["filtered"]["R"]) - heading(last["pose"]["R"]) > turn
    for bad in ({"predict_ms": -1}, {"predict_ms": 501}, {"smoothing": {"min_cutoff_hz": 0}},
                {"smoothing": {"beta": -1}}, {"frame": "directx"}, {"tilt": "best"}):
        with client.websocket_connect(url) as ws:
            assert ws.receive_json()["type"] == "hello"
            ws.send_text(json.dumps({"type": "config", **bad}))
            assert ws.receive_json()["code"] == "bad_config", bad


def test_an_environment_receiver_that_does_not_resolve_is_said_once_and_blocks_nothing(
        client: TestClient, pan: Pan, pan_environment: int) -> None:
    _, _, _, frames, _ = pan
    client.put(f"/environments/{pan_environment}/freed", json={"host": "no-such-host.invalid", "port": 40000})
    with client.websocket_connect(f"/track?environment_id={pan_environment}") as ws:
        assert ws.receive_json()["type"] == "hello"
        error = ws.receive_json()
        assert error["code"] == "freed" and "resolve" in error["message"]
        replies = stream_frames(ws, frames[:2], {"frame": "unity"}, hello=False)  # other settings still apply
    assert [r["pose"]["frame_pose"]["frame"] for r in replies] == ["unity", "unity"]
