"""``uvicorn app.main:app`` with ``FIDOTRACK_*`` set, and ``fidotrack serve``, are complete
deployments: a real server process answers /readyz and keeps its data across restarts."""

from __future__ import annotations

import json
import re
import sys
import time
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


def test_api_keys_in_urls_never_reach_the_log(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    # Clients that cannot set headers pass ``?api_key=`` on /track; the server prints
    # every URL it serves. Accepted or refused, the key must not be in the log.
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    monkeypatch.setenv("FIDOTRACK_API_KEYS", "true")
    secret = "fdtk_SeCrEt0123456789"
    log = tmp_path / "server.log"
    with running_server(tmp_path / "data", log) as server:
        assert httpx.get(f"{server.url}/environments?api_key={secret}").status_code in (401, 403)
        ws_url = server.url.replace("http://", "ws://")
        try:
            with connect(f"{ws_url}/track?environment_id=1&api_key={secret}", open_timeout=5):
                pass
        except InvalidStatus:
            pass
    text = log.read_text()
    assert "api_key=***" in text  # the lines are there, the key is not
    assert secret not in text


def test_clients_leaving_right_after_the_handshake_leave_no_traceback(tmp_path: Path) -> None:
    # The server's first message (the hello, or the refusal of an unknown environment)
    # goes to a client that has already gone: that is a client leaving, not a fault.
    import socket
    import struct

    from websockets.sync.client import connect

    from tests.conftest import example_map

    log = tmp_path / "server.log"
    with running_server(tmp_path / "data", log) as server:
        env = httpx.post(f"{server.url}/environments", json={"name": "lab", "marker_size_m": 0.2}).json()
        assert httpx.put(f"{server.url}/environments/{env['id']}/map", json=example_map()).status_code == 200
        ws_url = server.url.replace("http://", "ws://")
        host, port = server.url.removeprefix("http://").split(":")
        for environment_id in (env["id"], 999) * 5:
            # A raw handshake, so no client library closes the socket behind the test's back.
            with socket.create_connection((host, int(port)), timeout=5) as raw:
                raw.sendall(
                    (
                        f"GET /track?environment_id={environment_id} HTTP/1.1\r\nHost: {host}\r\n"
                        "Upgrade: websocket\r\nConnection: Upgrade\r\n"
                        "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
                    ).encode()
                )
                assert raw.recv(4096).startswith(b"HTTP/1.1 101")
                # gone at once, without a closing handshake: a reset, not a FIN
                raw.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        with connect(f"{ws_url}/track?environment_id={env['id']}", open_timeout=5) as ws:
            assert '"hello"' in ws.recv(timeout=5)  # and the server still serves
    text = log.read_text()
    assert "Traceback" not in text, text[-3000:]


def test_track_refused_for_its_key_says_why_with_close_code_1008(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    # A real server can answer a refused handshake only with a bare HTTP 403: the client
    # learns nothing. The connection is accepted and closed with 1008 and the reason.
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    monkeypatch.setenv("FIDOTRACK_API_KEYS", "true")
    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        ws_url = server.url.replace("http://", "ws://")
        with connect(f"{ws_url}/track?environment_id=1", open_timeout=5) as ws:
            try:
                ws.recv(timeout=5)
                raise AssertionError("the server sent a message to a client without a key")
            except ConnectionClosed as closed:
                assert closed.rcvd is not None and closed.rcvd.code == 1008
                assert "API key" in closed.rcvd.reason


def test_oversized_track_frames_get_frame_too_large_until_the_transport_limit(tmp_path: Path) -> None:
    # Between max_frame_bytes (4 MiB) and the transport's limit (5 MiB here) a frame is
    # answered with frame_too_large and the connection stays; beyond it the connection is
    # closed (1009), text messages alike.
    import json

    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    from tests.conftest import example_map

    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        env = httpx.post(f"{server.url}/environments", json={"name": "lab", "marker_size_m": 0.2}).json()
        assert httpx.put(f"{server.url}/environments/{env['id']}/map", json=example_map()).status_code == 200
        url = server.url.replace("http://", "ws://") + f"/track?environment_id={env['id']}"
        with connect(url, open_timeout=5, max_size=None) as ws:
            assert json.loads(ws.recv(timeout=5))["type"] == "hello"
            ws.send(b"\xff\xd8\xff" + bytes(4 * 1024 * 1024 + 1000))
            reply = json.loads(ws.recv(timeout=10))
            assert reply["type"] == "error" and reply["code"] == "frame_too_large"
            for oversized in (b"\xff\xd8\xff" + bytes(6 * 1024 * 1024), '{"type": "config"' + " " * 6 * 2**20 + "}"):
                with connect(url, open_timeout=5, max_size=None) as again:
                    assert json.loads(again.recv(timeout=5))["type"] == "hello"
                    try:
                        again.send(oversized)
                        again.recv(timeout=10)
                        raise AssertionError("a 6 MiB message was read")
                    except ConnectionClosed as closed:
                        # The server closes with 1009 while the client may still be sending:
                        # then the close frame can be lost in the reset, but never another code.
                        assert closed.rcvd is None or closed.rcvd.code == 1009, closed.rcvd


def test_requests_without_a_key_are_refused_before_their_body_is_read(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    # The client declares a large body and sends a few bytes of it: the refusal must come
    # without the server waiting for (or reading) the rest.
    import socket
    from urllib.parse import urlsplit

    monkeypatch.setenv("FIDOTRACK_API_KEYS", "true")
    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        address = urlsplit(server.url)
        for method, path, content_type, length in (
            ("POST", "/environments/1/survey", "multipart/form-data; boundary=b", 200 * 2**20),
            ("POST", "/classifiers", "multipart/form-data; boundary=b", 100 * 2**20),
            ("PUT", "/environments/1/map", "application/json", 900 * 2**10),
        ):
            with socket.create_connection((address.hostname, address.port), timeout=10) as sock:
                head = (f"{method} {path} HTTP/1.1\r\nHost: fidotrack\r\nContent-Type: {content_type}\r\n"
                        f"Content-Length: {length}\r\n\r\n")
                sock.sendall(head.encode() + b"--b\r\n")
                reply = b""
                while chunk := sock.recv(4096):  # the server closes the connection after its reply
                    reply += chunk
            assert reply.startswith(b"HTTP/1.1 401"), (path, reply[:200])
            assert b"API key" in reply


def _new_lines(log: Path, seen: int) -> list[str]:
    return log.read_text().splitlines()[seen:]


def _request_id(line: str) -> str | None:
    """The request id a log line names, if it is one of the service's lines."""
    try:
        return json.loads(line).get("request_id")
    except (ValueError, AttributeError):
        return None


def _wait_for_line(log: Path, seen: int, needle: str, timeout: float = 5.0) -> list[str]:
    """The log's lines after the first `seen`, once one of them holds `needle`."""
    deadline = time.monotonic() + timeout
    while True:
        lines = _new_lines(log, seen)
        if any(needle in line for line in lines):
            return lines
        assert time.monotonic() < deadline, (needle, lines)
        time.sleep(0.05)


def test_each_request_is_logged_once(tmp_path: Path) -> None:
    # The service's own line (request id, route template, never the query) is the only
    # one: uvicorn's access line and the WebSocket library's bare lines repeat it.
    from websockets.sync.client import connect

    from tests.conftest import example_map

    log = tmp_path / "server.log"
    with running_server(tmp_path / "data", log) as server:
        env = httpx.post(f"{server.url}/environments", json={"name": "lab", "marker_size_m": 0.2}).json()
        assert httpx.put(f"{server.url}/environments/{env['id']}/map", json=example_map()).status_code == 200
        for k, (method, path) in enumerate((("GET", "/environments"), ("GET", "/environments/999"),
                                             ("GET", "/livez"))):
            seen = len(log.read_text().splitlines())
            request_id = f"once-{k}"
            assert httpx.request(method, f"{server.url}{path}", headers={"X-Request-ID": request_id}).status_code
            _wait_for_line(log, seen, f'"{request_id}"')
            time.sleep(0.3)  # anything else it would print comes at once
            # The lines about this request: its own, and any other naming its path, but
            # for a line of an earlier request that comes late (it names another id).
            lines = [line for line in _new_lines(log, seen)
                     if f'"{request_id}"' in line or (path in line and _request_id(line) in (None, request_id))]
            assert len(lines) == 1, lines
            assert json.loads(lines[0])["status"] in (200, 404) and json.loads(lines[0])["method"] == method

        seen = len(log.read_text().splitlines())
        with connect(server.url.replace("http://", "ws://") + f"/track?environment_id={env['id']}") as ws:
            assert json.loads(ws.recv(timeout=5))["type"] == "hello"
        _wait_for_line(log, seen, "track connection closed")
        time.sleep(0.3)
        lines = _new_lines(log, seen)
        # the handshake (uvicorn's, the client's address and the URL with any key hidden), then the service's own
        assert len(lines) == 3, lines
        assert '"WebSocket /track?environment_id=' in lines[0] and "[accepted]" in lines[0]
        assert [json.loads(line)["msg"] for line in lines[1:]] == ["track connection opened", "track connection closed"]


def test_the_server_answers_while_the_kernels_compile(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    # A machine's first start compiles the detector's kernels (numba, 10-30 s): the server
    # answers meanwhile, /livez at once and /readyz 503 with the reason, and a frame sent
    # before they are ready waits for them instead of failing.
    import cv2
    import numpy as np
    from websockets.sync.client import connect

    from app.local_server import launch_server
    from tests.conftest import example_map

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "numba-cache"))  # cold: nothing compiled yet
    port, log = free_port(), tmp_path / "server.log"
    url = f"http://127.0.0.1:{port}"
    started = time.monotonic()
    server = launch_server(tmp_path / "data", port=port, log=log)  # not waiting: /readyz is what is watched
    process = server.process
    try:
        while True:  # the server answers...
            try:
                if httpx.get(f"{url}/livez", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert process.poll() is None, log.read_text()
            assert time.monotonic() - started < 120.0, log.read_text()  # (not to hang: no bound is asserted)
            time.sleep(0.05)
        while True:  # ... and says why it is not ready: first loading, then compiling
            ready = httpx.get(f"{url}/readyz")
            assert ready.status_code == 503, ready.text  # answered before the kernels were done
            assert ready.json()["status"] == "not ready", ready.text
            if ready.json()["reason"] == "compiling the detector's kernels":
                break
            assert ready.json()["reason"] == "loading the detector's kernels", ready.text
            time.sleep(0.05)
        assert "compiling the detector's kernels" in log.read_text()

        created = httpx.post(f"{url}/environments", json={"name": "lab", "marker_size_m": 0.2}).json()
        assert httpx.put(f"{url}/environments/{created['id']}/map", json=example_map()).status_code == 200
        frame = cv2.imencode(".png", np.full((480, 640), 200, np.uint8))[1].tobytes()
        with connect(f"ws://127.0.0.1:{port}/track?environment_id={created['id']}", open_timeout=5) as ws:
            assert json.loads(ws.recv(timeout=5))["type"] == "hello"
            ws.send(frame)
            reply = json.loads(ws.recv(timeout=240))
        assert reply["type"] == "frame" and reply["targets"] == [], reply

        while (ready := httpx.get(f"{url}/readyz")).status_code != 200:
            assert ready.status_code == 503 and ready.json()["reason"] == "compiling the detector's kernels"
            assert time.monotonic() - started < 240, log.read_text()
            time.sleep(0.2)
        assert ready.json()["status"] == "ready" and ready.json()["reason"] is None
        assert re.search(r"kernels ready \(\d+\.\d s\)", log.read_text()), log.read_text()
    finally:
        server.stop()
