"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from fastapi.responses import JSONResponse
from sqlalchemy import text
from sqlalchemy.exc import SQLAlchemyError

from app.db import current_revisions, head_revisions
from app.deps import EngineDep, MetricsDep
from app.routers.json_bodies import JsonBodyRoute
from app.schemas import Readiness
from app.services.metrics import CONTENT_TYPE_LATEST

router = APIRouter(tags=["health"], route_class=JsonBodyRoute)


@router.get("/livez", summary="Check the process is up")
def livez() -> dict[str, str]:
    """The process is up and serving."""
    return {"status": "ok"}


@router.get("/readyz", response_model=Readiness, summary="Check the service is ready",
            responses={503: {"model": Readiness, "description": "Not ready yet: the reason says why"}})
def readyz(engine: EngineDep, request: Request) -> Response:
    """Ready when the database answers, its schema is at the newest migration and the
    detector's kernels are compiled; 503 with the reason until then."""
    heads = sorted(head_revisions())
    try:
        with engine.connect() as connection:
            connection.execute(text("SELECT 1"))
            current = sorted(current_revisions(connection))
        database = "ok"
    except SQLAlchemyError as exc:
        current, database = [], f"unreachable: {type(exc).__name__}"
    if database != "ok":
        reason = f"database {database}"
    elif current != heads:
        reason = "the database schema is not at the newest migration"
    else:
        reason = request.app.state.kernels.not_ready
    body = Readiness(
        status="ready" if reason is None else "not ready",
        reason=reason,
        database=database,
        schema_revision=current,
        head_revision=heads,
    )
    return JSONResponse(body.model_dump(), status_code=200 if reason is None else 503)


@router.get("/metrics", response_class=Response, summary="Get the Prometheus metrics")
def metrics(registry: MetricsDep) -> Response:
    """Prometheus text exposition."""
    return Response(registry.exposition(), media_type=CONTENT_TYPE_LATEST)
