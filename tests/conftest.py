"""Shared fixtures and helpers: every test gets its own data directory and database.
Real server processes, free ports, job waits and the example map come from
`app.local_server` (the benchmarks and scripts use it too); the names here fail the test
where that module raises.

The API tests (those that use the ``settings`` or ``client`` fixture, and those under
``tests/routers/`` that build a service on their own ``tmp_path``) run twice, on SQLite
and on PostgreSQL: their ids end in ``[sqlite]`` or ``[postgresql]``. PostgreSQL is a
throwaway cluster of the distribution's server, started once per test run on a unix
socket in a temporary directory; each test gets a fresh database copied from a migrated
template, and ``FIDOTRACK_DATABASE_URL`` names it, so that every ``Settings()`` the test
builds (and every server process it starts) uses it."""

from __future__ import annotations

import itertools
import os
import pwd
import shutil
import subprocess
import tempfile
import time
from collections.abc import Callable, Collection, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient

from app import local_server
from app.db import make_engine, upgrade_to_head
from app.local_server import (  # example_map and free_port: for the tests, which import them from here
    FINISHED,
    ServerNotReady,
    example_map,  # noqa: F401
    fidotrack_command,
    free_port,  # noqa: F401
)
from app.local_server import LocalServer as Server
from app.main import create_app
from app.settings import Settings

#: ``fidotrack serve`` of this environment.
FIDOTRACK_SERVE = [*fidotrack_command(), "serve"]


#: The engines the API tests run on, as their ids name them.
DATABASES = ("sqlite", "postgresql")
#: Where the distribution's packages put each PostgreSQL version's server programs.
POSTGRES_LIBS = Path("/usr/lib/postgresql")
#: Why PostgreSQL variants skip on a machine without the server.
NO_POSTGRES = "needs PostgreSQL: apt-get install postgresql (.ci/run does)"


def postgres_bin_dir() -> Path | None:
    """The directory of initdb, pg_ctl and postgres: on PATH, else the newest version the
    distribution installed (Debian keeps them off PATH); None when there is none."""
    on_path = shutil.which("pg_ctl")
    if on_path and shutil.which("initdb"):
        return Path(on_path).parent
    versions = [d.parent for d in POSTGRES_LIBS.glob("*/bin") if (d / "initdb").exists() and d.parent.name.isdigit()]
    return max(versions, key=lambda d: int(d.name)) / "bin" if versions else None


@dataclass
class PostgresCluster:
    """A throwaway PostgreSQL server listening only on a unix socket in `directory`."""

    directory: Path
    bin_dir: Path
    #: The user its programs run as: they refuse to run as root, so tests run as root
    #: start the server as the distribution's ``postgres`` user.
    run_as: str | None
    template: str = "fidotrack_template"
    _names: Iterator[int] = field(default_factory=itertools.count)

    def url(self, database: str) -> str:
        return f"postgresql+psycopg://postgres@/{database}?host={self.directory}"

    def _command(self, program: str, *args: str) -> list[str]:
        command = [str(self.bin_dir / program), *args]
        return ["runuser", "-u", self.run_as, "--", *command] if self.run_as else command

    def start(self) -> None:
        data = self.directory / "data"
        subprocess.run(self._command("initdb", "-D", str(data), "-U", "postgres", "-A", "trust", "-E", "UTF8",
                                     "--no-sync", "--no-instructions"),
                       check=True, capture_output=True, cwd=self.directory)
        # Durability is of no use to a cluster deleted at the end of the run.
        options = (f"-k {self.directory} -c listen_addresses= -c fsync=off -c synchronous_commit=off "
                   "-c full_page_writes=off -c max_connections=200")
        subprocess.run(self._command("pg_ctl", "-D", str(data), "-l", str(self.directory / "server.log"),
                                     "-o", options, "-w", "-s", "start"), check=True, capture_output=True,
                       cwd=self.directory)

    def stop(self) -> None:
        subprocess.run(self._command("pg_ctl", "-D", str(self.directory / "data"), "-m", "immediate", "-s", "stop"),
                       capture_output=True, cwd=self.directory)

    def execute(self, *statements: str) -> None:
        """Run statements outside a transaction (CREATE and DROP DATABASE need that)."""
        engine = make_engine(self.url("postgres"))
        try:
            with engine.connect().execution_options(isolation_level="AUTOCOMMIT") as connection:
                for statement in statements:
                    connection.exec_driver_sql(statement)
        finally:
            engine.dispose()

    def migrate_template(self) -> None:
        """The template every test database is copied from: the schema at head. Copying it
        takes about 40 ms; creating an empty database and migrating it, about 270 ms."""
        self.execute(f"CREATE DATABASE {self.template}")
        engine = make_engine(self.url(self.template))
        try:
            upgrade_to_head(engine, self.directory)
        finally:
            engine.dispose()

    def new_database(self, *, migrated: bool = True) -> str:
        """The name of a fresh database, at the newest schema or (not `migrated`) empty."""
        name = f"fidotrack_{next(self._names)}"
        self.execute(f"CREATE DATABASE {name}" + (f" TEMPLATE {self.template}" if migrated else ""))
        return name

    def drop_database(self, name: str) -> None:
        # FORCE: a job's worker process may still hold a connection when the test ends.
        self.execute(f"DROP DATABASE IF EXISTS {name} WITH (FORCE)")


