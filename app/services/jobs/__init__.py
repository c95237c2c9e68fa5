"""Long-running jobs (surveys, classifier training) in worker processes.

A job is a row in ``jobs`` (`store`); the web process only creates and reads rows. The
`runner` of the web process starts each job in its own spawned process (vision work
holds the CPU for minutes and must not stall the event loop or the GIL of the web
process), at most ``max_concurrent_jobs`` at once, the rest waiting in a queue. In the
`worker`, the job's handler (`registry`) reports its stage and progress through its
`JobContext`, which stops it when the row says it was cancelled.
"""

from app.services.jobs.context import Cancelled, JobContext
from app.services.jobs.registry import JobHandler, JobKind, JobResult, handler_for, job_handler
from app.services.jobs.runner import JobRunner
from app.services.jobs.store import ACTIVE, cancel, create, get, job_out, new_job_id, uploads_dir

__all__ = [
    "ACTIVE",
    "Cancelled",
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
