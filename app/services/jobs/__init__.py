"""Long-running jobs (surveys, classifier training) on the job engine, Dask distributed.

A job is a row in ``jobs`` (`store`), and the row is its truth. The web process's
`runner` stores the row and hands the job to the engine's scheduler (`cluster`: a local
cluster by default, or a scheduler with workers on any machines); vision work holds a
core for minutes, so it never runs in the web process. On a worker, the task (`worker`)
claims the job's next attempt, keeps a heartbeat on the row, and runs the job's handler
(`registry`), which reports its stage and progress and fans work out over every worker
through its `JobContext`; the context stops it when the row says it was cancelled or a
newer attempt took over. Each web process fails the jobs the engine lost: a worker gone
silent, a scheduler gone.
"""

from app.services.jobs.context import Cancelled, JobContext
from app.services.jobs.registry import JobHandler, JobKind, JobResult, handler_for, job_handler
from app.services.jobs.runner import JobRunner
from app.services.jobs.store import ACTIVE, Claim, cancel, create, get, job_out, new_job_id, uploads_dir

__all__ = [
    "ACTIVE",
    "Cancelled",
    "Claim",
    "JobContext",
    "JobHandler",
    "JobKind",
    "JobResult",
    "JobRunner",
    "cancel",
    "create",
    "get",
    "handler_for",
    "job_handler",
    "job_out",
    "new_job_id",
    "uploads_dir",
]
