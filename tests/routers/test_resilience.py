"""Crash safety and limits: a server killed during a survey, body limits enforced before
the body is read, job queue limits, request ids in structured logs."""

from __future__ import annotations

import json
import logging
import signal
import time
import threading
from dataclasses import dataclass
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.core.geometry.camera import Camera, Pose
from app.sim.scenes import Scene, camera_walk, render_walk, room_scene
from app.main import create_app
from app.schemas import MapDocument
from app.services import jobs
from app.settings import Settings
from tests.conftest import FINISHED, example_map, free_port, start_server, wait_for_job
from tests.services.job_handlers import CountParams


@dataclass
class Room:
    scene: Scene
    camera: Camera
    video: bytes  # a calibration walk, MJPEG AVI
    frames: list[bytes]  # JPEG frames of a tracking walk
    poses: list[Pose]


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> Room:
    rng = np.random.default_rng(4)
    scene = room_scene(rng, (5.0, 4.0, 2.6), n_targets=20, marker_size_m=0.25)
    camera = Camera.pinhole(700.0, 640, 480)
    path = tmp_path_factory.mktemp("video") / "room.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (640, 480))
    for image, _ in render_walk(scene, camera, camera_walk(rng, scene.room_size, 120), rng, degradation="none"):
        writer.write(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
    writer.release()
    poses = camera_walk(rng, scene.room_size, 30, kind="tracking")
    frames = [cv2.imencode(".jpg", image)[1].tobytes() for image, _ in render_walk(scene, camera, poses, rng)]
    return Room(scene, camera, path.read_bytes(), frames, poses)


def test_server_killed_during_a_survey_restarts_consistent(tmp_path: Path, room: Room) -> None:
    data, port, log = tmp_path / "data", free_port(), tmp_path / "server.log"
    server = start_server(data, log, port=port)
    api = httpx.Client(base_url=server.url)
    try:
        env = api.post("/environments", json={"name": "room", "marker_size_m": 0.25}).json()["id"]
        api.put(f"/environments/{env}/map", json=example_map(2)).raise_for_status()
        job = api.post(f"/environments/{env}/survey", files={"video": ("v.avi", room.video, "video/avi")},
                       data={"feature_tracks": "false"}, timeout=60).json()
        state = wait_for_job(api, job["id"], lambda state: state["progress"] > 0.05 or state["status"] in FINISHED,
                             timeout=60, poll=0.05)
        assert state["status"] == "running", state
        assert any((data / "uploads").iterdir())
        server.process.send_signal(signal.SIGKILL)  # no shutdown hook runs
        server.process.wait(10)
        time.sleep(3.0)  # the orphaned worker notices at its next progress report and stops
        server = start_server(data, log, port=port)
        failed = api.get(f"/jobs/{job['id']}").json()
        assert failed["status"] == "failed" and failed["stage"] == "interrupted", failed
        assert api.get(f"/environments/{env}/map").json() == example_map(2)
        assert not any((data / "uploads").iterdir())
        time.sleep(2.0)  # and nothing writes behind the new server's back
        assert api.get(f"/jobs/{job['id']}").json()["status"] == "failed"
        assert api.get(f"/environments/{env}/map").json() == example_map(2)
        # The restarted server surveys normally.
        again = api.post(f"/environments/{env}/survey", files={"video": ("v.avi", room.video, "video/avi")},
                         data={"feature_tracks": "false"}, timeout=60).json()
        state = wait_for_job(api, again["id"])
        assert state["status"] == "succeeded", state
        assert api.get(f"/environments/{env}/map").json()["survey_job_id"] == again["id"]
    finally:
        server.stop()
        api.close()
    lines = [json.loads(line) for line in log.read_text().splitlines() if line.startswith("{")]
    assert any(line.get("job_id") == again["id"] and line["msg"] == "job succeeded" for line in lines)
    assert any("request_id" in line and line["msg"] == "request" for line in lines)


def test_body_limits_refuse_before_reading(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path / "data", max_image_bytes=64 * 1024, max_upload_bytes=256 * 1024)
    with TestClient(create_app(settings)) as client:
        big = b"\xff\xd8" + bytes(2 * 1024 * 1024)
        reply = client.post("/detect", content=big, headers={"content-type": "image/jpeg"})
        assert reply.status_code == 413 and "limit" in reply.json()["detail"]

        def chunks():  # no Content-Length: counted as it streams
            for _ in range(64):
                yield bytes(64 * 1024)

        reply = client.post("/detect", content=chunks(), headers={"content-type": "image/jpeg"})
        assert reply.status_code == 413
        env = client.post("/environments", json={"name": "a", "marker_size_m": 0.2}).json()["id"]
        reply = client.post(f"/environments/{env}/survey", files={"video": ("v.mp4", bytes(512 * 1024), "video/mp4")})
        assert reply.status_code == 413
        reply = client.put(f"/environments/{env}/map", content=b"[" * (2 * 1024 * 1024),
                           headers={"content-type": "application/json"})
        assert reply.status_code == 413
        reply = client.post("/detect", content=b"x", headers={"content-length": "abc"})
        assert reply.status_code == 400
        assert client.get("/livez").status_code == 200


def test_job_queue_limit_is_429_and_stores_nothing(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path / "data", max_queued_jobs=1)
    with TestClient(create_app(settings)) as client:
        with client.app.state.sessionmaker() as session:  # a job that occupies the queue
            jobs.create(session, "count", CountParams())
        image = client.get("/markers/3.png?px=200").content
        reply = client.post("/classifiers", files=[("images", ("a.png", image, "image/png"))], data={"name": "x"})
        assert reply.status_code == 429 and "try again" in reply.json()["detail"]
        assert not any((settings.data_dir / "uploads").glob("*/*"))


def test_request_ids_are_echoed_and_logged(client: TestClient, caplog: pytest.LogCaptureFixture) -> None:
    logger = logging.getLogger("app")
    logger.addHandler(caplog.handler)
    try:
        with caplog.at_level(logging.INFO, logger="app"):
            reply = client.get("/environments", headers={"X-Request-ID": "abc-123"})
            assert reply.headers["x-request-id"] == "abc-123"
            hostile = client.get("/environments", headers={"X-Request-ID": "x\" injected"})
            assert hostile.headers["x-request-id"] != "x\" injected"
    finally:
        logger.removeHandler(caplog.handler)
    assert any(getattr(r, "fields", {}).get("route") == "/environments" for r in caplog.records)


def test_survey_and_several_tracking_clients_at_once_lose_nothing(client: TestClient, room: Room) -> None:
    tracked = client.post("/environments", json={"name": "tracked", "marker_size_m": 0.25}).json()["id"]
    true_map = room.scene.map_document(room.camera)
    client.put(f"/environments/{tracked}/map", json=true_map).raise_for_status()
    surveyed = client.post("/environments", json={"name": "surveyed", "marker_size_m": 0.25}).json()["id"]
    job = client.post(f"/environments/{surveyed}/survey", files={"video": ("v.avi", room.video, "video/avi")},
                      data={"feature_tracks": "false"}).json()

    results: dict[int, list[dict]] = {}
    failures: list[BaseException] = []

    def track(worker: int) -> None:
        try:
            replies = []
            with client.websocket_connect(f"/track?environment_id={tracked}") as ws:
                assert ws.receive_json()["type"] == "hello"
                for data in room.frames:
                    ws.send_bytes(data)
                    replies.append(ws.receive_json())
            results[worker] = replies
        except BaseException as exc:  # noqa: BLE001  (reported below)
            failures.append(exc)

    threads = [threading.Thread(target=track, args=(k,)) for k in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(240)
    assert not failures, failures
    for replies in results.values():
        assert [r["type"] for r in replies] == ["frame"] * len(room.frames)
        assert [r["seq"] for r in replies] == list(range(len(room.frames)))
        assert sum(r["dropped"] for r in replies) == 0
        errors = [np.linalg.norm(np.asarray(r["pose"]["position"]) - room.poses[r["seq"]].position)
                  for r in replies if r["pose"] is not None]
        assert len(errors) >= len(room.frames) // 2 and np.median(errors) < 0.02
    state = wait_for_job(client, job["id"])
    assert state["status"] == "succeeded", state
    assert client.get(f"/environments/{surveyed}/map").json()["survey_job_id"] == job["id"]
    assert client.get(f"/environments/{tracked}/map").json() == MapDocument.model_validate(true_map).model_dump(
        mode="json")
