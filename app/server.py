"""The HTTP server of `fidotrack serve`: uvicorn, with its HTTP/1.1 protocol held to
deadlines so that a slow client cannot keep connections (and the process's file
descriptors) from everyone else.

uvicorn times out only an idle connection between requests: a connection that sends
nothing, or part of a request's header, or a body that stops, stays open for good. Here:

* the whole header block of a request must arrive within ``request_header_timeout_s`` of
  the connection's start or of the previous response's end (else 408, or a plain close
  when not a byte of a request came);
* a body that brings no byte for ``request_body_timeout_s``, or whose average rate falls
  under ``request_body_min_bytes_per_s`` once that long has passed, is dropped (408);
  time the server itself stops reading (the application has not taken what came, or has
  not yet asked for a ``100-continue`` body) does not count against the client;
* one peer address holds at most ``max_connections_per_address`` connections in one
  process, WebSockets included; a connection past that is closed as soon as it is
  accepted, before anything is read or allocated for it.

A WebSocket is held to none of the deadlines once upgraded: its handshake request meets
the header deadline, then the WebSocket's own pings and the /track idle timeout govern it.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import resource
import sys
import time
from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import uvicorn
from uvicorn.config import STARTUP_FAILURE
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
from uvicorn.supervisors import Multiprocess

from app.services.rate_limits import client_address

if TYPE_CHECKING:
    from asyncio.events import TimerHandle

    from app.settings import Settings

log = logging.getLogger("uvicorn.error")

#: One address may hold at most this share of the process's file descriptors, whatever
#: `max_connections_per_address` says, so that it runs out of its share before the
#: process runs out of descriptors.
ADDRESS_SHARE_OF_FDS = 4
#: A peer address refused for holding too many connections is logged at most this often, s.
REFUSAL_LOG_PERIOD_S = 60.0
#: Past this many refused addresses, those not refused within the period are forgotten.
REFUSALS_REMEMBERED = 1024

TIMEOUT_BODY = b'{"detail":"request timed out: the client sent its request too slowly"}'
TIMEOUT_REPLY = b"".join([
    b"HTTP/1.1 408 Request Timeout\r\n",
    b"content-type: application/json\r\n",
    b"content-length: ", str(len(TIMEOUT_BODY)).encode(), b"\r\n",
    b"connection: close\r\n",
    b"\r\n",
    TIMEOUT_BODY,
])


@dataclass(frozen=True)
class SlowClientLimits:
    """How long a client may take over a request, and how many connections one address may hold."""

    header_timeout_s: float
    body_timeout_s: float
    body_min_bytes_per_s: int
    connections_per_address: int

    @classmethod
    def from_settings(cls, settings: Settings) -> SlowClientLimits:
        return cls(settings.request_header_timeout_s, settings.request_body_timeout_s,
                   settings.request_body_min_bytes_per_s, settings.max_connections_per_address)


class PeerConnections:
    """The open connections of one server process, counted per peer address."""

    def __init__(self, cap: int) -> None:
        self.cap = cap
        self._open: Counter[str] = Counter()
        self._refusal_logged: dict[str, float] = {}

    def take(self, address: str) -> bool:
        """Count a new connection from `address`; False (and nothing counted) when it already holds the cap."""
        if self._open[address] >= self.cap:
            now = time.monotonic()
            if now - self._refusal_logged.get(address, -REFUSAL_LOG_PERIOD_S) >= REFUSAL_LOG_PERIOD_S:
                if len(self._refusal_logged) >= REFUSALS_REMEMBERED:
                    self._refusal_logged = {a: t for a, t in self._refusal_logged.items()
                                            if now - t < REFUSAL_LOG_PERIOD_S}
                self._refusal_logged[address] = now
                log.warning("%s holds %d connections, the most one address may: closing its new ones",
                            address, self.cap)
            return False
        self._open[address] += 1
        return True

    def add(self, address: str) -> None:
        """Count a connection that is already accepted (an upgraded WebSocket)."""
        self._open[address] += 1

    def release(self, address: str) -> None:
        self._open[address] -= 1
        if self._open[address] <= 0:
            del self._open[address]


class ServerConfig(uvicorn.Config):
    """uvicorn's configuration with the slow-client limits and this process's connection
    counts (each server process gets its own copy: the config is pickled to its workers)."""

    def __init__(self, app: str, *, slow_clients: SlowClientLimits, **options: Any) -> None:
        # WebSockets: websockets-sansio ("websockets", the legacy implementation, is deprecated).
        super().__init__(app, http=GuardedHttpProtocol, ws=CountedWebSocketProtocol, **options)
        self.slow_clients = slow_clients
        self.peer_connections = PeerConnections(slow_clients.connections_per_address)


def _slow_client_state(config: uvicorn.Config) -> tuple[SlowClientLimits, PeerConnections]:
    """The limits and connection counts of `config`'s server. A plain uvicorn.Config
    (``uvicorn app.main:app --http app.server:GuardedHttpProtocol --ws
    app.server:CountedWebSocketProtocol``) gets them from the settings, once per process."""
    if not isinstance(config, ServerConfig) and not hasattr(config, "slow_clients"):
        from app.settings import Settings

        limits = slow_client_limits(Settings(), resource.getrlimit(resource.RLIMIT_NOFILE)[0])
        config.slow_clients = limits  # type: ignore[attr-defined]
        config.peer_connections = PeerConnections(limits.connections_per_address)  # type: ignore[attr-defined]
    return config.slow_clients, config.peer_connections  # type: ignore[attr-defined]


def _peer_address(transport: asyncio.BaseTransport) -> str:
    """The address a connection counts against: its TCP peer's (a proxy's, behind one),
    never a forwarded header's; for IPv6, the peer's /64 network."""
    peer = transport.get_extra_info("peername")  # (read once by asyncio when it accepted the connection)
    host = str(peer[0]) if isinstance(peer, tuple) and peer else None
    return client_address(host) or ""


class GuardedHttpProtocol(HttpToolsProtocol):
    """uvicorn's httptools HTTP/1.1 protocol with header and body deadlines and the per-address cap."""

    def __init__(self, config: uvicorn.Config, *args: Any, **kwargs: Any) -> None:
        super().__init__(config, *args, **kwargs)
        self.limits, self.peers = _slow_client_state(config)
        self.peer = ""
        self.counted = False
        self.header_timer: TimerHandle | None = None
        self.body_timer: TimerHandle | None = None
        self.request_begun = False  # a byte of the next request's header has come
        self.body_since = 0.0  # the body's rate is measured from here (loop time) ...
        self.body_bytes = 0  # ... over these bytes
        self.body_last = 0.0  # loop time of the body's last bytes

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        self.peer = _peer_address(transport)
        if not self.peers.take(self.peer):
            self.transport = transport
            transport.abort()
            return
        self.counted = True
        super().connection_made(transport)
        self._await_header()

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.counted:  # refused in connection_made: nothing of it was set up
            return
        self._cancel_timers()
        self._uncount()
        super().connection_lost(exc)

    def _uncount(self) -> None:
        if self.counted:
            self.counted = False
            self.peers.release(self.peer)

    def _cancel_timers(self) -> None:
        for timer in (self.header_timer, self.body_timer):
            if timer is not None:
                timer.cancel()
        self.header_timer = self.body_timer = None

    # The header deadline: from the connection's start or the previous response's end.
    def _await_header(self) -> None:
        if self.header_timer is not None:
            self.header_timer.cancel()
        self.header_timer = self.loop.call_later(self.limits.header_timeout_s, self._header_timed_out)

    def _header_timed_out(self) -> None:
        self.header_timer = None
        if self.transport.is_closing():
            return
        if self.request_begun:  # an idle connection is just closed, as keep-alive does
            self.transport.write(TIMEOUT_REPLY)
        self.transport.close()

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self.request_begun = True

    def on_headers_complete(self) -> None:
        if self.header_timer is not None:
            self.header_timer.cancel()
            self.header_timer = None
        self.request_begun = False
        super().on_headers_complete()
        if self.parser.should_upgrade() and self._should_upgrade():
            return  # a WebSocket handshake: no body, and the WebSocket protocol takes over
        now = self.loop.time()
        self.body_since = self.body_last = now
        self.body_bytes = 0
        self.body_timer = self.loop.call_later(self.limits.body_timeout_s, self._check_body)

    def on_body(self, body: bytes) -> None:
        super().on_body(body)
        self.body_bytes += len(body)
        self.body_last = self.loop.time()

    def on_message_complete(self) -> None:
        super().on_message_complete()
        if self.body_timer is not None:
            self.body_timer.cancel()
            self.body_timer = None

    def on_response_complete(self) -> None:
        # A pipelined request waiting in line has its header already: only an empty line awaits one.
        await_header = not self.pipeline
        super().on_response_complete()
        if await_header and not self.transport.is_closing():
            self._await_header()

    # The body deadline: no byte for body_timeout_s, or under the minimum rate after that long.
    def _check_body(self) -> None:
        self.body_timer = None
        if self.transport.is_closing():
            return
        now = self.loop.time()
        timeout = self.limits.body_timeout_s
        cycle = self.cycle
        if self.flow.read_paused or (cycle is not None and cycle.waiting_for_100_continue):
            # The server is not reading: the client is not the one holding things up.
            self.body_since = self.body_last = now
            self.body_bytes = 0
        elif now - self.body_last >= timeout or (
                now - self.body_since >= timeout
                and self.body_bytes < self.limits.body_min_bytes_per_s * (now - self.body_since)):
            self._body_timed_out()
            return
        self.body_timer = self.loop.call_later(max(self.body_last + timeout - now, 0.05), self._check_body)

    def _body_timed_out(self) -> None:
        cycle = self.cycle
        if cycle is not None and not cycle.response_started:
            # The application sees the client gone; its replies, if any, go nowhere.
            cycle.disconnected = True
            cycle.message_event.set()
            self.transport.write(TIMEOUT_REPLY)
        self.transport.close()

    def handle_websocket_upgrade(self) -> None:
        # The WebSocket protocol counts the connection from here (this protocol's
        # connection_lost is never called once the transport is handed over).
        self._cancel_timers()
        self._uncount()
        super().handle_websocket_upgrade()


