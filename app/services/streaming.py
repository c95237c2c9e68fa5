"""The /track sessions: admission against the connection limit, a token bucket per
connection, and the loop in which the newest frame always wins.

A connection has two tasks: one receives messages (frames are kept as the one pending
frame, a newer one replacing it; config messages apply at once), the other processes
the pending frame whenever there is one, in order, one at a time. Frames that arrive
while one is processed replace each other and are counted in the next reply's
``dropped``. A client over ``max_track_fps`` loses its excess frames the same way
(never the newest) and gets at most one ``rate_limited`` error a second.

The service speaks to the client through a `TrackChannel` (the router's WebSocket) in
the messages of ``app.schemas`` (`TrackHello`, `TrackFrame`, `TrackConfig`,
`TrackError`, `TrackRefusal`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections.abc import AsyncIterator
from functools import partial
from typing import Protocol

import anyio
from pydantic import ValidationError

from app import logs
from app.schemas import (
    MAX_JSON_KEYS,
    FreeDOutput,
    TrackCloseCode,
    TrackConfig,
    TrackError,
    TrackErrorCode,
    TrackFrame,
    TrackHello,
    TrackRefusal,
    TrackRefusalCode,
    TrackServerMessage,
    error_summary,
    load_json,
)
from app.services import freed
from app.services.errors import ServiceError
from app.services.freed import FreeDSender, FreeDUnusable
from app.services.pose_output import PoseOutput
from app.services.tracking import StreamFrame, TrackingContext, TrackingService, TrackState
from app.settings import Settings

log = logging.getLogger(__name__)

#: At most one rate_limited (and one freed) error message per this many seconds.
RATE_LIMIT_NOTICE_S = 1.0
#: Longest config message, characters (a config with intrinsics has a few hundred): a
#: longer one is refused before it is parsed.
MAX_CONFIG_CHARS = 16 * 1024


class TrackChannel(Protocol):
    """A client connection as the service uses it."""

    async def receive(self) -> bytes | str | None:
        """The next binary (bytes) or text (str) message; None once the client has left."""
        ...

    async def send(self, message: TrackServerMessage) -> None:
        """Send one message; `ClientGone` if the client has left."""
        ...

    async def close(self, code: TrackCloseCode, reason: str = "") -> None: ...


class ClientGone(Exception):
    """The client left while the server was sending to it (not an error of the server)."""


class Refused(Exception):
    """The connection is refused with `refusal` (sent before it is closed)."""

    def __init__(self, code: TrackRefusalCode, message: str) -> None:
        super().__init__(message)
        self.refusal = TrackRefusal(code=code, message=message)


class ConnectionSlots:
    """Open connections against a limit."""

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


class TokenBucket:
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


class _Stream:
    """One connection's state: the newest unprocessed frame, counters, config and the
    tracking state (frames of one connection are processed one at a time, in order)."""

    def __init__(self, context: TrackingContext, bucket: TokenBucket, freed_output: FreeDOutput | None) -> None:
        self.context = context
        self.bucket = bucket
        self.rate_notice_at = -1e9  # monotonic time of the last rate_limited message
        self.freed_notice_at = -1e9  # ... and of the last freed message
        self.config = TrackConfig()
        self.tracker = TrackState()  # poses of this connection, to predict regions
        self.output = PoseOutput()  # client convention, smoothing, prediction
        self.freed_output = freed_output  # the environment's, read when the connection opened
        self.sender: FreeDSender | None = None
        self.pending: tuple[int, bytes, float] | None = None  # seq, data, monotonic time it arrived
        self.received = 0  # binary messages so far; the next one's seq
        self.dropped = 0  # replaced before processing, since the last reply
        self.wake = asyncio.Event()
        self.closed = False


class TrackStreams:
    """The /track connections of one application."""

    def __init__(self, tracking: TrackingService, *, settings: Settings, limiter: anyio.CapacityLimiter) -> None:
        self.tracking = tracking
        self.settings = settings
        self.limiter = limiter  # the threads that process frames, shared by every connection
        self.slots = ConnectionSlots(settings.max_track_connections)

    @contextlib.asynccontextmanager
    async def connection(self, environment_id: str | None) -> AsyncIterator[None]:
        """One connection's slot, for the duration of the block: Refused when all are
        taken. Every log line inside carries the connection's id."""
        if not self.slots.acquire():
            raise Refused("too_many_connections",
                          f"the server already tracks {self.slots.limit} connections; try again later")
        token = logs.connection_id.set(logs.new_id())
        log.info("track connection opened", extra={"fields": {"environment_id": environment_id}})
        try:
            yield
        finally:
            self.slots.release()
            log.info("track connection closed")
            logs.connection_id.reset(token)

    async def serve(self, channel: TrackChannel, environment_id: int) -> None:
        """Track the frames of `channel` against the environment's map until the client
        leaves: Refused when the environment or its map does not exist."""
        try:
            context = await anyio.to_thread.run_sync(self.tracking.context, environment_id)
        except ServiceError as exc:
            raise Refused("unknown_environment" if exc.status_code == 404 else "no_map", exc.detail) from None
        freed_output = await anyio.to_thread.run_sync(self._freed_output, environment_id)
        await channel.send(TrackHello(environment_id=environment_id, camera=context.camera_model,
                                      targets=len(context.discs), map_frame=context.map_frame))
        fps = self.settings.max_track_fps
        stream = _Stream(context, TokenBucket(rate=fps, burst=max(1.0, fps)), freed_output)
        try:
            await self._use_freed(channel, stream, stream.config)
        except FreeDUnusable as exc:
            await _error(channel, "freed", str(exc))
        receiver = asyncio.create_task(self._receive(channel, stream))
        processor = asyncio.create_task(self._process(channel, stream))
        try:
            done, _ = await asyncio.wait({receiver, processor}, return_when=asyncio.FIRST_COMPLETED)
        finally:  # also when this handler is cancelled (server shutdown)
            for task in (receiver, processor):
                task.cancel()
            if stream.sender is not None:
                stream.sender.close()
        failed = False
        for task in done:
            if task.cancelled():
                continue
            if isinstance(exc := task.exception(), Refused):
                raise exc  # refused while open (idle): said and closed by the caller
            if exc is not None and not isinstance(exc, ClientGone):
                log.warning("track connection ended with %r", exc)
                failed = True
        if failed:
            with contextlib.suppress(Exception):
                await channel.close(TrackCloseCode.SERVER_ERROR)

    def _freed_output(self, environment_id: int) -> FreeDOutput | None:
        with self.tracking.sessions() as session:
            return freed.find(session, environment_id)

    async def _use_freed(self, channel: TrackChannel, stream: _Stream, config: TrackConfig) -> None:
        """Point the connection's FreeD sender where `config` says (FreeDUnusable: it
        cannot, and the sender is left as it was)."""
        to = freed.destination(config.freed, stream.freed_output, self.settings.freed_connection_receivers)
        if stream.sender is not None and stream.sender.to == to:
            return
        sender = None if to is None else await anyio.to_thread.run_sync(FreeDSender.open, to)
        if stream.sender is not None:
            stream.sender.close()
        stream.sender = sender

    async def _receive(self, channel: TrackChannel, stream: _Stream) -> None:
        max_frame_bytes = self.settings.max_frame_bytes
        idle_s = self.settings.track_idle_timeout_s
        try:
            while True:
                try:
                    async with asyncio.timeout(idle_s):
                        message = await channel.receive()
                except TimeoutError:
                    raise Refused("idle", f"no message for {idle_s:g} s: the connection is closed; connect again "
                                  "to go on") from None
                if message is None:
                    break
                if isinstance(message, bytes):
                    seq = stream.received
                    stream.received += 1
                    if len(message) > max_frame_bytes:
                        await _error(channel, "frame_too_large",
                                     f"frame {seq} has {len(message)} bytes; the limit is {max_frame_bytes}", seq)
                        continue
                    if stream.pending is not None:
                        stream.dropped += 1
                    stream.pending = (seq, message, time.monotonic())
                    stream.wake.set()
                else:
                    await self._configure(channel, stream, message)
        finally:
            stream.closed = True
            stream.wake.set()

    async def _process(self, channel: TrackChannel, stream: _Stream) -> None:
        while True:
            await stream.wake.wait()
            stream.wake.clear()
            if stream.pending is None:
                if stream.closed:
                    return
                continue
            # Over the rate: wait for a token while newer frames replace the pending one
            # (each counted in `dropped`); the newest is processed when the token comes.
            if (delay := stream.bucket.wait_time()) > 0:
                now = time.monotonic()
                if now - stream.rate_notice_at >= RATE_LIMIT_NOTICE_S:
                    stream.rate_notice_at = now
                    await _error(channel, "rate_limited", f"more than {stream.bucket.rate:g} frames a second: "
                                 "older frames are dropped (see 'dropped')", stream.pending[0])
                await asyncio.sleep(delay)
                if stream.pending is None:  # cannot happen (only this task takes it), but be safe
                    continue
            stream.bucket.take()
            (seq, data, arrived), stream.pending = stream.pending, None
            dropped, stream.dropped = stream.dropped, 0
            frame = StreamFrame(config=stream.config, seq=seq, state=stream.tracker)
            try:
                result = await anyio.to_thread.run_sync(
                    partial(self.tracking.locate_frame, stream.context, data, frame), limiter=self.limiter)
            except ServiceError as exc:
                stream.dropped += dropped  # reported with the next frame reply
                await _error(channel, "bad_frame", f"frame {seq}: {exc.detail}", seq)
                continue
            except Exception:  # a bug, not the client's fault: report it, keep the connection
                log.exception("track: frame %d of environment %d failed", seq, stream.context.environment_id)
                stream.dropped += dropped
                await _error(channel, "internal_error", f"frame {seq} could not be processed (server error)", seq)
                continue
            shaped = stream.output.shape(result.pose, arrived, stream.config)
            timing_ms = result.timing_ms
            if stream.sender is not None and shaped.R is not None:
                # FreeD before the reply: a studio's renderer waits for it, the client less so.
                try:
                    if stream.sender.send(shaped.R, shaped.t):
                        timing_ms = {**timing_ms, "freed": round((time.monotonic() - arrived) * 1e3, 3)}
                except OSError as exc:
                    now = time.monotonic()
                    if now - stream.freed_notice_at >= RATE_LIMIT_NOTICE_S:
                        stream.freed_notice_at = now
                        await _error(channel, "freed", f"frame {seq}: the FreeD packet to "
                                     f"{stream.sender.to.host}:{stream.sender.to.port} was not sent ({exc})", seq)
            await channel.send(TrackFrame(
                seq=seq, width=result.width, height=result.height, targets=result.targets, pose=shaped.pose,
                pose_error=result.pose_error, timing_ms=timing_ms, dropped=dropped, scan=result.scan,
                scan_reason=result.scan_reason,  # type: ignore[arg-type]
                filtered=shaped.filtered,
            ))

    async def _configure(self, channel: TrackChannel, stream: _Stream, text: str) -> None:
        config = await _parse_config(channel, text)
        if config is None:
            return
        if config.freed != stream.config.freed:
            try:
                await self._use_freed(channel, stream, config)
            except FreeDUnusable as exc:
                await _error(channel, "freed", f"{exc}; the config is not applied")
                return
        stream.config = config
        await channel.send(config)


async def _parse_config(channel: TrackChannel, text: str) -> TrackConfig | None:
    """The config in a text message, or None after telling the client why not."""
    if len(text) > MAX_CONFIG_CHARS:
        await _error(channel, "bad_message", f"a text message has {len(text)} characters; a config has at most "
                     f"{MAX_CONFIG_CHARS}")
        return None
    try:
        message = load_json(text)
    except (ValueError, RecursionError):  # JSONDecodeError, or nesting deeper than Python's stack
        await _error(channel, "bad_message", "text messages must be JSON objects of at most "
                     f"{MAX_JSON_KEYS} keys; frames go as binary messages")
        return None
    if not isinstance(message, dict) or message.get("type") != "config":
        await _error(channel, "bad_message", 'the only text message is {"type": "config", ...}')
        return None
    try:
        return TrackConfig.model_validate(message)
    except ValidationError as exc:
        await _error(channel, "bad_config", error_summary(exc.errors(include_url=False, include_input=False)))
        return None


async def _error(channel: TrackChannel, code: TrackErrorCode, message: str, seq: int | None = None) -> None:
    await channel.send(TrackError(code=code, message=message, seq=seq))
