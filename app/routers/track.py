"""WebSocket /track (frames in, detections and poses out) and POST /environments/{id}/locate."""

from __future__ import annotations

import contextlib
from typing import Annotated

from fastapi import APIRouter, Query, Request, WebSocket, WebSocketDisconnect

from app.deps import ImageWorkersDep, RowId, SettingsDep, TrackStreamsDep
from app.routers.json_bodies import JsonBodyRoute
from app.routers.responses import IMAGE_REFUSED, NO_MAP, invalid, not_found
from app.routers.uploads import IMAGE_BODY_DOC, read_image_body
from app.schemas import LocateResponse, TrackCloseCode, TrackConfig, TrackRefusal, TrackServerMessage
from app.services import keys
from app.services.rate_limits import client_address
from app.services.streaming import ClientGone, Refused, TrackClient

router = APIRouter(tags=["tracking"], route_class=JsonBodyRoute)


@router.post(
    "/environments/{environment_id}/locate",
    response_model=LocateResponse,
    summary="Locate the camera from one image",
    openapi_extra=IMAGE_BODY_DOC,
    responses={**not_found("environment"), **IMAGE_REFUSED, **NO_MAP,
               **invalid("The request does not validate, or the image cannot be used")},
)
async def locate(
    environment_id: RowId,
    request: Request,
    settings: SettingsDep,
    workers: ImageWorkersDep,
    method: Annotated[str, Query(pattern="^(nonlinear|posit|mean|single)$", description=(
        "Pose estimator, as in the /track config: nonlinear (the paper's), posit, mean or single."))] = "nonlinear",
    estimate_focal: Annotated[bool, Query(description="Free the focal length (a zoom lens).")] = False,
) -> LocateResponse:
    """Detections and the camera pose for one image (``pose`` is null with a reason
    in ``pose_error`` when the visible targets do not determine it)."""
    with workers.admitted():
        data = await read_image_body(request, settings.max_image_bytes)
        config = TrackConfig(method=method, estimate_focal=estimate_focal)  # type: ignore[arg-type]
        return await workers.locate(environment_id, data, config)


@router.websocket("/track")
async def track(websocket: WebSocket, streams: TrackStreamsDep, environment_id: str | None = None) -> None:
    """Stream JPEG frames (binary messages), get one ``frame`` reply per processed frame.

    The newest frame always wins: frames that arrive while one is being processed
    replace each other, and the reply says how many were dropped since the last one.
    A client over ``max_track_fps`` loses its excess frames the same way (never the
    newest) and gets at most one ``rate_limited`` error a second; connections beyond
    ``max_track_connections`` (of the whole service, every server process together) are
    closed with 1013 (try again later), and so are those of a client address or API key
    beyond its share (``max_track_connections_per_address``, ``_per_key``) or opened
    faster than its rate (``track_open_rate_per_address``, ``_per_key``: the refusal says
    ``retry_after_s``). A connection whose API key is revoked is closed within a few
    seconds (``key_revoked``, 1008).

    When the environment's map or classifier changes while a connection is open (a
    survey, an import, an alignment), the connection switches to it within
    ``map_poll_s`` and sends a new hello (``reason``: ``map_changed`` or
    ``classifier_changed``) before the first reply posed against it.

    Each connection keeps its own tracking state: its previous poses predict where the
    map's targets are, and only those regions are searched (config ``regions``, on by
    default; ``full_scan_every``). Each reply says ``scan`` ("full" or "regions") and
    ``scan_reason`` (first, regions, periodic, lost, fallback, wide, stale, camera, off);
    ``timing_ms.regions`` counts the regions searched.

    The messages are `TrackConfig` (client to server), `TrackHello`, `TrackFrame`,
    `TrackError` and `TrackRefusal` (server to client), listed among the OpenAPI
    document's schemas; docs/protocol.md is the protocol in full.
    """
    await websocket.accept()
    channel = _WebSocketChannel(websocket)
    try:
        async with streams.connection():
            await streams.serve(channel, _environment_id(environment_id), _client(websocket))
    except Refused as refused:
        with contextlib.suppress(ClientGone):
            await channel.refuse(refused.refusal)
    except ClientGone:
        pass  # the client left before the first message reached it: nothing to answer


def _client(websocket: WebSocket) -> TrackClient:
    """The connection's client address and, with API keys on, its key as the gate verified it."""
    client = websocket.scope.get("client")
    credential = websocket.scope.get("state", {}).get(keys.CREDENTIAL_STATE)
    return TrackClient(client_address(client[0] if client else None), credential)


def _environment_id(text: str | None) -> int:
    if text is None or text == "":
        raise Refused("bad_request", "the query parameter environment_id is required")
    try:
        return int(text)
    except ValueError:
        raise Refused("bad_request", f"environment_id must be an integer, got {text[:40]!r}") from None


class _WebSocketChannel:
    """A /track WebSocket as the streaming service's `TrackChannel`: messages out as JSON text."""

    def __init__(self, websocket: WebSocket) -> None:
        self.websocket = websocket

    async def receive(self) -> bytes | str | None:
        while True:
            message = await self.websocket.receive()
            if message["type"] == "websocket.disconnect":
                return None
            if (data := message.get("bytes")) is not None:
                return data
            if (text := message.get("text")) is not None:
                return text

    async def send(self, message: TrackServerMessage | TrackRefusal) -> None:
        try:
            await self.websocket.send_json(message.model_dump())
        except (WebSocketDisconnect, OSError):  # the server's own ClientDisconnected is an OSError
            raise ClientGone from None

    async def close(self, code: TrackCloseCode, reason: str = "") -> None:
        await self.websocket.close(code=code, reason=reason)

    async def refuse(self, refusal: TrackRefusal) -> None:
        await self.send(refusal)
        with contextlib.suppress(WebSocketDisconnect, OSError, RuntimeError):  # gone meanwhile
            await self.close(refusal.close_code, refusal.message[:120])
