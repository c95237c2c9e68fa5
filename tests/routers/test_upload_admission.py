"""Uploads are admitted before their bodies are read: a full job queue (429) and uploads
in flight over the server's limit (503) are refused while the client is still sending,
with Retry-After and the connection closed; N uploads racing for the last job slot get
one read; an admitted upload is written once, straight into its job's upload folder
(nothing in the temporary directory)."""

from __future__ import annotations

import os
import select
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import httpx
import numpy as np
import psutil
import pytest
from pydantic import BaseModel

from app.db import make_engine, make_sessionmaker
from app.services.jobs import store
from app.settings import Settings
from tests.conftest import Server, running_server

BOUNDARY = "fidotrackTestBoundary"
#: What the tests' clients send of a body before they wait for the reply.
FIRST_CHUNK = 64 * 1024
#: How long a reply that comes before the body may take (the server answers at once).
REPLY_WAIT_S = 20.0
#: The first bytes of an AVI: enough for its container to be recognised.
AVI_HEAD = b"RIFF\0\0\0\0AVI LIST"


class _Idle(BaseModel):
    """Parameters of the jobs that fill the queue: nothing runs them."""

    note: str = "fills a job slot"


@contextmanager
def engine_stand_in() -> Iterator[str]:
    """The address of a listening socket, named as the jobs' scheduler: the server's reaper
    sees something listen there and leaves the jobs queued."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        yield f"tcp://127.0.0.1:{listener.getsockname()[1]}"


def queue_jobs(data_dir: Path, engine: str, count: int) -> None:
    """Store `count` queued jobs in the server's database (it has migrated it)."""
    db = make_engine(Settings(data_dir=data_dir).resolved_database_url)
    try:
        with make_sessionmaker(db)() as session:
            for _ in range(count):
                store.create(session, "survey", _Idle(), engine=engine)
    finally:
        db.dispose()


def jobs_stored(server: Server) -> int:
    return len(httpx.get(f"{server.url}/jobs", timeout=30).json())


def part_head(field: str, filename: str, content_type: str) -> bytes:
    return (f"--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"{field}\"; filename=\"{filename}\"\r\n"
            f"Content-Type: {content_type}\r\n\r\n").encode()


def part_tail() -> bytes:
    return f"\r\n--{BOUNDARY}--\r\n".encode()


def start_upload(server: Server, path: str, length: int | None, first: bytes) -> socket.socket:
    """A connection that has sent an upload's headers (Content-Length `length`, or chunked
    when None) and `first` bytes of its body."""
    port = int(server.url.rsplit(":", 1)[1])
    conn = socket.create_connection(("127.0.0.1", port), timeout=REPLY_WAIT_S)
    framing = f"Content-Length: {length}" if length is not None else "Transfer-Encoding: chunked"
    conn.sendall((f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n{framing}\r\n"
                  f"Content-Type: multipart/form-data; boundary={BOUNDARY}\r\n\r\n").encode())
    conn.sendall(first if length is not None else f"{len(first):x}\r\n".encode() + first + b"\r\n")
    return conn


def read_reply(conn: socket.socket, timeout: float = REPLY_WAIT_S) -> tuple[int, dict[str, str], bytes] | None:
    """Status, headers and body of the reply on `conn`; None when none came in `timeout`."""
    conn.settimeout(timeout)
    data = b""
    try:
        while b"\r\n\r\n" not in data:
            chunk = conn.recv(65536)
            if not chunk:
                break
            data += chunk
    except TimeoutError:
        return None
    if b"\r\n\r\n" not in data:
        return None
    head, body = data.split(b"\r\n\r\n", 1)
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, v in (line.split(":", 1) for line in lines[1:])}
    try:
        while len(body) < int(headers.get("content-length", 0)):
            chunk = conn.recv(65536)
            if not chunk:
                break
            body += chunk
    except TimeoutError:
        pass
    return int(lines[0].split()[1]), headers, body