@pytest.fixture(scope="session")
def postgres_cluster() -> Iterator[PostgresCluster]:
    """One PostgreSQL server for the whole run, with the migrated template; skips its
    tests where the server or the driver is not installed."""
    bin_dir = postgres_bin_dir()
    if bin_dir is None:
        pytest.skip(NO_POSTGRES)
    try:
        import psycopg  # noqa: F401
    except ImportError:
        pytest.skip("needs the PostgreSQL driver: pip install -e '.[postgres]' (the test extra has it)")
    run_as = None
    if os.geteuid() == 0:
        try:
            run_as = pwd.getpwnam("postgres").pw_name
        except KeyError:
            pytest.skip("needs the `postgres` user to run PostgreSQL as (the postgresql package creates it)")
    # Under the system's temporary directory, not pytest's: that one is private to the
    # user running the tests, which the server's user may not enter.
    directory = Path(tempfile.mkdtemp(prefix="fidotrack-pg-"))
    if run_as:
        shutil.chown(directory, run_as, run_as)
    cluster = PostgresCluster(directory, bin_dir, run_as)
    try:
        cluster.start()
        cluster.migrate_template()
        yield cluster
    finally:
        cluster.stop()
        shutil.rmtree(directory, ignore_errors=True)


def _runs_the_service(metafunc: pytest.Metafunc) -> bool:
    """Whether a test stores through the service: it uses `settings` (or `client`), or it
    is an API test that builds a service on its own temporary directory."""
    names = metafunc.fixturenames
    in_routers = Path(__file__).parent / "routers" in Path(metafunc.definition.path).parents
    return "settings" in names or (in_routers and "tmp_path" in names)


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if "database" in metafunc.fixturenames and _runs_the_service(metafunc):
        metafunc.parametrize("database", DATABASES, indirect=True)


@pytest.fixture(autouse=True)
def database(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """The engine this test's service stores in, "sqlite" unless the test runs on both:
    for "postgresql", ``FIDOTRACK_DATABASE_URL`` names a fresh database, dropped after."""
    engine: str = getattr(request, "param", "sqlite")
    if engine == "sqlite":
        # So that a variable set around the run does not turn a SQLite test into another.
        monkeypatch.delenv("FIDOTRACK_DATABASE_URL", raising=False)
        return engine
    cluster: PostgresCluster = request.getfixturevalue("postgres_cluster")
    name = cluster.new_database()
    request.addfinalizer(lambda: cluster.drop_database(name))
    monkeypatch.setenv("FIDOTRACK_DATABASE_URL", cluster.url(name))
    return engine


@pytest.fixture
def settings(tmp_path: Path, database: str) -> Settings:
    settings = Settings(data_dir=tmp_path / "data")
    assert settings.resolved_database_url.startswith(database)
    return settings


@pytest.fixture
def client(settings: Settings) -> Iterator[TestClient]:
    with TestClient(create_app(settings)) as test_client:
        # On a cold kernel cache the app answers while it compiles: wait as a client would.
        deadline = time.monotonic() + 300
        while test_client.get("/readyz").status_code != 200 and time.monotonic() < deadline:
            time.sleep(0.2)
        yield test_client


def wait_for_job(client: httpx.Client, job_id: str,
                 until: Collection[str] | Callable[[dict[str, Any]], bool] = FINISHED,
                 timeout: float = 240.0, poll: float = 0.2) -> dict[str, Any]:
    """The job as ``GET /jobs/{id}`` shows it once its status is in `until` (or `until`
    says so of it); fails the test after `timeout` seconds. `client` is a TestClient or
    an httpx client of a real server."""
    try:
        return local_server.wait_for_job(client, job_id, until, timeout=timeout, poll=poll)
    except TimeoutError as error:
        pytest.fail(str(error))


def start_server(data_dir: Path, log: Path, *, port: int | None = None,
                 command: Sequence[str] | None = None) -> Server:
    """Start `command` (``fidotrack serve`` unless told; it must take its port from
    ``FIDOTRACK_PORT`` or its own arguments) on `data_dir` with this process's
    environment, its output appended to `log`, and wait until ``/readyz`` says ready;
    fails the test, quoting the log, when it does not."""
    try:
        return local_server.start_server(data_dir, port=port, command=command, log=log, timeout=60)
    except ServerNotReady as error:
        pytest.fail(str(error))


@contextmanager
def running_server(data_dir: Path, log: Path, *, port: int | None = None,
                   command: Sequence[str] | None = None) -> Iterator[Server]:
    """`start_server`, stopped when the block ends."""
    server = start_server(data_dir, log, port=port, command=command)
    try:
        yield server
    finally:
        server.stop()


#: Debian's Chromium, which the browser tests drive through Playwright (skipped without it).
CHROMIUM = shutil.which("chromium")
NEEDS_CHROMIUM = pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium: apt-get install chromium (.ci/run does)")


@pytest.fixture(scope="module")
def playwright() -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as driver:
        yield driver


@pytest.fixture(scope="module")
def browser(playwright: Any) -> Iterator[Any]:
    launched = playwright.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
    yield launched
    launched.close()
