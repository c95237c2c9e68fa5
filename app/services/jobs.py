"""Long-running jobs (surveys, classifier training) in worker processes.

A job is a row in ``jobs``; the web process only creates and reads rows. Each job runs in
its own spawned process (vision work holds the CPU for minutes and must not stall the
event loop or the GIL of the web process), which writes its stage and progress to the
database and checks there, at each progress report, whether it was cancelled. At most
``max_concurrent_jobs`` run at once; the rest wait in a queue.
"""

from __future__ import annotations

import importlib
import logging
import multiprocessing
import os
import socket
import queue
import shutil
import threading
import time
import traceback
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session, sessionmaker

from app import logs
from app.db import make_engine, make_sessionmaker, utcnow
from app.models import Job
from app.schemas import JobOut
from app.services.errors import TooMany, get_or_404

log = logging.getLogger("app.jobs")

ACTIVE = ("queued", "running")
# Job kind -> "module:function" run in the worker; looked up by name so that the worker
# process imports only what its job needs.
HANDLERS: dict[str, str] = {
    "train_classifier": "app.services.classifiers:run_training_job",
    "survey": "app.services.surveys:run_survey_job",
}


class Cancelled(Exception):
    """Raised inside a job when its row says it was cancelled."""


def job_out(job: Job) -> JobOut:
    return JobOut.model_validate(job, from_attributes=True)


def uploads_dir(data_dir: Path, job_id: str) -> Path:
    """Where a job's uploads live: server-chosen names only, removed when the job ends."""
    return data_dir / "uploads" / job_id


def runner_id() -> str:
    """This web process, as recorded on the jobs it owns."""
    return f"{socket.gethostname()}:{os.getpid()}"


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def create(session: Session, kind: str, params: dict[str, Any], environment_id: int | None = None,
           job_id: str | None = None, max_active: int | None = None) -> Job:
    """Queue a job row (the caller submits it to the runner). With `max_active`, 429
    when that many jobs are already queued or running."""
    if kind not in HANDLERS:
        raise ValueError(f"unknown job kind {kind!r}")
    if max_active is not None:
        active = session.scalar(select(func.count()).select_from(Job).where(Job.status.in_(ACTIVE))) or 0
        if active >= max_active:
            raise TooMany(f"{active} jobs are queued or running (the limit is {max_active}); try again later")
    job = Job(id=job_id or new_job_id(), kind=kind, params=params, environment_id=environment_id,
              status="queued", progress=0.0, stage="queued", message="", runner=runner_id())
    session.add(job)
    session.commit()
    return job


def new_job_id() -> str:
    return uuid.uuid4().hex


def get(session: Session, job_id: str) -> Job:
    return get_or_404(session, Job, job_id, "job")


def cancel(session: Session, job_id: str) -> Job:
    """Mark a queued or running job cancelled; the worker stops at its next progress
    report. Finished jobs are returned as they are."""
    job = get(session, job_id)
    if job.status in ACTIVE:
        job.status = "cancelled"
        job.stage = "cancelled"
        job.message = "cancelled by request"
        job.finished_at = utcnow()
        session.commit()
    return job


def fail_interrupted(session: Session, reason: str) -> int:
    """Jobs left queued or running by a web process that died are failed, never left
    hanging. Jobs of a sibling process on this host that is still alive are left alone;
    a job owned by another host cannot be checked from here and is failed only when it
    has no owner recorded."""
    host = socket.gethostname()
    me = runner_id()
    orphans = []
    for job_id, runner in session.execute(select(Job.id, Job.runner).where(Job.status.in_(ACTIVE))):
        owner_host, _, pid = (runner or "").rpartition(":")
        if runner is None or runner == me or (owner_host == host and not (pid.isdigit() and _process_alive(int(pid)))):
            orphans.append(job_id)
    if not orphans:
        return 0
    result = session.execute(
        update(Job)
        .where(Job.id.in_(orphans), Job.status.in_(ACTIVE))
        .values(status="failed", stage="interrupted", error=reason, message=reason, finished_at=utcnow())
    )
    session.commit()
    return int(result.rowcount or 0)  # type: ignore[attr-defined]


# --- inside the worker process ------------------------------------------------------


@dataclass
class JobContext:
    """What a job handler gets: its parameters, the database and progress reporting."""

    job_id: str
    kind: str
    params: dict[str, Any]
    environment_id: int | None
    data_dir: Path
    sessions: sessionmaker[Session]
    finished: bool = False
    parent_pid: int | None = None
    _last_write: float = field(default=0.0, repr=False)

    def progress(self, stage: str, fraction: float, message: str = "") -> None:
        """Report progress (at most a few writes a second) and stop if cancelled, or if
        the web process that started this worker is gone (its restart fails the job)."""
        if self.parent_pid is not None and os.getppid() != self.parent_pid:
            raise Cancelled(self.job_id)
        now = time.monotonic()
        if now - self._last_write < 0.2 and fraction < 1.0:
            return
        self._last_write = now
        with self.sessions() as session:
            status = session.scalar(select(Job.status).where(Job.id == self.job_id))
            if status != "running":
                raise Cancelled(self.job_id)
            session.execute(
                update(Job)
                .where(Job.id == self.job_id)
                .values(stage=stage[:64], progress=min(max(float(fraction), 0.0), 1.0), message=message)
            )
            session.commit()

    @contextmanager
    def finishing(self, result: dict[str, Any]) -> Iterator[Session]:
        """A session whose changes commit together with the job's success, or not at
        all if the job was cancelled meanwhile (so a cancelled survey changes nothing).
        ``result`` is stored as it is when the block ends (the block may fill it in)."""
        with self.sessions() as session:
            yield session
            job = session.get(Job, self.job_id, with_for_update=True)
            if job is None or job.status != "running":
                session.rollback()
                raise Cancelled(self.job_id)
            job.status, job.stage, job.progress = "succeeded", "done", 1.0
            job.result, job.finished_at, job.message = dict(result), utcnow(), "done"
            session.commit()
            self.finished = True


