"""Database engine, declarative base and schema migration to head.

SQLite is the embedded default: it runs with WAL (readers never block the writer),
foreign keys on (SQLite leaves them off unless asked) and a busy timeout (so two
workers writing at once wait instead of failing). PostgreSQL (``postgresql+psycopg://``)
is the tested alternative; its sessions run in UTC.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import TypeVar

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Connection, Engine, MetaData, create_engine, event, text
from sqlalchemy.orm import DeclarativeBase, sessionmaker, Session

log = logging.getLogger(__name__)

#: A model class.
M = TypeVar("M", bound="Base")

MIGRATIONS_DIR = Path(__file__).resolve().parent.parent / "migrations"

# Constraint names are fixed from the first revision so that batch-mode migrations
# on SQLite (which recreate tables) can find and alter them later.
NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)


def utcnow() -> datetime:
    return datetime.now(UTC)


def make_engine(url: str, busy_timeout_ms: int = 5000) -> Engine:
    """An engine for ``url``; SQLite connections get WAL, foreign keys and a busy timeout,
    PostgreSQL ones the UTC time zone."""
    is_sqlite = url.startswith("sqlite")
    connect_args: dict[str, object] = {}
    if is_sqlite:
        # Sessions are used from FastAPI's thread pool and from job threads.
        connect_args = {"check_same_thread": False, "timeout": busy_timeout_ms / 1000}
    elif url.startswith("postgresql"):
        # Times come back in the session's zone: UTC, whatever the server's default, so
        # that the API's times read the same on every deployment.
        connect_args = {"options": "-c timezone=UTC"}
    engine = create_engine(url, connect_args=connect_args, pool_pre_ping=not is_sqlite)
    if is_sqlite:

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_connection, _record) -> None:  # type: ignore[no-untyped-def]
            cursor = dbapi_connection.cursor()
            if ":memory:" not in url and url not in ("sqlite://", "sqlite:///"):
                cursor.execute("PRAGMA journal_mode=WAL")
            cursor.execute("PRAGMA foreign_keys=ON")
            cursor.execute(f"PRAGMA busy_timeout={int(busy_timeout_ms)}")
            cursor.close()

    return engine


def make_sessionmaker(engine: Engine) -> sessionmaker[Session]:
    return sessionmaker(engine, expire_on_commit=False)


def lock_for_writing(session: Session, table: str) -> None:
    """Make the session's transaction, until it ends, the only one writing `table` (on
    SQLite: the database), so that a check and the insert it decides cannot interleave
    with another process's; readers go on. Call it before the transaction's first
    statement: SQLite takes its write lock with the transaction's BEGIN."""
    connection = session.connection()
    if connection.dialect.name == "sqlite":
        connection.exec_driver_sql("BEGIN IMMEDIATE")
    elif connection.dialect.name == "postgresql":
        # Conflicts with itself and with writers (ROW EXCLUSIVE), not with readers.
        connection.exec_driver_sql(f"LOCK TABLE {table} IN SHARE ROW EXCLUSIVE MODE")


def lock_row_for_writing(session: Session, model: type[M], key: object) -> M | None:
    """The row of `model` with primary key `key` (None if there is none), read afresh and
    held by the session's transaction until it ends, so that what the transaction reads
    and writes on its account cannot interleave with another writer's; readers go on. On
    SQLite the database's write lock (as `lock_for_writing`), on PostgreSQL that row's
    (``SELECT ... FOR UPDATE``: writers of other rows go on). Call it before the
    transaction's first statement."""
    if session.connection().dialect.name == "sqlite":
        lock_for_writing(session, model.__tablename__)
    return session.get(model, key, with_for_update=True, populate_existing=True)


def alembic_config(connection: Connection | None = None) -> Config:
    """Alembic configuration pointing at the repository's ``migrations/``."""
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    if connection is not None:
        cfg.attributes["connection"] = connection
    return cfg


def head_revisions() -> set[str]:
    return set(ScriptDirectory.from_config(alembic_config()).get_heads())


def current_revisions(connection: Connection) -> set[str]:
    return set(MigrationContext.configure(connection).get_current_heads())


def schema_at_head(engine: Engine) -> bool:
    with engine.connect() as connection:
        return current_revisions(connection) == head_revisions()


@contextlib.contextmanager
def _migration_lock(engine: Engine, lock_dir: Path) -> Iterator[None]:
    """Serialise migrations across processes: a file lock for every backend (workers
    share the data directory), plus an advisory lock on PostgreSQL (workers on other hosts)."""
    lock_dir.mkdir(parents=True, exist_ok=True)
    with open(lock_dir / ".migrate.lock", "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            if engine.dialect.name == "postgresql":
                with engine.connect() as connection:
                    connection.execute(text("SELECT pg_advisory_lock(727001)"))
                    try:
                        yield
                    finally:
                        connection.execute(text("SELECT pg_advisory_unlock(727001)"))
            else:
                yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def upgrade_to_head(engine: Engine, lock_dir: Path) -> None:
    """Bring an empty or old database to the newest schema, once, even when several
    workers start together (the second one finds the schema at head and does nothing)."""
    with _migration_lock(engine, lock_dir):
        with engine.begin() as connection:
            if current_revisions(connection) == head_revisions():
                return
            log.info("migrating database schema to head")
            command.upgrade(alembic_config(connection), "head")
