"""Revoking an API key closes the /track connections opened with it within a few seconds,
whichever way it is revoked (``DELETE /keys/{id}``, ``fidotrack keys revoke`` in another
process, the database itself), while connections with other keys go on."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import update
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

from app.db import make_engine, make_sessionmaker, utcnow
from app.models import ApiKey
from app.settings import Settings
from tests.conftest import Server, example_map, running_server

FIDOTRACK = str(Path(sys.executable).with_name("fidotrack"))
#: A revocation must close the connection within this (the server checks every 2 s).
CLOSE_WITHIN_S = 10.0


def _cli(data_dir: Path, *args: str) -> str:
    env = {**os.environ, "FIDOTRACK_API_KEYS": "true", "FIDOTRACK_DATA_DIR": str(data_dir)}
    done = subprocess.run([FIDOTRACK, *args], env=env, capture_output=True, text=True, timeout=120, check=True)
    return done.stdout.strip()


@pytest.fixture
def server(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[Server, str]]:
    """A real server with API keys on, and an admin key made with ``fidotrack keys create``."""
    data_dir = tmp_path / "data"
    admin = _cli(data_dir, "keys", "create", "--name", "admin", "--scopes", "admin").splitlines()[-1]
    monkeypatch.setenv("FIDOTRACK_API_KEYS", "true")
    with running_server(data_dir, tmp_path / "server.log") as running:
        yield running, admin


def _open(stack: ExitStack, url: str, key: str) -> ClientConnection:
    ws = stack.enter_context(connect(url, additional_headers={"X-API-Key": key}, open_timeout=30))
    hello = json.loads(ws.recv(timeout=30))
    assert hello["type"] == "hello", hello
    return ws


def _closed_for_revocation(ws: ClientConnection) -> float:
    """Seconds until the server refuses `ws` with ``key_revoked`` and closes it with 1008."""
    started = time.monotonic()
    try:
        message = json.loads(ws.recv(timeout=CLOSE_WITHIN_S))
    except TimeoutError:
        pytest.fail(f"the connection was still open {CLOSE_WITHIN_S:g} s after its key was revoked")
    assert message["type"] == "error" and message["code"] == "key_revoked", message
    with pytest.raises(ConnectionClosed) as closed:
        ws.recv(timeout=CLOSE_WITHIN_S)
    assert closed.value.rcvd is not None and closed.value.rcvd.code == 1008
    return time.monotonic() - started


def _still_open(ws: ClientConnection) -> None:
    ws.send(json.dumps({"type": "config"}))
    assert json.loads(ws.recv(timeout=30))["type"] == "config"


def test_revoking_a_key_closes_its_track_connections(server: tuple[Server, str], tmp_path: Path) -> None:
    running, admin = server
    http = httpx.Client(base_url=running.url, headers={"X-API-Key": admin}, timeout=30)
    environment = http.post("/environments", json={"name": "lab", "marker_size_m": 0.2}).json()["id"]
    assert http.put(f"/environments/{environment}/map", json=example_map()).status_code == 200
    created: dict[str, Any] = {name: http.post("/keys", json={"name": name, "scopes": ["track"]}).json()
                               for name in ("api", "cli", "db", "kept")}
    url = running.url.replace("http://", "ws://") + f"/track?environment_id={environment}"
    with ExitStack() as stack:
        stack.callback(http.close)
        connections = {name: _open(stack, url, key["key"]) for name, key in created.items()}
        # Through the API.
        assert http.delete(f"/keys/{created['api']['id']}").status_code == 200
        _closed_for_revocation(connections["api"])
        _still_open(connections["cli"])
        # Through another process: `fidotrack keys revoke` on the same database.
        _cli(tmp_path / "data", "keys", "revoke", str(created["cli"]["id"]))
        _closed_for_revocation(connections["cli"])
        _still_open(connections["db"])
        # In the database itself.
        engine = make_engine(Settings(data_dir=tmp_path / "data").resolved_database_url)
        with make_sessionmaker(engine)() as session:
            session.execute(update(ApiKey).where(ApiKey.id == created["db"]["id"]).values(revoked_at=utcnow()))
            session.commit()
        engine.dispose()
        _closed_for_revocation(connections["db"])
        # The connection whose key holds was never disturbed.
        _still_open(connections["kept"])
