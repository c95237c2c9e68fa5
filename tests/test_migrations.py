"""The schema only changes through migrations, and the service brings any database to
head: an empty SQLite file and an empty PostgreSQL database alike."""

from __future__ import annotations

import multiprocessing
from collections.abc import Iterator
from multiprocessing.synchronize import Barrier
from pathlib import Path

import pytest
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from fastapi.testclient import TestClient
from sqlalchemy import inspect, text

from app import models  # noqa: F401
from app.db import (Base, alembic_config, head_revisions, make_engine, make_sessionmaker, schema_at_head,
                    upgrade_to_head)
from app.main import create_app
from app.services import classifiers
from app.settings import Settings
from tests.conftest import DATABASES, PostgresCluster


def _url(tmp_path: Path) -> str:
    return f"sqlite:///{tmp_path / 'm.db'}"


@pytest.fixture(params=DATABASES)
def empty_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """The URL of an empty database: a new SQLite file, or a new PostgreSQL database."""
    if request.param == "sqlite":
        yield _url(tmp_path)
        return
    cluster: PostgresCluster = request.getfixturevalue("postgres_cluster")
    name = cluster.new_database(migrated=False)
    yield cluster.url(name)
    cluster.drop_database(name)


def test_models_and_migrations_agree(empty_url: str, tmp_path: Path) -> None:
    engine = make_engine(empty_url)
    upgrade_to_head(engine, tmp_path)
    with engine.connect() as connection:
        context = MigrationContext.configure(connection, opts={"compare_type": True})
        differences = compare_metadata(context, Base.metadata)
    assert differences == [], f"models differ from migrations: {differences}"
    engine.dispose()


def test_sqlite_runs_with_wal_foreign_keys_and_busy_timeout(tmp_path: Path) -> None:
    engine = make_engine(_url(tmp_path), busy_timeout_ms=4321)
    with engine.connect() as connection:
        assert connection.execute(text("PRAGMA journal_mode")).scalar_one() == "wal"
        assert connection.execute(text("PRAGMA foreign_keys")).scalar_one() == 1
        assert connection.execute(text("PRAGMA busy_timeout")).scalar_one() == 4321


def test_downgrade_and_upgrade_round_trip(empty_url: str, tmp_path: Path) -> None:
    engine = make_engine(empty_url)
    upgrade_to_head(engine, tmp_path)
    with engine.begin() as connection:
        command.downgrade(alembic_config(connection), "base")
    assert set(inspect(engine).get_table_names()) <= {"alembic_version"}
    assert not schema_at_head(engine)
    upgrade_to_head(engine, tmp_path)
    assert schema_at_head(engine)
    assert {"environments", "maps", "classifiers", "classifier_arrays", "jobs"} <= set(
        inspect(engine).get_table_names()
    )
    engine.dispose()


def _start_worker(url: str, lock_dir: str, migrated: Barrier) -> None:
    """What a server does at start: migrate, then store the default classifier (all the
    workers at once, to give them every chance to collide)."""
    engine = make_engine(url)
    upgrade_to_head(engine, Path(lock_dir))
    migrated.wait(60)
    with make_sessionmaker(engine)() as session:
        classifiers.install_default(session)
    engine.dispose()


def test_workers_starting_together_do_not_collide(empty_url: str, tmp_path: Path) -> None:
    url = empty_url
    # PostgreSQL workers may run on different hosts, each with its own data directory: the
    # database's advisory lock alone must keep them apart.
    lock_dirs = [tmp_path if url.startswith("sqlite") else tmp_path / f"host{i}" for i in range(4)]
    spawn = multiprocessing.get_context("spawn")
    migrated = spawn.Barrier(len(lock_dirs))
    workers = [spawn.Process(target=_start_worker, args=(url, str(lock_dir), migrated)) for lock_dir in lock_dirs]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join(120)
    assert [w.exitcode for w in workers] == [0, 0, 0, 0]
    engine = make_engine(url)
    assert schema_at_head(engine)
    with engine.connect() as connection:
        assert connection.execute(text("SELECT count(*) FROM alembic_version")).scalar_one() == 1
        assert connection.execute(text("SELECT count(*) FROM classifiers")).scalar_one() == 1
    engine.dispose()


def test_service_migrates_an_old_database_on_start_and_readyz_tracks_it(empty_url: str, tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path, database_url=empty_url)
    engine = make_engine(settings.resolved_database_url)
    upgrade_to_head(engine, tmp_path)
    with engine.begin() as connection:
        command.downgrade(alembic_config(connection), "base")
    with TestClient(create_app(settings)) as client:
        ready = client.get("/readyz")
        assert ready.status_code == 200 and ready.json()["status"] == "ready"
        assert ready.json()["schema_revision"] == sorted(head_revisions())
        with client.app.state.engine.begin() as connection:
            command.downgrade(alembic_config(connection), "base")
        behind = client.get("/readyz")
        assert behind.status_code == 503 and behind.json()["status"] == "not ready"
    engine.dispose()
