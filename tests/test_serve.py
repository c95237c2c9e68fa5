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
