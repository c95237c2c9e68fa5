"""FreeD output: each environment's receiver (stored, one transaction per public
function), where packets may go, and the UDP sender of one /track connection.

A connection sends to the environment's receiver unless its config names its own host,
port or camera id, or switches FreeD off (`app.schemas.FreeDConnection`). The
environment's receiver is read when the connection opens: a change reaches the
connections opened after it.

Where packets may go (`FreeDPolicy`): a connection's own receiver only when the server
allows them, and only inside the networks it lists; any receiver never at a loopback,
link-local, multicast, broadcast, unspecified or reserved address unless a listed network
contains it. Every address a host name resolves to is checked, once, before the
connection's sender is made; the sender then keeps that address. Names are looked up on
threads of their own (`FreeDSenders`), never the API's, with a timeout, and cached.
"""

from __future__ import annotations

import asyncio
import ipaddress
import socket
import threading
import time
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from sqlalchemy.orm import Session

from app.core import freed
from app.models import FreeDReceiver
from app.schemas import FreeDConnection, FreeDOutput
from app.services import environments
from app.services.errors import Invalid, NotFound
from app.settings import Settings

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address
IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network

#: Threads looking up receivers' host names: a name slow to resolve holds one of these,
#: not a thread of the API.
RESOLVER_THREADS = 4
#: Lookups running or waiting at once, at most; past it a receiver's name is refused
#: until some finish (distinct slow names cannot queue up without bound).
MAX_PENDING_LOOKUPS = 16
#: Host names whose lookups are remembered, at most (the oldest are forgotten first).
MAX_CACHED_NAMES = 1024
#: Names that always mean this machine (RFC 6761), refused when stored like 127.0.0.1 and ::1.
_LOOPBACK_NAMES = ("localhost",)
_LOOPBACK_ADDRESSES = (ipaddress.ip_address("127.0.0.1"), ipaddress.ip_address("::1"))
#: "This network" (RFC 1122): no receiver is there; 0.0.0.0 itself is the unspecified address.
_THIS_NETWORK = ipaddress.ip_network("0.0.0.0/8")
_BROADCAST = ipaddress.ip_address("255.255.255.255")


def get(session: Session, environment_id: int) -> FreeDOutput:
    """The environment's FreeD output: NotFound without the environment or without one."""
    environments.get_row(session, environment_id)
    row = session.get(FreeDReceiver, environment_id)
    if row is None:
        raise NotFound(f"environment {environment_id} has no FreeD output")
    return _to_out(row)


def find(session: Session, environment_id: int) -> FreeDOutput | None:
    """The environment's FreeD output, or None."""
    row = session.get(FreeDReceiver, environment_id)
    return None if row is None else _to_out(row)


def put(session: Session, environment_id: int, output: FreeDOutput, *, policy: FreeDPolicy) -> FreeDOutput:
    """Set the environment's FreeD output (replacing the one it had): Invalid when its host
    is an address (or a name of this machine) that `policy` does not let packets go to."""
    environments.get_row(session, environment_id)
    if (why := _stored_host_refusal(output.host, policy)) is not None:
        raise Invalid(why)
    row = session.get(FreeDReceiver, environment_id)
    if row is None:
        row = FreeDReceiver(environment_id=environment_id)
        session.add(row)
    for name, value in output.model_dump().items():
        setattr(row, name, value)
    session.commit()
    return _to_out(row)


def delete(session: Session, environment_id: int) -> None:
    """Remove the environment's FreeD output: NotFound if it has none."""
    environments.get_row(session, environment_id)
    row = session.get(FreeDReceiver, environment_id)
    if row is None:
        raise NotFound(f"environment {environment_id} has no FreeD output")
    session.delete(row)
    session.commit()


def _to_out(row: FreeDReceiver) -> FreeDOutput:
    # Not validated again: a host stored before the host rules tightened still reaches the
    # connection, which refuses it (error `freed`) instead of failing to open.
    return FreeDOutput.model_construct(host=row.host, port=row.port, camera_id=row.camera_id, enabled=row.enabled)


class FreeDUnusable(ValueError):
    """A connection's FreeD settings cannot be used; the message says why, for a person."""


@dataclass(frozen=True)
class FreeDDestination:
    """Where one connection's packets go: a receiver's host, port and the camera id;
    `own` when the connection named the host or port itself (not the environment's)."""

    host: str
    port: int
    camera_id: int
    own: bool = False


def destination(connection: FreeDConnection | None, output: FreeDOutput | None,
                own_receivers: bool) -> FreeDDestination | None:
    """Where a connection sends, from its config's `freed` and the environment's output
    (None: it sends nothing). `own_receivers` False refuses a host or port of the
    connection's own (the setting ``freed_connection_receivers``)."""
    if connection is None:
        if output is None or not output.enabled:
            return None
        return FreeDDestination(output.host, output.port, output.camera_id)
    if not connection.enabled:
        return None
    own = connection.host is not None or connection.port is not None
    if own and not own_receivers:
        raise FreeDUnusable("this server sends FreeD only to the environment's receiver (PUT "
                            "/environments/{id}/freed): leave out host and port")
    host = connection.host if connection.host is not None else output.host if output is not None else None
    port = connection.port if connection.port is not None else output.port if output is not None else None
    if host is None or port is None:
        raise FreeDUnusable("freed: give host and port, or set the environment's FreeD output "
                            "(PUT /environments/{id}/freed)")
    return FreeDDestination(host, port, connection.camera_id, own=own)


