"""Reading uploaded bytes with limits: refuse by Content-Length before reading, and stop
reading as soon as a body grows past the limit (413 either way).

A job's upload (`receive_job_upload`) is admitted before any of its body is read: a
job slot is reserved (429 when the queue is full) and its bytes counted against the
uploads in flight (503); its form is then parsed as it arrives and each file written
once, straight into the job's upload folder. A refusal before the body's end closes the
connection, as the middleware's do: the client may still be sending.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from typing import Any, TypeVar

import anyio
from fastapi import HTTPException, Request, UploadFile, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ValidationError
from starlette.datastructures import UploadFile as StarletteUploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException

from app.middleware import MULTIPART_FRAMING_BYTES
from app.schemas import JobOut
from app.services import jobs
from app.services.errors import ServiceError
from app.services.jobs import JobRunner
from app.services.uploads import StreamedForm, UploadsInFlight, UploadTarget
from app.settings import Settings

T = TypeVar("T", bound=UploadTarget)
F = TypeVar("F", bound=BaseModel)

#: Seconds a client is told to wait (Retry-After): for a job slot (jobs take minutes), and
#: for room among the uploads in flight (a 512 MiB upload takes seconds on a LAN).
RETRY_AFTER_S = {status.HTTP_429_TOO_MANY_REQUESTS: 30, status.HTTP_503_SERVICE_UNAVAILABLE: 10}
#: Bytes of a body gathered before they are parsed and written (in a worker thread).
FEED_BYTES = 512 * 1024

IMAGE_BODY_DOC = {
    "requestBody": {
        "required": True,
        "description": "A JPEG or PNG as the body, or multipart/form-data with an `image` file.",
        "content": {
            "image/jpeg": {"schema": {"type": "string", "format": "binary"}},
            "image/png": {"schema": {"type": "string", "format": "binary"}},
            "multipart/form-data": {
                "schema": {"type": "object", "properties": {"image": {"type": "string", "format": "binary"}},
                           "required": ["image"]}
            },
        },
    }
}


def too_large(limit: int) -> HTTPException:
    return HTTPException(status.HTTP_413_CONTENT_TOO_LARGE, f"body exceeds the limit of {limit} bytes")


def check_declared_length(request: Request, limit: int) -> None:
    declared = request.headers.get("content-length")
    if declared is not None:
        try:
            size = int(declared)
        except ValueError:
            raise HTTPException(status.HTTP_400_BAD_REQUEST, "Content-Length is not a number") from None
        if size > limit:
            raise too_large(limit)


async def read_upload(upload: UploadFile, limit: int) -> bytes:
    data = await upload.read(limit + 1)
    if len(data) > limit:
        raise too_large(limit)
    return data


async def read_image_body(request: Request, limit: int) -> bytes:
    """The image of a request: the raw body, or the `image` part of a multipart form."""
    content_type = request.headers.get("content-type", "")
    check_declared_length(request, limit + MULTIPART_FRAMING_BYTES if content_type.startswith("multipart/") else limit)
    if content_type.startswith("multipart/form-data"):
        form = await request.form(max_files=1, max_fields=8)
        part = form.get("image")
        if not isinstance(part, StarletteUploadFile):
            raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, "image: a file field named 'image' is required")
        return await read_upload(part, limit)
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise too_large(limit)
        chunks.append(chunk)
    return b"".join(chunks)


def multipart_doc(form: type[BaseModel], files: dict[str, dict[str, Any]], required: tuple[str, ...] = ()
                  ) -> dict[str, Any]:
    """`openapi_extra` of a route that reads its multipart form itself: the file fields
    (`files`: name to schema, with its description) and the text fields of `form`."""
    schema = form.model_json_schema()
    properties = {**files, **schema.get("properties", {})}
    needed = [*required, *schema.get("required", [])]
    body = {"type": "object", "properties": properties, **({"required": needed} if needed else {})}
    return {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": body}}}}


def form_fields(form: type[F], fields: dict[str, str]) -> F:
    """The text fields of a form as `form` (a blank field counts as absent); 422 as for
    any request that does not validate."""
    try:
        return form.model_validate({name: value for name, value in fields.items() if value != ""})
    except ValidationError as exc:
        errors = exc.errors(include_url=False, include_input=False, include_context=False)
        raise RequestValidationError([{**e, "loc": ("body", *e["loc"])} for e in errors]) from None


def refusal(exc: ServiceError | StarletteHTTPException, *, body_read: bool) -> JSONResponse:
    """The reply to a refused upload: Retry-After when waiting helps, and the connection
    closed when the body was not read to its end."""
    code = exc.status_code
    detail = exc.detail if isinstance(exc, ServiceError) else str(exc.detail)
    headers = {"retry-after": str(RETRY_AFTER_S[code])} if code in RETRY_AFTER_S else {}
    if not body_read:
        headers["connection"] = "close"
    return JSONResponse({"detail": detail}, status_code=code, headers=headers)


async def receive_job_upload(request: Request, settings: Settings, runner: JobRunner, in_flight: UploadsInFlight, *,
                             admit: Callable[[], None], target: Callable[..., T],
                             submit: Callable[[T, dict[str, str], str], JobOut]) -> JobOut | JSONResponse:
    """A job's upload: `admit` (checks that need no body, e.g. 404), a job slot reserved
    and the body's bytes admitted in flight, all before the body is read; the form
    streamed into the job's upload folder through `target(folder)`; then `submit(target,
    text fields, job id)` stores the job. A refused or failed upload leaves no folder."""
    body_read = False
    reservation = lease = form = None
    folder = None
    try:
        await anyio.to_thread.run_sync(admit)
        reservation = await anyio.to_thread.run_sync(runner.reserve, settings.max_queued_jobs)
        declared = request.headers.get("content-length")
        lease = in_flight.admit(int(declared) if declared and declared.isdigit() else None)
        job_id = jobs.new_job_id()
        folder = jobs.uploads_dir(settings.data_dir, job_id)
        folder.mkdir(parents=True)
        upload = target(folder)
        form = StreamedForm(request.headers.get("content-type", ""), upload, settings.max_upload_bytes)
        pending, received = bytearray(), 0
        async for chunk in request.stream():
            received += len(chunk)
            if declared is None:
                lease.grow_to(received)
            pending += chunk
            if len(pending) >= FEED_BYTES:
                await anyio.to_thread.run_sync(form.feed, bytes(pending))
                pending.clear()
        body_read = True
        await anyio.to_thread.run_sync(form.feed, bytes(pending))
        fields = await anyio.to_thread.run_sync(form.finish)
        job = await anyio.to_thread.run_sync(submit, upload, fields, job_id)
        folder = None  # the job's now
        return job
    except (ServiceError, StarletteHTTPException) as exc:
        return refusal(exc, body_read=body_read)
    finally:
        if form is not None:
            form.abort()
        if folder is not None:
            shutil.rmtree(folder, ignore_errors=True)
        if lease is not None:
            lease.release()
        if reservation is not None:
            reservation.release()
