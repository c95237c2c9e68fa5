"""The job engine: Dask distributed, on a local cluster that `fidotrack serve` starts
itself (the embedded default) or on a scheduler and workers of their own, on any machines
(`fidotrack scheduler`, `fidotrack worker`).

Every worker process reads its settings from its own ``FIDOTRACK_*`` environment (the
local cluster's workers get the web process's). A job runs as one task holding one
``job`` resource: each worker process has one, so each runs at most one job at a time,
while the pieces a job fans out (`map_on_workers`) need none and run on every worker.

Whoever can send a message to a scheduler, a nanny or a worker can run code there (Dask's
``run`` operation takes a pickled function). So every socket of the engine listens where
it is told, the loopback unless told otherwise, and Dask's HTTP endpoints (health, metrics)
only on the loopback; the local cluster speaks TLS with a key it makes at its start, and an
engine across machines speaks TLS with certificates of the deployment's own authority
(`engine_security`), each end accepting only a peer holding one.
"""

from __future__ import annotations

import ctypes
import ipaddress
import logging
import os
import signal
import sys
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar
from urllib.parse import urlsplit

from sqlalchemy.orm import Session, sessionmaker

from app.settings import Settings

if TYPE_CHECKING:
    from distributed import Security

S = TypeVar("S")
I = TypeVar("I")  # noqa: E741
R = TypeVar("R")

#: The resource a job task holds: one per worker process.
JOB_RESOURCE = "job"
#: prctl's option to have a signal sent when the parent process dies (linux/prctl.h).
PR_SET_PDEATHSIG = 1
#: Settings the local cluster's workers take from the web process (through their environment).
_WORKER_SETTINGS = ("data_dir", "sqlite_busy_timeout_ms", "log_format", "log_level", "job_heartbeat_s",
                    "job_attempts", "max_image_pixels")

log = logging.getLogger("app.jobs")

#: Where the engine's sockets listen unless told otherwise.
LOOPBACK = "127.0.0.1"
#: Dask's HTTP endpoints of every scheduler and worker (health, metrics, and pages that
#: show the workers and their logs): on the loopback, at a free port. No dashboard.
HTTP_ADDRESS = f"{LOOPBACK}:0"
#: `fidotrack scheduler`'s HTTP endpoints: on the loopback, at Dask's usual port (another
#: when it is taken), for a health check on its machine (``/health``).
SCHEDULER_HTTP_ADDRESS = f"{LOOPBACK}:8787"


class EngineSetupError(ValueError):
    """The engine's addresses or certificates cannot be used as given; says why."""


@dataclass(frozen=True)
class EngineTls:
    """The PEM files of one process of the engine: the authority's certificate, and the
    process's certificate (which that authority signed) and key."""

    ca_file: Path
    cert_file: Path
    key_file: Path

    def security(self) -> Security:
        """Dask's TLS with mutual authentication: every connection is TLS, and each end
        accepts only a peer whose certificate the authority signed."""
        from distributed import Security

        files = {"tls_ca_file": str(self.ca_file)}
        for role in ("client", "scheduler", "worker"):
            files[f"tls_{role}_cert"] = str(self.cert_file)
            files[f"tls_{role}_key"] = str(self.key_file)
        return Security(require_encryption=True, **files)


def engine_tls(settings: Settings) -> EngineTls | None:
    """The engine's TLS files from `settings` (``job_tls_*``); None when none is set;
    EngineSetupError when only some are, or one cannot be read."""
    files = (settings.job_tls_ca_file, settings.job_tls_cert_file, settings.job_tls_key_file)
    if all(f is None for f in files):
        return None
    if any(f is None for f in files):
        raise EngineSetupError("the job engine's TLS needs all three of FIDOTRACK_JOB_TLS_CA_FILE, "
                               "FIDOTRACK_JOB_TLS_CERT_FILE and FIDOTRACK_JOB_TLS_KEY_FILE")
    unreadable = [str(f) for f in files if f is not None and not os.access(f, os.R_OK)]
    if unreadable:
        raise EngineSetupError(f"the job engine's TLS files cannot be read: {', '.join(unreadable)}")
    ca_file, cert_file, key_file = files
    assert ca_file is not None and cert_file is not None and key_file is not None
    return EngineTls(ca_file, cert_file, key_file)


def engine_security(settings: Settings, address: str) -> Security | None:
    """How a process connects to the scheduler at `address`: TLS with the certificates of
    `settings` for ``tls://``, plain for ``tcp://`` (None); EngineSetupError when the two
    do not match (a ``tls://`` scheduler without certificates, or certificates and a
    ``tcp://`` scheduler, which would take them to mean nothing)."""
    tls = engine_tls(settings)
    scheme = urlsplit(address).scheme
    if scheme == "tls" and tls is None:
        raise EngineSetupError(f"the job scheduler {address} speaks TLS: set FIDOTRACK_JOB_TLS_CA_FILE, "
                               "FIDOTRACK_JOB_TLS_CERT_FILE and FIDOTRACK_JOB_TLS_KEY_FILE")
    if scheme != "tls" and tls is not None:
        raise EngineSetupError(f"the job engine's TLS is set: give the scheduler as tls://, not {address}")
    return None if tls is None else tls.security()