@dataclass(frozen=True)
class FreeDPolicy:
    """Where FreeD packets may go (the settings ``freed_connection_receivers`` and
    ``freed_allowed_networks``)."""

    connection_receivers: bool = False
    allowed_networks: tuple[IPNetwork, ...] = ()

    @classmethod
    def from_settings(cls, settings: Settings) -> FreeDPolicy:
        return cls(settings.freed_connection_receivers, tuple(settings.freed_allowed_networks))

    def listed(self, address: IPAddress) -> bool:
        """Whether a listed network holds `address` (or, IPv4-mapped, the IPv4 address it reaches)."""
        unmapped = _unmapped(address)
        return any(address in network or unmapped in network for network in self.allowed_networks)

    def refusal(self, address: IPAddress, *, own: bool) -> str | None:
        """Why packets may not go to `address` (None: they may). A connection's own
        receiver (`own`) must be in a listed network; any other, outside one, must not be
        at a special address."""
        if self.listed(address):
            return None
        if own:
            return (f"{address} is not in the networks this server lets a connection send FreeD to "
                    "(freed_allowed_networks)")
        kind = _special(_unmapped(address))
        if kind is None:
            return None
        return f"{address} is {kind} address, where this server sends FreeD only if freed_allowed_networks lists it"


def _unmapped(address: IPAddress) -> IPAddress:
    """An IPv4-mapped IPv6 address (::ffff:a.b.c.d) as the IPv4 address it reaches."""
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return address.ipv4_mapped
    return address


def _special(address: IPAddress) -> str | None:
    """What kind of address packets must not go to unless listed, or None for an ordinary one."""
    if address.is_unspecified or (isinstance(address, ipaddress.IPv4Address) and address in _THIS_NETWORK):
        return "an unspecified"
    if address.is_loopback:
        return "a loopback"
    if address.is_link_local:
        return "a link-local"
    if address.is_multicast:
        return "a multicast"
    if address == _BROADCAST:
        return "the broadcast"
    if address.is_reserved:
        return "a reserved"
    if isinstance(address, ipaddress.IPv6Address) and address.is_site_local:
        return "a site-local"
    return None


def _literal(host: str) -> IPAddress | None:
    try:
        return ipaddress.ip_address(host)
    except ValueError:
        return None


def _stored_host_refusal(host: str, policy: FreeDPolicy) -> str | None:
    """Why an environment's receiver may not be at `host`, as far as is known without a
    lookup (an address, or a name that always means this machine); names are checked by
    address when a connection uses them."""
    name = host.lower()
    literal = _literal(host)
    if literal is not None:
        addresses: tuple[IPAddress, ...] = (literal,)
    elif name in _LOOPBACK_NAMES or name.endswith(".localhost"):
        addresses = _LOOPBACK_ADDRESSES
    else:
        return None
    for address in addresses:
        if (why := policy.refusal(address, own=False)) is not None:
            return f"host {host}: {why}" if literal is None else why
    return None


@dataclass(frozen=True)
class ResolvedAddress:
    """One address a host name resolved to, with its socket family."""

    family: int
    address: IPAddress


def _getaddrinfo(host: str) -> tuple[ResolvedAddress, ...]:
    """Every distinct IPv4 and IPv6 address of `host` (blocking: run on the resolver's threads)."""
    found: dict[ResolvedAddress, None] = {}
    for family, _, _, _, sockaddr in socket.getaddrinfo(host, None, type=socket.SOCK_DGRAM):
        if family in (socket.AF_INET, socket.AF_INET6):
            found[ResolvedAddress(family, ipaddress.ip_address(sockaddr[0]))] = None
    if not found:
        raise OSError(f"{host!r} has no IPv4 or IPv6 address")
    return tuple(found)


@dataclass
class _Lookup:
    future: Future[tuple[ResolvedAddress, ...]]
    done_at: float | None = field(default=None)


