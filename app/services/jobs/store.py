"""Job rows: create, read, cancel, and every change of a job's status.

Each function that changes a row commits, except `finish`, whose changes commit together
with the job's own (see `JobContext.finishing`).
"""

from __future__ import annotations

import os
import socket
import uuid
from collections.abc import Collection, Iterable
from pathlib import Path
from typing import Any

from pydantic import BaseModel
from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from app.db import utcnow
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
    """This web process, as recorded on the jobs it owns."""
    return f"{socket.gethostname()}:{os.getpid()}"


def create(session: Session, kind: str, params: BaseModel, *, environment_id: int | None = None,
           job_id: str | None = None, max_active: int | None = None) -> Job:
    """Store a queued job owned by this process. With `max_active`, TooMany (429) when that
    many jobs are already queued or running."""
    if max_active is not None:
        active = count_active(session)
        if active >= max_active:
            raise TooMany(f"{active} jobs are queued or running (the limit is {max_active}); try again later")
    job = Job(id=job_id or new_job_id(), kind=kind, params=params.model_dump(mode="json"),
              environment_id=environment_id, status=JobStatus.QUEUED.value, progress=0.0,
              stage=JobStatus.QUEUED.value, message="", runner=runner_id())
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


def start(session: Session, job_id: str) -> Job | None:
    """Mark a queued job running; None when it is no longer queued (cancelled before it
    started)."""
    job = session.get(Job, job_id)
    if job is None or job.status != JobStatus.QUEUED:
        return None
    job.status, job.stage, job.started_at = JobStatus.RUNNING.value, "starting", utcnow()
    session.commit()
    return job


def report_progress(session: Session, job_id: str, stage: str, fraction: float, message: str) -> bool:
    """Store a running job's stage and progress; False (nothing stored) when the job is
    no longer running."""
    if session.scalar(select(Job.status).where(Job.id == job_id)) != JobStatus.RUNNING:
        return False
    session.execute(
        update(Job)
        .where(Job.id == job_id)
        .values(stage=stage[:64], progress=min(max(float(fraction), 0.0), 1.0), message=message)
    )
    session.commit()
    return True


def finish(session: Session, job_id: str, result: dict[str, Any]) -> bool:
    """Mark a running job succeeded with `result`, locking its row; the caller commits.
    False (nothing changed) when the job is no longer running."""
    job = session.get(Job, job_id, with_for_update=True)
    if job is None or job.status != JobStatus.RUNNING:
        return False
    job.status, job.stage, job.progress = JobStatus.SUCCEEDED.value, "done", 1.0
    job.result, job.finished_at, job.message = dict(result), utcnow(), "done"
    return True


def fail(session: Session, job_ids: Iterable[str], reason: str, *, stage: str = "failed",
         statuses: Collection[JobStatus] = ACTIVE) -> int:
    """Mark those of `job_ids` that are in `statuses` failed, saying why; how many were."""
    result = session.execute(
        update(Job)
        .where(Job.id.in_(list(job_ids)), Job.status.in_(statuses))
        .values(status=JobStatus.FAILED.value, stage=stage, error=reason, message=reason, finished_at=utcnow())
    )
    session.commit()
    return int(result.rowcount or 0)  # type: ignore[attr-defined]


def fail_interrupted(session: Session, reason: str) -> int:
    """Fail the jobs left queued or running by a web process that died, rather than leave
    them hanging. Jobs of a sibling process on this host that is still alive are left
    alone; a job owned by another host cannot be checked from here and is failed only
    when it has no owner recorded."""
    host = socket.gethostname()
    me = runner_id()
    orphans = []
    for job_id, runner in session.execute(select(Job.id, Job.runner).where(Job.status.in_(ACTIVE))):
        owner_host, _, pid = (runner or "").rpartition(":")
        if runner is None or runner == me or (owner_host == host and not (pid.isdigit() and _process_alive(int(pid)))):
            orphans.append(job_id)
    if not orphans:
        return 0
    return fail(session, orphans, reason, stage="interrupted")


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
