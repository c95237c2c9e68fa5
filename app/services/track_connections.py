"""Open /track connections counted in the database, so that ``max_track_connections``
holds for the whole service: every server process (``fidotrack serve --workers N``, or
servers on several machines) sharing the database counts the same rows.

Each open connection is a `TrackConnection` row held by the process serving it. The
process renews its rows' ``seen_at`` every lease / 3 from a thread of its own; a row not
renewed for a lease (its process died without closing it) is dropped by the next
admission and stops counting. Admission checks and inserts in one transaction under
`lock_for_writing`, so two processes cannot both take the last connection. A row also
names its client's address and API key, so that the share each of them may hold
(``max_track_connections_per_address``, ``_per_key``) holds across processes too.
"""

from __future__ import annotations

import logging
import threading
import uuid
from datetime import timedelta

from sqlalchemy import delete, func, select, update
from sqlalchemy.orm import Session, sessionmaker

from app.db import lock_for_writing, utcnow
from app.models import TrackConnection
from app.services.jobs.store import runner_id
from app.services.rate_limits import Limit

log = logging.getLogger(__name__)


class ClientAtLimit(Exception):
    """The connection's client address or API key already holds `share` connections."""

    def __init__(self, limit: Limit, share: int) -> None:
        super().__init__(f"{limit}: {share}")
        self.limit = limit
        self.share = share


class TrackConnections:
    """This process's /track connections against a limit shared by every process on the
    database, and a share of it per client address and per API key (0: none). The methods
    block on the database: call them from a worker thread."""

    def __init__(self, sessions: sessionmaker[Session], *, limit: int, lease_s: float, per_address: int = 0,
                 per_key: int = 0) -> None:
        self.sessions = sessions
        self.limit = limit
        self.lease_s = lease_s
        self.per_address = per_address
        self.per_key = per_key
        self.server = runner_id()
        self._held: set[str] = set()  # ids of the rows this object opened and has not closed
        self._lock = threading.Lock()
        self._stopped = threading.Event()
        self._renewer: threading.Thread | None = None

    @property
    def held(self) -> int:
        """Connections this process holds open."""
        with self._lock:
            return len(self._held)

    def open(self, environment_id: int, *, address: str | None = None, key_id: int | None = None) -> str | None:
        """Take a connection for `environment_id`, for a client at `address` with API key
        `key_id` (None: not known): its id, or None when the service already holds `limit`
        live connections; ClientAtLimit when the address or the key holds its share."""
        now = utcnow()
        lease_id = uuid.uuid4().hex
        with self.sessions() as session:
            lock_for_writing(session, TrackConnection.__tablename__)
            session.execute(delete(TrackConnection).where(
                TrackConnection.seen_at < now - timedelta(seconds=self.lease_s)))
            live = session.scalar(select(func.count()).select_from(TrackConnection)) or 0
            if live >= self.limit:
                session.commit()  # the stale rows stay dropped
                return None
            for limit, share, column, value in ((Limit.TRACK_CONNECTIONS_PER_ADDRESS, self.per_address,
                                                 TrackConnection.client_address, address),
                                                (Limit.TRACK_CONNECTIONS_PER_KEY, self.per_key,
                                                 TrackConnection.key_id, key_id)):
                if share and value is not None and (session.scalar(
                        select(func.count()).select_from(TrackConnection).where(column == value)) or 0) >= share:
                    session.commit()
                    raise ClientAtLimit(limit, share)
            session.add(TrackConnection(id=lease_id, server=self.server, environment_id=environment_id,
                                        opened_at=now, seen_at=now, client_address=address, key_id=key_id))
            session.commit()
        with self._lock:
            self._held.add(lease_id)
            self._start_renewing()
        return lease_id

    def close(self, lease_id: str) -> None:
        """Give the connection back (a row already gone, dropped as stale or with its
        environment, is no error)."""
        with self._lock:
            self._held.discard(lease_id)  # first: not renewed again whatever happens below
        with self.sessions() as session:
            session.execute(delete(TrackConnection).where(TrackConnection.id == lease_id))
            session.commit()

    def renew(self) -> int:
        """Mark this process's open connections as alive now; how many rows were renewed."""
        with self._lock:
            held = list(self._held)
        if not held:
            return 0
        with self.sessions() as session:
            result = session.execute(update(TrackConnection)
                                     .where(TrackConnection.server == self.server, TrackConnection.id.in_(held))
                                     .values(seen_at=utcnow()))
            session.commit()
        renewed = int(result.rowcount or 0)  # type: ignore[attr-defined]
        if renewed < len(held):
            # Another process dropped them as stale (this one stalled for a lease), or their
            # environment was deleted: those connections go on uncounted until they close.
            log.warning("%d open /track connection(s) of this process were no longer in the database",
                        len(held) - renewed)
        return renewed

    def close_all(self) -> None:
        """Stop renewing and delete this process's rows (at shutdown: a restart must not
        wait a lease for the connections it dropped to stop counting)."""
        self._stopped.set()
        with self._lock:
            held, self._held = list(self._held), set()
            renewer = self._renewer
        if renewer is not None:
            renewer.join(timeout=self.lease_s / 3)
        if held:
            with self.sessions() as session:
                session.execute(delete(TrackConnection).where(TrackConnection.server == self.server,
                                                              TrackConnection.id.in_(held)))
                session.commit()

    def _start_renewing(self) -> None:
        """Start the renewing thread unless it runs (with `_lock` held): it runs while this
        process holds connections, so an idle server (and a test's app) leaves none behind."""
        if self._renewer is None and not self._stopped.is_set():
            self._renewer = threading.Thread(target=self._renew_while_held, name="track-connections", daemon=True)
            self._renewer.start()

    def _renew_while_held(self) -> None:
        while not self._stopped.wait(self.lease_s / 3):
            with self._lock:
                if not self._held:
                    self._renewer = None
                    return
            try:
                self.renew()
            except Exception as exc:  # a busy or unreachable database: the next round tries again
                log.warning("could not renew the open /track connections: %r", exc)
        with self._lock:
            self._renewer = None
