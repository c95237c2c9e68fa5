"""A slow client cannot hold a real ``fidotrack serve``'s connections: a request header
or body that stalls is cut at its deadline, one address holds at most
``max_connections_per_address`` connections, and others (another address, a normal
keep-alive client, an idle /track WebSocket) are served all along."""

from __future__ import annotations

import contextlib
import select
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from websockets.sync.client import connect

from tests.conftest import Server, example_map, running_server

HEADER_TIMEOUT_S = 2.0
BODY_TIMEOUT_S = 2.0
PER_ADDRESS = 12
#: Room for a loaded machine over a deadline, s.
SLACK_S = 3.0


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    tmp = tmp_path_factory.mktemp("slow-clients")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("FIDOTRACK_REQUEST_HEADER_TIMEOUT_S", str(HEADER_TIMEOUT_S))
        patch.setenv("FIDOTRACK_REQUEST_BODY_TIMEOUT_S", str(BODY_TIMEOUT_S))
        patch.setenv("FIDOTRACK_MAX_CONNECTIONS_PER_ADDRESS", str(PER_ADDRESS))
        with running_server(tmp / "data", tmp / "server.log") as running:
            yield running


def _port(server: Server) -> int:
    return int(server.url.rsplit(":", 1)[1])


def _open(server: Server, source: str, first_bytes: bytes = b"") -> socket.socket:
    """A connection to the server from `source` (a loopback address), `first_bytes` sent."""
    sock = socket.socket()
    sock.bind((source, 0))
    sock.connect(("127.0.0.1", _port(server)))
    if first_bytes:
        sock.sendall(first_bytes)
    return sock


def _read_until_closed(sock: socket.socket, within_s: float) -> bytes | None:
    """What the server sent before closing `sock`, or None if it is still open after `within_s`."""
    received = b""
    deadline = time.monotonic() + within_s
    while (left := deadline - time.monotonic()) > 0:
        if not select.select([sock], [], [], left)[0]:
            break
        try:
            chunk = sock.recv(65536)
        except ConnectionResetError:
            return received
        if not chunk:
            return received
        received += chunk
    return None


def _get_livez(sock: socket.socket) -> bytes:
    """GET /livez on the open connection `sock`; the whole reply (its header and its body)."""
    sock.sendall(b"GET /livez HTTP/1.1\r\nHost: fidotrack\r\n\r\n")
    sock.settimeout(10)
    reply = b""
    while b"\r\n\r\n" not in reply or len(reply.partition(b"\r\n\r\n")[2]) < _content_length(reply):
        chunk = sock.recv(65536)
        assert chunk, f"closed during a reply: {reply!r}"
        reply += chunk
    return reply


def _content_length(reply: bytes) -> int:
    for line in reply.partition(b"\r\n\r\n")[0].lower().split(b"\r\n"):
        if line.startswith(b"content-length:"):
            return int(line.split(b":")[1])
    return 0


def _all_open(socks: list[socket.socket]) -> bool:
    """Whether the server kept every one of `socks` open (given a moment to accept them)."""
    time.sleep(1.0)
    return all(_read_until_closed(sock, 0.01) is None for sock in socks)


def _livez(server: Server) -> int:
    """The status a fresh connection from 127.0.0.1 gets from /livez (an exception if none comes)."""
    return httpx.get(f"{server.url}/livez", timeout=30).status_code


def test_a_stalled_request_header_is_closed_at_its_deadline(server: Server) -> None:
    partial = _open(server, "127.0.0.3", b"GET /livez HTTP/1.1\r\nHost: fidotrack\r\nX-Slow: ")
    silent = _open(server, "127.0.0.3")
    with partial, silent:
        start = time.monotonic()
        reply = _read_until_closed(partial, HEADER_TIMEOUT_S + SLACK_S)
        assert reply is not None, "a partial header held its connection past the header deadline"
        assert time.monotonic() - start >= HEADER_TIMEOUT_S - 0.5
        assert reply.startswith(b"HTTP/1.1 408 ") and b'"detail"' in reply
        # Not a byte: closed at the same deadline, with no reply (as an idle keep-alive connection).
        assert _read_until_closed(silent, SLACK_S) == b""


