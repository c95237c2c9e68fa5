"""Job rows: create, read, cancel, and every change of a job's status.

Each function that changes a row commits, except `finish`, whose changes commit together
with the job's own (see `JobContext.finishing`).
"""

from __future__ import annotations

import json
import os
import socket
import uuid
from collections.abc import Collection, Iterable
from pathlib import Path
from datetime import timedelta
from typing import Any, NamedTuple

from pydantic import BaseModel
from sqlalchemy import Select, case, func, select, update
from sqlalchemy.orm import Session

from app.db import lock_for_writing, utcnow
from app.models import Job
from app.schemas import JobOut, JobStatus
from app.services.errors import TooMany, can_match, get_or_404

#: A job in one of these may still change.
ACTIVE = (JobStatus.QUEUED, JobStatus.RUNNING)
#: Most jobs one listing returns, and how many it returns unless told.
MAX_LISTED = 500
DEFAULT_LISTED = 50


def job_out(job: Job) -> JobOut:
    return JobOut.model_validate(job, from_attributes=True)


def new_job_id() -> str:
    return uuid.uuid4().hex


def uploads_dir(data_dir: Path, job_id: str) -> Path:
    """Where a job's uploads live: server-chosen names only, removed when the job ends."""
    return data_dir / "uploads" / job_id


def runner_id() -> str:
    """This process, as "host:pid"."""
    return f"{socket.gethostname()}:{os.getpid()}"


def create(session: Session, kind: str, params: BaseModel, *, engine: str | None = None,
           environment_id: int | None = None, job_id: str | None = None, max_active: int | None = None) -> Job:
    """Store a queued job, to be run by the job engine whose scheduler is at `engine` (None:
    by none; the reaper fails such a row once it is older than a submission takes). With
    `max_active`, TooMany (429) when that many jobs are already queued or running, counted
    and inserted under one lock so that web processes submitting at once cannot overshoot."""
    if max_active is not None:
        session.commit()  # the caller's reads end here: SQLite's write lock opens a transaction
        lock_for_writing(session, "jobs")
        active = count_active(session)
        if active >= max_active:
            session.rollback()
            raise TooMany(f"{active} jobs are queued or running (the limit is {max_active}); try again later")
    job = Job(id=job_id or new_job_id(), kind=kind, params=params.model_dump(mode="json"),
              environment_id=environment_id, status=JobStatus.QUEUED.value, progress=0.0,
              stage=JobStatus.QUEUED.value, message="", runner=engine)
    session.add(job)
    session.commit()
    return job


def get(session: Session, job_id: str) -> Job:
    return get_or_404(session, Job, job_id, "job")


def list_recent(session: Session, *, kind: str | None = None, status: JobStatus | None = None,
                environment_id: int | None = None, limit: int = DEFAULT_LISTED) -> list[Job]:
    """The newest `limit` jobs (at most `MAX_LISTED`) of the given kind, status and
    environment (each filter only when given), newest first."""
    if environment_id is not None and not can_match(environment_id):
        return []
    query = select(Job)
    if kind is not None:
        query = query.where(Job.kind == kind)
    if status is not None:
        query = query.where(Job.status == status.value)
    if environment_id is not None:
        query = query.where(Job.environment_id == environment_id)
    # Ids break ties between jobs created in the same instant: the same order on every call.
    query = query.order_by(Job.created_at.desc(), Job.id.desc()).limit(min(max(limit, 1), MAX_LISTED))
    return list(session.scalars(query))


def count_active(session: Session) -> int:
    """Jobs queued or running, of every web process."""
    return session.scalar(select(func.count()).select_from(Job).where(Job.status.in_(ACTIVE))) or 0


def active_ids(session: Session) -> set[str]:
    """Ids of the jobs queued or running, of every web process."""
    return set(session.scalars(select(Job.id).where(Job.status.in_(ACTIVE))))


def cancel(session: Session, job_id: str) -> Job:
    """Mark a queued or running job cancelled; its worker stops at its next progress
    report. A finished job is returned as it is."""
    job = get(session, job_id)
    if job.status in ACTIVE:
        job.status = JobStatus.CANCELLED.value
        job.stage = JobStatus.CANCELLED.value
        job.message = "cancelled by request"
        job.finished_at = utcnow()
        session.commit()
    return job


class Claim(NamedTuple):
    """A worker's hold on a job: which run of it this is."""

    job_id: str
    attempt: int


