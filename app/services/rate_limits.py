"""Token buckets, and the per-client ones: the HTTP request rate and the /track
connection-open rate of each client address and each API key.

A bucket holds at most ``burst`` tokens and gains ``rate`` a second; a request takes one,
and one that finds none is refused with the time until the next one (``Retry-After``).
The buckets live in the process that serves the request (a client spread over several
server processes gets each process's rate); they are checked on the event loop, a few
microseconds a request, so that a flood is refused for less than it costs to send.
"""

from __future__ import annotations

import functools
import ipaddress
import math
import time
from dataclasses import dataclass
from enum import StrEnum
from typing import Literal

from app.settings import Settings

#: Clients remembered per kind of bucket; past it, the buckets that are full again (as
#: good as new) are dropped, then all of them.
MAX_CLIENTS = 100_000


class TokenBucket:
    """``rate`` tokens a second, at most ``burst`` saved up."""

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

    def take_or_wait(self) -> float:
        """Take a token and return 0, or return the seconds until one is available."""
        if (wait := self.wait_time()) > 0:
            return wait
        self.tokens -= 1.0
        return 0.0

    @property
    def full(self) -> bool:
        self._refill()
        return self.tokens >= self.burst


class Buckets:
    """One `TokenBucket` per client (an address or a key id), made on its first request.
    Not thread-safe: used from the event loop only."""

    def __init__(self, rate: float, burst: float, max_clients: int = MAX_CLIENTS) -> None:
        self.rate = rate
        self.burst = burst
        self.max_clients = max_clients
        self._buckets: dict[str | int, TokenBucket] = {}

    def take(self, client: str | int) -> float:
        """Take one of `client`'s tokens: 0, or the seconds until it has one."""
        bucket = self._buckets.get(client)
        if bucket is None:
            if len(self._buckets) >= self.max_clients:
                self._forget()
            bucket = self._buckets[client] = TokenBucket(self.rate, self.burst)
        return bucket.take_or_wait()

    def _forget(self) -> None:
        self._buckets = {client: b for client, b in self._buckets.items() if not b.full}
        if len(self._buckets) >= self.max_clients:  # a flood from that many clients at once
            self._buckets.clear()


class Limit(StrEnum):
    """The per-client limits, as the refusals and the metrics name them."""

    REQUESTS_PER_ADDRESS = "requests_per_address"
    REQUESTS_PER_KEY = "requests_per_key"
    TRACK_OPENS_PER_ADDRESS = "track_opens_per_address"
    TRACK_OPENS_PER_KEY = "track_opens_per_key"
    TRACK_CONNECTIONS_PER_ADDRESS = "track_connections_per_address"
    TRACK_CONNECTIONS_PER_KEY = "track_connections_per_key"


@dataclass(frozen=True)
class RateRefusal:
    """A request over a rate: which limit, and when to try again."""

    limit: Limit
    retry_after_s: float
    message: str

    @property
    def retry_after_header(self) -> bytes:
        """``Retry-After``: whole seconds, at least 1."""
        return str(max(1, math.ceil(self.retry_after_s))).encode()


#: What a request is: an HTTP request, or the opening of a /track connection.
RequestKind = Literal["http", "websocket"]


class ClientRates:
    """The request-rate and connection-open-rate buckets of one server process, per client
    address and per API key; a rate of 0 in the settings turns its buckets off."""

    def __init__(self, settings: Settings) -> None:
        def buckets(rate: float, burst: int) -> Buckets | None:
            return Buckets(rate, burst) if rate > 0 else None

        self.by_address: dict[str, Buckets | None] = {
            "http": buckets(settings.request_rate_per_address, settings.request_burst_per_address),
            "websocket": buckets(settings.track_open_rate_per_address, settings.track_open_burst_per_address)}
        self.by_key: dict[str, Buckets | None] = {
            "http": buckets(settings.request_rate_per_key, settings.request_burst_per_key),
            "websocket": buckets(settings.track_open_rate_per_key, settings.track_open_burst_per_key)}

    def admit_address(self, kind: RequestKind, address: str) -> RateRefusal | None:
        """None, or why `address` may not make this request now."""
        limit = Limit.REQUESTS_PER_ADDRESS if kind == "http" else Limit.TRACK_OPENS_PER_ADDRESS
        return _take(self.by_address[kind], address, limit, "this address")

    def admit_key(self, kind: RequestKind, key_id: int) -> RateRefusal | None:
        """None, or why API key `key_id` may not make this request now."""
        limit = Limit.REQUESTS_PER_KEY if kind == "http" else Limit.TRACK_OPENS_PER_KEY
        return _take(self.by_key[kind], key_id, limit, "this API key")


def _take(buckets: Buckets | None, client: str | int, limit: Limit, who: str) -> RateRefusal | None:
    if buckets is None or not (wait := buckets.take(client)):
        return None
    what = "requests" if limit in (Limit.REQUESTS_PER_ADDRESS, Limit.REQUESTS_PER_KEY) else "/track connections"
    return RateRefusal(limit, wait, f"{who} is over its rate of {buckets.rate:g} {what} a second: try again in "
                                    f"{max(wait, 0.1):.1f} s")


@functools.lru_cache(maxsize=4096)
def client_address(host: str | None) -> str | None:
    """The address a client is counted by: its IP address as the server saw it (or as a
    trusted proxy forwarded it); for IPv6, its /64 network, which one machine usually
    holds whole. None when there is none (a Unix socket)."""
    if not host:
        return None
    if ":" not in host:
        return host
    try:
        address = ipaddress.IPv6Address(host.split("%", 1)[0])
    except ValueError:
        return host
    if address.ipv4_mapped is not None:
        return str(address.ipv4_mapped)
    return str(ipaddress.IPv6Network((address, 64), strict=False))