def files_under(directory: Path) -> list[Path]:
    return sorted(p for p in directory.rglob("*") if p.is_file()) if directory.exists() else []


def bytes_under(directory: Path) -> int:
    return sum(p.stat().st_size for p in files_under(directory))


def temp_bytes(server: Server, directory: Path) -> int:
    """Bytes of the files under `directory` that the server's processes hold open, deleted
    ones too (a spooled upload is a temporary file unlinked at once)."""
    root = psutil.Process(server.process.pid)
    total = 0
    for process in (root, *root.children(recursive=True)):
        for fd in Path(f"/proc/{process.pid}/fd").iterdir():
            try:
                if os.readlink(fd).startswith(str(directory)):
                    total += fd.stat().st_size
            except OSError:
                pass  # closed meanwhile
    return total


def noise_video(path: Path, frames: int = 24) -> bytes:
    """An MJPEG AVI of noise (incompressible: about 0.2 MB a frame)."""
    rng = np.random.default_rng(3)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25, (640, 480))
    for _ in range(frames):
        writer.write(rng.integers(0, 256, (480, 640, 3), dtype=np.uint8))
    writer.release()
    return path.read_bytes()


@pytest.fixture
def server_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The server's temporary directory, empty (TMPDIR)."""
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setenv("TMPDIR", str(tmp))
    return tmp


