"""Jobs: progress and outcome of surveys and classifier training; listing; cancellation."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from app.deps import SessionDep
from app.routers.json_bodies import JsonBodyRoute
from app.routers.responses import invalid, not_found
from app.schemas import JobOut, JobStatus
from app.services import jobs
from app.services.errors import MAX_ID
from app.services.jobs import JobKind
from app.services.jobs.store import DEFAULT_LISTED, MAX_LISTED, list_recent

router = APIRouter(prefix="/jobs", tags=["jobs"], route_class=JsonBodyRoute)
_404 = not_found("job")
_422 = invalid()


@router.get("", response_model=list[JobOut], summary="List jobs", responses=_422)
def list_jobs(
    session: SessionDep,
    kind: Annotated[JobKind | None, Query(description="Only jobs of this kind.")] = None,
    status: Annotated[JobStatus | None, Query(description="Only jobs in this status.")] = None,
    environment_id: Annotated[int | None, Query(ge=1, le=MAX_ID, description=(
        "Only the jobs of this environment (its surveys)."))] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_LISTED, description="At most this many jobs.")] = DEFAULT_LISTED,
) -> list[JobOut]:
    """The newest jobs first, of every kind unless filtered, each with its result once it
    succeeded: e.g. ``?kind=survey&environment_id=1&limit=1`` is an environment's last
    survey."""
    found = list_recent(session, kind=kind, status=status, environment_id=environment_id, limit=limit)
    return [jobs.job_out(job) for job in found]


@router.get("/{job_id}", response_model=JobOut, summary="Get a job", responses={**_404, **_422})
def get_job(job_id: str, session: SessionDep) -> JobOut:
    """Status, stage and progress (0..1); the result once it succeeded."""
    return jobs.job_out(jobs.get(session, job_id))


@router.delete("/{job_id}", response_model=JobOut, summary="Cancel a job", responses={**_404, **_422})
def cancel_job(job_id: str, session: SessionDep) -> JobOut:
    """Cancel a queued or running job (a finished one is returned unchanged)."""
    return jobs.job_out(jobs.cancel(session, job_id))
