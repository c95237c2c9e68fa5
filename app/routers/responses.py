"""The error replies the routes document in the OpenAPI description, written once."""

from __future__ import annotations

from typing import Any

from app.schemas import Problem, ValidationProblem

__all__ = ["IMAGE_REFUSED", "JOB_QUEUE_FULL", "NO_MAP", "UPLOAD_TOO_LARGE", "invalid", "not_found", "problem"]


def problem(status: int, description: str) -> dict[int | str, dict[str, Any]]:
    """A route's `responses` entry for an error reply with a `Problem` body."""
    return {status: {"model": Problem, "description": description}}


def not_found(what: str) -> dict[int | str, dict[str, Any]]:
    """404 for an unknown `what` (an environment, a job, ...)."""
    return problem(404, f"No such {what}")


def invalid(description: str = "The request does not validate") -> dict[int | str, dict[str, Any]]:
    """422 with the fields that do not validate (`ValidationProblem`)."""
    return {422: {"model": ValidationProblem, "description": description}}


#: 409 for an environment that has no map yet.
NO_MAP = problem(409, "The environment has no map yet")
#: 413 for an upload (a video, images) over a limit.
UPLOAD_TOO_LARGE = problem(413, "The upload is over a limit")
#: 429 when the job slots are taken.
JOB_QUEUE_FULL = problem(429, "Too many jobs are queued or running")
#: What a route that takes one image refuses it with: too large, not an image, no room.
IMAGE_REFUSED = {**problem(413, "The image is over a limit"), **problem(415, "Not a JPEG or PNG"),
                 **problem(503, "The server is busy with other images; retry")}