def test_a_stalled_request_body_is_dropped_at_its_deadline(server: Server) -> None:
    head = (b"POST /environments HTTP/1.1\r\nHost: fidotrack\r\nContent-Type: application/json\r\n"
            b"Content-Length: 200\r\n\r\n")
    with _open(server, "127.0.0.3", head + b'{"name": "sl') as sock:
        start = time.monotonic()
        reply = _read_until_closed(sock, BODY_TIMEOUT_S + SLACK_S)
        assert reply is not None, "a stalled body held its connection past the body deadline"
        assert time.monotonic() - start >= BODY_TIMEOUT_S - 0.5
        assert reply.startswith(b"HTTP/1.1 408 ")
    assert not [env for env in httpx.get(f"{server.url}/environments").json() if env["name"].startswith("sl")]


def test_slowloris_from_one_address_is_capped_and_others_are_served(server: Server) -> None:
    held = [_open(server, "127.0.0.2", b"GET / HTTP/1.1\r\n") for _ in range(PER_ADDRESS)]
    try:
        extra = [_open(server, "127.0.0.2", b"GET / HTTP/1.1\r\n") for _ in range(10)]
        for sock in extra:
            assert _read_until_closed(sock, SLACK_S) is not None, "a connection past the per-address cap was kept"
            sock.close()
        assert _all_open(held)
        # Another address is served (how fast is the load benchmark's to measure, not a test's).
        assert [_livez(server) for _ in range(5)] == [200] * 5
        # Trickling the header does not keep it alive: every held connection is cut at the deadline.
        for sock in held:
            sock.sendall(b"X-A: b\r\n")
        for sock in held:
            assert _read_until_closed(sock, HEADER_TIMEOUT_S + SLACK_S) is not None
    finally:
        for sock in held:
            sock.close()
    # The closed connections no longer count: the address gets its share again.
    again = [_open(server, "127.0.0.2") for _ in range(PER_ADDRESS)]
    for sock in again:
        with sock:
            assert _get_livez(sock).startswith(b"HTTP/1.1 200 ")


def test_keep_alive_requests_and_an_idle_track_websocket_keep_working(server: Server) -> None:
    # Keep-alive: requests on one connection, each after a pause under the header deadline.
    with _open(server, "127.0.0.5") as sock:
        for _ in range(3):
            assert _get_livez(sock).startswith(b"HTTP/1.1 200 ")
            time.sleep(HEADER_TIMEOUT_S * 0.6)
    env = httpx.post(f"{server.url}/environments", json={"name": "lab", "marker_size_m": 0.2}).json()
    assert httpx.put(f"{server.url}/environments/{env['id']}/map", json=example_map()).status_code == 200
    url = server.url.replace("http://", "ws://") + f"/track?environment_id={env['id']}"
    with contextlib.ExitStack() as stack:
        websockets = [stack.enter_context(connect(url, sock=_open(server, "127.0.0.4"), open_timeout=10))
                      for _ in range(3)]
        for ws in websockets:
            assert '"hello"' in str(ws.recv(timeout=10))
        # WebSockets count against their address: with them open, only the rest of the cap is left.
        raw = [_open(server, "127.0.0.4") for _ in range(PER_ADDRESS - len(websockets))]
        with _open(server, "127.0.0.4") as past_cap:
            assert _read_until_closed(past_cap, 1.5) is not None
        for sock in raw:
            sock.close()
        # Upgraded, a WebSocket is held to neither deadline: idle past both, it still answers.
        time.sleep(max(HEADER_TIMEOUT_S, BODY_TIMEOUT_S) + 1.5)
        for ws in websockets:
            ws.send('{"type": "config"}')
            assert '"config"' in str(ws.recv(timeout=10))
    # Their close gives the address its connections back.
    time.sleep(0.5)
    raw = [_open(server, "127.0.0.4") for _ in range(PER_ADDRESS)]
    try:
        assert _all_open(raw)
    finally:
        for sock in raw:
            sock.close()
    # (Nor did any deadline or count fail inside the server, in this test or those before.)
    text = Path(server.log).read_text()
    assert "GuardedHttpProtocol" not in text and "CountedWebSocketProtocol" not in text, text[-3000:]


def test_one_address_gets_at_most_a_quarter_of_the_open_file_limit() -> None:
    from app.server import slow_client_limits
    from app.settings import Settings

    assert slow_client_limits(Settings(max_connections_per_address=10_000), 1024).connections_per_address == 256
    assert slow_client_limits(Settings(max_connections_per_address=100), 1024).connections_per_address == 100
