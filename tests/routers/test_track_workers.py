"""``fidotrack serve --workers 2``: two server processes on one database hold one
``max_track_connections`` between them and both take connections (the database's rows
name the worker holding each); a map replaced through the API, whichever worker takes
the request, reaches the open connections, and the Python client's `track` reads the
new hello mid-stream."""

from __future__ import annotations

import asyncio
import json
import re
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
import websockets
from sqlalchemy import select

from app.client import Client
from app.db import make_engine
from app.models import TrackConnection
from app.schemas import TrackHello
from app.settings import Settings
from tests.conftest import FIDOTRACK_SERVE, Server, example_map, running_server
from tests.routers.conftest import Pan
from tests.routers.test_track_map_change import SHIFT, shifted_map

#: The open connections the whole service allows in these tests.
LIMIT = 2
#: Connections tried at once: more than the limit of one process, and of both.
AT_ONCE = 7
MAP_POLL_S = 0.3


@pytest.fixture
def server(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Server]:
    monkeypatch.setenv("FIDOTRACK_MAX_TRACK_CONNECTIONS", str(LIMIT))
    monkeypatch.setenv("FIDOTRACK_MAP_POLL_S", str(MAP_POLL_S))
    monkeypatch.setenv("FIDOTRACK_MAX_TRACK_FPS", "1000")
    # Hundreds of connections, all from 127.0.0.1, for the service-wide limit alone.
    monkeypatch.setenv("FIDOTRACK_TRACK_OPEN_RATE_PER_ADDRESS", "0")
    with running_server(tmp_path / "data", tmp_path / "server.log", command=[*FIDOTRACK_SERVE, "--workers", "2"]) as s:
        yield s


def _worker_pids(server: Server) -> set[int]:
    """The pids of the server's worker processes, as uvicorn announces them."""
    return {int(pid) for pid in re.findall(r"Started server process \[(\d+)\]", server.log.read_text())}


def _holders(data_dir: Path) -> list[int]:
    """The pids of the processes holding the open connections, as the database has them."""
    engine = make_engine(Settings(data_dir=data_dir).resolved_database_url)
    try:
        with engine.connect() as connection:
            return [int(server.rsplit(":", 1)[1]) for server in connection.scalars(select(TrackConnection.server))]
    finally:
        engine.dispose()


async def _connect(url: str) -> tuple[websockets.ClientConnection, dict]:
    ws = await websockets.connect(url, open_timeout=20)
    return ws, json.loads(await asyncio.wait_for(ws.recv(), 20))


async def _close_code(ws: websockets.ClientConnection) -> int | None:
    try:
        await asyncio.wait_for(ws.recv(), 20)
    except websockets.ConnectionClosed as closed:
        return closed.rcvd.code if closed.rcvd is not None else None
    raise AssertionError("a refused connection stayed open")


def test_two_workers_hold_one_connection_limit_and_both_take_connections(server: Server, tmp_path: Path) -> None:
    env = httpx.post(f"{server.url}/environments", json={"name": "lab", "marker_size_m": 0.2}).json()
    assert httpx.put(f"{server.url}/environments/{env['id']}/map", json=example_map()).status_code == 200
    url = server.url.replace("http://", "ws://") + f"/track?environment_id={env['id']}"
    workers = _worker_pids(server)
    assert len(workers) == 2, server.log.read_text()

    async def at_once() -> tuple[list[tuple[websockets.ClientConnection, dict]], list[int]]:
        """AT_ONCE connections together: the accepted ones held open, the refused ones'
        close codes."""
        opened = await asyncio.gather(*(_connect(url) for _ in range(AT_ONCE)))
        accepted = [(ws, m) for ws, m in opened if m["type"] == "hello"]
        refused = [(ws, m) for ws, m in opened if m["type"] != "hello"]
        for _, message in refused:
            assert message["type"] == "error" and message["code"] == "too_many_connections", message
            assert f"tracks {LIMIT} connections" in message["message"], message
        codes = [await _close_code(ws) for ws, _ in refused]
        return accepted, codes

    async def scenario() -> set[int]:
        holders_seen: set[int] = set()
        for round_ in range(30):
            accepted, codes = await at_once()
            assert len(accepted) == LIMIT, f"round {round_}: {len(accepted)} accepted, limit {LIMIT}"
            assert codes == [1013] * (AT_ONCE - LIMIT)
            holders = _holders(tmp_path / "data")
            assert len(holders) == LIMIT and set(holders) <= workers
            holders_seen |= set(holders)
            # While they are open, no other connection gets in, through either process.
            for _ in range(4):
                ws, message = await _connect(url)
                assert message["code"] == "too_many_connections"
                await ws.close()
            for ws, _ in accepted:
                await ws.close()
            # Closed, their places come back (each process notices its close a moment later).
            deadline = time.monotonic() + 10
            while True:
                ws, message = await _connect(url)
                await ws.close()
                if message["type"] == "hello":
                    break
                assert message["code"] == "too_many_connections"
                assert time.monotonic() < deadline, "closed connections never gave their places back"
                await asyncio.sleep(0.05)
            while _holders(tmp_path / "data"):
                assert time.monotonic() < deadline, "a closed connection stayed in the database"
                await asyncio.sleep(0.05)
            if round_ >= 2 and holders_seen == workers:
                break
        return holders_seen

    assert asyncio.run(scenario()) == workers, "every accepted connection landed on the same worker"


