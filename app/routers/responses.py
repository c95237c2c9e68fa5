"""The error replies the routes document in the OpenAPI description, written once."""

from __future__ import annotations

from typing import Any

from app.schemas import Problem, ValidationProblem

__all__ = ["IMAGE_REFUSED", "JOB_QUEUE_FULL", "MAP_CHANGED", "NO_MAP", "UPLOADS_BUSY", "UPLOAD_TOO_LARGE", "invalid",
           "not_found", "problem"]


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
#: 412 for a map write whose If-Match no longer names the map's revision.
MAP_CHANGED = problem(412, "If-Match names a revision the map has left, or there is no map: nothing was written. "
                           "Read the map again (its ETag) and redo the change on it")
#: 413 for an upload (a video, images) over a limit.
UPLOAD_TOO_LARGE = problem(413, "The upload is over a limit")
#: 429 when the job slots are taken (before the upload is read, with Retry-After).
JOB_QUEUE_FULL = problem(429, "Too many jobs are queued or running: retry after Retry-After seconds")
#: 503 when the uploads being read fill the server's limit (before the upload is read).
UPLOADS_BUSY = problem(503, "The uploads being received fill the server's limit: retry after Retry-After seconds")
#: What a route that takes one image refuses it with: too large, not an image, no room.
IMAGE_REFUSED = {**problem(413, "The image is over a limit"), **problem(415, "Not a JPEG or PNG"),
                 **problem(503, "The server is busy with other images; retry")}