def write_tls_files(security: Security, folder: Path) -> EngineTls:
    """The in-memory certificate and key of `security` (a local cluster's) as files in
    `folder`, readable by this user only, for other processes of this server to connect."""
    files = EngineTls(folder / "ca.pem", folder / "engine.pem", folder / "engine-key.pem")
    for path, text in ((files.ca_file, security.tls_ca_file), (files.cert_file, security.tls_client_cert),
                       (files.key_file, security.tls_client_key)):
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as out:
            out.write(text)
    return files


def is_loopback(host: str) -> bool:
    """Whether `host` (an address or a name) is on the loopback; a name other than
    localhost is taken to be off it (it is not looked up)."""
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def insecure_reason(command: str, hosts: Sequence[str]) -> str | None:
    """Why `command` may not use `hosts` without TLS (the first off the loopback), or
    None when all are on the loopback."""
    remote = [host for host in hosts if not is_loopback(host)]
    if not remote:
        return None
    return (f"fidotrack {command}: refusing {remote[0]} without TLS: whoever reaches the job engine's ports can run "
            "code as this user; set FIDOTRACK_JOB_TLS_CA_FILE, _CERT_FILE and _KEY_FILE (`fidotrack engine-certs` "
            "makes them), or give --insecure on a network only the engine's machines reach")


def engine_config(settings: Settings) -> dict[str, object]:
    """Dask settings of a scheduler that runs fidotrack's jobs. A job whose worker died is
    run again; the job's row bounds the runs (`store.claim` fails the job, saying why, at
    the run after its last attempt), so the engine gives up one run later than that."""
    return {
        "distributed.scheduler.allowed-failures": settings.job_attempts,
        # Idle workers keep their processes: a survey's pieces start on warm workers.
        "distributed.scheduler.idle-timeout": None,
    }


def worker_environment(settings: Settings) -> dict[str, str]:
    """The ``FIDOTRACK_*`` variables that give a worker process the web process's settings."""
    env = {f"FIDOTRACK_{name.upper()}": str(getattr(settings, name)) for name in _WORKER_SETTINGS}
    env["FIDOTRACK_DATABASE_URL"] = settings.resolved_database_url
    env["FIDOTRACK_DATA_DIR"] = str(settings.data_dir.resolve())
    return env


def local_cluster(settings: Settings):  # type: ignore[no-untyped-def]  (distributed.SpecCluster)
    """The embedded engine: a scheduler on 127.0.0.1 and one single-threaded worker process
    per core (at least `max_concurrent_jobs`); the first `max_concurrent_jobs` take jobs,
    all take a job's pieces. Every socket is on the loopback, and TLS with a key made here
    (held in memory, handed to the workers through their nannies' pipes) keeps the other
    users of the machine from running code through them."""
    import dask
    from distributed import Nanny, Scheduler, Security, SpecCluster

    n_workers = max(os.cpu_count() or 1, settings.max_concurrent_jobs)
    env = worker_environment(settings)
    security = Security.temporary()
    listen = {"host": LOOPBACK, "protocol": "tls", "security": security}
    workers = {
        f"local-{k}": {"cls": Nanny, "options": {
            **listen, "nthreads": 1, "env": env, "dashboard": False, "dashboard_address": HTTP_ADDRESS,
            "preload": [__name__],
            # (Their INFO lines, every start and stop, would fill the server's log.)
            "silence_logs": logging.WARNING,
            "resources": {JOB_RESOURCE: 1} if k < settings.max_concurrent_jobs else {},
        }}
        for k in range(n_workers)
    }
    scheduler = {"cls": Scheduler, "options": {**listen, "port": 0, "dashboard": False,
                                               "dashboard_address": HTTP_ADDRESS}}
    # The scheduler runs in this process: its INFO lines (every client, every worker) would
    # drown the service's own.
    logging.getLogger("distributed").setLevel(logging.WARNING)
    with dask.config.set(engine_config(settings)):
        return SpecCluster(workers=workers, scheduler=scheduler, silence_logs=logging.WARNING, security=security)


# --- on a worker ---------------------------------------------------------------------------


class EngineLost(RuntimeError):
    """The job engine failed a job from under it: its scheduler gone, or the workers of
    its pieces dying past the engine's retries."""


@dataclass(frozen=True)
class WorkerState:
    """A worker process's settings and database, made once per process."""

    settings: Settings
    sessions: sessionmaker[Session]


@cache
def worker_state() -> WorkerState:
    from app import logs
    from app.db import make_engine, make_sessionmaker

    settings = Settings()
    logs.configure(settings.log_format, settings.log_level)
    engine = make_engine(settings.resolved_database_url, settings.sqlite_busy_timeout_ms)
    return WorkerState(settings, make_sessionmaker(engine))


