"""The survey end to end through the API: a rendered room video in, a map out; the
job's progress, cancellation and failures; alignment to world coordinates."""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.core.geometry.alignment import similarity_from_points
from app.core.geometry.camera import Camera
from app.main import create_app
from app.settings import Settings
from app.sim.scenes import Scene, camera_walk, render_walk, room_scene
from tests.conftest import example_map, wait_for_job

ROOM = (5.0, 4.0, 2.6)
MARKER_M = 0.25


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> tuple[Scene, Camera, bytes]:
    """A small room with 24 cards filmed on a 90-frame calibration walk, as an MP4."""
    rng = np.random.default_rng(11)
    scene = room_scene(rng, ROOM, n_targets=24, marker_size_m=MARKER_M)
    camera = Camera(np.array([[700.0, 0, 319.5], [0, 700.0, 239.5], [0, 0, 1]]), np.array([-0.1, 0.0, 0, 0, 0]),
                    640, 480)
    poses = camera_walk(rng, ROOM, 90, kind="calibration")
    path = tmp_path_factory.mktemp("video") / "room.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (640, 480))
    for image, _ in render_walk(scene, camera, poses, rng, degradation="none"):
        writer.write(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image)
    writer.release()
    return scene, camera, path.read_bytes()


def _environment(client: TestClient) -> int:
    return client.post("/environments", json={"name": "room", "marker_size_m": MARKER_M}).json()["id"]


def _post_video(client: TestClient, env: int, data: bytes, **form: str):
    return client.post(f"/environments/{env}/survey", files={"video": ("room.mp4", data, "video/mp4")}, data=form)


def test_survey_of_a_rendered_room_gives_its_camera_and_discs(client: TestClient, room) -> None:
    scene, camera, video = room
    env = _environment(client)
    reply = _post_video(client, env, video, feature_tracks="false")  # the cards alone
    assert reply.status_code == 202, reply.text
    job = reply.json()
    assert reply.headers["location"] == f"/jobs/{job['id']}" and job["kind"] == "survey"
    body = wait_for_job(client, job["id"])
    assert body["status"] == "succeeded", body
    result = body["result"]
    assert result["feature_tracks"] is False and "tracking" not in result["stage_s"]
    assert result["n_registered"] >= 50 and result["rms_px"] < 0.5
    assert len(result["trajectory"]) == result["frames_used"]
    # The warnings about parts of the map name their cards (the web app shows them against the cards).
    for warning in result["card_warnings"]:
        assert warning["message"] in result["warnings"] and warning["target_ids"], warning

    document = client.get(f"/environments/{env}/map").json()
    assert document["frame"] == "survey" and document["survey_job_id"] == job["id"]
    focal = document["camera"]["K"][0][0]
    assert abs(focal - 700.0) / 700.0 < 0.01
    truth = {t.id: t.discs for t in scene.targets}
    surveyed = {t["id"]: np.asarray(t["discs"]) for t in document["targets"]}
    assert len(surveyed) >= 12 and set(surveyed) <= set(truth)
    ids = sorted(surveyed)
    src = np.concatenate([surveyed[i] for i in ids])
    dst = np.concatenate([truth[i] for i in ids])
    # Metric scale comes from the card size: a rigid alignment (no scale) must fit.
    rigid = similarity_from_points(src, dst, with_scale=False)
    error = np.linalg.norm(rigid.apply(src) - dst, axis=1)
    assert np.sqrt(np.mean(error**2)) < 0.01, error
    assert all(len(t["std_m"]) == 4 and t["n_views"] >= 3 for t in document["targets"])

    # Alignment: three discs with known world coordinates move the whole map.
    points = [{"target_id": i, "disc": d, "world": truth[i][d].tolist()} for i, d in ((ids[0], 0), (ids[1], 2),
                                                                                       (ids[2], 1), (ids[3], 3))]
    aligned = client.post(f"/environments/{env}/alignment", json={"points": points})
    assert aligned.status_code == 200, aligned.text
    out = aligned.json()
    assert out["map"]["frame"] == "world" and len(out["residuals"]) == 4 and out["rms_m"] < 0.01
    moved = {t["id"]: np.asarray(t["discs"]) for t in client.get(f"/environments/{env}/map").json()["targets"]}
    assert np.sqrt(np.mean([np.sum((moved[i] - truth[i]) ** 2, axis=1).mean() for i in ids])) < 0.01

    # The simpler option: one target is the origin, its plane z = 0.
    origin = client.post(f"/environments/{env}/alignment", json={"origin_target_id": ids[0]})
    assert origin.status_code == 200
    first = {t["id"]: np.asarray(t["discs"]) for t in origin.json()["map"]["targets"]}[ids[0]]
    np.testing.assert_allclose(first[:, 2], 0.0, atol=1e-4)  # its best-fit plane
    np.testing.assert_allclose(first.mean(axis=0), 0.0, atol=1e-6)
    assert np.linalg.norm(first[1] - first[0]) == pytest.approx(0.6 * MARKER_M, rel=0.02)


