"""FastAPI dependencies, as annotated types (``SessionDep``, ``SettingsDep``)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, HTTPException, Request, WebSocketException
from starlette.requests import HTTPConnection
from sqlalchemy import Engine
from sqlalchemy.orm import Session

from app.services import keys
from app.services.detection import DetectorCache
from app.services.jobs import JobRunner
from app.services.metrics import Metrics
from app.settings import Settings


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_engine(request: Request) -> Engine:
    return request.app.state.engine


def get_session(request: Request) -> Iterator[Session]:
    with request.app.state.sessionmaker() as session:
        yield session


def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


def get_detectors(request: Request) -> DetectorCache:
    return request.app.state.detectors


def get_jobs(request: Request) -> JobRunner:
    return request.app.state.jobs


SettingsDep = Annotated[Settings, Depends(get_settings)]
EngineDep = Annotated[Engine, Depends(get_engine)]
SessionDep = Annotated[Session, Depends(get_session)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
DetectorsDep = Annotated[DetectorCache, Depends(get_detectors)]
JobsDep = Annotated[JobRunner, Depends(get_jobs)]


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


def authorize(connection: HTTPConnection) -> keys.Principal | None:
    """Every route's gate when ``api_keys`` is on (the policy is `required_scope`).
    HTTP: 401 without a valid key, 403 without the scope. WebSocket: closed before
    accept with code 1008 and the reason."""
    if not connection.app.state.settings.api_keys:
        return None
    route = connection.scope.get("route")
    method = "WEBSOCKET" if connection.scope["type"] == "websocket" else connection.scope["method"]
    scope = required_scope(method, getattr(route, "path", connection.url.path))
    if scope is None:
        return None
    with connection.app.state.sessionmaker() as session:
        principal = keys.verify(session, presented_key(connection))
    if principal is None or not principal.allows(scope):
        reason = ("a valid API key is required (header X-API-Key)" if principal is None
                  else f"this API key lacks the {scope!r} scope")
        if connection.scope["type"] == "websocket":
            raise WebSocketException(WS_POLICY_VIOLATION, reason)
        raise HTTPException(401 if principal is None else 403, reason,
                            headers={"WWW-Authenticate": "ApiKey"} if principal is None else None)
    return principal


PrincipalDep = Annotated[keys.Principal | None, Depends(authorize)]
