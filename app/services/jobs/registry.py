"""Kinds of job and their handlers, registered where they are defined.

A handler is a module-level function taking its parameters (a pydantic model, stored
with the job as JSON) and its `JobContext`, and returning the job's result::

    @job_handler(JobKind.SURVEY, SurveyParams)
    def run_survey(params: SurveyParams, context: JobContext) -> JobResult: ...

The runner hands the `JobHandler` to a spawned worker process, where unpickling it
imports the handler's module by reference: a worker loads what its own job needs and
nothing else.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Generic, Protocol, TypeVar

from pydantic import BaseModel

from app.services.jobs.context import JobContext

#: A job's result, stored as JSON on its row.
JobResult = dict[str, Any]

P = TypeVar("P", bound=BaseModel)


class JobKind(StrEnum):
    """The kinds of job the service runs (``JobOut.kind``)."""

    SURVEY = "survey"
    TRAIN_CLASSIFIER = "train_classifier"


@dataclass(frozen=True)
class JobHandler(Generic[P]):
    """A kind of job: the model of its parameters and the function that runs it."""

    kind: str
    params: type[P]
    function: Callable[[P, JobContext], JobResult]

    def run(self, stored: Mapping[str, object], context: JobContext) -> JobResult:
        """Run the job on its stored parameters (in the worker process)."""
        return self.function(self.params.model_validate(stored), context)


class RegisteredHandler(Protocol):
    """A registered handler as the runner and the worker see it, whatever its parameters."""

    @property
    def kind(self) -> str: ...

    @property
    def params(self) -> type[BaseModel]: ...

    def run(self, stored: Mapping[str, object], context: JobContext) -> JobResult: ...


_HANDLERS: dict[str, RegisteredHandler] = {}


def job_handler(kind: str, params: type[P]) -> Callable[[Callable[[P, JobContext], JobResult]],
                                                       Callable[[P, JobContext], JobResult]]:
    """Register the decorated function as the handler of jobs of `kind` (a `JobKind`;
    tests register kinds of their own) taking parameters of the model `params`. The
    function is returned unchanged, so that workers can import it by its name."""

    def register(function: Callable[[P, JobContext], JobResult]) -> Callable[[P, JobContext], JobResult]:
        handler = JobHandler(kind, params, function)
        if _HANDLERS.setdefault(kind, handler) != handler:
            raise ValueError(f"job kind {kind!r} already has a handler")
        return function

    return register


def handler_for(kind: str) -> RegisteredHandler:
    """The handler registered for `kind`; ValueError if there is none."""
    try:
        return _HANDLERS[kind]
    except KeyError:
        raise ValueError(f"unknown job kind {kind!r}") from None