def test_the_python_client_follows_a_map_replaced_mid_stream(server: Server, tmp_path: Path, pan: Pan) -> None:
    scene, camera, poses, frames, _ = pan
    document = scene.map_document(camera)
    env = httpx.post(f"{server.url}/environments", json={"name": "pan", "marker_size_m": 0.2}).json()
    assert httpx.put(f"{server.url}/environments/{env['id']}/map", json=document).status_code == 200
    hellos: list[TrackHello] = []
    replaced: list[float] = []

    def stream() -> Iterator[bytes]:
        """The pan's first frames, then, once the map is replaced, its first frame until
        the new hello comes, then the first frames again."""
        yield from frames[:3]
        assert httpx.put(f"{server.url}/environments/{env['id']}/map",
                         json=shifted_map(document, SHIFT)).status_code == 200
        replaced.append(time.monotonic())
        while len(hellos) < 2:
            assert time.monotonic() - replaced[0] < 20 * MAP_POLL_S, "no hello after the map changed"
            yield frames[0]
            time.sleep(MAP_POLL_S / 4)
        yield from frames[:3]

    with Client(server.url) as client:
        replies = []
        for reply in client.track(env["id"], stream(), on_hello=hellos.append):
            replies.append((reply, len(hellos)))
    assert [h.reason for h in hellos] == ["connected", "map_changed"]
    assert hellos[1].targets == len(document["targets"]) and hellos[1].environment_id == env["id"]
    before = [r for r, seen in replies if seen == 1]
    after = [r for r, seen in replies if seen == 2]
    assert len(before) >= 3 and len(after) >= 3
    truth = [*poses[:3], *[poses[0]] * (len(before) - 3)]
    for reply, pose in zip(before, truth, strict=True):
        assert np.linalg.norm(np.asarray(reply.pose.position) - pose.position) < 0.01
    # The last three replies are the pan's first frames again, posed against the new map.
    for reply, pose in zip(after[-3:], poses[:3], strict=True):
        assert reply.pose is not None
        assert np.linalg.norm(np.asarray(reply.pose.position) - (pose.position + SHIFT)) < 0.01
    assert after[0].scan_reason == "first"  # tracked afresh on the new map


def test_every_open_connection_gets_the_new_map(server: Server, tmp_path: Path, pan: Pan) -> None:
    # LIMIT connections held at once, on whichever workers they land, idle: each one hears
    # of the map replaced through the HTTP API (on either worker) and poses against it.
    scene, camera, poses, frames, _ = pan
    document = scene.map_document(camera)
    env = httpx.post(f"{server.url}/environments", json={"name": "pan", "marker_size_m": 0.2}).json()
    assert httpx.put(f"{server.url}/environments/{env['id']}/map", json=document).status_code == 200
    url = server.url.replace("http://", "ws://") + f"/track?environment_id={env['id']}"

    async def scenario() -> list[list[float]]:
        opened = await asyncio.gather(*(_connect(url) for _ in range(LIMIT)))
        assert all(m["type"] == "hello" for _, m in opened)
        async with httpx.AsyncClient() as http:
            response = await http.put(f"{server.url}/environments/{env['id']}/map", json=shifted_map(document, SHIFT))
            assert response.status_code == 200
        positions = []
        for ws, _ in opened:
            message = json.loads(await asyncio.wait_for(ws.recv(), 20 * MAP_POLL_S))
            assert message["type"] == "hello" and message["reason"] == "map_changed", message
            await ws.send(frames[1])
            reply = json.loads(await asyncio.wait_for(ws.recv(), 20))
            assert reply["type"] == "frame" and reply["scan_reason"] == "first", reply
            positions.append(reply["pose"]["position"])
            await ws.close()
        return positions

    for position in asyncio.run(scenario()):
        assert np.linalg.norm(np.asarray(position) - (poses[1].position + SHIFT)) < 0.01