class FreeDSenders:
    """The FreeD senders of one application: the policy, and host lookups on threads of
    their own (at most `RESOLVER_THREADS` at a time, `MAX_PENDING_LOOKUPS` running or
    waiting), each waited for at most ``freed_resolve_timeout_s`` and remembered for
    ``freed_resolve_cache_s`` (failures too), so that a name asked for again, or by many
    connections at once, is looked up once."""

    def __init__(self, settings: Settings) -> None:
        self.policy = FreeDPolicy.from_settings(settings)
        self.timeout_s = settings.freed_resolve_timeout_s
        self.cache_s = settings.freed_resolve_cache_s
        self.lookups = 0  # names looked up (not found in the cache)
        self._executor = ThreadPoolExecutor(RESOLVER_THREADS, thread_name_prefix="freed-resolve")
        self._cache: OrderedDict[str, _Lookup] = OrderedDict()
        self._pending = 0
        self._lock = threading.RLock()  # a future already done runs its callback at once, lock held

    async def open(self, to: FreeDDestination) -> FreeDSender:
        """A sender to `to`, once every address of its host is one packets may go to:
        FreeDUnusable (saying why) if one is not, or the host does not resolve in time."""
        if to.own and not self.policy.allowed_networks:
            raise FreeDUnusable("freed: this server lists no network a connection may send FreeD to "
                                "(freed_allowed_networks): leave out host and port to send to the environment's "
                                "receiver")
        addresses = await self.resolve(to.host)
        for resolved in addresses:
            if (why := self.policy.refusal(resolved.address, own=to.own)) is not None:
                named = "" if _literal(to.host) is not None else f"host {to.host!r} resolves to "
                raise FreeDUnusable(f"freed: {named}{why}")
        first = addresses[0]
        try:
            return FreeDSender((str(first.address), to.port), first.family, to)
        except OSError as exc:
            raise FreeDUnusable(f"freed: cannot send to {first.address} ({exc})") from None

    async def resolve(self, host: str) -> tuple[ResolvedAddress, ...]:
        """The addresses of `host` (an IP address is its own, without a lookup)."""
        if (literal := _literal(host)) is not None:
            family = socket.AF_INET if isinstance(literal, ipaddress.IPv4Address) else socket.AF_INET6
            return (ResolvedAddress(family, literal),)
        waited = asyncio.wrap_future(self._lookup(host))
        try:
            done, _ = await asyncio.wait({waited}, timeout=self.timeout_s)
        except asyncio.CancelledError:  # the connection ended meanwhile
            waited.cancel()
            raise
        if not done or waited.cancelled():
            waited.cancel()  # a lookup not yet started is dropped; a running one finishes and is cached
            raise FreeDUnusable(f"freed: cannot resolve host {host!r}: the lookup took more than "
                                f"{self.timeout_s:g} s (freed_resolve_timeout_s)")
        if (exc := waited.exception()) is not None:
            raise FreeDUnusable(f"freed: cannot resolve host {host!r} ({exc})")
        return waited.result()

    def _lookup(self, host: str) -> Future[tuple[ResolvedAddress, ...]]:
        """The cached or running lookup of `host`, or a new one."""
        key = host.lower()
        with self._lock:
            entry = self._cache.get(key)
            if entry is not None and not entry.future.cancelled() and (
                    entry.done_at is None or time.monotonic() - entry.done_at < self.cache_s):
                self._cache.move_to_end(key)
                return entry.future
            if self._pending >= MAX_PENDING_LOOKUPS:
                raise FreeDUnusable(f"freed: cannot resolve host {host!r} now: {MAX_PENDING_LOOKUPS} host lookups "
                                    "are in progress; try again later")
            try:
                future = self._executor.submit(_getaddrinfo, host)
            except RuntimeError:  # shut down
                raise FreeDUnusable("freed: the server is shutting down") from None
            self._pending += 1
            self.lookups += 1
            entry = _Lookup(future)
            self._cache[key] = entry
            while len(self._cache) > MAX_CACHED_NAMES:
                self._cache.popitem(last=False)
            future.add_done_callback(partial(self._finished, entry))
            return future

    def _finished(self, entry: _Lookup, _future: Future[tuple[ResolvedAddress, ...]]) -> None:
        with self._lock:
            self._pending -= 1
            entry.done_at = time.monotonic()

    def close(self) -> None:
        """Stop the lookup threads (at the application's shutdown; a running lookup is not
        waited for)."""
        self._executor.shutdown(wait=False, cancel_futures=True)


class FreeDSender:
    """A UDP socket that sends one connection's poses as FreeD D1 packets to one address
    (`FreeDSenders.open` checked it); a send never blocks (UDP, non-blocking socket)."""

    def __init__(self, address: tuple[str, int], family: int, to: FreeDDestination) -> None:
        self.to = to
        self.address = address
        self._socket = socket.socket(family, socket.SOCK_DGRAM)
        self._socket.setblocking(False)
        self.sent = 0

    def send(self, R: np.ndarray, t: np.ndarray) -> bool:
        """Send the pose (map to camera, the map's z up) as one packet: False when FreeD
        cannot carry it (a camera further than 131 m from the map's origin: nothing is
        sent, as for a frame without a pose); OSError if the network refuses it."""
        try:
            packet = freed.encode(freed.packet_from_pose(R, t, camera_id=self.to.camera_id))
        except ValueError:
            return False
        self._socket.sendto(packet, self.address)
        self.sent += 1
        return True

    def close(self) -> None:
        self._socket.close()
