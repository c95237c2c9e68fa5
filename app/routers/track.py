"""WebSocket /track (frames in, detections and poses out) and POST /environments/{id}/locate."""

from __future__ import annotations

import asyncio
import json
import logging
from typing import Annotated, Any

import anyio
from fastapi import APIRouter, Query, Request, WebSocket, WebSocketDisconnect
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool

from app.deps import SessionDep, SettingsDep
from app.routers.uploads import IMAGE_BODY_DOC, read_image_body
from app.schemas import LocateResponse, Problem
from app.services import tracking
from app.services.errors import ServiceError
from app.services.tracking import TrackConfig

log = logging.getLogger(__name__)
router = APIRouter(tags=["tracking"])

# WebSocket close codes: 1008 policy violation (bad request), 1011 server error.
CLOSE_POLICY = 1008


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
async def track(websocket: WebSocket, environment_id: int | None = None) -> None:
    """Stream JPEG frames (binary messages), get one ``frame`` reply per processed frame.

    The newest frame always wins: frames that arrive while one is being processed
    replace each other, and the reply says how many were dropped since the last one.
    """
    app = websocket.app
    settings = app.state.settings
    await websocket.accept()
    if environment_id is None:
        await _refuse(websocket, "bad_request", "the query parameter environment_id is required")
        return
    contexts: tracking.TrackingContexts = app.state.tracking
    try:
        context = await run_in_threadpool(_load_context, app, contexts, environment_id)
    except ServiceError as exc:
        code = "unknown_environment" if exc.status_code == 404 else "no_map"
        await _refuse(websocket, code, exc.detail)
        return
    await websocket.send_json({"type": "hello", "environment_id": environment_id, "camera": context.camera_dict,
                               "targets": len(context.discs)})

    session = _Session(context=context)
    receiver = asyncio.create_task(_receive(websocket, session, settings.max_frame_bytes))
    processor = asyncio.create_task(_process(websocket, session, app, contexts, settings))
    done, pending = await asyncio.wait({receiver, processor}, return_when=asyncio.FIRST_COMPLETED)
    for task in pending:
        task.cancel()
    for task in done:
        if (exc := task.exception()) is not None and not isinstance(exc, WebSocketDisconnect):
            log.warning("track connection ended with %r", exc)


def _load_context(app: Any, contexts: tracking.TrackingContexts, environment_id: int) -> tracking.TrackingContext:
    with app.state.sessionmaker() as session:
        return contexts.get(session, environment_id)


async def _refuse(websocket: WebSocket, code: str, message: str) -> None:
    await websocket.send_json({"type": "error", "code": code, "message": message})
    await websocket.close(code=CLOSE_POLICY, reason=message[:120])


class _Session:
    """Per-connection state: the newest unprocessed frame, counters and config."""

    def __init__(self, context: tracking.TrackingContext) -> None:
        self.context = context
        self.config = TrackConfig()
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
    except json.JSONDecodeError:
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
        (seq, data), session.pending = session.pending, None
        dropped, session.dropped = session.dropped, 0
        config = session.config
        try:
            result = await anyio.to_thread.run_sync(
                tracking.locate_frame, session.context, contexts.detectors, app.state.sessionmaker, settings,
                data, config, limiter=limiter,
            )
        except ServiceError as exc:
            session.dropped += dropped  # reported with the next frame reply
            await _error(websocket, "bad_frame", f"frame {seq}: {exc.detail}", seq)
            continue
        await websocket.send_json({
            "type": "frame", "seq": seq, "width": result.width, "height": result.height,
            "targets": result.targets, "pose": result.pose, "pose_error": result.pose_error,
            "timing_ms": result.timing_ms, "dropped": dropped,
        })
