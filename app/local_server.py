"""A fidotrack server on this machine, as a process of its own: what the tests, the
benchmarks, the scripts and ``fidotrack demo`` start when they need a real server.

    from app.local_server import running_server

    with running_server(Path("scratch/data"), settings={"FIDOTRACK_MAX_TRACK_FPS": "1000"}) as server:
        httpx.post(f"{server.url}/environments", json={"name": "lab", "marker_size_m": 0.2})

`start_server` runs ``fidotrack serve`` (the console script beside this interpreter,
else ``python -m app.cli serve``) on a free port of 127.0.0.1 and a data directory, with
this process's environment plus the given ``FIDOTRACK_*`` settings, its output appended to
a log file, and returns once ``/readyz`` answers 200; when the process exits first or
the time is up it raises `ServerNotReady` with the end of the log. `running_server` stops
it when its block ends. It imports nothing of the service: the server is another process.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

__all__ = [
    "FINISHED",
    "LocalServer",
    "ServerNotReady",
    "example_map",
    "fidotrack_command",
    "free_port",
    "launch_server",
    "running_server",
    "start_server",
    "wait_for_job",
]

#: Job statuses after which a job no longer changes.
FINISHED = frozenset({"succeeded", "failed", "cancelled"})
#: Seconds `start_server` waits for ``/readyz`` unless told: a machine's first start
#: compiles the detector's kernels (10-30 s), on a busy machine more.
READY_TIMEOUT_S = 120.0
#: Seconds `LocalServer.stop` waits for the process to end after asking it to, before it kills it.
STOP_TIMEOUT_S = 30.0
#: Lines of the server's log that `ServerNotReady` quotes.
LOG_TAIL_LINES = 60


class ServerNotReady(RuntimeError):
    """The server exited, or did not answer ``/readyz`` with 200 in time: the message
    says which, and quotes the end of its log (also in `log_tail`)."""

    def __init__(self, message: str, log_tail: str) -> None:
        super().__init__(f"{message}; its log ends:\n{log_tail}" if log_tail else f"{message}; its log is empty")
        self.log_tail = log_tail


def fidotrack_command() -> list[str]:
    """The ``fidotrack`` command of this Python environment.

    Returns
    -------
    list of str
        The console script beside the interpreter when it is installed there, else
        ``python -m app.cli`` with this interpreter.
    """
    script = Path(sys.executable).parent / "fidotrack"
    return [str(script)] if script.exists() else [sys.executable, "-m", "app.cli"]


def free_port() -> int:
    """A TCP port of 127.0.0.1 that nothing listens on now.

    Returns
    -------
    int
        The port (the system's choice; another process may take it before it is used).
    """
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def wait_for_job(client: httpx.Client, job_id: str | int,
                 until: Collection[str] | Callable[[dict[str, Any]], bool] = FINISHED,
                 timeout: float = 240.0, poll: float = 0.2) -> dict[str, Any]:
    """Poll ``GET /jobs/{job_id}`` until the job is where `until` says.

    Parameters
    ----------
    client : httpx.Client
        A client whose base URL is the service's: an httpx client of a real server, or a
        ``TestClient`` of the application.
    job_id : str or int
        The job.
    until : collection of str or callable
        The statuses to wait for (default: `FINISHED`), or a test of the job's JSON.
    timeout : float
        Seconds to wait at most.
    poll : float
        Seconds between two reads.

    Returns
    -------
    dict
        The job as ``GET /jobs/{job_id}`` showed it last.

    Raises
    ------
    TimeoutError
        When `timeout` passed first; the message carries the job's last state.
    """
    done = until if callable(until) else (lambda job: job["status"] in until)
    deadline = time.monotonic() + timeout
    while not done(job := client.get(f"/jobs/{job_id}").json()):
        if time.monotonic() > deadline:
            raise TimeoutError(f"job {job_id} not there after {timeout:g} s: {job}")
        time.sleep(poll)
    return job


def _log_tail(log: Path, lines: int = LOG_TAIL_LINES) -> str:
    try:
        text = log.read_text(errors="replace")
    except OSError:
        return ""
    return "\n".join(text.splitlines()[-lines:])


@dataclass
class LocalServer:
    """A server process on 127.0.0.1: its process, base URL, data directory and log file."""

    process: subprocess.Popen[bytes]
    url: str
    data_dir: Path
    log: Path

    @property
    def port(self) -> int:
        """The TCP port it listens on."""
        return int(self.url.rsplit(":", 1)[1])

    @property
    def ws_url(self) -> str:
        """The base URL of its WebSocket routes (``ws://``, or ``wss://`` under TLS)."""
        return "ws" + self.url.removeprefix("http")

    def wait_until_ready(self, timeout: float = READY_TIMEOUT_S, ready_in_a_row: int = 1) -> None:
        """Wait until ``/readyz`` answers 200 `ready_in_a_row` times in a row.

        Parameters
        ----------
        timeout : float
            Seconds to wait at most.
        ready_in_a_row : int
            Answers of 200 in a row that count as ready: with several server processes
            (``--workers``) each answers some, and one that is ready says nothing of the
            others.

        Raises
        ------
        ServerNotReady
            When the process exits first or `timeout` passes (the process is left as it is).
        """
        deadline = time.monotonic() + timeout
        in_a_row = 0
        with httpx.Client(timeout=2, verify=False) as http:  # verify: the certificate may be self-signed
            while in_a_row < ready_in_a_row:
                try:
                    ready = http.get(f"{self.url}/readyz").status_code == 200
                except httpx.TransportError:
                    ready = False
                in_a_row = in_a_row + 1 if ready else 0
                if in_a_row >= ready_in_a_row:
                    return
                if (code := self.process.poll()) is not None:
                    raise ServerNotReady(f"the server for {self.data_dir} exited with code {code} before it was "
                                         "ready", _log_tail(self.log))
                if time.monotonic() > deadline:
                    raise ServerNotReady(f"the server on {self.url} was not ready within {timeout:g} s",
                                         _log_tail(self.log))
                time.sleep(0.05 if ready else 0.2)

    def wait_for_job(self, job_id: str | int,
                     until: Collection[str] | Callable[[dict[str, Any]], bool] = FINISHED,
                     timeout: float = 240.0, poll: float = 0.2) -> dict[str, Any]:
        """Poll ``GET /jobs/{job_id}`` on this server until the job is where `until` says.

        Parameters
        ----------
        job_id : str or int
            The job.
        until : collection of str or callable
            The statuses to wait for (default: `FINISHED`), or a test of the job's JSON.
        timeout : float
            Seconds to wait at most.
        poll : float
            Seconds between two reads.

        Returns
        -------
        dict
            The job as ``GET /jobs/{job_id}`` showed it last.

        Raises
        ------
        TimeoutError
            When `timeout` passed first.
        """
        with httpx.Client(base_url=self.url, timeout=30, verify=False) as http:
            return wait_for_job(http, job_id, until, timeout=timeout, poll=poll)

    def stop(self, timeout: float = STOP_TIMEOUT_S) -> None:
        """Ask the process to end (SIGTERM), wait for it, and kill it if it is still there.

        Parameters
        ----------
        timeout : float
            Seconds to wait before killing it.
        """
        self.process.terminate()
        try:
            self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


def _serve_command(command: Sequence[str] | None, workers: int | None) -> list[str]:
    if command is None:
        return [*fidotrack_command(), "serve", *(["--workers", str(workers)] if workers is not None else [])]
    if workers is not None:
        raise ValueError("workers goes with the default command only: give --workers in `command` instead")
    return list(command)


def launch_server(data_dir: Path, *, port: int | None = None, settings: Mapping[str, str] | None = None,
                  command: Sequence[str] | None = None, log: Path | None = None,
                  workers: int | None = None) -> LocalServer:
    """Start a server process and return at once, without waiting for it to be ready.

    Parameters
    ----------
    data_dir : Path
        Its ``FIDOTRACK_DATA_DIR``.
    port : int, optional
        Its ``FIDOTRACK_PORT``; default: a free one.
    settings : mapping of str to str, optional
        Environment variables (``FIDOTRACK_*`` settings and any other) set for the server
        over this process's environment; ``FIDOTRACK_DATA_DIR`` and ``FIDOTRACK_PORT`` are
        `data_dir`'s and `port`'s whatever they say. An empty ``FIDOTRACK_DATABASE_URL``
        means the default, a SQLite file in `data_dir`.
    command : sequence of str, optional
        The server's command line; default: ``fidotrack serve`` (`fidotrack_command`). It
        must take its port from ``FIDOTRACK_PORT`` or from its own arguments.
    log : Path, optional
        The file its output (stdout and stderr) is appended to; default:
        ``server.log`` in `data_dir`.
    workers : int, optional
        ``--workers`` of the default command: that many server processes.

    Returns
    -------
    LocalServer
        The process, its URL (``https`` when ``FIDOTRACK_TLS_CERTFILE`` is set), data
        directory and log.
    """
    port = port or free_port()
    env = {**os.environ, **(settings or {}), "FIDOTRACK_DATA_DIR": str(data_dir), "FIDOTRACK_PORT": str(port)}
    if log is None:
        data_dir.mkdir(parents=True, exist_ok=True)
        log = data_dir / "server.log"
    argv = _serve_command(command, workers)
    with log.open("ab") as out:
        process = subprocess.Popen(argv, env=env, stdout=out, stderr=subprocess.STDOUT)
    scheme = "https" if env.get("FIDOTRACK_TLS_CERTFILE") else "http"
    return LocalServer(process, f"{scheme}://127.0.0.1:{port}", data_dir, log)


def start_server(data_dir: Path, *, port: int | None = None, settings: Mapping[str, str] | None = None,
                 command: Sequence[str] | None = None, log: Path | None = None, workers: int | None = None,
                 ready_in_a_row: int = 1, timeout: float = READY_TIMEOUT_S) -> LocalServer:
    """Start a server process and wait until ``/readyz`` answers 200.

    Parameters
    ----------
    data_dir : Path
        Its ``FIDOTRACK_DATA_DIR``.
    port : int, optional
        Its ``FIDOTRACK_PORT``; default: a free one.
    settings : mapping of str to str, optional
        Environment variables set for the server over this process's environment
        (`launch_server`).
    command : sequence of str, optional
        The server's command line; default: ``fidotrack serve``.
    log : Path, optional
        The file its output is appended to; default: ``server.log`` in `data_dir`.
    workers : int, optional
        ``--workers`` of the default command.
    ready_in_a_row : int
        Answers of 200 in a row that count as ready (`LocalServer.wait_until_ready`).
    timeout : float
        Seconds to wait at most.

    Returns
    -------
    LocalServer
        The ready server.

    Raises
    ------
    ServerNotReady
        When the process exits first or `timeout` passes; the process is stopped.
    """
    server = launch_server(data_dir, port=port, settings=settings, command=command, log=log, workers=workers)
    try:
        server.wait_until_ready(timeout, ready_in_a_row)
    except BaseException:
        server.stop()
        raise
    return server


@contextmanager
def running_server(data_dir: Path, *, port: int | None = None, settings: Mapping[str, str] | None = None,
                   command: Sequence[str] | None = None, log: Path | None = None, workers: int | None = None,
                   ready_in_a_row: int = 1, timeout: float = READY_TIMEOUT_S) -> Iterator[LocalServer]:
    """`start_server`, stopped when the block ends.

    Parameters
    ----------
    data_dir : Path
        Its ``FIDOTRACK_DATA_DIR``.
    port, settings, command, log, workers, ready_in_a_row, timeout
        As `start_server` takes them.

    Yields
    ------
    LocalServer
        The ready server.
    """
    server = start_server(data_dir, port=port, settings=settings, command=command, log=log, workers=workers,
                          ready_in_a_row=ready_in_a_row, timeout=timeout)
    try:
        yield server
    finally:
        server.stop()


def example_map(n_targets: int = 2) -> dict[str, Any]:
    """A small valid map document, to give a local server's environment a map.

    Parameters
    ----------
    n_targets : int
        Its targets: ids 0 to ``n_targets - 1``, 0.1 m squares 2 m away, one beside the other.

    Returns
    -------
    dict
        The document, as ``PUT /environments/{id}/map`` takes it.
    """
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
