"""PostgreSQL as the service's database: its URLs, its driver, a real server process on
it, and inputs that PostgreSQL cannot store, answered as on SQLite.

The API tests run on PostgreSQL too (``tests/conftest.py``); these are what they do not
cover."""

from __future__ import annotations

import sys
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError
from sqlalchemy import text
from starlette.websockets import WebSocketDisconnect

from app.db import head_revisions, make_engine
from app.main import create_app
from app.settings import Settings
from tests.conftest import PostgresCluster, example_map, running_server

#: An id no PostgreSQL row can have (id columns are 32-bit there) but SQLite's could.
BEYOND_32_BITS = 2**31


@pytest.mark.parametrize("given", [
    "postgresql://fido:secret@db.example:5432/fidotrack",
    "postgres://fido:secret@db.example:5432/fidotrack",
    "postgresql+psycopg://fido:secret@db.example:5432/fidotrack",
])
def test_postgresql_urls_mean_psycopg_3(given: str) -> None:
    settings = Settings(database_url=given)
    assert settings.resolved_database_url == "postgresql+psycopg://fido:secret@db.example:5432/fidotrack"


def test_a_missing_driver_is_named_with_its_extra_and_the_password_is_not_shown(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # None in sys.modules makes `import psycopg` fail as on a machine without it.
    monkeypatch.setitem(sys.modules, "psycopg", None)
    with pytest.raises(ValidationError) as refused:
        Settings(database_url="postgresql://fido:secret@db.example/fidotrack")
    message = str(refused.value)
    assert "driver of postgresql+psycopg URLs is not installed" in message
    assert "pip install 'fidotrack[postgres]'" in message
    assert "secret" not in message


@pytest.mark.parametrize("given", ["not a url", "nosuchdb://host/name"])
def test_an_unknown_database_url_is_refused_saying_so(given: str) -> None:
    with pytest.raises(ValidationError, match="not a database URL that SQLAlchemy knows"):
        Settings(database_url=given)


def test_served_on_postgresql_it_is_ready_and_keeps_its_data_across_a_restart(
        postgres_cluster: PostgresCluster, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    name = postgres_cluster.new_database(migrated=False)
    url = postgres_cluster.url(name)
    monkeypatch.setenv("FIDOTRACK_DATABASE_URL", url)
    log = tmp_path / "server.log"
    with running_server(tmp_path / "first", log) as server:
        ready = httpx.get(f"{server.url}/readyz").json()
        assert ready["status"] == "ready" and ready["schema_revision"] == sorted(head_revisions())
        kept = httpx.post(f"{server.url}/environments", json={"name": "studio", "marker_size_m": 0.15}).json()
        assert httpx.put(f"{server.url}/environments/{kept['id']}/map", json=example_map(3)).status_code == 200
        gone = httpx.post(f"{server.url}/environments", json={"name": "gone", "marker_size_m": 0.2}).json()
        assert httpx.delete(f"{server.url}/environments/{gone['id']}").status_code == 204
    # Another data directory: whatever comes back can only have come from PostgreSQL.
    with running_server(tmp_path / "second", log) as server:
        assert httpx.get(f"{server.url}/readyz").status_code == 200
        listed = httpx.get(f"{server.url}/environments").json()
        assert [(e["id"], e["name"], e["has_map"]) for e in listed] == [(kept["id"], "studio", True)]
        assert len(httpx.get(f"{server.url}/environments/{kept['id']}/map").json()["targets"]) == 3
        # The id of the deleted environment is not handed out again after the restart.
        new = httpx.post(f"{server.url}/environments", json={"name": "new", "marker_size_m": 0.2}).json()
        assert new["id"] > gone["id"] > kept["id"]
    assert not (tmp_path / "first" / "fidotrack.db").exists()
    engine = make_engine(url)
    with engine.connect() as connection:
        assert connection.execute(text("SELECT count(*) FROM environments")).scalar_one() == 2
    engine.dispose()
    postgres_cluster.drop_database(name)


def test_inputs_postgresql_cannot_store_are_answered_as_on_sqlite(client: TestClient) -> None:
    # Ids beyond 32 bits and text with NUL: PostgreSQL refuses them in a query (an error,
    # a 500), SQLite just finds nothing. Both engines must answer 404 or 422.
    env = client.post("/environments", json={"name": "room", "marker_size_m": 0.2}).json()
    assert client.put(f"/environments/{env['id']}/map", json=example_map(2)).status_code == 200
    for method, path in [("GET", f"/environments/{BEYOND_32_BITS}"), ("DELETE", f"/environments/{BEYOND_32_BITS}"),
                         ("GET", f"/environments/{BEYOND_32_BITS}/map"),
                         ("GET", f"/environments/{BEYOND_32_BITS}/freed"),
                         ("GET", f"/classifiers/{BEYOND_32_BITS}"), ("DELETE", f"/classifiers/{BEYOND_32_BITS}"),
                         ("GET", "/jobs/abc%00def"), ("DELETE", "/jobs/abc%00def")]:
        reply = client.request(method, path)
        assert reply.status_code == 404, (method, path, reply.text)
    reply = client.patch(f"/environments/{BEYOND_32_BITS}", json={"name": "x"})
    assert reply.status_code == 404, reply.text
    reply = client.put(f"/environments/{BEYOND_32_BITS}/map", json=example_map(1))
    assert reply.status_code == 404, reply.text
    reply = client.post(f"/environments/{env['id']}/map/restore", json={"version": BEYOND_32_BITS})
    assert reply.status_code == 404, reply.text
    reply = client.get("/jobs", params={"environment_id": BEYOND_32_BITS})
    assert reply.status_code == 200 and reply.json() == []
    reply = client.post("/environments", json={"name": "a", "marker_size_m": 0.2, "classifier_id": BEYOND_32_BITS})
    assert reply.status_code == 422 and "classifier" in reply.text
    reply = client.patch(f"/environments/{env['id']}", json={"classifier_id": BEYOND_32_BITS})
    assert reply.status_code == 422 and "classifier" in reply.text
    for job_id in ("job\x00", "job\nforged log line"):
        reply = client.put(f"/environments/{env['id']}/map", json={**example_map(2), "survey_job_id": job_id})
        assert reply.status_code == 422 and "survey_job_id" in reply.text and "control" in reply.text
    # The refused map left the stored one as it was.
    assert client.get(f"/environments/{env['id']}/map").json()["survey_job_id"] is None


def test_a_key_postgresql_cannot_store_is_refused_as_any_wrong_key(settings: Settings) -> None:
    with TestClient(create_app(settings.model_copy(update={"api_keys": True}))) as client:
        # Browsers' WebSockets pass the key in the query, where a NUL can be sent.
        for key in ["ft_ab%00cd_secret", "ft_%00_%00"]:
            with pytest.raises(WebSocketDisconnect) as closed:
                with client.websocket_connect(f"/track?environment_id=1&api_key={key}") as ws:
                    ws.receive_json()
            assert closed.value.code == 1008, key
