"""``uvicorn app.main:app`` with ``FIDOTRACK_*`` set, and ``fidotrack serve``, are complete
deployments: a real server process answers /readyz and keeps its data across restarts."""

from __future__ import annotations

import sys
from pathlib import Path

import httpx

from tests.conftest import free_port, running_server


def test_fidotrack_serve_then_uvicorn_on_same_data(tmp_path: Path) -> None:
    data, log, port = tmp_path / "data", tmp_path / "server.log", free_port()
    with running_server(data, log, port=port) as server:
        ready = httpx.get(f"{server.url}/readyz").json()
        assert ready["status"] == "ready"
        created = httpx.post(f"{server.url}/environments", json={"name": "lab", "marker_size_m": 0.15})
        assert created.status_code == 201
    assert (data / "fidotrack.db").exists()
    uvicorn = [sys.executable, "-m", "uvicorn", "app.main:app", "--port", str(port)]
    with running_server(data, log, port=port, command=uvicorn) as server:
        assert [e["name"] for e in httpx.get(f"{server.url}/environments").json()] == ["lab"]
