"""Limits per client: one address or one API key holds at most its share of the /track
connections, and gets 429 (HTTP) or ``too_many_requests`` (/track) beyond its request
rate, while other addresses and keys go on; probes are never limited."""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from app.main import create_app
from app.services import keys
from app.settings import Settings
from tests.conftest import example_map
from tests.routers.conftest import receive

#: The header a test names its client address in (the app sees it as the ASGI scope's client).
CLIENT_HEADER = "x-test-client"


def _as_client(app: Any) -> Any:
    """`app` seeing each request as coming from the address in `CLIENT_HEADER` (as a real
    server would from the connection's source address)."""

    async def with_client(scope: dict[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] in ("http", "websocket"):
            for name, value in scope.get("headers") or []:
                if name == CLIENT_HEADER.encode():
                    scope = {**scope, "client": (value.decode(), 50000)}
        await app(scope, receive, send)

    return with_client


def from_(address: str, **headers: str) -> dict[str, str]:
    return {CLIENT_HEADER: address, **headers}


@pytest.fixture
def make_client(tmp_path: Path) -> Iterator[Any]:
    """Opens a TestClient on an app with the given settings (others as the test suite's
    defaults); closed at the end."""
    with ExitStack() as stack:

        def make(**settings: Any) -> TestClient:
            app = create_app(Settings(data_dir=tmp_path / "data", **settings))
            client = stack.enter_context(TestClient(_as_client(app)))
            client.service = app  # type: ignore[attr-defined]
            return client

        yield make


def _environment(client: TestClient, headers: dict[str, str]) -> int:
    created = client.post("/environments", json={"name": "lab", "marker_size_m": 0.2}, headers=headers)
    assert created.status_code == 201, created.text
    environment = int(created.json()["id"])
    assert client.put(f"/environments/{environment}/map", json=example_map(), headers=headers).status_code == 200
    return environment


def _refused(ws: Any, code: str) -> dict[str, Any]:
    """The refusal `code` on `ws`, then its close with 1013."""
    message = receive(ws)
    assert message["type"] == "error" and message["code"] == code, message
    with pytest.raises(WebSocketDisconnect) as closed:
        receive(ws)
    assert closed.value.code == 1013
    return message


def test_one_address_holds_at_most_its_share_of_track_connections(make_client: Any) -> None:
    client = make_client(max_track_connections=64, max_track_connections_per_address=3,
                         track_open_rate_per_address=0)
    environment = _environment(client, from_("10.0.0.9"))
    url = f"/track?environment_id={environment}"
    with ExitStack() as stack:
        held = [stack.enter_context(client.websocket_connect(url, headers=from_("127.0.0.1"))) for _ in range(3)]
        for ws in held:
            assert receive(ws)["type"] == "hello"
        with client.websocket_connect(url, headers=from_("127.0.0.1")) as fourth:
            message = _refused(fourth, "client_connections")
            assert "address already holds 3" in message["message"]
        # Another address still gets one, and the held ones go on.
        with client.websocket_connect(url, headers=from_("127.0.0.2")) as other:
            assert receive(other)["type"] == "hello"
            held[0].send_text(json.dumps({"type": "config"}))
            assert receive(held[0])["type"] == "config"


def test_one_key_holds_at_most_its_share_of_track_connections(make_client: Any) -> None:
    client = make_client(api_keys=True, max_track_connections_per_key=2, max_track_connections_per_address=0,
                         track_open_rate_per_address=0, track_open_rate_per_key=0)
    admin, first, second = (_create_key(client, name) for name in ("admin", "a", "b"))
    environment = _environment(client, from_("10.0.0.9", **{"X-API-Key": admin}))
    url = f"/track?environment_id={environment}"
    # The key's connections from two addresses count together.
    with ExitStack() as stack:
        held = [stack.enter_context(client.websocket_connect(url, headers=from_(f"127.0.0.{i}", **{"X-API-Key": key})))
                for i, key in ((1, first), (2, first))]
        for ws in held:
            assert receive(ws)["type"] == "hello"
        with client.websocket_connect(url, headers=from_("127.0.0.3", **{"X-API-Key": first})) as third:
            assert "API key already holds 2" in _refused(third, "client_connections")["message"]
        with client.websocket_connect(url, headers=from_("127.0.0.3", **{"X-API-Key": second})) as other:
            assert receive(other)["type"] == "hello"


def _create_key(client: TestClient, name: str) -> str:
    """A key with every scope, made in the client's database as `fidotrack keys create` does."""
    with client.service.state.sessionmaker() as session:  # type: ignore[attr-defined]
        return keys.create(session, name, ["admin"]).key


def test_a_burst_over_the_address_rate_gets_429_with_retry_after(make_client: Any) -> None:
    client = make_client(request_rate_per_address=0.5, request_burst_per_address=5)
    for _ in range(5):
        assert client.get("/environments", headers=from_("127.0.0.1")).status_code == 200
    refused = client.post("/environments", json={"name": "over", "marker_size_m": 0.2},
                          headers=from_("127.0.0.1"))
    assert refused.status_code == 429
    assert int(refused.headers["retry-after"]) >= 1
    assert "rate" in refused.json()["detail"]
    # Probes are not limited, for that address either.
    for _ in range(20):
        assert client.get("/livez", headers=from_("127.0.0.1")).status_code == 200
        assert client.get("/readyz", headers=from_("127.0.0.1")).status_code == 200
    # Another address is unaffected; the refused POST created nothing.
    listed = client.get("/environments", headers=from_("127.0.0.2"))
    assert listed.status_code == 200 and listed.json() == []


def test_a_burst_over_the_key_rate_gets_429_from_any_address(make_client: Any) -> None:
    client = make_client(api_keys=True, request_rate_per_key=0.5, request_burst_per_key=4)
    busy, other = _create_key(client, "busy"), _create_key(client, "other")
    for i in range(4):
        assert client.get("/environments", headers=from_(f"127.0.0.{i + 1}", **{"X-API-Key": busy})).status_code == 200
    refused = client.get("/environments", headers=from_("127.0.0.9", **{"X-API-Key": busy}))
    assert refused.status_code == 429 and int(refused.headers["retry-after"]) >= 1
    assert "API key" in refused.json()["detail"]
    assert client.get("/environments", headers=from_("127.0.0.9", **{"X-API-Key": other})).status_code == 200


def test_track_connections_opened_too_fast_are_refused_with_a_retry_time(make_client: Any) -> None:
    client = make_client(track_open_rate_per_address=0.2, track_open_burst_per_address=2)
    environment = _environment(client, from_("10.0.0.9"))
    url = f"/track?environment_id={environment}"
    for _ in range(2):
        with client.websocket_connect(url, headers=from_("127.0.0.1")) as ws:
            assert receive(ws)["type"] == "hello"
    with client.websocket_connect(url, headers=from_("127.0.0.1")) as ws:
        message = _refused(ws, "too_many_requests")
        assert 0 < message["retry_after_s"] <= 5.0
    with client.websocket_connect(url, headers=from_("127.0.0.2")) as ws:
        assert receive(ws)["type"] == "hello"


def test_addresses_count_as_the_machine_holding_them() -> None:
    from app.services.rate_limits import client_address

    assert client_address("192.0.2.7") == "192.0.2.7"
    # An IPv6 machine holds a whole /64: every address in it counts as one client.
    assert client_address("2001:db8:1:2::5") == client_address("2001:db8:1:2:ffff::9") == "2001:db8:1:2::/64"
    assert client_address("2001:db8:1:3::5") != client_address("2001:db8:1:2::5")
    assert client_address("::ffff:192.0.2.7") == "192.0.2.7"
    assert client_address(None) is None
