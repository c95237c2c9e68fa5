"""What a job handler gets on its worker besides its parameters: the database, progress
reporting, the engine's other workers for work that splits, and the transaction that ends
the job."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from sqlalchemy.orm import Session, sessionmaker

from app.services.jobs import store

S = TypeVar("S")
I = TypeVar("I")  # noqa: E741
R = TypeVar("R")


class Cancelled(Exception):
    """Raised inside a job when its row says it was cancelled, or that this attempt is no
    longer the job's running one (failed as lost, or run again elsewhere)."""


@dataclass
class JobContext:
    """One attempt of a running job, seen from its handler."""

    claim: store.Claim
    environment_id: int | None
    data_dir: Path
    sessions: sessionmaker[Session]
    finished: bool = False
    #: Set by the heartbeat when the row no longer runs this attempt.
    stopped: threading.Event = field(default_factory=threading.Event, repr=False)
    _last_write: float = field(default=0.0, repr=False)

    @property
    def job_id(self) -> str:
        return self.claim.job_id

    def progress(self, stage: str, fraction: float, message: str = "") -> None:
        """Report progress (at most a few writes a second) and stop if the job was
        cancelled or this attempt superseded."""
        if self.stopped.is_set():
            raise Cancelled(self.job_id)
        now = time.monotonic()
        if now - self._last_write < 0.2 and fraction < 1.0:
            return
        self._last_write = now
        with self.sessions() as session:
            if not store.report_progress(session, self.claim, stage, fraction, message):
                self.stopped.set()
                raise Cancelled(self.job_id)

    def fan_out(self, function: Callable[[S, I], R], shared: S, items: Sequence[I],
                done: Callable[[int, int], None] | None = None) -> list[R]:
        """``[function(shared, item) for item in items]``, spread over every worker of the
        job engine when the job runs on one (`shared` sent to each worker once), else in
        this process. ``done(finished, total)`` after each item, in the order they end;
        an exception in it (Cancelled from `progress`) drops the items not yet run."""
        from app.services.jobs.cluster import map_on_workers

        return map_on_workers(function, shared, items, done or (lambda finished, total: None), self.job_id)

    @contextmanager
    def finishing(self, result: dict[str, Any]) -> Iterator[Session]:
        """A session whose changes commit together with the job's success, or not at
        all if the job was cancelled (or this attempt superseded) meanwhile, so that a
        cancelled survey changes nothing. ``result`` is stored as it is when the block
        ends (the block may fill it in)."""
        with self.sessions() as session:
            yield session
            if not store.finish(session, self.claim, result):
                session.rollback()
                raise Cancelled(self.job_id)
            session.commit()
            self.finished = True
