"""Application factory and lifespan: database at head, shared state, routes; the
detector's kernels compile in the background (/readyz says when they are ready).

``uvicorn app.main:app`` with ``FIDOTRACK_*`` variables set is a complete deployment.
"""

from __future__ import annotations

import logging
from pathlib import Path
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import anyio
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from starlette.requests import ClientDisconnect

from app import __version__, logs
from app.db import make_engine, make_sessionmaker, upgrade_to_head
from app.middleware import (DOCS_ASSETS_URL, WEB_APP_URL, ApiKeyGate, BodyLimit, ClientLimits, OriginGate,
                            RequestObserver, SecurityHeaders, web_app_csp)
from app.routers import classifiers as classifiers_router
from app.routers import detect, environments, health, jobs, keys, markers, surveys, track
from app.schemas import MAX_LISTED_ERRORS, complete_openapi, error_summary
from app.services import classifiers
from app.services.detection import DetectorCache, DetectorKernels
from app.services.errors import ServiceError
from app.services.image_workers import ImageWorkers
from app.services.images import MemoryBudget, limit_compute_threads
from app.services.jobs import JobRunner
from app.services.keys import VerifiedKeys
from app.services.metrics import Metrics
from app.services.rate_limits import ClientRates
from app.services.streaming import TrackStreams
from app.services.tracking import TrackingService
from app.services.uploads import UploadsInFlight
from app.settings import Settings

log = logging.getLogger("app")

#: How long start-up waits at most for the detector's kernels to load from numba's cache
#: (under a second), so that a restart comes up ready. It never waits for a compilation
#: (10-30 s, a machine's first start): the server answers meanwhile, /readyz with 503.
KERNELS_LOAD_WAIT_S = 10.0

#: The web app's files: plain ES modules and vendored three.js, shipped in the package.
WEB_DIR = Path(__file__).parent / "web"


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    settings: Settings = app.state.settings
    logs.configure(settings.log_format, settings.log_level)
    limit_compute_threads(settings.compute_threads)
    # Started first, to overlap the database's start-up.
    kernels = DetectorKernels()
    kernels.start()
    app.state.kernels = kernels
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    engine = make_engine(settings.resolved_database_url, settings.sqlite_busy_timeout_ms)
    upgrade_to_head(engine, settings.data_dir)
    sessions = make_sessionmaker(engine)
    with sessions() as session:
        classifiers.install_default(session)
    runner = JobRunner(settings, sessions)
    await anyio.to_thread.run_sync(runner.start)
    app.state.engine = engine
    app.state.sessionmaker = sessions
    app.state.jobs = runner
    app.state.detectors = DetectorCache()
    app.state.image_memory = MemoryBudget(settings.image_memory_bytes)
    # Started by the first image (about 2 s): most deployments never call /detect or /locate.
    app.state.image_workers = ImageWorkers(settings, app.state.image_memory)
    app.state.tracking = TrackingService(detectors=app.state.detectors, sessions=sessions, settings=settings,
                                         memory=app.state.image_memory)
    # Frames of all clients share a few worker threads (OpenCV releases the GIL).
    app.state.track_streams = TrackStreams(app.state.tracking, settings=settings,
                                           limiter=anyio.CapacityLimiter(settings.track_threads),
                                           verified_keys=app.state.verified_keys)
    await anyio.to_thread.run_sync(kernels.wait_unless_compiling, KERNELS_LOAD_WAIT_S)
    try:
        yield
    finally:
        app.state.image_workers.shutdown()
        await anyio.to_thread.run_sync(app.state.track_streams.shutdown)
        await anyio.to_thread.run_sync(runner.shutdown)
        engine.dispose()


def create_app(settings: Settings | None = None) -> FastAPI:
    # /docs and /redoc with their scripts and styles served from the installed package
    # (FastAPI's own pages load them from a CDN: blank without internet).
    app = FastAPIOffline(
        static_url=DOCS_ASSETS_URL,
        title="fidotrack",
        version=__version__,
        summary="Marker-based camera tracking: learned fiducial detection, automatic survey, "
        "per-frame pose (Claus & Fitzgibbon, WACV 2005).",
        lifespan=lifespan,
    )
    # The document with the /track messages and the models' own examples (FastAPI drops
    # their nulls); built on first request, not at every create_app.
    build_openapi = app.openapi
    app.openapi = lambda: complete_openapi(build_openapi())  # type: ignore[method-assign]
    settings = settings or Settings()
    app.state.settings = settings
    app.state.metrics = Metrics()
    app.state.verified_keys = VerifiedKeys()
    app.state.uploads_in_flight = UploadsInFlight(settings.max_upload_bytes_in_flight)

    @app.exception_handler(ServiceError)
    async def _service_error(_request: Request, exc: ServiceError) -> JSONResponse:
        return JSONResponse({"detail": exc.detail}, status_code=exc.status_code)

    @app.exception_handler(ClientDisconnect)
    async def _client_gone(_request: Request, _exc: ClientDisconnect) -> JSONResponse:
        # A client that left mid-body (or whose body the server cut for coming too slowly)
        # reads no reply; this one only keeps it out of the error log and the 5xx counts.
        return JSONResponse({"detail": "the client went away before its request was read"}, status_code=400)

    @app.exception_handler(RequestValidationError)
    async def _invalid_request(_request: Request, exc: RequestValidationError) -> JSONResponse:
        # Which field and why, for the first few; the offending input is not echoed (it
        # may be huge, or a NaN that JSON cannot carry).
        errors = [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in exc.errors()]
        return JSONResponse({"detail": error_summary(errors), "errors": errors[:MAX_LISTED_ERRORS]},
                            status_code=422)

    # Innermost: the request rates per API key, once the gate below has verified the key.
    rates = ClientRates(settings)
    app.add_middleware(ClientLimits, rates=rates, by="key", metrics=app.state.metrics)
    # Every request passes the API-key gate (a no-op unless settings.api_keys).
    app.add_middleware(ApiKeyGate)
    # Pages of other origins may not open /track or change anything (before the key's lookup).
    app.add_middleware(OriginGate, allowed=settings.allowed_origins)
    app.add_middleware(RequestObserver, metrics=app.state.metrics)
    # A body over the limit is refused before any of it is read.
    app.add_middleware(BodyLimit, upload_limit=settings.max_upload_bytes, image_limit=settings.max_image_bytes,
                       json_limit=settings.max_json_bytes)
    # The request rates per client address, before anything that costs: a flood is refused cheaply.
    app.add_middleware(ClientLimits, rates=rates, by="address", metrics=app.state.metrics)
    # Around the others, so that their refusals carry the headers too.
    app.add_middleware(SecurityHeaders, csp=web_app_csp((WEB_DIR / "index.html").read_text()))

    app.include_router(health.router)
    app.include_router(environments.router)
    app.include_router(surveys.router)
    app.include_router(markers.router)
    app.include_router(detect.router)
    app.include_router(classifiers_router.router)
    app.include_router(jobs.router)
    app.include_router(track.router)
    app.include_router(keys.router)
    # The web app: the service's own pages, from the package (html=True serves index.html).
    app.mount(WEB_APP_URL, StaticFiles(directory=WEB_DIR, html=True), name="web")

    @app.get("/", include_in_schema=False)
    async def _front_door() -> RedirectResponse:
        return RedirectResponse(WEB_APP_URL + "/")

    return app


app = create_app()
