"""FastAPI dependencies, as annotated types (``SessionDep``, ``SettingsDep``, ...): the
application's shared state, for HTTP routes and WebSockets alike."""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Annotated

import anyio
from fastapi import Depends, HTTPException, Path, WebSocket, WebSocketException
from pydantic import BeforeValidator
from sqlalchemy import Engine
from sqlalchemy.orm import Session
from starlette.requests import HTTPConnection

from app.services import keys
from app.services.detection import DetectorCache
from app.services.images import MemoryBudget
from app.services.jobs import JobRunner
from app.services.metrics import Metrics
from app.services.streaming import TrackStreams
from app.services.tracking import TrackingService
from app.settings import Settings


def get_settings(connection: HTTPConnection) -> Settings:
    return connection.app.state.settings


def get_engine(connection: HTTPConnection) -> Engine:
    return connection.app.state.engine


def get_session(connection: HTTPConnection) -> Iterator[Session]:
    with connection.app.state.sessionmaker() as session:
        yield session


def get_metrics(connection: HTTPConnection) -> Metrics:
    return connection.app.state.metrics


def get_detectors(connection: HTTPConnection) -> DetectorCache:
    return connection.app.state.detectors


def get_jobs(connection: HTTPConnection) -> JobRunner:
    return connection.app.state.jobs


def get_image_memory(connection: HTTPConnection) -> MemoryBudget:
    return connection.app.state.image_memory


def get_image_threads(connection: HTTPConnection) -> anyio.CapacityLimiter:
    return connection.app.state.image_threads


def get_tracking(connection: HTTPConnection) -> TrackingService:
    return connection.app.state.tracking


def get_track_streams(connection: HTTPConnection) -> TrackStreams:
    return connection.app.state.track_streams


_ROW_ID = re.compile(r"[1-9][0-9]{0,17}")


def _row_id(value: object) -> object:
    if isinstance(value, str) and not _ROW_ID.fullmatch(value):
        raise ValueError("must be a positive whole number in plain digits")
    return value


#: A stored row's id in a URL path: plain digits only. An int path parameter alone would
#: also take "1 ", "+1" and "01" for row 1, so that a mistyped URL (a stray space) acts on
#: a row all the same.
RowId = Annotated[int, BeforeValidator(_row_id), Path()]

SettingsDep = Annotated[Settings, Depends(get_settings)]
EngineDep = Annotated[Engine, Depends(get_engine)]
SessionDep = Annotated[Session, Depends(get_session)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
DetectorsDep = Annotated[DetectorCache, Depends(get_detectors)]
JobsDep = Annotated[JobRunner, Depends(get_jobs)]
TrackingDep = Annotated[TrackingService, Depends(get_tracking)]
ImageMemoryDep = Annotated[MemoryBudget, Depends(get_image_memory)]
#: The threads of /detect and /locate (apart from /track's).
ImageThreadsDep = Annotated[anyio.CapacityLimiter, Depends(get_image_threads)]
TrackStreamsDep = Annotated[TrackStreams, Depends(get_track_streams)]


# --- API keys -------------------------------------------------------------------------

#: Paths anyone may call even with keys on: orchestrator probes carry no keys.
OPEN_PATHS = frozenset({"/livez", "/readyz"})
#: What a ``track`` key may do besides nothing else: stream frames and detect/locate.
TRACK_ROUTES = frozenset({("POST", "/detect"), ("POST", "/environments/{environment_id}/locate"),
                          ("WEBSOCKET", "/track")})
WS_POLICY_VIOLATION = 1008


def required_scope(method: str, route_path: str) -> str | None:
    """The scope a route needs: None (open), ``track``, ``read`` (GET) or ``admin``."""
    if route_path in OPEN_PATHS:
        return None
    if (method, route_path) in TRACK_ROUTES:
        return "track"
    if route_path.startswith("/keys"):
        return "admin"  # even listing keys
    if method in ("GET", "HEAD"):
        return "read"
    return "admin"


def presented_key(connection: HTTPConnection) -> str | None:
    """``X-API-Key``, or ``Authorization: Bearer``; WebSocket clients (browsers cannot
    set headers there) may also pass ``?api_key=``."""
    key = connection.headers.get("x-api-key")
    if key is None:
        auth = connection.headers.get("authorization", "")
        if auth[:7].lower() == "bearer ":
            key = auth[7:].strip()
    if key is None and connection.scope["type"] == "websocket":
        key = connection.query_params.get("api_key")
    return key


async def authorize(connection: HTTPConnection) -> keys.Principal | None:
    """Every route's gate when ``api_keys`` is on (the policy is `required_scope`).
    HTTP: 401 without a valid key, 403 without the scope. WebSocket: accepted, then
    closed with code 1008 and the reason (closed before accepting, a server can only
    answer the handshake with a bare HTTP 403, which no WebSocket client can read a
    reason from)."""
    if not connection.app.state.settings.api_keys:
        return None
    route = connection.scope.get("route")
    method = "WEBSOCKET" if connection.scope["type"] == "websocket" else connection.scope["method"]
    scope = required_scope(method, getattr(route, "path", connection.url.path))
    if scope is None:
        return None
    principal = await anyio.to_thread.run_sync(_verify, connection)
    if principal is None or not principal.allows(scope):
        reason = ("a valid API key is required (header X-API-Key)" if principal is None
                  else f"this API key lacks the {scope!r} scope")
        if isinstance(connection, WebSocket):
            await connection.accept()
            raise WebSocketException(WS_POLICY_VIOLATION, reason)
        raise HTTPException(401 if principal is None else 403, reason,
                            headers={"WWW-Authenticate": "ApiKey"} if principal is None else None)
    return principal


def _verify(connection: HTTPConnection) -> keys.Principal | None:
    with connection.app.state.sessionmaker() as session:
        return keys.verify(session, presented_key(connection))


PrincipalDep = Annotated[keys.Principal | None, Depends(authorize)]
