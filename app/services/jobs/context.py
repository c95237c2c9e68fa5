"""What a job handler gets in its worker process besides its parameters: the database,
progress reporting, and the transaction that ends the job."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from app.services.jobs import store


class Cancelled(Exception):
    """Raised inside a job when its row says it was cancelled (or its web process is gone)."""


@dataclass
class JobContext:
    """One running job, seen from its handler."""

    job_id: str
    environment_id: int | None
    data_dir: Path
    sessions: sessionmaker[Session]
    parent_pid: int | None = None
    finished: bool = False
    _last_write: float = field(default=0.0, repr=False)

    def progress(self, stage: str, fraction: float, message: str = "") -> None:
        """Report progress (at most a few writes a second) and stop if cancelled, or if
        the web process that started this worker is gone (its restart fails the job)."""
        if self.parent_pid is not None and os.getppid() != self.parent_pid:
            raise Cancelled(self.job_id)
        now = time.monotonic()
        if now - self._last_write < 0.2 and fraction < 1.0:
            return
        self._last_write = now
        with self.sessions() as session:
            if not store.report_progress(session, self.job_id, stage, fraction, message):
                raise Cancelled(self.job_id)

    @contextmanager
    def finishing(self, result: dict[str, Any]) -> Iterator[Session]:
        """A session whose changes commit together with the job's success, or not at
        all if the job was cancelled meanwhile (so a cancelled survey changes nothing).
        ``result`` is stored as it is when the block ends (the block may fill it in)."""
        with self.sessions() as session:
            yield session
            if not store.finish(session, self.job_id, result):
                session.rollback()
                raise Cancelled(self.job_id)
            session.commit()
            self.finished = True