class CountedWebSocketProtocol(WebSocketsSansIOProtocol):
    """uvicorn's websockets-sansio protocol, its connection counted against its peer address."""

    def __init__(self, config: uvicorn.Config, *args: Any, **kwargs: Any) -> None:
        super().__init__(config, *args, **kwargs)
        self.peers = _slow_client_state(config)[1]
        self.peer: str | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.peer = _peer_address(transport)
        self.peers.add(self.peer)
        super().connection_made(transport)

    def connection_lost(self, exc: Exception | None) -> None:
        if self.peer is not None:
            self.peers.release(self.peer)
            self.peer = None
        super().connection_lost(exc)


def raise_fd_limit() -> int:
    """Raise this process's soft limit on open files to its hard limit (connections are
    files; the workers inherit it); the limit now in force."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or soft == resource.RLIM_INFINITY or soft < hard:
        target = hard if hard != resource.RLIM_INFINITY else max(soft, 1 << 20)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError):  # (a hard limit the kernel's nr_open caps lower)
            pass
    return int(soft)


def slow_client_limits(settings: Settings, fd_limit: int) -> SlowClientLimits:
    """The settings' limits, the per-address cap lowered to a share of `fd_limit` if it is above it."""
    limits = SlowClientLimits.from_settings(settings)
    share = max(fd_limit // ADDRESS_SHARE_OF_FDS, 1)
    if limits.connections_per_address <= share:
        return limits
    return dataclasses.replace(limits, connections_per_address=share)


def run(settings: Settings, *, workers: int, **options: Any) -> None:
    """Serve ``app.main:app`` with uvicorn (`options` are uvicorn.Config's) in this
    process, or in `workers` processes sharing one socket; exits as uvicorn.run does
    when the server could not start."""
    fd_limit = raise_fd_limit()
    limits = slow_client_limits(settings, fd_limit)
    config = ServerConfig("app.main:app", slow_clients=limits, workers=workers, **options)  # (sets up logging)
    if limits.connections_per_address < settings.max_connections_per_address:
        log.warning("max_connections_per_address lowered to %d: a quarter of the %d open files this process "
                    "may have", limits.connections_per_address, fd_limit)
    server = uvicorn.Server(config)
    try:
        if config.workers > 1:
            Multiprocess(config, sockets=[config.bind_socket()]).run()
        else:
            server.run()
    except KeyboardInterrupt:
        pass
    if config.workers == 1 and not server.started:
        sys.exit(STARTUP_FAILURE)
