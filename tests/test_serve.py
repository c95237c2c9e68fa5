"""``uvicorn app.main:app`` with ``FIDOTRACK_*`` set, and ``fidotrack serve``, are complete
deployments: a real server process answers /readyz and keeps its data across restarts."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def _server(command: list[str], data_dir: Path, port: int) -> Iterator[str]:
    env = {**os.environ, "FIDOTRACK_DATA_DIR": str(data_dir), "FIDOTRACK_PORT": str(port)}
    process = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{base}/readyz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert process.poll() is None, process.stdout.read().decode() if process.stdout else ""
            assert time.monotonic() < deadline, "server did not become ready"
            time.sleep(0.2)
        yield base
    finally:
        process.terminate()
        process.wait(30)


def test_fidotrack_serve_then_uvicorn_on_same_data(tmp_path: Path) -> None:
    port = _free_port()
    serve = [str(Path(sys.executable).parent / "fidotrack"), "serve"]
    with _server(serve, tmp_path / "data", port) as base:
        ready = httpx.get(f"{base}/readyz").json()
        assert ready["status"] == "ready"
        created = httpx.post(f"{base}/environments", json={"name": "lab", "marker_size_m": 0.15})
        assert created.status_code == 201
    assert (tmp_path / "data" / "fidotrack.db").exists()
    uvicorn = [sys.executable, "-m", "uvicorn", "app.main:app", "--port", str(port)]
    with _server(uvicorn, tmp_path / "data", port) as base:
        assert [e["name"] for e in httpx.get(f"{base}/environments").json()] == ["lab"]
