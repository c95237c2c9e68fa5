"""Reading uploaded bytes with limits: refuse by Content-Length before reading, and stop
reading as soon as a body grows past the limit (413 either way)."""

from __future__ import annotations

from fastapi import HTTPException, Request, UploadFile, status
from starlette.datastructures import UploadFile as StarletteUploadFile

from app.middleware import MULTIPART_FRAMING_BYTES

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
