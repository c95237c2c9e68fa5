"""A job's task on a worker of the job engine: claim the job's next attempt, keep saying
it is alive, run the handler, record the outcome."""

from __future__ import annotations

import logging
import shutil
import threading

from app import logs
from app.models import Job
from app.schemas import JobStatus
from app.services.errors import ServiceError
from app.services.jobs import store
from app.services.jobs.cluster import EngineLost, worker_state
from app.services.jobs.context import Cancelled, JobContext
from app.services.jobs.registry import RegisteredHandler

log = logging.getLogger("app.jobs")


def failure_message(exc: Exception, job_id: str) -> str:
    """What a failed job tells its client. A refusal of the input (a `ServiceError`, or a
    `ValueError` such as the survey's `SurveyError`) says why in its own words; any other
    exception is a fault of the service, whose text (``index 0 is out of bounds...``)
    means nothing to the client and may show internals: the log has it, with the job's
    id."""
    if isinstance(exc, ServiceError | ValueError):
        return str(exc) or type(exc).__name__
    return f"internal error ({type(exc).__name__}); the server log has the details under job {job_id}"


class Heartbeat:
    """Writes the attempt's heartbeat every `interval` seconds from a thread of its own (a
    handler may compute for minutes between reports); sets ``context.stopped`` when the row
    no longer runs this attempt."""

    def __init__(self, context: JobContext, interval: float) -> None:
        self.context = context
        self.interval = interval
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"heartbeat-{context.job_id}", daemon=True)

    def __enter__(self) -> Heartbeat:
        self._thread.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self._done.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._done.wait(self.interval):
            try:
                with self.context.sessions() as session:
                    if not store.heartbeat(session, self.context.claim):
                        self.context.stopped.set()
                        return
            except Exception:  # noqa: BLE001  (a busy database: try again next beat)
                log.warning("job heartbeat not written", exc_info=True)


def run_job(job_id: str, handler: RegisteredHandler) -> None:
    """Run job `job_id` with `handler` (the engine's task): its outcome (result, failure or
    cancellation) ends up on its row; its uploads are removed once the job has ended."""
    from distributed import get_worker

    state = worker_state()
    logs.job_id.set(job_id)
    with state.sessions() as session:
        claim = store.claim(session, job_id, get_worker().address, state.settings.job_attempts)
        if claim is None:
            return  # cancelled before it started, or out of attempts
        job = session.get(Job, job_id)
        assert job is not None
        params, environment_id = dict(job.params), job.environment_id
    context = JobContext(claim, environment_id, state.settings.data_dir, state.sessions)
    log.info("job started", extra={"fields": {"kind": handler.kind, "attempt": claim.attempt}})
    try:
        with Heartbeat(context, state.settings.job_heartbeat_s):
            result = handler.run(params, context)
            if not context.finished:
                with context.finishing(result):
                    pass
        log.info("job succeeded")
    except Cancelled:
        log.info("job %s stopped: cancelled, or its attempt %d superseded", job_id, claim.attempt)
    except EngineLost as exc:
        log.warning("job %s: %s", job_id, exc)
        with state.sessions() as session:
            store.fail(session, [job_id], str(exc), stage="interrupted", statuses=(JobStatus.RUNNING,),
                       attempt=claim.attempt)
    except Exception as exc:  # noqa: BLE001  (any failure of the job is reported on the job)
        log.exception("job %s failed", job_id)
        with state.sessions() as session:
            store.fail(session, [job_id], failure_message(exc, job_id), statuses=(JobStatus.RUNNING,),
                       attempt=claim.attempt)
    finally:
        with state.sessions() as session:
            ended = session.scalar(store.status_of(job_id)) not in store.ACTIVE
        if ended:  # (a newer attempt elsewhere still needs them)
            shutil.rmtree(store.uploads_dir(state.settings.data_dir, job_id), ignore_errors=True)