def test_a_full_queue_refuses_an_upload_before_reading_its_body(
        tmp_path: Path, server_env: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FIDOTRACK_MAX_QUEUED_JOBS", "2")
    data_dir = tmp_path / "data"
    with running_server(data_dir, tmp_path / "server.log") as server, engine_stand_in() as engine:
        env = httpx.post(f"{server.url}/environments", json={"name": "hall", "marker_size_m": 0.2}, timeout=30).json()["id"]
        queue_jobs(data_dir, engine, 2)
        assert jobs_stored(server) == 2
        declared = 50 * 1024 * 1024
        first = part_head("video", "v.avi", "video/avi") + b"\0" * FIRST_CHUNK
        for path in (f"/environments/{env}/survey", "/classifiers"):
            conn = start_upload(server, path, declared, first)
            started = time.monotonic()
            with conn:
                reply = read_reply(conn)
            # The reply came while the client had sent 64 KiB of the 50 MiB it declared.
            assert reply is not None, f"{path}: no reply before the body was sent"
            status, headers, body = reply
            assert status == 429, body
            assert b"queued or running" in body and int(headers["retry-after"]) > 0
            assert headers.get("connection") == "close"
            assert time.monotonic() - started < REPLY_WAIT_S
        # Nothing was written: no upload folder, no temporary file, no job.
        assert files_under(data_dir / "uploads") == [] and files_under(server_env) == []
        assert jobs_stored(server) == 2


def test_uploads_racing_for_the_last_slot_get_one_read(
        tmp_path: Path, server_env: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FIDOTRACK_MAX_QUEUED_JOBS", "2")
    data_dir = tmp_path / "data"
    with running_server(data_dir, tmp_path / "server.log") as server, engine_stand_in() as engine:
        env = httpx.post(f"{server.url}/environments", json={"name": "hall", "marker_size_m": 0.2}, timeout=30).json()["id"]
        queue_jobs(data_dir, engine, 1)
        first = part_head("video", "v.avi", "video/avi") + AVI_HEAD + b"\0" * FIRST_CHUNK
        conns = [start_upload(server, f"/environments/{env}/survey", 8 * 1024 * 1024, first) for _ in range(5)]
        try:
            replies: dict[int, tuple[int, dict[str, str], bytes] | None] = {}
            deadline = time.monotonic() + REPLY_WAIT_S
            while len(replies) < len(conns) - 1 and time.monotonic() < deadline:
                readable, _, _ = select.select([c for c in conns if c.fileno() not in replies], [], [], 0.5)
                for conn in readable:
                    replies[conn.fileno()] = read_reply(conn, 5.0)
            statuses = sorted(r[0] for r in replies.values() if r is not None)
            assert statuses == [429] * 4, statuses
            # The fifth is being read: its body, alone, is arriving in its job's folder.
            time.sleep(0.5)
            assert len([c for c in conns if c.fileno() not in replies]) == 1
            assert len(list((data_dir / "uploads").iterdir())) == 1
        finally:
            for conn in conns:
                conn.close()
        # The one read is dropped when its client goes: nothing stays, no job was added.
        deadline = time.monotonic() + 30
        while files_under(data_dir / "uploads") and time.monotonic() < deadline:
            time.sleep(0.2)
        assert files_under(data_dir / "uploads") == [] and files_under(server_env) == []
        assert jobs_stored(server) == 1


def test_an_upload_is_written_once_into_its_jobs_folder(
        tmp_path: Path, server_env: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    data_dir = tmp_path / "data"
    video = noise_video(tmp_path / "noise.avi")
    assert len(video) > 3 * 1024 * 1024  # past the 1 MiB a form parser would keep in memory
    body = part_head("video", "noise.avi", "video/avi") + video + part_tail()
    with running_server(data_dir, tmp_path / "server.log") as server:
        env = httpx.post(f"{server.url}/environments", json={"name": "hall", "marker_size_m": 0.2}, timeout=30).json()["id"]
        before = files_under(server_env)
        half = len(body) // 2
        conn = start_upload(server, f"/environments/{env}/survey", len(body), body[:half])
        with conn:
            # Half-way: the video is arriving in its folder, and nowhere else.
            deadline = time.monotonic() + REPLY_WAIT_S
            while bytes_under(data_dir / "uploads") < half // 2 and time.monotonic() < deadline:
                time.sleep(0.1)
            arriving = files_under(data_dir / "uploads")
            assert files_under(server_env) == before and temp_bytes(server, server_env) == 0
            assert [p.name for p in arriving] == ["video"], arriving
            conn.sendall(body[half:])
            reply = read_reply(conn, 120.0)
        assert reply is not None
        status, headers, text = reply
        assert status == 202, text
        job_id = headers["location"].rsplit("/", 1)[1]
        assert arriving[0].parent.name == job_id


def test_uploads_in_flight_over_the_limit_are_refused_before_reading(
        tmp_path: Path, server_env: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FIDOTRACK_MAX_UPLOAD_BYTES_IN_FLIGHT", str(3 * 1024 * 1024))
    data_dir = tmp_path / "data"
    with running_server(data_dir, tmp_path / "server.log") as server:
        env = httpx.post(f"{server.url}/environments", json={"name": "hall", "marker_size_m": 0.2}, timeout=30).json()["id"]
        path = f"/environments/{env}/survey"
        first = part_head("video", "v.avi", "video/avi") + AVI_HEAD + b"\0" * FIRST_CHUNK
        # The first, alone, is let in: its 2 MiB are being read.
        held = start_upload(server, path, 2 * 1024 * 1024, first)
        with held:
            assert read_reply(held, 1.0) is None
            # 2 + 2 MiB would pass the 3 MiB in flight: refused from its Content-Length.
            with start_upload(server, path, 2 * 1024 * 1024, first) as conn:
                reply = read_reply(conn)
            assert reply is not None, "no reply before the body was sent"
            status, headers, body = reply
            assert status == 503 and int(headers["retry-after"]) > 0, body
            assert headers.get("connection") == "close"
            # Without Content-Length it is counted as it arrives: refused once it passes.
            with start_upload(server, path, None, first) as conn:
                chunk = b"\0" * (256 * 1024)
                reply = None
                for _ in range(8):
                    try:
                        conn.sendall(f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n")
                    except OSError:
                        break
                    if (reply := read_reply(conn, 0.5)) is not None:
                        break
                reply = reply or read_reply(conn)
            assert reply is not None and reply[0] == 503, reply
        assert jobs_stored(server) == 0
