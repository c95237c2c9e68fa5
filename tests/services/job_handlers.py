"""Job handlers the tests drive the job runner with (they run in worker processes),
registered as the service's own are."""

from __future__ import annotations

import os
import time
from typing import Any

from pydantic import BaseModel

from app.schemas import MapChange, MapDocument
from app.services import environments
from app.services.jobs import JobContext, JobResult, job_handler


class CountParams(BaseModel):
    steps: int = 5
    sleep: float = 0.05


class NoParams(BaseModel):
    pass


@job_handler("count", CountParams)
def count(params: CountParams, context: JobContext) -> JobResult:
    """Count to `steps`, reporting progress at each step."""
    for step in range(params.steps):
        context.progress("counting", step / params.steps)
        time.sleep(params.sleep)
    return {"counted": params.steps}


@job_handler("fail", NoParams)
def fail(params: NoParams, context: JobContext) -> JobResult:
    """Fail half way, as a survey of a video without markers does."""
    context.progress("failing", 0.5)
    raise ValueError("the survey video holds no markers")


@job_handler("crash", NoParams)
def crash(params: NoParams, context: JobContext) -> JobResult:
    """Fail on a fault of the service's own (an indexing bug), not on the input."""
    context.progress("crashing", 0.5)
    raise IndexError("index 0 is out of bounds for axis 0 with size 0")


class StoreMapParams(BaseModel):
    document: dict[str, Any]


@job_handler("store_map", StoreMapParams)
def store_map(params: StoreMapParams, context: JobContext) -> JobResult:
    """Store a map as a survey's last step does: staged in the transaction that marks the job succeeded."""
    assert context.environment_id is not None
    with context.finishing({"stored": True}) as session:
        environments.stage_map(session, context.environment_id, MapDocument.model_validate(params.document),
                               MapChange.SURVEY)
    return {"stored": True}


class SpreadParams(BaseModel):
    pieces: int = 8
    sleep: float = 0.3


def _piece(sleep: float, piece: int) -> tuple[int, int]:
    time.sleep(sleep)
    return piece, os.getpid()


@job_handler("spread", SpreadParams)
def spread(params: SpreadParams, context: JobContext) -> JobResult:
    """Fan `pieces` pieces of work out over the engine's workers; which process ran each."""
    done = context.fan_out(_piece, params.sleep, list(range(params.pieces)),
                           lambda finished, total: context.progress("spreading", finished / total))
    return {"pieces": [piece for piece, _ in done], "pids": sorted({pid for _, pid in done}),
            "job_pid": os.getpid()}


@job_handler("nan_result", NoParams)
def nan_result(params: NoParams, context: JobContext) -> JobResult:
    """Finish with a result JSON cannot carry (a bug's NaN)."""
    return {"rms_px": float("nan")}