def dask_setup(worker: object) -> None:
    """(Dask's preload hook, in each worker process at its start.) The worker dies with the
    process that started it: a local cluster's workers with their server, a `fidotrack
    worker`'s with it, even when it is killed outright. Its job is then failed or run
    again as for any dead worker, rather than finished behind a restarted server's back."""
    _die_with_parent()


def _die_with_parent() -> None:
    """Have this process killed when its parent dies (Linux; elsewhere nothing)."""
    if sys.platform == "linux":
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
        if os.getppid() == 1:  # its parent died before the line above
            os._exit(1)


def on_worker() -> bool:
    """Whether this code runs in a task of the job engine."""
    from distributed import get_worker

    try:
        get_worker()
    except ValueError:
        return False
    return True


def map_on_workers(function: Callable[[S, I], R], shared: S, items: Sequence[I],
                   done: Callable[[int, int], None], job_id: str) -> list[R]:
    """``[function(shared, item) for item in items]`` over every worker of the engine (see
    `JobContext.fan_out`); in this process when it is not a worker's."""
    total = len(items)
    if total <= 1 or not on_worker():
        results = []
        for finished, item in enumerate(items, 1):
            results.append(function(shared, item))
            done(finished, total)
        return results
    from concurrent.futures import CancelledError

    from distributed import KilledWorker, as_completed, worker_client
    from distributed.comm.core import CommClosedError

    results: list[R | None] = [None] * total
    try:
        # Leaves the worker's thread to the pieces while this task waits (it keeps its job slot).
        with worker_client() as client:
            sent = client.scatter(shared, broadcast=True, hash=False)
            run = uuid.uuid4().hex[:8]
            futures = client.map(function, [sent] * total, list(items), pure=False,
                                 key=[f"{job_id}-{run}-part-{k}" for k in range(total)])
            index = {future.key: k for k, future in enumerate(futures)}
            try:
                for finished, future in enumerate(as_completed(futures), 1):
                    results[index[future.key]] = future.result()
                    done(finished, total)
            finally:
                client.cancel(futures)  # those not run yet when `done` stopped the job
    except (CommClosedError, KilledWorker, CancelledError, TimeoutError) as exc:
        raise EngineLost(f"the job engine was lost while the job ran ({type(exc).__name__}): its scheduler or "
                         "the workers running its pieces went away; submit it again") from exc
    return results  # type: ignore[return-value]


# --- the commands -----------------------------------------------------------------------------


def run_scheduler(settings: Settings, host: str, port: int, tls: EngineTls | None) -> None:
    """Run the engine's scheduler on `host`:`port` until interrupted (`fidotrack
    scheduler`): TLS with `tls`'s certificates, else plain TCP."""
    import asyncio

    import dask
    from distributed import Scheduler

    security = None if tls is None else tls.security()

    async def serve() -> None:
        async with Scheduler(host=host, port=port, protocol="tcp" if tls is None else "tls", security=security,
                             dashboard=False, dashboard_address=SCHEDULER_HTTP_ADDRESS) as scheduler:
            log.info("job scheduler at %s", scheduler.address)
            await scheduler.finished()

    with dask.config.set(engine_config(settings)):
        asyncio.run(serve())


#: How long `fidotrack worker` waits before it starts its workers again after they
#: stopped on their own (their scheduler went away).
WORKER_RESTART_S = 2.0


def run_workers(scheduler: str, n_workers: int, nthreads: int, host: str, tls: EngineTls | None) -> int:
    """Run `n_workers` worker processes for `scheduler` until interrupted (`fidotrack
    worker`), each taking one job at a time, their nannies and workers listening on
    `host`, with TLS when `tls` is given. distributed's own worker command supervises
    them (restarts, signals); it ends when its scheduler goes away, so it is started
    again here, to wait for the scheduler's return (workers of a restarted scheduler
    register with it again)."""
    import subprocess
    import time

    command = [sys.executable, "-m", "distributed.cli.dask_worker", scheduler, "--nworkers", str(n_workers),
               "--nthreads", str(nthreads), "--resources", f"{JOB_RESOURCE}=1", "--host", host,
               "--no-dashboard", "--dashboard-address", HTTP_ADDRESS, "--preload", __name__]
    env = dict(os.environ)
    if tls is not None:
        command += ["--tls-ca-file", str(tls.ca_file), "--tls-cert", str(tls.cert_file),
                    "--tls-key", str(tls.key_file)]
        # (Dask's distributed.comm.require-encryption: every connection TLS, none plain.)
        env["DASK_DISTRIBUTED__COMM__REQUIRE_ENCRYPTION"] = "True"
    stopping: list[int] = []
    process: subprocess.Popen[bytes] | None = None

    def stop(signum: int, _frame: object) -> None:
        stopping.append(signum)
        if process is not None:
            process.send_signal(signum)

    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, stop)
    while True:
        # (It dies with this process, as its workers die with it.)
        process = subprocess.Popen(command, env=env, preexec_fn=_die_with_parent)
        code = process.wait()
        if stopping:
            return 0
        log.warning("job workers stopped (exit code %s): their scheduler went away; starting them again in "
                    "%g s", code, WORKER_RESTART_S)
        time.sleep(WORKER_RESTART_S)
