"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse
from sqlalchemy import text
from sqlalchemy.exc import SQLAlchemyError

from app.db import current_revisions, head_revisions
from app.deps import EngineDep, MetricsDep
from app.routers.json_bodies import JsonBodyRoute
from app.schemas import Readiness
from app.services.metrics import CONTENT_TYPE_LATEST

router = APIRouter(tags=["health"], route_class=JsonBodyRoute)


@router.get("/livez")
def livez() -> dict[str, str]:
    """The process is up and serving."""
    return {"status": "ok"}


@router.get("/readyz", response_model=Readiness, responses={503: {"model": Readiness}})
def readyz(engine: EngineDep) -> Response:
    """Ready when the database answers and its schema is at the newest migration."""
    heads = sorted(head_revisions())
    try:
        with engine.connect() as connection:
            connection.execute(text("SELECT 1"))
            current = sorted(current_revisions(connection))
        database = "ok"
    except SQLAlchemyError as exc:
        current, database = [], f"unreachable: {type(exc).__name__}"
    ready = database == "ok" and current == heads
    body = Readiness(
        status="ready" if ready else "not ready",
        database=database,
        schema_revision=current,
        head_revision=heads,
    )
    return JSONResponse(body.model_dump(), status_code=200 if ready else 503)


@router.get("/metrics", response_class=Response)
def metrics(registry: MetricsDep) -> Response:
    """Prometheus text exposition."""
    return Response(registry.exposition(), media_type=CONTENT_TYPE_LATEST)
