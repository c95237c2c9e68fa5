"""An open /track connection follows its environment's map: a map replaced through the
API while the connection is open reaches it within a few ``map_poll_s`` as a new hello
(``reason: map_changed``), and the replies after it are posed against the new map; an
environment deleted meanwhile closes the connection with the refusal a new one gets. The
web app's tracking page takes the new hello in its stride."""

from __future__ import annotations

import copy
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.testclient import WebSocketTestSession
from starlette.websockets import WebSocketDisconnect

from app.main import create_app
from app.settings import Settings
from app.sim.camera_feed import read_frame_index
from tests.conftest import running_server
from tests.routers.conftest import Pan
from tests.test_browser import CHROMIUM, StampedWalk, _camera_browser, _watched_page
from tests.test_browser import stamped_walk  # noqa: F401 (a fixture)

#: How often the connections of these tests look for a new map, seconds.
MAP_POLL_S = 0.2
#: The new map: the old one moved this far (metres), so that the same frame's camera
#: position moves as far.
SHIFT = np.array([1.0, -0.5, 0.25])


def shifted_map(document: dict, shift: np.ndarray) -> dict:
    """`document` with every disc moved by `shift` (a map in another frame)."""
    moved = copy.deepcopy(document)
    for target in moved["targets"]:
        target["discs"] = (np.asarray(target["discs"]) + shift).tolist()
    return moved


@pytest.fixture
def served(tmp_path: Path, pan: Pan) -> Iterator[tuple[TestClient, int, dict]]:
    """A service whose connections look for a new map every MAP_POLL_S, an environment
    with the pan's map, and that map."""
    scene, camera, _, _, _ = pan
    settings = Settings(data_dir=tmp_path / "data", map_poll_s=MAP_POLL_S, max_track_fps=1000)
    with TestClient(create_app(settings)) as client:
        env = client.post("/environments", json={"name": "pan", "marker_size_m": 0.2}).json()
        document = scene.map_document(camera)
        assert client.put(f"/environments/{env['id']}/map", json=document).status_code == 200
        yield client, int(env["id"]), document


def _frame_reply(ws: WebSocketTestSession, frame: bytes, hellos: list[dict]) -> dict:
    """Send `frame` and return its reply; hellos that come before it go to `hellos`."""
    ws.send_bytes(frame)
    while (message := ws.receive_json())["type"] == "hello":
        hellos.append(message)
    assert message["type"] == "frame", message
    return message


def test_an_open_connection_switches_to_a_replaced_map_and_says_so(served: tuple[TestClient, int, dict],
                                                                   pan: Pan) -> None:
    client, environment, document = served
    _, _, poses, frames, _ = pan
    with client.websocket_connect(f"/track?environment_id={environment}") as ws:
        hello = ws.receive_json()
        assert hello["type"] == "hello" and hello["reason"] == "connected"
        hellos: list[dict] = []
        before = [_frame_reply(ws, frame, hellos) for frame in frames[:3]]
        assert all(r["pose"] is not None for r in before) and hellos == []
        assert np.linalg.norm(np.array(before[0]["pose"]["position"]) - poses[0].position) < 0.01
        assert before[1]["scan_reason"] == "regions"  # the connection tracks: its poses predict regions

        new_map = shifted_map(document, SHIFT)
        new_map["targets"] = new_map["targets"][:-1]  # one card fewer: the hello says so
        assert client.put(f"/environments/{environment}/map", json=new_map).status_code == 200
        changed = time.monotonic()
        while True:
            assert time.monotonic() - changed < 10 * MAP_POLL_S, "no hello after the map changed"
            reply = _frame_reply(ws, frames[0], hellos)
            if hellos:
                break
            # Before the hello, replies are posed against the old map.
            assert np.linalg.norm(np.array(reply["pose"]["position"]) - poses[0].position) < 0.01
            time.sleep(MAP_POLL_S / 4)
        [again] = hellos
        assert again["type"] == "hello" and again["reason"] == "map_changed"
        assert again["environment_id"] == environment and again["targets"] == len(new_map["targets"])
        # After it: the new map, tracked from scratch (no regions from the old map's poses).
        after = [reply] + [_frame_reply(ws, frame, hellos) for frame in frames[1:3]]
        assert len(hellos) == 1
        assert after[0]["scan_reason"] == "first" and after[1]["scan_reason"] == "regions"
        for reply, pose in zip(after, poses[:3], strict=True):
            assert reply["pose"] is not None
            assert np.linalg.norm(np.array(reply["pose"]["position"]) - (pose.position + SHIFT)) < 0.01
        # An unchanged map sends no further hello.
        time.sleep(3 * MAP_POLL_S)
        _frame_reply(ws, frames[0], hellos)
        assert len(hellos) == 1


