"""WebSocket /track (frames in, detections and poses out) and POST /environments/{id}/locate."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import threading
import time
from typing import Annotated, Any

import anyio
from fastapi import APIRouter, Query, Request, WebSocket, WebSocketDisconnect
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool

from app import logs
from app.deps import SessionDep, SettingsDep
from app.routers.uploads import IMAGE_BODY_DOC, read_image_body
from app.schemas import LocateResponse, Problem
from app.services import tracking
from app.services.errors import ServiceError
from app.services.tracking import TrackConfig

log = logging.getLogger(__name__)
router = APIRouter(tags=["tracking"])

# WebSocket close codes: 1008 policy violation (bad request), 1011 server error,
# 1013 try again later (too many connections).
CLOSE_POLICY = 1008
CLOSE_SERVER_ERROR = 1011
CLOSE_TRY_LATER = 1013
# At most one rate_limited error message per this many seconds.
RATE_LIMIT_NOTICE_S = 1.0


@router.post(
    "/environments/{environment_id}/locate",
    response_model=LocateResponse,
    openapi_extra=IMAGE_BODY_DOC,
    responses={404: {"model": Problem}, 413: {"model": Problem}, 415: {"model": Problem}, 422: {"model": Problem}},
)
async def locate(
    environment_id: int,
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    method: Annotated[str, Query(pattern="^(nonlinear|posit|mean|single)$")] = "nonlinear",
    estimate_focal: bool = False,
) -> LocateResponse:
    """Detections and the camera pose for one image (``pose`` is null with a reason
    in ``pose_error`` when the visible targets do not determine it)."""
    data = await read_image_body(request, settings.max_image_bytes)
    contexts: tracking.TrackingContexts = request.app.state.tracking
    config = TrackConfig(method=method, estimate_focal=estimate_focal)  # type: ignore[arg-type]

    def work() -> tracking.FrameResult:
        context = contexts.get(session, environment_id)
        return tracking.locate_frame(context, contexts.detectors, request.app.state.sessionmaker, settings,
                                     data, config)

    result = await run_in_threadpool(work)
    return LocateResponse(width=result.width, height=result.height, targets=result.targets, pose=result.pose,
                          pose_error=result.pose_error, timing_ms=result.timing_ms)


@router.websocket("/track")
async def track(websocket: WebSocket, environment_id: str | None = None) -> None:
    """Stream JPEG frames (binary messages), get one ``frame`` reply per processed frame.

    The newest frame always wins: frames that arrive while one is being processed
    replace each other, and the reply says how many were dropped since the last one.
    A client over ``max_track_fps`` loses its excess frames the same way (never the
    newest) and gets at most one ``rate_limited`` error a second; connections beyond
    ``max_track_connections`` are closed with 1013 (try again later).

    Each connection keeps its own tracking state: its previous poses predict where the
    map's targets are, and only those regions are searched (config ``regions``, on by
    default; ``full_scan_every``). Each reply says ``scan`` ("full" or "regions") and
    ``scan_reason`` (first, regions, periodic, lost, fallback, wide, stale, camera, off);
    ``timing_ms.regions`` counts the regions searched.
    """
    app = websocket.app
    settings = app.state.settings
    connections = _connections(app)
    await websocket.accept()
    if not connections.acquire():
        await _refuse(websocket, "too_many_connections",
                      f"the server already tracks {connections.limit} connections; try again later", CLOSE_TRY_LATER)
        return
    # Every log line of this connection carries its id (and the key's name when keys are on).
    token = logs.connection_id.set(logs.new_id())
    log.info("track connection opened", extra={"fields": {"environment_id": environment_id}})
    try:
        await _serve(websocket, app, settings, environment_id)
    finally:
        connections.release()
        log.info("track connection closed")
        logs.connection_id.reset(token)


async def _serve(websocket: WebSocket, app: Any, settings: Any, environment_id: str | None) -> None:
    if environment_id is None or environment_id == "":
        await _refuse(websocket, "bad_request", "the query parameter environment_id is required")
        return
    try:
        env_id = int(environment_id)
    except ValueError:
        await _refuse(websocket, "bad_request", f"environment_id must be an integer, got {environment_id[:40]!r}")
        return
    contexts: tracking.TrackingContexts = app.state.tracking
    try:
        context = await run_in_threadpool(_load_context, app, contexts, env_id)
    except ServiceError as exc:
        code = "unknown_environment" if exc.status_code == 404 else "no_map"
        await _refuse(websocket, code, exc.detail)
        return
    await websocket.send_json({"type": "hello", "environment_id": env_id, "camera": context.camera_dict,
                               "targets": len(context.discs)})

    fps = float(getattr(settings, "max_track_fps", 120.0))
    session = _Session(context=context, bucket=_TokenBucket(rate=fps, burst=max(1.0, fps)))
    receiver = asyncio.create_task(_receive(websocket, session, settings.max_frame_bytes))
    processor = asyncio.create_task(_process(websocket, session, app, contexts, settings))
    try:
        done, _ = await asyncio.wait({receiver, processor}, return_when=asyncio.FIRST_COMPLETED)
    finally:  # also when this handler is cancelled (server shutdown)
        for task in (receiver, processor):
            task.cancel()
    failed = False
    for task in done:
        if task.cancelled():
            continue
        if (exc := task.exception()) is not None and not isinstance(exc, WebSocketDisconnect):
            log.warning("track connection ended with %r", exc)
            failed = True
    if failed:
        with contextlib.suppress(Exception):
            await websocket.close(code=CLOSE_SERVER_ERROR)


class _Connections:
    """Open /track connections of one app, against ``max_track_connections``."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.open = 0
        self._lock = threading.Lock()

    def acquire(self) -> bool:
        with self._lock:
            if self.open >= self.limit:
                return False
            self.open += 1
            return True

    def release(self) -> None:
        with self._lock:
            self.open -= 1


