"""Shared fixtures and helpers: every test gets its own data directory and SQLite
database; real server processes, free ports and job waits are made here once."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Collection, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings

#: Job statuses after which a job no longer changes.
FINISHED = frozenset({"succeeded", "failed", "cancelled"})
#: ``fidotrack serve`` of this environment.
FIDOTRACK_SERVE = [str(Path(sys.executable).parent / "fidotrack"), "serve"]


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    return Settings(data_dir=tmp_path / "data")


@pytest.fixture
def client(settings: Settings) -> Iterator[TestClient]:
    with TestClient(create_app(settings)) as test_client:
        # On a cold kernel cache the app answers while it compiles: wait as a client would.
        deadline = time.monotonic() + 300
        while test_client.get("/readyz").status_code != 200 and time.monotonic() < deadline:
            time.sleep(0.2)
        yield test_client


def example_map(n_targets: int = 2) -> dict:
    """A small valid map document."""
    return {
        "frame": "survey",
        "units": "m",
        "camera": {
            "width": 640,
            "height": 480,
            "K": [[820.0, 0.0, 320.0], [0.0, 820.0, 240.0], [0.0, 0.0, 1.0]],
            "dist": [-0.12, 0.01, 0.0, 0.0, 0.0],
        },
        "targets": [
            {
                "id": i,
                "discs": [[i + 0.0, 0.0, 2.0], [i + 0.1, 0.0, 2.0], [i + 0.1, 0.1, 2.0], [i + 0.0, 0.1, 2.0]],
                "std_m": [0.001, 0.001, 0.001, 0.001],
                "n_views": 12,
            }
            for i in range(n_targets)
        ],
        "rms_px": 0.21,
        "survey_job_id": None,
    }


def wait_for_job(client: httpx.Client, job_id: str,
                 until: Collection[str] | Callable[[dict[str, Any]], bool] = FINISHED,
                 timeout: float = 240.0, poll: float = 0.2) -> dict[str, Any]:
    """The job as ``GET /jobs/{id}`` shows it once its status is in `until` (or `until`
    says so of it); fails the test after `timeout` seconds. `client` is a TestClient or
    an httpx client of a real server."""
    done = until if callable(until) else (lambda job: job["status"] in until)
    deadline = time.monotonic() + timeout
    while not done(job := client.get(f"/jobs/{job_id}").json()):
        assert time.monotonic() < deadline, job
        time.sleep(poll)
    return job


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Server:
    """A real server process on 127.0.0.1."""

    process: subprocess.Popen[bytes]
    url: str
    log: Path

    def stop(self) -> None:
        self.process.terminate()
        self.process.wait(30)


def start_server(data_dir: Path, log: Path, *, port: int | None = None,
                 command: Sequence[str] = FIDOTRACK_SERVE) -> Server:
    """Start `command` (``fidotrack serve`` unless told; it must take its port from
    ``FIDOTRACK_PORT`` or its own arguments) on `data_dir`, its output appended to `log`,
    and wait until ``/readyz`` says ready."""
    port = port or free_port()
    env = {**os.environ, "FIDOTRACK_DATA_DIR": str(data_dir), "FIDOTRACK_PORT": str(port)}
    with log.open("ab") as out:
        process = subprocess.Popen(list(command), env=env, stdout=out, stderr=subprocess.STDOUT)
    # With FIDOTRACK_TLS_CERTFILE set the server speaks https (the tests' certificates are self-signed).
    scheme = "https" if env.get("FIDOTRACK_TLS_CERTFILE") else "http"
    server = Server(process, f"{scheme}://127.0.0.1:{port}", log)
    deadline = time.monotonic() + 60
    while True:
        try:
            if httpx.get(f"{server.url}/readyz", timeout=1, verify=False).status_code == 200:
                return server
        except httpx.TransportError:
            pass
        if process.poll() is not None or time.monotonic() > deadline:
            server.stop()
            pytest.fail(f"the server did not become ready:\n{log.read_text()}")
        time.sleep(0.2)


@contextmanager
def running_server(data_dir: Path, log: Path, *, port: int | None = None,
                   command: Sequence[str] = FIDOTRACK_SERVE) -> Iterator[Server]:
    """`start_server`, stopped when the block ends."""
    server = start_server(data_dir, log, port=port, command=command)
    try:
        yield server
    finally:
        server.stop()
