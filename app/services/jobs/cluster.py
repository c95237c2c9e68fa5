"""The job engine: Dask distributed, on a local cluster that `fidotrack serve` starts
itself (the embedded default) or on a scheduler and workers of their own, on any machines
(`fidotrack scheduler`, `fidotrack worker`).

Every worker process reads its settings from its own ``FIDOTRACK_*`` environment (the
local cluster's workers get the web process's). A job runs as one task holding one
``job`` resource: each worker process has one, so each runs at most one job at a time,
while the pieces a job fans out (`map_on_workers`) need none and run on every worker.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import sys
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cache
from typing import TypeVar

from sqlalchemy.orm import Session, sessionmaker

from app.settings import Settings

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
    all take a job's pieces."""
    import dask
    from distributed import Nanny, Scheduler, SpecCluster

    n_workers = max(os.cpu_count() or 1, settings.max_concurrent_jobs)
    env = worker_environment(settings)
    workers = {
        f"local-{k}": {"cls": Nanny, "options": {
            "nthreads": 1, "env": env, "dashboard": False, "preload": [__name__],
            # (Their INFO lines, every start and stop, would fill the server's log.)
            "silence_logs": logging.WARNING,
            "resources": {JOB_RESOURCE: 1} if k < settings.max_concurrent_jobs else {},
        }}
        for k in range(n_workers)
    }
    # (Its HTTP endpoints, health and metrics, on a free port of the loopback.)
    scheduler = {"cls": Scheduler, "options": {"host": "127.0.0.1", "port": 0, "dashboard": False,
                                               "dashboard_address": "127.0.0.1:0"}}
    # The scheduler runs in this process: its INFO lines (every client, every worker) would
    # drown the service's own.
    logging.getLogger("distributed").setLevel(logging.WARNING)
    with dask.config.set(engine_config(settings)):
        return SpecCluster(workers=workers, scheduler=scheduler, silence_logs=logging.WARNING)


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


def run_scheduler(settings: Settings, host: str, port: int) -> None:
    """Run the engine's scheduler until interrupted (`fidotrack scheduler`)."""
    import asyncio

    import dask
    from distributed import Scheduler

    async def serve() -> None:
        async with Scheduler(host=host, port=port, dashboard=False) as scheduler:
            log.info("job scheduler at %s", scheduler.address)
            await scheduler.finished()

    with dask.config.set(engine_config(settings)):
        asyncio.run(serve())


#: How long `fidotrack worker` waits before it starts its workers again after they
#: stopped on their own (their scheduler went away).
WORKER_RESTART_S = 2.0


def run_workers(scheduler: str, n_workers: int, nthreads: int) -> int:
    """Run `n_workers` worker processes for `scheduler` until interrupted (`fidotrack
    worker`), each taking one job at a time. distributed's own worker command supervises
    them (restarts, signals); it ends when its scheduler goes away, so it is started
    again here, to wait for the scheduler's return (workers of a restarted scheduler
    register with it again)."""
    import subprocess
    import time

    command = [sys.executable, "-m", "distributed.cli.dask_worker", scheduler, "--nworkers", str(n_workers),
               "--nthreads", str(nthreads), "--resources", f"{JOB_RESOURCE}=1", "--no-dashboard",
               "--preload", __name__]
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
        process = subprocess.Popen(command, preexec_fn=_die_with_parent)
        code = process.wait()
        if stopping:
            return 0
        log.warning("job workers stopped (exit code %s): their scheduler went away; starting them again in "
                    "%g s", code, WORKER_RESTART_S)
        time.sleep(WORKER_RESTART_S)