def claim(session: Session, job_id: str, worker: str, max_attempts: int) -> Claim | None:
    """Start the next attempt of a job on `worker`: a queued job's first, or, when the
    engine runs a job again because the worker of its last attempt died, the next one
    (the job is failed instead once it has had `max_attempts`). None when the job is no
    longer to be run (cancelled, finished, failed). Earlier attempts, should one still be
    alive, stop at their next report: only the newest attempt may report or finish."""
    lock_for_writing(session, "jobs")
    job = session.get(Job, job_id, with_for_update=True, populate_existing=True)
    if job is None or job.status not in ACTIVE:
        session.rollback()
        return None
    if job.status == JobStatus.RUNNING and job.attempt >= max_attempts:
        reason = (f"the worker running this job died ({job.worker}) and it had run {job.attempt} time(s), "
                  f"the most it may (job_attempts)")
        job.status, job.stage, job.error, job.message = JobStatus.FAILED.value, "worker lost", reason, reason
        job.finished_at = utcnow()
        session.commit()
        return None
    job.attempt += 1
    job.status, job.stage, job.worker = JobStatus.RUNNING.value, "starting", worker[:128]
    job.heartbeat_at = utcnow()
    job.started_at = job.started_at or job.heartbeat_at
    if job.attempt > 1:
        job.progress, job.message = 0.0, f"run again (attempt {job.attempt}): the worker of the last one died"
    session.commit()
    return Claim(job_id, job.attempt)


def _current(claim: Claim) -> Any:
    """Rows of `claim`'s job that are still running its attempt."""
    return (Job.id == claim.job_id) & (Job.attempt == claim.attempt) & (Job.status == JobStatus.RUNNING.value)


def heartbeat(session: Session, claim: Claim) -> bool:
    """Say the job's worker is alive; False when the attempt is no longer the job's
    running one (cancelled, failed as lost, or superseded)."""
    result = session.execute(update(Job).where(_current(claim)).values(heartbeat_at=utcnow()))
    session.commit()
    return bool(result.rowcount)  # type: ignore[attr-defined]


def report_progress(session: Session, claim: Claim, stage: str, fraction: float, message: str) -> bool:
    """Store a running job's stage and progress; False (nothing stored) when the job is
    no longer running this attempt."""
    result = session.execute(
        update(Job)
        .where(_current(claim))
        .values(stage=stage[:64], progress=min(max(float(fraction), 0.0), 1.0), message=message,
                heartbeat_at=utcnow())
    )
    session.commit()
    return bool(result.rowcount)  # type: ignore[attr-defined]


def finish(session: Session, claim: Claim, result: dict[str, Any]) -> bool:
    """Mark a running job succeeded with `result`, locking its row; the caller commits.
    False (nothing changed) when the job is no longer running this attempt."""
    try:
        # PostgreSQL's json refuses NaN and infinities, which SQLite would store: refused
        # alike on every engine, before anything is written.
        json.dumps(result, allow_nan=False)
    except ValueError:
        raise ValueError("the job's result holds NaN or an infinity, which JSON cannot carry") from None
    job = session.get(Job, claim.job_id, with_for_update=True)
    if job is None or job.status != JobStatus.RUNNING or job.attempt != claim.attempt:
        return False
    job.status, job.stage, job.progress = JobStatus.SUCCEEDED.value, "done", 1.0
    job.result, job.finished_at, job.message = dict(result), utcnow(), "done"
    return True


def status_of(job_id: str) -> Select[tuple[str]]:
    """The query of a job's status."""
    return select(Job.status).where(Job.id == job_id)


def fail(session: Session, job_ids: Iterable[str], reason: str, *, stage: str = "failed",
         statuses: Collection[JobStatus] = ACTIVE, attempt: int | None = None) -> int:
    """Mark those of `job_ids` that are in `statuses` (and at `attempt`, when given) failed,
    saying why; how many were."""
    result = session.execute(
        update(Job)
        .where(Job.id.in_(list(job_ids)), Job.status.in_(statuses),
               *([Job.attempt == attempt] if attempt is not None else []))
        .values(status=JobStatus.FAILED.value, stage=stage, error=reason, message=reason, finished_at=utcnow())
    )
    session.commit()
    return int(result.rowcount or 0)  # type: ignore[attr-defined]


def fail_silent(session: Session, lease_s: float) -> list[str]:
    """Fail the running jobs whose worker has said nothing for `lease_s` (its process hung,
    its machine gone); their ids."""
    cutoff = utcnow() - timedelta(seconds=lease_s)
    silent = list(session.scalars(select(Job.id).where(
        Job.status == JobStatus.RUNNING.value, func.coalesce(Job.heartbeat_at, Job.started_at) < cutoff)))
    if not silent:
        return []
    fail(session, silent, f"the worker running this job went silent for over {lease_s:g} s (worker lost)",
         stage="worker lost", statuses=(JobStatus.RUNNING,))
    return silent


def active_by_engine(session: Session, young_s: float) -> dict[str, list[tuple[str, bool]]]:
    """(id, whether it was created less than `young_s` ago) of the jobs queued or running,
    by the engine (scheduler address; "" for none) they were given to."""
    cutoff = utcnow() - timedelta(seconds=young_s)
    found: dict[str, list[tuple[str, bool]]] = {}
    young = case((Job.created_at >= cutoff, True), else_=False)
    for job_id, engine, is_young in session.execute(
            select(Job.id, Job.runner, young).where(Job.status.in_(ACTIVE))):
        found.setdefault(engine or "", []).append((job_id, bool(is_young)))
    return found