_CONNECTIONS_LOCK = threading.Lock()


def _connections(app: Any) -> _Connections:
    with _CONNECTIONS_LOCK:
        found = getattr(app.state, "track_connections", None)
        if found is None:
            found = _Connections(int(getattr(app.state.settings, "max_track_connections", 64)))
            app.state.track_connections = found
        return found


class _TokenBucket:
    """``rate`` tokens a second, at most ``burst`` saved up; one token per processed frame."""

    def __init__(self, rate: float, burst: float) -> None:
        self.rate = rate
        self.burst = burst
        self.tokens = burst
        self.stamp = time.monotonic()

    def _refill(self) -> None:
        now = time.monotonic()
        self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now

    def wait_time(self) -> float:
        """Seconds until a token is available (0 if one is now)."""
        self._refill()
        return 0.0 if self.tokens >= 1.0 else (1.0 - self.tokens) / self.rate

    def take(self) -> None:
        self._refill()
        self.tokens -= 1.0


def _load_context(app: Any, contexts: tracking.TrackingContexts, environment_id: int) -> tracking.TrackingContext:
    with app.state.sessionmaker() as session:
        return contexts.get(session, environment_id)


async def _refuse(websocket: WebSocket, code: str, message: str, close_code: int = CLOSE_POLICY) -> None:
    await websocket.send_json({"type": "error", "code": code, "message": message})
    await websocket.close(code=close_code, reason=message[:120])


class _Session:
    """Per-connection state: the newest unprocessed frame, counters, config and the
    tracking state (frames of one connection are processed one at a time, in order)."""

    def __init__(self, context: tracking.TrackingContext, bucket: _TokenBucket) -> None:
        self.context = context
        self.bucket = bucket
        self.rate_notice_at = -1e9  # monotonic time of the last rate_limited message
        self.config = TrackConfig()
        self.tracker = tracking.TrackState()  # poses of this connection, to predict regions
        self.pending: tuple[int, bytes] | None = None
        self.received = 0  # binary messages so far; the next one's seq
        self.dropped = 0  # replaced before processing, since the last reply
        self.wake = asyncio.Event()
        self.closed = False


