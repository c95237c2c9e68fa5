"""The entry point of a job's worker process: run one job to its end."""

from __future__ import annotations

import logging
import os
import shutil
import traceback
from dataclasses import dataclass
from pathlib import Path

from app import logs
from app.db import make_engine, make_sessionmaker
from app.schemas import JobStatus
from app.services.errors import ServiceError
from app.services.jobs import store
from app.services.jobs.context import Cancelled, JobContext
from app.services.jobs.registry import RegisteredHandler

log = logging.getLogger("app.jobs")


@dataclass(frozen=True)
class WorkerSetup:
    """What a worker process needs from the web process to reach the job's data."""

    database_url: str
    busy_timeout_ms: int
    data_dir: Path


def failure_message(exc: Exception, job_id: str) -> str:
    """What a failed job tells its client. A refusal of the input (a `ServiceError`, or a
    `ValueError` such as the survey's `SurveyError`) says why in its own words; any other
    exception is a fault of the service, whose text (``index 0 is out of bounds...``)
    means nothing to the client and may show internals: the log has it, with the job's
    id."""
    if isinstance(exc, ServiceError | ValueError):
        return str(exc) or type(exc).__name__
    return f"internal error ({type(exc).__name__}); the server log has the details under job {job_id}"


def run_job(setup: WorkerSetup, job_id: str, handler: RegisteredHandler) -> None:
    """Run the queued job `job_id` with `handler`: its outcome (result, failure or
    cancellation) ends up on its row, and its uploads are removed."""
    parent_pid = os.getppid()
    logs.configure(os.environ.get("FIDOTRACK_LOG_FORMAT", "json"), os.environ.get("FIDOTRACK_LOG_LEVEL", "INFO"))
    logs.job_id.set(job_id)
    engine = make_engine(setup.database_url, setup.busy_timeout_ms)
    sessions = make_sessionmaker(engine)
    try:
        with sessions() as session:
            job = store.start(session, job_id)
            if job is None:
                return  # cancelled before it started
            params = dict(job.params)
            context = JobContext(job.id, job.environment_id, setup.data_dir, sessions, parent_pid=parent_pid)
        log.info("job started", extra={"fields": {"kind": handler.kind}})
        try:
            result = handler.run(params, context)
            if not context.finished:
                with context.finishing(result):
                    pass
            log.info("job succeeded")
        except Cancelled:
            log.info("job %s cancelled", job_id)
        except Exception as exc:  # noqa: BLE001  (any failure of the job is reported on the job)
            log.exception("job %s failed", job_id)
            message = failure_message(exc, job_id)
            with sessions() as session:
                store.fail(session, [job_id], message, statuses=(JobStatus.RUNNING,))
            log.debug("%s", traceback.format_exc())
    finally:
        shutil.rmtree(store.uploads_dir(setup.data_dir, job_id), ignore_errors=True)
        engine.dispose()