def test_survey_tracks_features_by_default_and_maps_the_room_from_the_video(client: TestClient, room) -> None:
    scene, _, video = room
    env = _environment(client)
    reply = _post_video(client, env, video)
    assert reply.status_code == 202, reply.text
    body = wait_for_job(client, reply.json()["id"])
    assert body["status"] == "succeeded", body
    result = body["result"]
    assert result["feature_tracks"] is True and result["n_registered"] >= 50 and "tracking" in result["stage_s"]
    assert "plain walls" not in {w["kind"] for w in result["card_warnings"]}  # the room's walls are textured
    truth = {t.id: t.discs for t in scene.targets}
    surveyed = {t["id"]: np.asarray(t["discs"]) for t in client.get(f"/environments/{env}/map").json()["targets"]}
    assert len(surveyed) >= 12 and set(surveyed) <= set(truth)
    ids = sorted(surveyed)
    src, dst = np.concatenate([surveyed[i] for i in ids]), np.concatenate([truth[i] for i in ids])
    rigid = similarity_from_points(src, dst, with_scale=False)
    assert np.sqrt(np.mean(np.sum((rigid.apply(src) - dst) ** 2, axis=1))) < 0.01


def test_alignment_refuses_bad_points(client: TestClient) -> None:
    env = _environment(client)
    assert client.post(f"/environments/{env}/alignment", json={"origin_target_id": 0}).status_code == 409
    client.put(f"/environments/{env}/map", json=example_map(3))
    collinear = [{"target_id": 0, "disc": 0, "world": [0, 0, 0]}, {"target_id": 1, "disc": 0, "world": [1, 0, 0]},
                 {"target_id": 2, "disc": 0, "world": [2, 0, 0]}]
    reply = client.post(f"/environments/{env}/alignment", json={"points": collinear})
    assert reply.status_code == 422 and "collinear" in reply.json()["detail"]
    reply = client.post(f"/environments/{env}/alignment",
                        json={"points": [{"target_id": 9, "disc": 0, "world": [0, 0, 0]}] * 3})
    assert reply.status_code == 422 and "not in the map" in reply.json()["detail"]
    assert client.post(f"/environments/{env}/alignment", json={}).status_code == 422
    assert client.get(f"/environments/{env}/map").json() == example_map(3)


def test_video_without_markers_fails_and_keeps_the_old_map(client: TestClient, tmp_path: Path) -> None:
    env = _environment(client)
    client.put(f"/environments/{env}/map", json=example_map(2))
    path = tmp_path / "plain.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (320, 240))
    rng = np.random.default_rng(0)
    for _ in range(12):
        writer.write(cv2.GaussianBlur(rng.integers(0, 255, (240, 320, 3), dtype=np.uint8), (0, 0), 3))
    writer.release()
    reply = client.post(f"/environments/{env}/survey", files={"video": ("plain.avi", path.read_bytes(), "video/avi")})
    assert reply.status_code == 202, reply.text
    body = wait_for_job(client, reply.json()["id"])
    assert body["status"] == "failed" and "no target" in body["error"]
    assert client.get(f"/environments/{env}/map").json() == example_map(2)


def test_cancelled_survey_keeps_the_old_map(client: TestClient, room) -> None:
    _, _, video = room
    env = _environment(client)
    client.put(f"/environments/{env}/map", json=example_map(2))
    job = _post_video(client, env, video).json()
    wait_for_job(client, job["id"], lambda state: state["status"] != "queued", timeout=60, poll=0.05)
    cancelled = client.delete(f"/jobs/{job['id']}").json()
    assert cancelled["status"] == "cancelled"  # the survey takes seconds; it was still running
    time.sleep(2.0)  # the worker notices at its next progress report and stops
    body = client.get(f"/jobs/{job['id']}").json()
    assert body["status"] == "cancelled" and body["result"] is None
    assert client.get(f"/environments/{env}/map").json() == example_map(2)


