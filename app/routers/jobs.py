"""Jobs: progress and outcome of surveys and classifier training; cancellation."""

from __future__ import annotations

from fastapi import APIRouter

from app.deps import SessionDep
from app.routers.json_bodies import JsonBodyRoute
from app.schemas import JobOut, Problem
from app.services import jobs

router = APIRouter(prefix="/jobs", tags=["jobs"], route_class=JsonBodyRoute)
_404 = {404: {"model": Problem, "description": "No such job"}}


@router.get("/{job_id}", response_model=JobOut, responses=_404)
def get_job(job_id: str, session: SessionDep) -> JobOut:
    """Status, stage and progress (0..1); the result once it succeeded."""
    return jobs.job_out(jobs.get(session, job_id))


@router.delete("/{job_id}", response_model=JobOut, responses=_404)
def cancel_job(job_id: str, session: SessionDep) -> JobOut:
    """Cancel a queued or running job (a finished one is returned unchanged)."""
    return jobs.job_out(jobs.cancel(session, job_id))
