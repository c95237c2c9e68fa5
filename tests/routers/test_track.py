"""The /track WebSocket and POST /environments/{id}/locate."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from app.core.geometry.camera import Camera, Pose
from app.sim import degrade, scenes
from app.sim.walks import Walk
from tests.routers.conftest import Pan, pan_poses, pan_room, stream_frames

#: A scene of three cards, its camera, three poses and their frames (JPEG).
World = tuple[scenes.Scene, Camera, list[Pose], list[bytes]]


@pytest.fixture(scope="module")
def world() -> World:
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
def environment(client: TestClient, world: World) -> int:
    scene, camera, _, _ = world
    env = client.post("/environments", json={"name": "bench", "marker_size_m": 0.2}).json()
    assert client.put(f"/environments/{env['id']}/map", json=scene.map_document(camera)).status_code == 200
    return int(env["id"])


def test_hello_frames_and_poses_in_order(client: TestClient, world: World, environment: int) -> None:
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
            assert all(t["read_margin"] >= 0 for t in reply["targets"])  # how clearly each code was read
            assert reply["pose"]["n_targets"] == 3 and reply["pose"]["n_points"] == 12
            assert np.linalg.norm(np.array(reply["pose"]["position"]) - pose.position) < 0.01
            assert set(reply["timing_ms"]) >= {"decode", "detect", "pose", "total"}


def test_config_and_bad_messages(client: TestClient, world: World, environment: int) -> None:
    _, _, poses, frames = world
    with client.websocket_connect(f"/track?environment_id={environment}") as ws:
        ws.receive_json()
        ws.send_text(json.dumps({"type": "config", "method": "posit"}))
        assert ws.receive_json() == {"type": "config", "method": "posit", "estimate_focal": False,
                                     "intrinsics": None, "regions": True, "full_scan_every": 30, "frame": "opencv",
                                     "tilt": "track", "smoothing": None, "predict_ms": 0.0, "rolling_shutter": None,
                                     "freed": None}
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


def test_focal_estimation_on_request(client: TestClient, world: World, environment: int) -> None:
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


def test_flooding_client_loses_old_frames_never_the_newest(client: TestClient, world: World, environment: int) -> None:
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


def test_garbage_from_one_client_does_not_disturb_another(client: TestClient, world: World, environment: int) -> None:
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


def test_pose_covariance_carries_the_maps_uncertainty(client: TestClient, world: World, environment: int) -> None:
    # A surveyed map is only so good: its std_m shows in every pose's covariance, and a
    # map without it is taken as exact.
    scene, camera, _, frames = world

    def position_std_mm(std_m: float | None) -> float:
        document = scene.map_document(camera)
        for target in document["targets"]:
            target["std_m"] = None if std_m is None else [std_m] * 4
        assert client.put(f"/environments/{environment}/map", json=document).status_code == 200
        body = client.post(f"/environments/{environment}/locate", content=frames[1],
                           headers={"content-type": "image/jpeg"}).json()
        return 1000 * float(np.sqrt(np.trace(np.array(body["pose"]["covariance_position"]))))

    exact, surveyed = position_std_mm(None), position_std_mm(0.005)
    assert exact < 1.0 and surveyed > 3.0, (exact, surveyed)  # 5 mm cards: mm, not the image noise's tenths


def test_locate_one_image(client: TestClient, world: World, environment: int) -> None:
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


# --- regions of interest (per-connection tracking state) ----------------------------


def test_regions_give_the_poses_of_full_scans(client: TestClient, pan: Pan, pan_environment: int) -> None:
    _, _, poses, frames, visible = pan
    url = f"/track?environment_id={pan_environment}"
    with client.websocket_connect(url) as ws:
        on = stream_frames(ws, frames, {"full_scan_every": 1000})  # regions (the default), no periodic full scan
    with client.websocket_connect(url) as ws:
        off = stream_frames(ws, frames, {"regions": False})
    # Frame 1 has a position but no velocity yet: the wider margins may cover most of
    # the frame ("wide": a full scan); from frame 2 on, regions only.
    assert on[0]["scan_reason"] == "first" and on[1]["scan_reason"] in ("regions", "wide")
    assert [r["scan"] for r in on[2:]] == ["regions"] * (len(frames) - 2)
    assert {r["scan_reason"] for r in on[2:]} == {"regions"}
    assert all(r["timing_ms"]["regions"] >= 1 for r in on[2:])
    assert {r["scan"] for r in off} == {"full"} and {r["scan_reason"] for r in off} == {"off"}
    assert all("regions" not in r["timing_ms"] for r in off)
    for seq, (a, b) in enumerate(zip(on, off, strict=True)):
        assert [t["id"] for t in a["targets"]] == [t["id"] for t in b["targets"]], seq
        assert a["pose"] is not None and b["pose"] is not None
        assert np.linalg.norm(np.subtract(a["pose"]["position"], b["pose"]["position"])) < 1e-3
        assert np.linalg.norm(np.subtract(a["pose"]["position"], poses[seq].position)) < 0.02
    # Cards entering the view are found by the region scans (no full scan after frame 0).
    entering = {i for v in visible for i in v} - visible[0]
    assert entering
    for card in entering:
        first = min(k for k, v in enumerate(visible) if card in v)
        assert any(card in {t["id"] for t in r["targets"]} for r in on[first:first + 2]), card


def test_full_scans_first_periodically_and_after_losing_track(client: TestClient, pan: Pan, pan_environment: int) -> None:
    _, _, _, frames, _ = pan
    url = f"/track?environment_id={pan_environment}"
    with client.websocket_connect(url) as ws:
        replies = stream_frames(ws, frames, {"full_scan_every": 3})
    scans = "".join("R" if r["scan"] == "regions" else "F" for r in replies)
    assert scans[0] == "F" and "RRR" not in scans and "RR" in scans, scans
    assert "periodic" in {r["scan_reason"] for r in replies}

    blank = cv2.imencode(".jpg", np.full((480, 640), 200, np.uint8))[1].tobytes()
    with client.websocket_connect(url) as ws:
        replies = stream_frames(ws, [*frames[:4], blank, *frames[4:8]], {"full_scan_every": 1000})
    reasons = [r["scan_reason"] for r in replies]
    # 0 first; 1 (no velocity yet: maybe too wide); 2, 3 regions; 4 blank: the regions
    # give no pose, so the whole frame is searched at once (fallback) and the track is
    # lost; 5 lost: a full scan; 6 maybe wide again; then regions.
    assert reasons[0] == "first" and reasons[1] in ("regions", "wide") and reasons[6] in ("regions", "wide")
    assert reasons[2:6] == ["regions", "regions", "fallback", "lost"] and reasons[7:] == ["regions", "regions"]
    assert [r["scan"] for r in replies[2:6]] == ["regions", "regions", "full", "full"]
    assert replies[4]["pose"] is None and all(r["pose"] is not None for i, r in enumerate(replies) if i != 4)


def test_new_intrinsics_mean_a_full_scan(client: TestClient, pan: Pan, pan_environment: int) -> None:
    _, camera, _, frames, _ = pan
    intrinsics = {**camera.to_dict(), "K": (camera.K * [[1.01], [1.01], [1]]).tolist()}
    with client.websocket_connect(f"/track?environment_id={pan_environment}") as ws:
        replies = stream_frames(ws, frames[:3])
        ws.send_text(json.dumps({"type": "config", "intrinsics": intrinsics}))
        assert ws.receive_json()["regions"] is True
        for frame in frames[3:5]:
            ws.send_bytes(frame)
            replies.append(ws.receive_json())
    assert [r["scan_reason"] for r in replies][2:4] == ["regions", "camera"]
    assert replies[4]["scan_reason"] in ("regions", "wide")


def test_tracking_state_is_per_connection(client: TestClient, pan: Pan, pan_environment: int) -> None:
    _, _, _, frames, _ = pan
    url = f"/track?environment_id={pan_environment}"
    with client.websocket_connect(url) as a, client.websocket_connect(url) as b:
        assert a.receive_json()["type"] == "hello" and b.receive_json()["type"] == "hello"
        b.send_text(json.dumps({"type": "config", "regions": False}))
        b.receive_json()
        for k in range(4):
            a.send_bytes(frames[k])
            ra = a.receive_json()
            # b sees other frames (backwards): its poses would mislead a's prediction
            b.send_bytes(frames[-1 - k])
            rb = b.receive_json()
            assert ra["scan_reason"] == "first" if k == 0 else ra["scan_reason"] in ("regions", "wide")
            assert rb["scan_reason"] == "off" and rb["pose"] is not None and ra["pose"] is not None
    # A new connection starts afresh.
    with client.websocket_connect(url) as c:
        assert stream_frames(c, frames[5:6])[0]["scan_reason"] == "first"


def test_locate_scans_the_whole_frame(client: TestClient, pan: Pan, pan_environment: int) -> None:
    _, _, poses, frames, _ = pan
    for _ in range(2):  # no history between calls
        body = client.post(f"/environments/{pan_environment}/locate", content=frames[3],
                           headers={"content-type": "image/jpeg"}).json()
        assert "regions" not in body["timing_ms"] and "scan" not in body
        assert np.linalg.norm(np.array(body["pose"]["position"]) - poses[3].position) < 0.02


def test_region_config_is_validated(client: TestClient, pan_environment: int) -> None:
    with client.websocket_connect(f"/track?environment_id={pan_environment}") as ws:
        ws.receive_json()
        for bad in ({"regions": "sometimes"}, {"full_scan_every": 0}, {"full_scan_every": 2.5}):
            ws.send_text(json.dumps({"type": "config", **bad}))
            assert ws.receive_json()["code"] == "bad_config", bad
        ws.send_text(json.dumps({"type": "config", "regions": False, "full_scan_every": 5}))
        echo = ws.receive_json()
        assert echo["regions"] is False and echo["full_scan_every"] == 5


@pytest.fixture(scope="module")
def rolling_pan() -> tuple[scenes.Scene, Camera, list[Pose], list[bytes]]:
    """A phone turning 3 degrees a frame (90 degrees a second) in a room of cards, its
    rows read out over 20 ms at 30 frames a second."""
    rng = np.random.default_rng(4)
    camera, scene = pan_room(rng)
    poses = pan_poses(200.0, 3.0, 16)
    readouts = Walk("pan", poses, fps=30.0).readouts(0.020)
    frames = [cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
              for image, _ in scenes.render_walk(scene, camera, poses, rng, "none", readouts=readouts)]
    return scene, camera, poses, frames


def test_a_rolling_shutter_is_modelled_on_request(client: TestClient, rolling_pan) -> None:
    scene, camera, poses, frames = rolling_pan
    env = client.post("/environments", json={"name": "phone", "marker_size_m": 0.2}).json()
    assert client.put(f"/environments/{env['id']}/map", json=scene.map_document(camera)).status_code == 200
    errors = {}
    for modelled in (False, True):
        config = {"rolling_shutter": {"readout_ms": 20.0, "frame_rate": 30.0}} if modelled else None
        with client.websocket_connect(f"/track?environment_id={env['id']}") as ws:
            replies = stream_frames(ws, frames, config)
        errors[modelled] = [1000 * np.linalg.norm(np.array(r["pose"]["position"]) - pose.position)
                            for r, pose in zip(replies, poses, strict=True) if r["pose"] is not None]
        assert len(errors[modelled]) == len(frames)
    # Read as a global shutter the turn puts the poses decimetres off; modelled, the
    # poses are within millimetres.
    assert np.median(errors[False]) > 50
    assert np.median(errors[True]) < 3


def test_a_readout_longer_than_a_frame_is_a_bad_config(client: TestClient, environment: int) -> None:
    with client.websocket_connect(f"/track?environment_id={environment}") as ws:
        ws.receive_json()
        ws.send_text(json.dumps({"type": "config", "rolling_shutter": {"readout_ms": 40.0, "frame_rate": 30.0}}))
        error = ws.receive_json()
        assert error["code"] == "bad_config" and "longer than a frame" in error["message"]
        ws.send_text(json.dumps({"type": "config", "rolling_shutter": {"readout_ms": 20.0, "frame_rate": 30.0}}))
        assert ws.receive_json()["rolling_shutter"] == {"readout_ms": 20.0, "frame_rate": 30.0}