def test_bad_uploads_are_refused_and_leave_nothing(client: TestClient, settings, room) -> None:
    _, camera, video = room
    env = _environment(client)
    reply = _post_video(client, env, b"this is not a video at all, just text")
    assert reply.status_code == 415 and "container" in reply.json()["detail"]
    reply = _post_video(client, env, video[: len(video) // 20])  # truncated MP4
    assert reply.status_code == 422, reply.text
    assert client.post(f"/environments/{env}/survey").status_code == 422
    assert _post_video(client, 999, video).status_code == 404
    reply = _post_video(client, env, video, intrinsics="{not json")
    assert reply.status_code == 422 and "intrinsics" in reply.json()["detail"]
    reply = _post_video(client, env, video, intrinsics=json.dumps({"width": 640}))
    assert reply.status_code == 422 and "intrinsics" in reply.json()["detail"]
    # intrinsics of another shape than the video's are refused, not stretched onto it
    wrong_shape = {**camera.to_dict(), "height": camera.width}  # square, for a 4:3 video
    reply = _post_video(client, env, video, intrinsics=json.dumps(wrong_shape))
    assert reply.status_code == 422 and "shape" in reply.json()["detail"], reply.text
    reply = _post_video(client, env, video, max_frames="1")
    assert reply.status_code == 422
    # A readout longer than a frame (33 ms at 30 frames a second), and one with images
    # (no frame rate to count it in).
    reply = _post_video(client, env, video, readout_ms="40")
    assert reply.status_code == 422 and "readout_ms" in reply.json()["detail"], reply.text
    png = cv2.imencode(".png", np.full((240, 320), 200, np.uint8))[1].tobytes()
    reply = client.post(f"/environments/{env}/survey", files=[("images", ("a.png", png, "image/png"))],
                        data={"readout_ms": "20"})
    assert reply.status_code == 422 and "needs a video" in reply.json()["detail"], reply.text
    image = cv2.imencode(".png", np.full((240, 320), 200, np.uint8))[1].tobytes()
    reply = client.post(f"/environments/{env}/survey", files=[("images", ("a.png", image, "image/png")),
                                                               ("images", ("b.png", b"\x89PNG\r\n\x1a\nxx", "image/png"))])
    assert reply.status_code in (415, 422) and "images[1]" in reply.json()["detail"]
    uploads = settings.data_dir / "uploads"
    assert not uploads.exists() or not any(uploads.iterdir())
    assert client.get(f"/environments/{env}").json()["has_map"] is False


def test_a_survey_models_the_readout_it_is_given(client: TestClient, room) -> None:
    scene, _, video = room
    env = _environment(client)
    # The video's camera has a global shutter: a readout of 1 ms is a still camera to
    # within a few hundredths of a pixel, and the map must come out as without it.
    reply = _post_video(client, env, video, feature_tracks="false", readout_ms="1")
    assert reply.status_code == 202, reply.text
    body = wait_for_job(client, reply.json()["id"])
    assert body["status"] == "succeeded", body
    assert body["result"]["readout_ms"] == 1.0 and body["result"]["rms_px"] < 0.5
    document = client.get(f"/environments/{env}/map").json()
    assert abs(document["camera"]["K"][0][0] - 700.0) / 700.0 < 0.01
    truth = {t.id: t.discs for t in scene.targets}
    surveyed = {t["id"]: np.asarray(t["discs"]) for t in document["targets"]}
    src = np.concatenate([surveyed[i] for i in sorted(surveyed)])
    dst = np.concatenate([truth[i] for i in sorted(surveyed)])
    rigid = similarity_from_points(src, dst, with_scale=False)
    assert np.sqrt(np.mean(np.linalg.norm(rigid.apply(src) - dst, axis=1) ** 2)) < 0.01


def test_more_images_than_the_limit_get_its_422_not_the_form_parsers_400(tmp_path: Path) -> None:
    # The form parser's default (1000 files) used to answer first, with a bare 400.
    settings = Settings(data_dir=tmp_path / "data", max_survey_images=1000)
    image = cv2.imencode(".png", np.full((24, 32), 200, np.uint8))[1].tobytes()
    with TestClient(create_app(settings)) as client:
        env = _environment(client)
        files = [("images", (f"{k}.png", image, "image/png")) for k in range(1001)]
        reply = client.post(f"/environments/{env}/survey", files=files)
        assert reply.status_code == 422 and "at most 1000 images" in reply.json()["detail"], reply.text[:200]
        uploads = settings.data_dir / "uploads"
        assert not uploads.exists() or not any(uploads.iterdir())


def test_survey_from_a_set_of_images(client: TestClient, room, tmp_path: Path) -> None:
    scene, _, video = room
    path = tmp_path / "room.mp4"
    path.write_bytes(video)
    capture = cv2.VideoCapture(str(path))
    files = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        if len(files) < 45 and int(capture.get(cv2.CAP_PROP_POS_FRAMES)) % 2 == 0:
            files.append(("images", (f"f{len(files):03d}.jpg", cv2.imencode(".jpg", frame)[1].tobytes(), "image/jpeg")))
    capture.release()
    env = _environment(client)
    reply = client.post(f"/environments/{env}/survey", files=files, data={"feature_tracks": "false"})
    assert reply.status_code == 202, reply.text
    body = wait_for_job(client, reply.json()["id"])
    assert body["status"] == "succeeded", body
    assert body["result"]["frames_used"] == 45 and body["result"]["n_registered"] >= 30
    document = client.get(f"/environments/{env}/map").json()
    assert abs(document["camera"]["K"][0][0] - 700.0) / 700.0 < 0.01
    assert {t["id"] for t in document["targets"]} <= {t.id for t in scene.targets}