def test_a_map_change_keeps_the_connections_config(served: tuple[TestClient, int, dict], pan: Pan) -> None:
    client, environment, document = served
    _, _, poses, frames, _ = pan
    with client.websocket_connect(f"/track?environment_id={environment}") as ws:
        assert ws.receive_json()["reason"] == "connected"
        ws.send_text('{"type": "config", "regions": false, "frame": "opengl"}')
        assert ws.receive_json()["type"] == "config"
        assert client.put(f"/environments/{environment}/map", json=shifted_map(document, SHIFT)).status_code == 200
        hellos: list[dict] = []
        deadline = time.monotonic() + 10 * MAP_POLL_S
        while not hellos:
            assert time.monotonic() < deadline, "no hello after the map changed"
            _frame_reply(ws, frames[0], hellos)
            time.sleep(MAP_POLL_S / 4)
        reply = _frame_reply(ws, frames[1], hellos)
        assert reply["scan_reason"] == "off"  # regions still off, as configured
        assert reply["pose"]["frame_pose"]["frame"] == "opengl"
        assert np.linalg.norm(np.array(reply["pose"]["position"]) - (poses[1].position + SHIFT)) < 0.01


def test_deleting_the_environment_closes_its_open_connections(served: tuple[TestClient, int, dict],
                                                              pan: Pan) -> None:
    client, environment, _ = served
    frames = pan[3]
    with client.websocket_connect(f"/track?environment_id={environment}") as ws:
        assert ws.receive_json()["type"] == "hello"
        ws.send_bytes(frames[0])
        assert ws.receive_json()["type"] == "frame"
        assert client.delete(f"/environments/{environment}").status_code == 204
        started = time.monotonic()
        refusal = ws.receive_json()  # the connection idles meanwhile: nothing else comes
        assert refusal["type"] == "error" and refusal["code"] == "unknown_environment", refusal
        assert time.monotonic() - started < 10 * MAP_POLL_S
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
        assert closed.value.code == 1008


@pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium: apt-get install chromium (.ci/run does)")
def test_the_tracking_page_goes_on_in_lock_step_through_a_map_change(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, playwright: Any,  # noqa: F811
        stamped_walk: StampedWalk) -> None:  # noqa: F811
    monkeypatch.setenv("FIDOTRACK_MAP_POLL_S", str(MAP_POLL_S))
    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        env = httpx.post(f"{server.url}/environments", json={"name": "bench room", "marker_size_m": 0.2}).json()
        httpx.put(f"{server.url}/environments/{env['id']}/map", json=stamped_walk.map_document).raise_for_status()
        browser = _camera_browser(playwright, stamped_walk.y4m)
        try:
            page, errors = _watched_page(browser, permissions=["camera"])
            sent: list[bytes] = []
            page.on("websocket", lambda ws: ws.on(
                "framesent", lambda payload: sent.append(payload) if isinstance(payload, bytes) else None))
            page.goto(f"{server.url}/app/#/environments/{env['id']}/track")
            page.click("#start")
            page.wait_for_function("() => window.fidotrack.track.replies.length >= 20", timeout=90_000)
            httpx.put(f"{server.url}/environments/{env['id']}/map",
                      json=shifted_map(stamped_walk.map_document, SHIFT)).raise_for_status()
            page.wait_for_function("() => window.fidotrack.track.mapChanges === 1", timeout=20_000)
            changed_at = page.evaluate("window.fidotrack.track.replies.length")
            # (Frames where the walk shows few cards have no pose: 40 give enough that do.)
            page.wait_for_function(f"() => window.fidotrack.track.replies.length >= {changed_at + 40}", timeout=60_000)
            page.click("#start")  # stop
            state = page.evaluate("window.fidotrack.track")
            notice = page.locator("#notice").inner_text()
        finally:
            browser.close()
    assert errors == [] and state["errors"] == []
    assert state["hello"]["reason"] == "map_changed" and state["mapChanges"] == 1
    assert "The map changed" in notice
    replies = state["replies"]
    # Still lock-step: one frame out at a time, every frame answered, none dropped.
    assert [r["seq"] for r in replies] == list(range(len(replies)))
    assert all(r["dropped"] == 0 for r in replies)
    # Each frame sent carries its walk index: the poses before the change are in the old
    # map, those after it in the new one.
    indices = [read_frame_index(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)) for data in sent]

    def median_error_m(chosen: list[dict], shift: np.ndarray) -> float:
        posed = [r for r in chosen if r["pose"] is not None]
        assert len(posed) >= 10
        return float(np.median([np.linalg.norm(np.asarray(r["pose"]["position"])
                                               - (stamped_walk.truth[indices[r["seq"]]].position + shift))
                                for r in posed]))

    assert median_error_m(replies[:20], np.zeros(3)) < 0.02
    assert median_error_m(replies[changed_at:], SHIFT) < 0.02
