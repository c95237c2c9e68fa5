"""FreeD output: each environment's receiver (stored, one transaction per public
function) and the UDP sender of one /track connection.

A connection sends to the environment's receiver unless its config names its own host,
port or camera id, or switches FreeD off (`app.schemas.FreeDConnection`). The
environment's receiver is read when the connection opens: a change reaches the
connections opened after it.
"""

from __future__ import annotations

import socket
from dataclasses import dataclass

import numpy as np
from sqlalchemy.orm import Session

from app.core import freed
from app.models import FreeDReceiver
from app.schemas import FreeDConnection, FreeDOutput
from app.services import environments
from app.services.errors import NotFound


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


def put(session: Session, environment_id: int, output: FreeDOutput) -> FreeDOutput:
    """Set the environment's FreeD output (replacing the one it had)."""
    environments.get_row(session, environment_id)
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
    return FreeDOutput(host=row.host, port=row.port, camera_id=row.camera_id, enabled=row.enabled)


class FreeDUnusable(ValueError):
    """A connection's FreeD settings cannot be used; the message says why, for a person."""


@dataclass(frozen=True)
class FreeDDestination:
    """Where one connection's packets go: a receiver's host, port and the camera id."""

    host: str
    port: int
    camera_id: int


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
    if (connection.host is not None or connection.port is not None) and not own_receivers:
        raise FreeDUnusable("this server sends FreeD only to the environment's receiver (PUT "
                            "/environments/{id}/freed): leave out host and port")
    host = connection.host if connection.host is not None else output.host if output is not None else None
    port = connection.port if connection.port is not None else output.port if output is not None else None
    if host is None or port is None:
        raise FreeDUnusable("freed: give host and port, or set the environment's FreeD output "
                            "(PUT /environments/{id}/freed)")
    return FreeDDestination(host, port, connection.camera_id)


class FreeDSender:
    """A UDP socket that sends one connection's poses as FreeD D1 packets.

    The host is resolved once, when the sender is made (`open`, blocking: call it in a
    worker thread); a send never blocks (UDP, non-blocking socket).
    """

    def __init__(self, address: tuple, family: int, to: FreeDDestination) -> None:
        self.to = to
        self.address = address
        self._socket = socket.socket(family, socket.SOCK_DGRAM)
        self._socket.setblocking(False)
        self.sent = 0

    @classmethod
    def open(cls, to: FreeDDestination) -> FreeDSender:
        """A sender to `to`: FreeDUnusable if its host does not resolve."""
        try:
            family, _, _, _, address = socket.getaddrinfo(to.host, to.port, type=socket.SOCK_DGRAM)[0]
        except (OSError, UnicodeError) as exc:
            raise FreeDUnusable(f"freed: cannot resolve host {to.host!r} ({exc})") from None
        return cls(address, family, to)

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
