"""Open /track connections counted in the database: the limit holds for every process on
the database, a closed connection gives its place back, and those of a process that died
stop counting once their lease runs out while a live process's stay counted. On SQLite
and on PostgreSQL (the `settings` fixture)."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app.db import make_engine, make_sessionmaker, upgrade_to_head
from app.models import TrackConnection
from app.schemas import EnvironmentCreate
from app.services import environments
from app.services.track_connections import TrackConnections
from app.settings import Settings

#: A server process that opens one /track connection, says its id and lives on (renewing
#: it) until it is killed.
SERVER_PROCESS = """
import sys, time
from app.db import make_engine, make_sessionmaker
from app.services.track_connections import TrackConnections
connections = TrackConnections(make_sessionmaker(make_engine(sys.argv[1])), limit=100, lease_s=float(sys.argv[3]))
print(connections.open(int(sys.argv[2])), flush=True)
time.sleep(600)
"""


@pytest.fixture
def sessions(settings: Settings) -> Iterator[sessionmaker[Session]]:
    engine = make_engine(settings.resolved_database_url)
    upgrade_to_head(engine, settings.data_dir)
    try:
        yield make_sessionmaker(engine)
    finally:
        engine.dispose()


@pytest.fixture
def environment_id(sessions: sessionmaker[Session]) -> int:
    with sessions() as session:
        return environments.create(session, EnvironmentCreate(name="studio", marker_size_m=0.2)).id


def _rows(sessions: sessionmaker[Session]) -> list[TrackConnection]:
    with sessions() as session:
        return list(session.scalars(select(TrackConnection)))


def test_the_limit_holds_and_a_closed_connection_gives_its_place_back(sessions: sessionmaker[Session],
                                                                      environment_id: int) -> None:
    connections = TrackConnections(sessions, limit=2, lease_s=30)
    first, second = connections.open(environment_id), connections.open(environment_id)
    assert first and second and first != second
    assert connections.open(environment_id) is None
    assert connections.held == 2 and {r.id for r in _rows(sessions)} == {first, second}
    connections.close(first)
    third = connections.open(environment_id)
    assert third is not None and {r.id for r in _rows(sessions)} == {second, third}
    connections.close_all()
    assert _rows(sessions) == [] and connections.held == 0


def test_every_holder_on_the_database_counts_against_one_limit(sessions: sessionmaker[Session],
                                                               environment_id: int) -> None:
    # Two holders, as two server processes have: each under the limit, together at it.
    a = TrackConnections(sessions, limit=3, lease_s=30)
    b = TrackConnections(sessions, limit=3, lease_s=30)
    assert a.open(environment_id) and b.open(environment_id) and a.open(environment_id)
    assert b.open(environment_id) is None and a.open(environment_id) is None
    # One holder shutting down deletes its own connections, not the other's.
    a.close_all()
    assert len(_rows(sessions)) == 1
    assert b.open(environment_id) and b.open(environment_id)
    assert b.open(environment_id) is None
    b.close_all()


def test_a_dead_process_stops_counting_after_its_lease_and_a_live_one_keeps_counting(
        settings: Settings, sessions: sessionmaker[Session], environment_id: int) -> None:
    lease_s = 2.0
    process = subprocess.Popen([sys.executable, "-c", SERVER_PROCESS, settings.resolved_database_url,
                                str(environment_id), str(lease_s)], stdout=subprocess.PIPE, text=True)
    try:
        assert process.stdout is not None
        theirs = process.stdout.readline().strip()
        assert len(theirs) == 32, theirs
        [row] = _rows(sessions)
        assert row.id == theirs and row.server == f"{socket.gethostname()}:{process.pid}"
        ours = TrackConnections(sessions, limit=1, lease_s=lease_s)
        assert ours.server != row.server
        # Alive, the other process renews its connection: after more than a lease it still counts.
        time.sleep(lease_s * 1.6)
        assert ours.open(environment_id) is None
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait(10)
    # Killed without closing: its connection counts until its lease runs out ...
    assert ours.open(environment_id) is None
    deadline = time.monotonic() + lease_s * 3
    while (admitted := ours.open(environment_id)) is None:
        assert time.monotonic() < deadline, "the dead process's connection never stopped counting"
        time.sleep(0.2)
    # ... then it is dropped, and the place is ours.
    assert [r.id for r in _rows(sessions)] == [admitted]
    ours.close_all()


def test_renewal_keeps_a_quiet_connection_counted(sessions: sessionmaker[Session], environment_id: int) -> None:
    lease_s = 2.0
    holder = TrackConnections(sessions, limit=1, lease_s=lease_s)
    other = TrackConnections(sessions, limit=1, lease_s=lease_s)
    held = holder.open(environment_id)
    assert held is not None
    opened = _rows(sessions)[0].seen_at
    time.sleep(lease_s * 1.6)
    assert other.open(environment_id) is None  # renewed by its holder's thread, not stale
    [row] = _rows(sessions)
    assert row.id == held and row.seen_at > opened
    holder.close(held)
    assert other.open(environment_id) is not None
    other.close_all()
    holder.close_all()


def test_deleting_the_environment_deletes_its_connections(sessions: sessionmaker[Session],
                                                          environment_id: int) -> None:
    connections = TrackConnections(sessions, limit=1, lease_s=30)
    held = connections.open(environment_id)
    assert held is not None
    with sessions() as session:
        environments.delete(session, environment_id)
    assert _rows(sessions) == []
    assert connections.renew() == 0  # gone meanwhile: no error
    connections.close(held)
    connections.close_all()
