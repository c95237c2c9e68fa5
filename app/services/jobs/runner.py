"""The web process's side of jobs: the queue, the worker processes it spawns, at most
``max_concurrent`` at a time, and the recovery of jobs a dead server left behind."""

from __future__ import annotations

import logging
import multiprocessing
import queue
import shutil
import threading
from pathlib import Path

from pydantic import BaseModel
from sqlalchemy.orm import Session, sessionmaker

from app.models import Job
from app.services.jobs import store
from app.services.jobs.registry import RegisteredHandler, handler_for
from app.services.jobs.worker import WorkerSetup, run_job

log = logging.getLogger("app.jobs")


class JobRunner:
    """Runs queued jobs in spawned worker processes, ``max_concurrent`` at a time."""

    def __init__(self, database_url: str, busy_timeout_ms: int, data_dir: Path,
                 sessions: sessionmaker[Session], max_concurrent: int = 1) -> None:
        self._setup = WorkerSetup(database_url, busy_timeout_ms, data_dir)
        self._sessions = sessions
        self._data_dir = data_dir
        self._queue: queue.Queue[tuple[str, RegisteredHandler] | None] = queue.Queue()
        self._processes: dict[str, multiprocessing.process.BaseProcess] = {}
        self._lock = threading.Lock()
        self._threads = [
            threading.Thread(target=self._dispatch, name=f"job-dispatch-{i}", daemon=True)
            for i in range(max(1, max_concurrent))
        ]
        self._spawn = multiprocessing.get_context("spawn")

    def start(self) -> None:
        """Fail the jobs a dead server left queued or running, remove their uploads, and
        start dispatching."""
        with self._sessions() as session:
            failed = store.fail_interrupted(session, "the server stopped while this job was queued or running")
        if failed:
            log.warning("marked %d interrupted job(s) failed", failed)
        # Uploads of jobs that will never run again; a live sibling's stay.
        uploads = self._data_dir / "uploads"
        if uploads.is_dir():
            with self._sessions() as session:
                active = store.active_ids(session)
            for folder in uploads.iterdir():
                if folder.name not in active:
                    shutil.rmtree(folder, ignore_errors=True)
        for thread in self._threads:
            thread.start()

    def submit(self, session: Session, kind: str, params: BaseModel, *, environment_id: int | None = None,
               job_id: str | None = None, max_active: int | None = None) -> Job:
        """Store a job of `kind` (a registered kind; `params` of its handler's model) and
        queue it. With `max_active`, TooMany (429) when that many jobs are queued or running."""
        handler = handler_for(kind)
        if not isinstance(params, handler.params):
            raise TypeError(f"{kind} jobs take {handler.params.__name__}, not {type(params).__name__}")
        job = store.create(session, kind, params, environment_id=environment_id, job_id=job_id,
                           max_active=max_active)
        self._queue.put((job.id, handler))
        return job

    def _dispatch(self) -> None:
        while (item := self._queue.get()) is not None:
            job_id, handler = item
            process = self._spawn.Process(target=run_job, args=(self._setup, job_id, handler), name=f"job-{job_id}")
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
            store.fail(session, [job_id], reason)
        shutil.rmtree(store.uploads_dir(self._data_dir, job_id), ignore_errors=True)

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
