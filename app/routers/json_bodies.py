"""JSON request bodies, parsed and validated in a worker thread rather than on the event
loop (`JsonBodyRoute`), so that a large body does not hold up every other client: the
body is bounded first (``max_json_bytes``, by `app.middleware.BodyLimit`), its objects
by `app.schemas.MAX_JSON_KEYS`, its lists by the models' own bounds. A body of any other
type is refused (415)."""

from __future__ import annotations

import email.message
from collections.abc import Callable, Coroutine
from typing import Any

import anyio
from fastapi import HTTPException, params
from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute
from pydantic import TypeAdapter, ValidationError
from starlette.requests import Request
from starlette.responses import Response

from app.schemas import load_json


class JsonBodyRoute(APIRoute):
    """A route whose JSON body (one pydantic model) is parsed and validated in a worker
    thread; FastAPI then receives the validated model."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()
        field = self.body_field
        if field is None or isinstance(field.field_info, (params.Form, params.File)):
            return handler
        adapter: TypeAdapter[Any] = TypeAdapter(field.field_info.annotation)

        async def parsed_first(request: Request) -> Response:
            if not _is_json(request.headers.get("content-type")):
                # Before the body is read. A page of another origin can send a form or a
                # text/plain body without asking the service first (a CORS preflight,
                # which the service never grants); it cannot send JSON.
                raise HTTPException(415, "the body must be JSON, sent with Content-Type: application/json")
            body = await request.body()
            if not body:
                return await handler(request)
            value = await anyio.to_thread.run_sync(_validate, adapter, body)
            return await handler(_ParsedRequest(request, body, value))

        return parsed_first


def _is_json(content_type: str | None) -> bool:
    # The test FastAPI itself applies before it parses a body as JSON.
    if not content_type:
        return False
    message = email.message.Message()
    message["content-type"] = content_type
    subtype = message.get_content_subtype()
    return message.get_content_maintype() == "application" and (subtype == "json" or subtype.endswith("+json"))


def _validate(adapter: TypeAdapter[Any], body: bytes) -> Any:
    try:
        data = load_json(body)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError is a ValueError
        raise RequestValidationError([{"type": "json_invalid", "loc": ("body",),
                                       "msg": f"JSON decode error: {str(exc)[:200]}"}]) from None
    try:
        return adapter.validate_python(data)
    except ValidationError as exc:
        # All of them: the reply lists the first few and counts the rest. (The bounds on
        # the body, its objects and its lists bound their number.)
        errors = exc.errors(include_url=False, include_input=False, include_context=False)
        raise RequestValidationError([{**e, "loc": ("body", *e["loc"])} for e in errors]) from None


class _ParsedRequest(Request):
    """The request with its body read and its JSON already validated."""

    def __init__(self, request: Request, body: bytes, value: Any) -> None:
        super().__init__(request.scope, request.receive)
        self._raw_body = body
        self._value = value

    async def body(self) -> bytes:
        return self._raw_body

    async def json(self) -> Any:
        return self._value