async def _receive(websocket: WebSocket, session: _Session, max_frame_bytes: int) -> None:
    try:
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                break
            data, text = message.get("bytes"), message.get("text")
            if data is not None:
                seq = session.received
                session.received += 1
                if len(data) > max_frame_bytes:
                    await _error(websocket, "frame_too_large",
                                 f"frame {seq} has {len(data)} bytes; the limit is {max_frame_bytes}", seq)
                    continue
                if session.pending is not None:
                    session.dropped += 1
                session.pending = (seq, data)
                session.wake.set()
            elif text is not None:
                await _configure(websocket, session, text)
    finally:
        session.closed = True
        session.wake.set()


async def _configure(websocket: WebSocket, session: _Session, text: str) -> None:
    try:
        message = json.loads(text)
    except (ValueError, RecursionError):  # JSONDecodeError, or nesting deeper than Python's stack
        await _error(websocket, "bad_message", "text messages must be JSON; frames go as binary messages")
        return
    if not isinstance(message, dict) or message.get("type") != "config":
        await _error(websocket, "bad_message", 'the only text message is {"type": "config", ...}')
        return
    try:
        session.config = TrackConfig.model_validate(message)
    except ValidationError as exc:
        detail = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        await _error(websocket, "bad_config", detail)
        return
    await websocket.send_json({"type": "config", **session.config.model_dump(exclude={"type"}, mode="json")})


async def _error(websocket: WebSocket, code: str, message: str, seq: int | None = None) -> None:
    await websocket.send_json({"type": "error", "code": code, "message": message, "seq": seq})


async def _process(websocket: WebSocket, session: _Session, app: Any, contexts: tracking.TrackingContexts,
                   settings: Any) -> None:
    limiter: anyio.CapacityLimiter = app.state.track_limiter
    while True:
        await session.wake.wait()
        session.wake.clear()
        if session.pending is None:
            if session.closed:
                return
            continue
        # Over the rate: wait for a token while newer frames replace the pending one
        # (each counted in `dropped`); the newest is processed when the token comes.
        if (delay := session.bucket.wait_time()) > 0:
            now = time.monotonic()
            if now - session.rate_notice_at >= RATE_LIMIT_NOTICE_S:
                session.rate_notice_at = now
                fps = session.bucket.rate
                await _error(websocket, "rate_limited",
                             f"more than {fps:g} frames a second: older frames are dropped (see 'dropped')",
                             session.pending[0])
            await asyncio.sleep(delay)
            if session.pending is None:  # cannot happen (only we take it), but be safe
                continue
        session.bucket.take()
        (seq, data), session.pending = session.pending, None
        dropped, session.dropped = session.dropped, 0
        frame = tracking.StreamFrame(config=session.config, seq=seq, state=session.tracker)
        try:
            result = await anyio.to_thread.run_sync(
                tracking.locate_frame, session.context, contexts.detectors, app.state.sessionmaker, settings,
                data, frame, limiter=limiter,
            )
        except ServiceError as exc:
            session.dropped += dropped  # reported with the next frame reply
            await _error(websocket, "bad_frame", f"frame {seq}: {exc.detail}", seq)
            continue
        except Exception:  # a bug, not the client's fault: report it, keep the connection
            log.exception("track: frame %d of environment %d failed", seq, session.context.environment_id)
            session.dropped += dropped
            await _error(websocket, "internal_error", f"frame {seq} could not be processed (server error)", seq)
            continue
        await websocket.send_json({
            "type": "frame", "seq": seq, "width": result.width, "height": result.height,
            "targets": result.targets, "pose": result.pose, "pose_error": result.pose_error,
            "timing_ms": result.timing_ms, "dropped": dropped,
            # whole frame or predicted regions (timing_ms.regions: how many), and why
            "scan": result.scan, "scan_reason": result.scan_reason,
        })