def execute_job(database_url: str, busy_timeout_ms: int, data_dir: str, job_id: str, handler_path: str) -> None:
    """Entry point of a worker process: run one job to its end with the handler at
    ``handler_path`` ("module:function")."""
    parent_pid = os.getppid()
    logs.configure(os.environ.get("FIDOTRACK_LOG_FORMAT", "json"), os.environ.get("FIDOTRACK_LOG_LEVEL", "INFO"))
    logs.job_id.set(job_id)
    engine = make_engine(database_url, busy_timeout_ms)
    sessions = make_sessionmaker(engine)
    try:
        with sessions() as session:
            job = session.get(Job, job_id)
            if job is None or job.status != "queued":
                return  # cancelled before it started
            job.status, job.stage, job.started_at = "running", "starting", utcnow()
            session.commit()
            context = JobContext(job.id, job.kind, dict(job.params), job.environment_id, Path(data_dir), sessions,
                                 parent_pid=parent_pid)
        log.info("job started", extra={"fields": {"kind": context.kind}})
        module_name, function_name = handler_path.split(":")
        handler: Callable[[JobContext], dict[str, Any]] = getattr(
            importlib.import_module(module_name), function_name
        )
        try:
            result = handler(context)
            if not context.finished:
                with context.finishing(result):
                    pass
            log.info("job succeeded")
        except Cancelled:
            log.info("job %s cancelled", job_id)
        except Exception as exc:  # noqa: BLE001  (any failure of the job is reported on the job)
            log.exception("job %s failed", job_id)
            message = str(exc) or type(exc).__name__
            with sessions() as session:
                session.execute(
                    update(Job)
                    .where(Job.id == job_id, Job.status == "running")
                    .values(status="failed", stage="failed", error=message, message=message,
                            finished_at=utcnow())
                )
                session.commit()
            log.debug("%s", traceback.format_exc())
    finally:
        shutil.rmtree(uploads_dir(Path(data_dir), job_id), ignore_errors=True)
        engine.dispose()


# --- in the web process ---------------------------------------------------------------


class JobRunner:
    """Dispatches queued jobs to worker processes, ``max_concurrent`` at a time."""

    def __init__(self, database_url: str, busy_timeout_ms: int, data_dir: Path,
                 sessions: sessionmaker[Session], max_concurrent: int = 1) -> None:
        self._args = (database_url, busy_timeout_ms, str(data_dir))
        self._sessions = sessions
        self._data_dir = data_dir
        self._queue: queue.Queue[tuple[str, str] | None] = queue.Queue()
        self._processes: dict[str, multiprocessing.process.BaseProcess] = {}
        self._lock = threading.Lock()
        self._threads = [
            threading.Thread(target=self._dispatch, name=f"job-dispatch-{i}", daemon=True)
            for i in range(max(1, max_concurrent))
        ]
        self._spawn = multiprocessing.get_context("spawn")

    def start(self) -> None:
        with self._sessions() as session:
            failed = fail_interrupted(session, "the server stopped while this job was queued or running")
        if failed:
            log.warning("marked %d interrupted job(s) failed", failed)
        # Uploads of jobs that will never run again; a live sibling's stay.
        uploads = self._data_dir / "uploads"
        if uploads.is_dir():
            with self._sessions() as session:
                active = set(session.scalars(select(Job.id).where(Job.status.in_(ACTIVE))))
            for folder in uploads.iterdir():
                if folder.name not in active:
                    shutil.rmtree(folder, ignore_errors=True)
        for thread in self._threads:
            thread.start()

    def submit(self, job_id: str, kind: str) -> None:
        self._queue.put((job_id, HANDLERS[kind]))

    def _dispatch(self) -> None:
        while (item := self._queue.get()) is not None:
            job_id, handler_path = item
            process = self._spawn.Process(
                target=execute_job, args=(*self._args, job_id, handler_path), name=f"job-{job_id}"
            )
            with self._lock:
                self._processes[job_id] = process
            process.start()
            process.join()
            with self._lock:
                self._processes.pop(job_id, None)
            if process.exitcode not in (0, None):
                self._fail_if_active(job_id, f"the job's worker process died (exit code {process.exitcode})")

    def _fail_if_active(self, job_id: str, reason: str) -> None:
        with self._sessions() as session:
            session.execute(
                update(Job).where(Job.id == job_id, Job.status.in_(ACTIVE))
                .values(status="failed", stage="failed", error=reason, message=reason, finished_at=utcnow())
            )
            session.commit()
        shutil.rmtree(uploads_dir(self._data_dir, job_id), ignore_errors=True)

    def shutdown(self) -> None:
        """Stop dispatching; jobs still running are stopped and marked failed (queued ones
        are failed at the next start)."""
        while True:
            try:
                self._queue.get_nowait()
            except queue.Empty:
                break
        for _ in self._threads:
            self._queue.put(None)
        with self._lock:
            running = dict(self._processes)
        for job_id, process in running.items():
            process.terminate()
            process.join(10)
            self._fail_if_active(job_id, "the server shut down while this job was running")
        for thread in self._threads:
            thread.join(15)
