"""Where FreeD packets may go: a connection's own receivers only when the server allows
them and only inside its listed networks; no receiver at a special address (loopback,
link-local, multicast, broadcast, ...) unless listed; hosts checked when stored; host
names looked up off the API's threads, with a timeout, and cached.

No test here streams a frame after naming a receiver outside the loopback: a refusal is
checked on the config's reply alone, so that no packet could leave even if it were not
refused.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from ipaddress import ip_network
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from starlette.testclient import WebSocketTestSession

from app.main import create_app
from app.settings import Settings
from tests.conftest import example_map
from tests.routers.conftest import Pan, stream_frames

#: Receivers a /track client must not get packets sent to: loopback, multicast, the cloud
#: metadata service (link-local), IPv6 loopback, broadcast.
SPECIAL_HOSTS = ["127.0.0.1", "224.0.0.1", "169.254.169.254", "::1", "255.255.255.255"]
#: A documentation network (RFC 5737): listed, it contains none of the hosts above.
ELSEWHERE = ip_network("192.0.2.0/24")
LOOPBACK_ONE = ip_network("127.0.0.1/32")
#: Many connections from the test client's one address: the per-address limits let them.
NO_ADDRESS_LIMITS = {"max_track_connections_per_address": 0, "track_open_rate_per_address": 0,
                     "request_rate_per_address": 0}


@contextmanager
def _service(tmp_path: Path, **settings: Any) -> Iterator[tuple[TestClient, int]]:
    """A service with these settings and an environment with a map."""
    with TestClient(create_app(Settings(data_dir=tmp_path / "data", **settings))) as client:
        env = client.post("/environments", json={"name": "studio", "marker_size_m": 0.1}).json()["id"]
        assert client.put(f"/environments/{env}/map", json=example_map()).status_code == 200
        yield client, env


def _configure(ws: WebSocketTestSession, freed: dict[str, Any]) -> dict[str, Any]:
    """The reply to a config naming `freed` (the config echoed, or an error)."""
    ws.send_text(json.dumps({"type": "config", "freed": freed}))
    return ws.receive_json()


def _refused(reply: dict[str, Any]) -> str:
    assert reply["type"] == "error" and reply["code"] == "freed", reply
    return str(reply["message"])


def test_special_addresses_are_refused_at_config_time(tmp_path: Path) -> None:
    with _service(tmp_path, freed_connection_receivers=True, freed_allowed_networks=[ELSEWHERE]) as (client, env):
        with client.websocket_connect(f"/track?environment_id={env}") as ws:
            assert ws.receive_json()["type"] == "hello"
            for host in SPECIAL_HOSTS:
                message = _refused(_configure(ws, {"host": host, "port": 40000}))
                assert host in message and "freed_allowed_networks" in message and "config is not applied" in message
            ws.send_text(json.dumps({"type": "config", "frame": "unity"}))  # the connection goes on, FreeD off
            reply = ws.receive_json()
            assert reply["type"] == "config" and reply["frame"] == "unity" and reply["freed"] is None


def test_a_connections_own_receivers_are_refused_by_default(tmp_path: Path) -> None:
    assert Settings.model_fields["freed_connection_receivers"].default is False
    with _service(tmp_path) as (client, env):
        with client.websocket_connect(f"/track?environment_id={env}") as ws:
            assert ws.receive_json()["type"] == "hello"
            assert "leave out host and port" in _refused(_configure(ws, {"host": "127.0.0.1", "port": 40000}))


def test_a_listed_loopback_receiver_gets_packets_and_no_other(tmp_path: Path, pan: Pan) -> None:
    """127.0.0.1/32 listed (Unreal on the server's machine): a connection's own receiver
    and the environment's there get every posed frame; 127.0.0.2, unlisted, is refused."""
    scene, camera, _, frames, _ = pan
    settings = Settings(data_dir=tmp_path / "data", freed_connection_receivers=True,
                        freed_allowed_networks=[LOOPBACK_ONE])
    with (TestClient(create_app(settings)) as client,
          socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as receiver):
        receiver.bind(("127.0.0.1", 0))
        receiver.settimeout(5.0)
        port = receiver.getsockname()[1]
        env = client.post("/environments", json={"name": "pan", "marker_size_m": 0.2}).json()["id"]
        client.put(f"/environments/{env}/map", json=scene.map_document(camera))
        url = f"/track?environment_id={env}"
        with client.websocket_connect(url) as ws:
            assert ws.receive_json()["type"] == "hello"
            assert "127.0.0.2" in _refused(_configure(ws, {"host": "127.0.0.2", "port": port}))
            replies = stream_frames(ws, frames[:3], {"freed": {"host": "127.0.0.1", "port": port, "camera_id": 7}},
                                    hello=False)
        assert sum(r["pose"] is not None for r in replies) == 3
        assert [receiver.recv(64)[1] for _ in range(3)] == [7, 7, 7]
        assert client.put(f"/environments/{env}/freed", json={"host": "127.0.0.1", "port": port}).status_code == 200
        with client.websocket_connect(url) as ws:
            stream_frames(ws, frames[:2])
        assert [receiver.recv(64)[1] for _ in range(2)] == [1, 1]


def test_a_malformed_host_is_refused_when_stored(tmp_path: Path) -> None:
    with _service(tmp_path) as (client, env):
        for host in ["::::::", "-", "a..b", " x", "x ", "", "a_b", "127.1", "0x7f000001", "a.", "fe80::1%eth0",
                     "host name", "-a.b", "a" * 64 + ".com"]:
            reply = client.put(f"/environments/{env}/freed", json={"host": host, "port": 40000})
            assert reply.status_code == 422, (host, reply.text)
            detail = reply.json()["detail"]
            assert "host" in detail and any(why in detail for why in ("host name", "zone", "at least 1")), detail
        assert client.get(f"/environments/{env}/freed").status_code == 404


def test_an_environment_receiver_at_a_special_address_is_refused_unless_listed(tmp_path: Path) -> None:
    with _service(tmp_path, freed_allowed_networks=[LOOPBACK_ONE]) as (client, env):
        url = f"/environments/{env}/freed"
        for host, kind in [("169.254.169.254", "link-local"), ("224.0.0.1", "multicast"), ("::1", "loopback"),
                           ("255.255.255.255", "broadcast"), ("0.0.0.0", "unspecified"), ("127.0.0.2", "loopback"),
                           ("::ffff:169.254.169.254", "link-local"), ("localhost", "loopback")]:
            reply = client.put(url, json={"host": host, "port": 40000})
            assert reply.status_code == 422, (host, reply.text)
            assert kind in reply.json()["detail"] and "freed_allowed_networks" in reply.json()["detail"], reply.text
        assert client.get(url).status_code == 404
        for host in ("127.0.0.1", "192.168.1.40", "studio-pc.local"):  # listed, or an ordinary address or name
            assert client.put(url, json={"host": host, "port": 40000}).status_code == 200, host


def test_a_stored_receiver_no_longer_allowed_is_refused_when_a_connection_opens(tmp_path: Path) -> None:
    """Stored while 127.0.0.1/32 was listed, then the server restarted without it: the
    connection says so at once, before any frame, and sends nothing."""
    with _service(tmp_path, freed_allowed_networks=[LOOPBACK_ONE]) as (client, env):
        assert client.put(f"/environments/{env}/freed", json={"host": "127.0.0.1", "port": 40000}).status_code == 200
    with TestClient(create_app(Settings(data_dir=tmp_path / "data"))) as client:
        with client.websocket_connect(f"/track?environment_id={env}") as ws:
            assert ws.receive_json()["type"] == "hello"
            ws.send_text(json.dumps({"type": "config", "freed": {"enabled": False}}))
            assert "loopback" in _refused(ws.receive_json())  # said before the config's echo
            assert ws.receive_json()["type"] == "config"


class FakeResolver:
    """socket.getaddrinfo for test names: ``*.slow.test`` waits until released (then
    fails), ``*.fast.test`` is 127.0.0.1 at once, ``mixed.test`` is 127.0.0.1 and the
    metadata service's address; other names go to the system's resolver. Counts calls."""

    def __init__(self, real: Any) -> None:
        self.real = real
        self.calls: Counter[str] = Counter()
        self.release = threading.Event()

    def __call__(self, host: Any, *args: Any, **kwargs: Any) -> list[tuple[Any, ...]]:
        name = host.decode() if isinstance(host, bytes) else str(host)
        if name.endswith(".slow.test"):
            self.calls[name] += 1
            self.release.wait(60)
            raise socket.gaierror(socket.EAI_AGAIN, "Temporary failure in name resolution")
        if name.endswith(".fast.test") or name == "mixed.test":
            self.calls[name] += 1
            port = args[0] if args and args[0] is not None else 0
            addresses = ["127.0.0.1"] + (["169.254.169.254"] if name == "mixed.test" else [])
            return [(socket.AF_INET, socket.SOCK_DGRAM, 17, "", (a, port)) for a in addresses]
        return self.real(host, *args, **kwargs)


@pytest.fixture
def resolver(monkeypatch: pytest.MonkeyPatch) -> Iterator[FakeResolver]:
    fake = FakeResolver(socket.getaddrinfo)
    monkeypatch.setattr(socket, "getaddrinfo", fake)
    try:
        yield fake
    finally:
        fake.release.set()


def _get_within(client: TestClient, path: str, seconds: float) -> float | None:
    """How long GET `path` took, or None if it did not answer within `seconds`."""
    took: list[float] = []

    def get() -> None:
        start = time.monotonic()
        assert client.get(path).status_code == 200
        took.append(time.monotonic() - start)

    thread = threading.Thread(target=get, daemon=True)
    thread.start()
    thread.join(seconds)
    return took[0] if took else None


def test_slow_lookups_do_not_block_the_api_and_time_out(tmp_path: Path, resolver: FakeResolver) -> None:
    """45 connections name hosts whose lookups hang: GET /environments still answers
    while they hang, and each connection is refused once its lookup's time is up."""
    settings = {"freed_connection_receivers": True, "freed_allowed_networks": [ELSEWHERE],
                "freed_resolve_timeout_s": 1.0, **NO_ADDRESS_LIMITS}
    with _service(tmp_path, **settings) as (client, env), ExitStack() as stack:
        try:
            sockets = [stack.enter_context(client.websocket_connect(f"/track?environment_id={env}"))
                       for _ in range(45)]
            for i, ws in enumerate(sockets):
                assert ws.receive_json()["type"] == "hello"
                ws.send_text(json.dumps({"type": "config", "freed": {"host": f"cam{i}.slow.test", "port": 40000}}))
            deadline = time.monotonic() + 30
            while sum(resolver.calls.values()) < 4 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert sum(resolver.calls.values()) >= 4  # lookups are hanging now
            assert _get_within(client, "/environments", 15.0) is not None, "GET /environments waited for lookups"
            messages = [_refused(ws.receive_json()) for ws in sockets]
            assert all("cannot resolve" in m for m in messages)
            assert any("took more than 1 s" in m for m in messages)
            assert not resolver.release.is_set()  # refused while the lookups still hung
        finally:
            resolver.release.set()


def test_lookups_are_cached_and_every_address_is_checked(tmp_path: Path, resolver: FakeResolver) -> None:
    settings = {"freed_connection_receivers": True, "freed_allowed_networks": [LOOPBACK_ONE],
                "freed_resolve_timeout_s": 1.0, "freed_resolve_cache_s": 300.0, **NO_ADDRESS_LIMITS}
    with _service(tmp_path, **settings) as (client, env):
        url = f"/track?environment_id={env}"
        with client.websocket_connect(url) as ws, client.websocket_connect(url) as other:
            for socket_ in (ws, other):
                assert socket_.receive_json()["type"] == "hello"
            for socket_ in (ws, other, ws):
                reply = _configure(socket_, {"host": "receiver.fast.test", "port": 40000, "camera_id": 2})
                assert reply["type"] == "config", reply
                _configure(socket_, {"enabled": False})
            assert resolver.calls["receiver.fast.test"] == 1
            # A name with one address outside the allowed networks is refused, whatever the others.
            message = _refused(_configure(ws, {"host": "mixed.test", "port": 40000}))
            assert "'mixed.test' resolves to 169.254.169.254" in message and "freed_allowed_networks" in message
            # Many connections asking for one hanging name wait on one lookup; its failure is kept.
            for socket_ in (ws, other):
                socket_.send_text(json.dumps({"type": "config", "freed": {"host": "one.slow.test", "port": 40000}}))
            assert all("took more than" in _refused(s.receive_json()) for s in (ws, other))
            resolver.release.set()
            time.sleep(0.5)
            assert "Temporary failure" in _refused(_configure(ws, {"host": "one.slow.test", "port": 40000}))
            assert resolver.calls["one.slow.test"] == 1
