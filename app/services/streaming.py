"""The /track sessions: admission against the service-wide connection limit, a token
bucket per connection, the loop in which the newest frame always wins, and the switch to
a new map while a connection is open.

A connection is admitted once its environment and map are found: it then takes one of
the ``max_track_connections`` of the whole service (`TrackConnections`, rows in the
database that every server process counts) and gives it back when it ends.

A connection has three tasks: one receives messages (frames are kept as the one pending
frame, a newer one replacing it; config messages apply at once), one processes the
pending frame whenever there is one, in order, one at a time, and one asks every
``map_poll_s`` whether the environment's map or classifier changed (a survey, an
import, an alignment, on any server process). Frames that arrive while one is
processed replace each other and are counted in the next reply's ``dropped``. A client
over ``max_track_fps`` loses its excess frames the same way (never the newest) and gets
at most one ``rate_limited`` error a second. A changed map is taken between two frames:
the connection's tracking state starts afresh and a new `TrackHello` (``reason``
``map_changed`` or ``classifier_changed``) says so before the first frame posed
against it. A connection opened with an API key has a fourth task, which checks every
`KEY_CHECK_S` that the key was not revoked (by any process) and ends the connection
when it was. A client address and an API key may each hold only a share of the
connections (``max_track_connections_per_address``, ``_per_key``).

The service speaks to the client through a `TrackChannel` (the router's WebSocket) in
the messages of ``app.schemas`` (`TrackHello`, `TrackFrame`, `TrackConfig`,
`TrackError`, `TrackRefusal`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from functools import partial
from typing import Protocol

import anyio
from pydantic import ValidationError
from sqlalchemy.exc import IntegrityError

from app import logs
from app.core.tracking import TrackState
from app.schemas import (
    MAX_JSON_KEYS,
    FreeDOutput,
    TrackCloseCode,
    TrackConfig,
    TrackError,
    TrackErrorCode,
    TrackFrame,
    TrackHello,
    TrackHelloReason,
    TrackRefusal,
    TrackRefusalCode,
    TrackServerMessage,
    error_summary,
    load_json,
)
from app.services import freed, keys
from app.services.errors import ServiceError
from app.services.freed import FreeDSender, FreeDUnusable
from app.services.pose_output import PoseOutput
from app.services.rate_limits import Limit, TokenBucket
from app.services.track_connections import ClientAtLimit, TrackConnections
from app.services.tracking import StreamFrame, TrackingContext, TrackingService
from app.settings import Settings

log = logging.getLogger(__name__)

#: At most one rate_limited (and one freed) error message per this many seconds.
RATE_LIMIT_NOTICE_S = 1.0
#: How often an open connection with an API key checks that the key was not revoked, s:
#: the lifetime of a verified key in the cache, so a revocation closes it within twice this.
KEY_CHECK_S = keys.VERIFIED_TTL_S
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


@dataclass(frozen=True)
class TrackClient:
    """Who opened a connection: its address as the limits count it
    (`rate_limits.client_address`) and, with API keys on, its verified key."""

    address: str | None = None
    credential: keys.Credential | None = None


class _Stream:
    """One connection's state: the newest unprocessed frame, counters, config and the
    tracking state (frames of one connection are processed one at a time, in order)."""

    def __init__(self, context: TrackingContext, bucket: TokenBucket, freed_output: FreeDOutput | None) -> None:
        self.context = context
        self.next_context: TrackingContext | None = None  # a changed map, taken before the next frame
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
    """The /track connections of one application (one server process)."""

    def __init__(self, tracking: TrackingService, *, settings: Settings, limiter: anyio.CapacityLimiter,
                 verified_keys: keys.VerifiedKeys | None = None) -> None:
        self.tracking = tracking
        self.settings = settings
        self.limiter = limiter  # the threads that process frames, shared by every connection
        self.verified_keys = verified_keys or keys.VerifiedKeys()  # the API-key gate's, to see revocations
        self.freed = freed.FreeDSenders(settings)  # where FreeD may go; host lookups off the API's threads
        self.connections = TrackConnections(tracking.sessions, limit=settings.max_track_connections,
                                            lease_s=settings.track_connection_lease_s,
                                            per_address=settings.max_track_connections_per_address,
                                            per_key=settings.max_track_connections_per_key)

    def shutdown(self) -> None:
        """Stop renewing this process's connections and delete them from the database (at
        the application's shutdown, while the database is still there)."""
        self.connections.close_all()
        self.freed.close()

    @contextlib.asynccontextmanager
    async def connection(self) -> AsyncIterator[None]:
        """One connection's scope: every log line inside carries the connection's id."""
        token = logs.connection_id.set(logs.new_id())
        try:
            yield
        finally:
            logs.connection_id.reset(token)

    async def serve(self, channel: TrackChannel, environment_id: int, client: TrackClient | None = None) -> None:
        """Track the frames of `channel` against the environment's map until the client
        leaves: Refused when the environment or its map does not exist, when the service
        already holds ``max_track_connections`` connections or `client` its share of them,
        or when the client's API key is revoked while the connection is open."""
        client = client or TrackClient()
        context = await self._context(environment_id)
        key_id = client.credential.principal.key_id if client.credential is not None else None
        try:
            lease = await anyio.to_thread.run_sync(
                partial(self.connections.open, environment_id, address=client.address, key_id=key_id))
        except IntegrityError:  # the environment was deleted a moment ago
            raise Refused("unknown_environment", f"environment {environment_id} not found") from None
        except ClientAtLimit as full:
            holder = "address" if full.limit == Limit.TRACK_CONNECTIONS_PER_ADDRESS else "API key"
            raise Refused("client_connections", f"this {holder} already holds {full.share} /track connections, "
                          "its share of the service's; close one first") from None
        if lease is None:
            raise Refused("too_many_connections",
                          f"the service already tracks {self.connections.limit} connections, its limit for all "
                          "of its server processes together; try again later")
        log.info("track connection opened", extra={"fields": {"environment_id": environment_id}})
        try:
            await self._track(channel, context, client)
        finally:
            # Also when the handler is cancelled (server shutdown): the slot must come back.
            with anyio.CancelScope(shield=True):
                try:
                    await anyio.to_thread.run_sync(self.connections.close, lease)
                except Exception as exc:  # the row goes stale and stops counting after a lease
                    log.warning("track: could not release the connection: %r", exc)
            log.info("track connection closed")

    async def _context(self, environment_id: int) -> TrackingContext:
        """The environment's tracking context, or Refused as a client connecting now would be."""
        try:
            return await anyio.to_thread.run_sync(self.tracking.context, environment_id)
        except ServiceError as exc:
            raise Refused("unknown_environment" if exc.status_code == 404 else "no_map", exc.detail) from None

    async def _track(self, channel: TrackChannel, context: TrackingContext, client: TrackClient) -> None:
        environment_id = context.environment_id
        freed_output = await anyio.to_thread.run_sync(self._freed_output, environment_id)
        await channel.send(_hello(context, "connected"))
        fps = self.settings.max_track_fps
        stream = _Stream(context, TokenBucket(rate=fps, burst=max(1.0, fps)), freed_output)
        try:
            await self._use_freed(channel, stream, stream.config)
        except FreeDUnusable as exc:
            await _error(channel, "freed", str(exc))
        tasks = {asyncio.create_task(self._receive(channel, stream)),
                 asyncio.create_task(self._process(channel, stream)),
                 asyncio.create_task(self._watch_map(stream))}
        if client.credential is not None:
            tasks.add(asyncio.create_task(self._watch_key(client.credential)))
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:  # also when this handler is cancelled (server shutdown)
            for task in tasks:
                task.cancel()
            if stream.sender is not None:
                stream.sender.close()
        failed = False
        for task in done:
            if task.cancelled():
                continue
            if isinstance(exc := task.exception(), Refused):
                raise exc  # refused while open (idle, map gone): said and closed by the caller
            if exc is not None and not isinstance(exc, ClientGone):
                log.warning("track connection ended with %r", exc)
                failed = True
        if failed:
            with contextlib.suppress(Exception):
                await channel.close(TrackCloseCode.SERVER_ERROR)

    async def _watch_map(self, stream: _Stream) -> None:
        """Every ``map_poll_s``, ask (in a thread) for the environment's context: a new map
        or classifier, stored by any process, is handed to the processing task; a map or
        environment gone ends the connection with the refusal a new one would get."""
        environment_id = stream.context.environment_id
        while True:
            await asyncio.sleep(self.settings.map_poll_s)
            try:
                context = await anyio.to_thread.run_sync(self.tracking.context, environment_id)
            except ServiceError as exc:
                raise Refused("unknown_environment" if exc.status_code == 404 else "no_map", exc.detail) from None
            except Exception as exc:  # a busy database: the connection goes on with the map it has
                log.warning("track: could not check environment %d's map: %r", environment_id, exc)
                continue
            current = stream.next_context or stream.context
            if _reason(current, context) is not None:
                stream.next_context = context
                stream.wake.set()

    async def _watch_key(self, credential: keys.Credential) -> None:
        """Every `KEY_CHECK_S`, whether the connection's API key still holds: from the
        cache of verified keys, which a revocation through this process empties, else
        from the database, where any process revokes it. A revoked key ends the connection
        (``key_revoked``, close code 1008)."""
        while True:
            await asyncio.sleep(KEY_CHECK_S)
            if self.verified_keys.get(credential.key) is not None:
                continue
            try:
                principal = await anyio.to_thread.run_sync(keys.verify_in, self.tracking.sessions, credential.key)
            except Exception as exc:  # a busy database: the connection goes on until the next check
                log.warning("track: could not check the connection's API key: %r", exc)
                continue
            if principal is None:
                raise Refused("key_revoked", f"API key {credential.principal.name!r} was revoked: the connection "
                              "is closed")
            self.verified_keys.remember(credential.key, principal)

    async def _take_new_map(self, channel: TrackChannel, stream: _Stream) -> None:
        """Switch to the changed context, between two frames: the poses so far were in the
        old map (and its tracked regions, filter and prediction with them), so tracking
        starts afresh; the new hello comes before the first reply posed against it."""
        context, stream.next_context = stream.next_context, None
        if context is None:
            return
        reason = _reason(stream.context, context)
        if reason is None:
            return
        stream.context = context
        stream.tracker = TrackState()
        stream.output = PoseOutput()
        log.info("track connection switched map", extra={"fields": {"reason": reason,
                                                                     "map_version": context.map_version}})
        await channel.send(_hello(context, reason))

    def _freed_output(self, environment_id: int) -> FreeDOutput | None:
        with self.tracking.sessions() as session:
            return freed.find(session, environment_id)

    async def _use_freed(self, channel: TrackChannel, stream: _Stream, config: TrackConfig) -> None:
        """Point the connection's FreeD sender where `config` says, its host resolved and
        checked before any packet goes (FreeDUnusable: it cannot, not there or not in
        time, and the sender is left as it was)."""
        to = freed.destination(config.freed, stream.freed_output, self.freed.policy.connection_receivers)
        if stream.sender is not None and stream.sender.to == to:
            return
        sender = None if to is None else await self.freed.open(to)
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
            await self._take_new_map(channel, stream)
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
                await self._take_new_map(channel, stream)  # one that came during the wait
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
            shaped = stream.output.shape(result.tracked.estimate, arrived, stream.config)
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
                scan_reason=result.tracked.reason.value,  # type: ignore[arg-type]
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


def _hello(context: TrackingContext, reason: TrackHelloReason) -> TrackHello:
    return TrackHello(environment_id=context.environment_id, camera=context.camera_model,
                      targets=len(context.map.discs), map_frame=context.map_frame, reason=reason)


def _reason(current: TrackingContext, new: TrackingContext) -> TrackHelloReason | None:
    """Why a connection on `current` must switch to `new`, or None when they are the same
    map and classifier (another object for the same version is no change)."""
    if new.map_version != current.map_version:
        return "map_changed"
    if new.detector_key != current.detector_key:
        return "classifier_changed"
    return None


async def _error(channel: TrackChannel, code: TrackErrorCode, message: str, seq: int | None = None) -> None:
    await channel.send(TrackError(code=code, message=message, seq=seq))
