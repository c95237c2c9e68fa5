"""Requests from pages of other origins: no state-changing request and no /track
connection from a page the service does not serve (or the allowed_origins setting does
not name), and nothing a cross-site form or a ``no-cors`` fetch can send (a body that is
not JSON, no body) changes anything either."""

from __future__ import annotations

import io
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from app.main import create_app
from app.settings import Settings
from tests.conftest import example_map
from tests.routers.conftest import Pan, stream_frames

#: The origin of the service's own pages as TestClient reaches it.
OWN = "http://testserver"
#: A page somewhere else (another port of the same machine is another origin).
FOREIGN = "http://127.0.0.1:9000"


def _environment_with_two_maps(client: TestClient) -> int:
    env = client.post("/environments", json={"name": "studio", "marker_size_m": 0.15}).json()["id"]
    assert client.put(f"/environments/{env}/map", json=example_map(2)).status_code == 200
    assert client.put(f"/environments/{env}/map", json=example_map(3)).status_code == 200
    return int(env)


def _state(client: TestClient, env: int) -> tuple[list, dict, list]:
    return (client.get("/environments").json(), client.get(f"/environments/{env}/map").json(),
            client.get(f"/environments/{env}/map/versions").json())


@pytest.mark.parametrize("origin_headers", [
    {"origin": FOREIGN},
    {"origin": "https://testserver"},  # the same host over another scheme is another origin
    {"origin": "null"},  # a sandboxed frame or a local file
    {"sec-fetch-site": "cross-site"},  # a browser's request from another site that names no origin
], ids=["other-port", "other-scheme", "null", "sec-fetch-site"])
def test_state_changing_requests_from_other_origins_are_refused_and_change_nothing(
        client: TestClient, origin_headers: dict[str, str]) -> None:
    env = _environment_with_two_maps(client)
    before = _state(client, env)
    refused = [
        client.post("/environments", json={"name": "evil", "marker_size_m": 0.1}, headers=origin_headers),
        client.patch(f"/environments/{env}", json={"name": "evil"}, headers=origin_headers),
        client.put(f"/environments/{env}/map", json=example_map(1), headers=origin_headers),
        client.post(f"/environments/{env}/map/restore", json={}, headers=origin_headers),
        client.put(f"/environments/{env}/freed", json={"host": "127.0.0.1", "port": 40000}, headers=origin_headers),
        client.post(f"/environments/{env}/survey", files={"video": ("v.mp4", io.BytesIO(b"x" * 100), "video/mp4")},
                    headers=origin_headers),
        client.post("/keys", json={"name": "evil", "scopes": ["admin"]}, headers=origin_headers),
        client.delete(f"/environments/{env}", headers=origin_headers),
    ]
    for reply in refused:
        assert reply.status_code == 403, (reply.request.method, reply.request.url, reply.text)
        assert "allowed" in reply.json()["detail"] or "Origin" in reply.json()["detail"]
    assert _state(client, env) == before
    # Reading is not refused: another origin's page cannot read the reply (no CORS headers).
    assert client.get(f"/environments/{env}/map", headers=origin_headers).status_code == 200
    # The service's own pages, and clients that send no Origin (curl, the Python client), may.
    for headers in ({"origin": OWN}, {}, {"sec-fetch-site": "same-origin"}):
        assert client.patch(f"/environments/{env}", json={"name": "renamed"}, headers=headers).status_code == 200
        assert client.post(f"/environments/{env}/map/restore", json={}, headers=headers).status_code == 200


def test_a_refusal_comes_before_the_body_is_read(client: TestClient) -> None:
    env = _environment_with_two_maps(client)
    sent: list[bytes] = []

    def body() -> Iterator[bytes]:
        for chunk in (b'{"targets"', b": []}"):
            sent.append(chunk)
            yield chunk

    reply = client.put(f"/environments/{env}/map", content=body(),
                       headers={"origin": FOREIGN, "content-type": "application/json"})
    assert reply.status_code == 403 and sent == []


def test_the_setting_allows_other_origins(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path / "data", allowed_origins="https://studio.example:443, http://127.0.0.1:9000")
    assert settings.allowed_origins == ("https://studio.example", "http://127.0.0.1:9000")
    with TestClient(create_app(settings)) as client:
        for origin in ("https://studio.example", FOREIGN, OWN):
            assert client.post("/environments", json={"name": origin, "marker_size_m": 0.1},
                               headers={"origin": origin}).status_code == 201
        assert client.post("/environments", json={"name": "x", "marker_size_m": 0.1},
                           headers={"origin": "http://127.0.0.1:9001"}).status_code == 403
    with TestClient(create_app(Settings(data_dir=tmp_path / "data", allowed_origins="*"))) as client:
        assert client.post("/environments", json={"name": "any", "marker_size_m": 0.1},
                           headers={"origin": "http://anywhere.example"}).status_code == 201
    with pytest.raises(ValueError, match="not an origin"):
        Settings(data_dir=tmp_path / "data", allowed_origins="https://studio.example/path")


def test_bodies_a_cross_site_form_can_send_are_refused(client: TestClient) -> None:
    env = _environment_with_two_maps(client)
    before = _state(client, env)
    # No body, as a no-cors fetch or a form without fields sends it: the restore needs JSON.
    assert client.post(f"/environments/{env}/map/restore").status_code == 415
    for content_type in ("text/plain", "application/x-www-form-urlencoded", "multipart/form-data; boundary=x"):
        restore = client.post(f"/environments/{env}/map/restore", content=b"{}", headers={"content-type": content_type})
        assert restore.status_code == 415, restore.text
        assert "application/json" in restore.json()["detail"]
        created = client.post("/environments", content=b'{"name": "evil", "marker_size_m": 0.1}',
                              headers={"content-type": content_type})
        assert created.status_code == 415, created.text
    assert client.put(f"/environments/{env}/map", content=b"{}", headers={}).status_code == 415
    assert _state(client, env) == before
    # As JSON: {} restores the map the last change replaced, {"version": n} that version.
    restored = client.post(f"/environments/{env}/map/restore", json={})
    assert restored.status_code == 200 and len(restored.json()["targets"]) == 2
    assert client.post(f"/environments/{env}/map/restore", content=b"", headers={"content-type": "application/json"}
                       ).status_code == 422


def test_track_from_another_origin_is_closed_with_1008_before_any_frame(client: TestClient, pan_environment: int,
                                                                        pan: Pan) -> None:
    frames = pan[3][:2]
    url = f"/track?environment_id={pan_environment}"
    for origin in (FOREIGN, "null"):
        with pytest.raises(WebSocketDisconnect) as closed:
            with client.websocket_connect(url, headers={"origin": origin}) as ws:
                ws.receive_json()  # today's service says hello first; a refused connection sends nothing
                ws.send_bytes(frames[0])
                ws.receive_json()
        assert closed.value.code == 1008
        assert "is not allowed" in closed.value.reason
    with client.websocket_connect(url, headers={"origin": OWN}) as ws:
        replies = stream_frames(ws, frames)
    assert [r["type"] for r in replies] == ["frame", "frame"]
    with client.websocket_connect(url) as ws:  # no Origin: the Python client, the websockets library
        assert len(stream_frames(ws, frames[:1])) == 1
