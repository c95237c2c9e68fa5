"""/track on HD frames: a stream whose discs are large is decoded at half size, and its
replies (targets, pose, the connection's next regions) are in the frame's own pixels,
as close to the truth as the whole frame's."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.core.geometry.camera import Camera, Pose
from app.sim import degrade, scenes
from tests.routers.conftest import stream_frames

#: A scene of three cards, an HD camera, a short walk and its frames (JPEG).
Walk = tuple[scenes.Scene, Camera, list[Pose], list[bytes]]


@pytest.fixture(scope="module")
def walk() -> Walk:
    rng = np.random.default_rng(7)
    camera = Camera.pinhole(1640.0, 1280, 720, dist=[-0.1, 0.0, 0.0, 0.0, 0.0])
    scene = scenes.single_frame_scene(rng, camera, n_targets=3, distance_m=(1.4, 2.0), tilt_deg=(0, 30))
    poses = [Pose.look_at([x, 0.02 * x, 0.0], [0.0, 0.0, 1.7], up=(0.0, -1.0, 0.0))
             for x in np.linspace(-0.06, 0.06, 7)]
    frames = []
    for pose in poses:
        image, _ = scenes.render_frame(scene, camera, pose, rng, degrade.PRESETS["none"].sample(rng))
        frames.append(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes())
    return scene, camera, poses, frames


def _stream(client: TestClient, environment: int, frames: list[bytes], regions: bool) -> list[dict]:
    with client.websocket_connect(f"/track?environment_id={environment}") as ws:
        return stream_frames(ws, frames, {"regions": regions})


def test_hd_stream_is_decoded_smaller_and_answers_in_the_frames_pixels(client: TestClient, walk: Walk) -> None:
    scene, camera, poses, frames = walk
    env = client.post("/environments", json={"name": "hd", "marker_size_m": 0.2}).json()
    assert client.put(f"/environments/{env['id']}/map", json=scene.map_document(camera)).status_code == 200
    fast = _stream(client, env["id"], frames, regions=True)
    whole = _stream(client, env["id"], frames, regions=False)
    assert all(r["type"] == "frame" and r["pose"] is not None for r in fast + whole)
    # The first frame: no pose to predict from, decoded whole; then regions, at half size.
    assert "reduction" not in fast[0]["timing_ms"] and fast[0]["scan"] == "full"
    assert all(r["timing_ms"].get("reduction") == 2 and r["scan"] == "regions" for r in fast[2:])
    assert all("reduction" not in r["timing_ms"] for r in whole)
    for seq, (a, b) in enumerate(zip(fast, whole, strict=True)):
        assert (a["width"], a["height"]) == (1280, 720)
        # Targets in the frame's pixels: the same discs as the whole frame's, to a fraction of a pixel.
        discs_a = {t["id"]: np.array(t["discs"]) for t in a["targets"]}
        discs_b = {t["id"]: np.array(t["discs"]) for t in b["targets"]}
        assert discs_a.keys() == discs_b.keys() and len(discs_a) == 3
        for k in discs_a:
            assert np.abs(discs_a[k] - discs_b[k]).max() < 0.5
        # The pose's pixel quantities in the frame's pixels too.
        assert a["pose"]["focal_px"] == pytest.approx(camera.fx)
        assert a["pose"]["reprojection_rms_px"] < 0.5
        truth = poses[seq].position
        assert np.linalg.norm(np.array(a["pose"]["position"]) - truth) < 0.005
        assert np.linalg.norm(np.array(b["pose"]["position"]) - truth) < 0.005


def test_lone_images_are_decoded_whole(client: TestClient, walk: Walk) -> None:
    scene, camera, _, frames = walk
    env = client.post("/environments", json={"name": "hd lone", "marker_size_m": 0.2}).json()
    assert client.put(f"/environments/{env['id']}/map", json=scene.map_document(camera)).status_code == 200
    reply = client.post(f"/environments/{env['id']}/locate", content=frames[0],
                        headers={"content-type": "image/jpeg"}).json()
    assert reply["width"] == 1280 and "reduction" not in reply["timing_ms"] and len(reply["targets"]) == 3
