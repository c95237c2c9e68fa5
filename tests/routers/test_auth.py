"""Optional API keys: off by default; when on, every route (but the health probes)
refuses a missing, wrong or revoked key and a key without the route's scope."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from app.cli import main as cli
from app.middleware import OPEN_PATHS, required_scope
from app.main import create_app
from app.models import ApiKey
from app.services import keys
from app.settings import Settings
from tests.conftest import example_map


@pytest.fixture
def secured(tmp_path: Path) -> Iterator[tuple[TestClient, dict[str, str]]]:
    # (Without the per-address request rate: these tests send every route at once.)
    settings = Settings(data_dir=tmp_path / "data", api_keys=True, request_rate_per_address=0)
    with TestClient(create_app(settings)) as client:
        with client.app.state.sessionmaker() as session:
            made = {scope: keys.create(session, f"{scope} key", [scope]).key for scope in keys.SCOPES}
        yield client, made


def _h(key: str) -> dict[str, str]:
    return {"X-API-Key": key}


def _concrete(path: str) -> str:
    return re.sub(r"\{[^}]+\}", "1", path)


def test_every_route_refuses_missing_and_wrong_keys(secured) -> None:
    client, made = secured
    wrong = made["admin"][:-4] + "AAAA"
    checked = 0
    for path, operations in client.app.openapi()["paths"].items():
        if path in OPEN_PATHS:
            continue
        for method in operations:
            for headers in ({}, _h(wrong), _h("nonsense"), {"Authorization": "Bearer " + wrong}):
                reply = client.request(method.upper(), _concrete(path), headers=headers)
                assert reply.status_code == 401, (method, path, headers, reply.text)
                assert "API key" in reply.json()["detail"]
            checked += 1
    for query in ("", "&api_key=" + wrong):
        with pytest.raises(WebSocketDisconnect) as closed:
            with client.websocket_connect(f"/track?environment_id=1{query}") as ws:
                ws.receive_json()
        assert closed.value.code == 1008
    assert checked >= 20
    for path in OPEN_PATHS:
        assert client.get(path).status_code == 200


def test_scopes_decide_what_a_key_may_do(secured) -> None:
    client, made = secured
    admin, read, track = _h(made["admin"]), _h(made["read"]), _h(made["track"])
    env = client.post("/environments", json={"name": "a", "marker_size_m": 0.2}, headers=admin)
    assert env.status_code == 201
    env_id = env.json()["id"]
    assert client.put(f"/environments/{env_id}/map", json=example_map(2), headers=admin).status_code == 200

    assert client.get("/environments", headers=read).status_code == 200
    assert client.get(f"/environments/{env_id}/map", headers=read).status_code == 200
    reply = client.post("/environments", json={"name": "b", "marker_size_m": 0.2}, headers=read)
    assert reply.status_code == 403 and "admin" in reply.json()["detail"]
    assert client.delete(f"/environments/{env_id}", headers=track).status_code == 403
    assert client.get("/environments", headers=track).status_code == 403
    assert client.get("/keys", headers=read).status_code == 403

    png = client.get("/markers/3.png?px=200", headers=read).content
    assert client.post("/detect", content=png, headers={**track, "content-type": "image/png"}).status_code == 200
    assert client.post("/detect", content=png, headers={**read, "content-type": "image/png"}).status_code == 403
    with client.websocket_connect(f"/track?environment_id={env_id}&api_key={made['track']}") as ws:
        assert ws.receive_json()["type"] == "hello"
    with client.websocket_connect(f"/track?environment_id={env_id}", headers=track) as ws:
        assert ws.receive_json()["type"] == "hello"
    with pytest.raises(WebSocketDisconnect) as closed:
        with client.websocket_connect(f"/track?environment_id={env_id}", headers=read) as ws:
            ws.receive_json()
    assert closed.value.code == 1008


def test_keys_are_stored_hashed_created_by_admins_and_revocable(secured) -> None:
    client, made = secured
    admin = _h(made["admin"])
    created = client.post("/keys", json={"name": "headset", "scopes": ["track"]}, headers=admin)
    assert created.status_code == 201
    secret = created.json()["key"]
    listed = client.get("/keys", headers=admin).json()
    assert secret not in str(listed) and all("key" not in row for row in listed)
    with client.app.state.sessionmaker() as session:
        for row in session.query(ApiKey):
            assert secret not in (row.key_sha256, row.prefix, row.name)
    png = client.get("/markers/3.png?px=200", headers=admin).content
    detect = {"X-API-Key": secret, "content-type": "image/png"}
    assert client.post("/detect", content=png, headers=detect).status_code == 200
    assert client.delete(f"/keys/{created.json()['id']}", headers=admin).json()["revoked_at"] is not None
    assert client.post("/detect", content=png, headers=detect).status_code == 401
    assert client.post("/keys", json={"name": "x", "scopes": ["root"]}, headers=admin).status_code == 422


def test_keys_are_off_by_default(client: TestClient) -> None:
    assert client.get("/environments").status_code == 200
    assert required_scope("GET", "/livez") is None and required_scope("POST", "/detect") == "track"


def test_cli_creates_a_key_that_the_service_accepts(tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.setenv("FIDOTRACK_DATA_DIR", str(tmp_path / "data"))
    assert cli(["keys", "create", "--name", "ops", "--scopes", "read"]) == 0
    secret = capsys.readouterr().out.strip()
    assert secret.startswith("ft_")
    assert cli(["keys", "create", "--name", "bad", "--scopes", "root"]) == 2
    with TestClient(create_app(Settings(data_dir=tmp_path / "data", api_keys=True))) as client:
        assert client.get("/environments", headers=_h(secret)).status_code == 200
        assert client.get("/environments").status_code == 401
    assert cli(["keys", "list"]) == 0
    assert secret not in capsys.readouterr().out


def test_a_key_revoked_by_another_process_is_refused_within_seconds(secured) -> None:
    # The server remembers a verified key for a moment (one database lookup per key, not
    # per request); a revocation made elsewhere (the CLI, another server) reaches it then.
    import time

    client, made = secured
    read = _h(made["read"])
    assert client.get("/environments", headers=read).status_code == 200
    with client.app.state.sessionmaker() as session:
        row = next(k for k in keys.list_all(session) if k.name == "read key")
        keys.revoke(session, row.id)
    deadline = time.monotonic() + keys.VERIFIED_TTL_S + 1.0
    while client.get("/environments", headers=read).status_code == 200:
        assert time.monotonic() < deadline, "a revoked key was still accepted"
        time.sleep(0.1)
    assert client.get("/environments", headers=read).status_code == 401
