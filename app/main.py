"""Application factory and lifespan: database at head, shared state, routes.

``uvicorn app.main:app`` with ``FIDOTRACK_*`` variables set is a complete deployment.
"""

from __future__ import annotations

import logging
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager

import anyio
from fastapi import FastAPI, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from app import __version__
from app.db import make_engine, make_sessionmaker, upgrade_to_head
from app.routers import classifiers as classifiers_router
from app.routers import detect, environments, health, jobs, markers, surveys, track
from app.services import classifiers
from app.services.detection import DetectorCache
from app.services.errors import ServiceError
from app.services.jobs import JobRunner
from app.services.tracking import TrackingContexts
from app.services.metrics import Metrics
from app.settings import Settings

log = logging.getLogger("app")


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    settings: Settings = app.state.settings
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    engine = make_engine(settings.resolved_database_url, settings.sqlite_busy_timeout_ms)
    upgrade_to_head(engine, settings.data_dir)
    sessions = make_sessionmaker(engine)
    with sessions() as session:
        classifiers.install_default(session)
    runner = JobRunner(settings.resolved_database_url, settings.sqlite_busy_timeout_ms, settings.data_dir,
                       sessions, settings.max_concurrent_jobs)
    runner.start()
    app.state.engine = engine
    app.state.sessionmaker = sessions
    app.state.jobs = runner
    app.state.detectors = DetectorCache()
    app.state.tracking = TrackingContexts(app.state.detectors)
    # Frames of all clients share a few worker threads (OpenCV releases the GIL).
    app.state.track_limiter = anyio.CapacityLimiter(settings.track_threads)
    try:
        yield
    finally:
        runner.shutdown()
        engine.dispose()


def create_app(settings: Settings | None = None) -> FastAPI:
    app = FastAPI(
        title="fidotrack",
        version=__version__,
        summary="Marker-based camera tracking: learned fiducial detection, automatic survey, "
        "per-frame pose (Claus & Fitzgibbon, WACV 2005).",
        lifespan=lifespan,
    )
    app.state.settings = settings or Settings()
    app.state.metrics = Metrics()

    @app.exception_handler(ServiceError)
    async def _service_error(_request: Request, exc: ServiceError) -> JSONResponse:
        return JSONResponse({"detail": exc.detail}, status_code=exc.status_code)

    @app.exception_handler(RequestValidationError)
    async def _invalid_request(_request: Request, exc: RequestValidationError) -> JSONResponse:
        # Which field and why; the offending input is not echoed (it may be huge, or a
        # NaN that JSON cannot carry).
        errors = [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in exc.errors()]
        return JSONResponse({"detail": errors}, status_code=422)

    @app.middleware("http")
    async def _observe(request: Request, call_next: Callable[[Request], Awaitable[Response]]) -> Response:
        started = time.perf_counter()
        response = await call_next(request)
        route = request.scope.get("route")
        template = getattr(route, "path", "unmatched")
        app.state.metrics.observe_request(
            request.method, template, response.status_code, time.perf_counter() - started
        )
        return response

    app.include_router(health.router)
    app.include_router(environments.router)
    app.include_router(surveys.router)
    app.include_router(markers.router)
    app.include_router(detect.router)
    app.include_router(classifiers_router.router)
    app.include_router(jobs.router)
    app.include_router(track.router)
    return app


app = create_app()
