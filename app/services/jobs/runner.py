"""The web process's side of jobs: submit them to the job engine, and fail those the engine
lost (a worker gone silent, a scheduler gone) rather than leave them queued or running."""

from __future__ import annotations

import logging
import shutil
import socket
import threading
from collections.abc import Iterable
from urllib.parse import urlsplit

from pydantic import BaseModel
from sqlalchemy.orm import Session, sessionmaker

from app.models import Job
from app.services.errors import Busy, TooMany
from app.services.jobs import store
from app.services.jobs.cluster import JOB_RESOURCE, EngineSetupError, engine_security, local_cluster
from app.services.jobs.registry import handler_for
from app.services.jobs.worker import run_job
from app.settings import Settings

log = logging.getLogger("app.jobs")

#: A job row younger than this may not have reached its scheduler yet (it is stored first).
SUBMIT_GRACE_S = 10.0
#: How long a web process waits for an external scheduler before saying it cannot be reached.
CONNECT_TIMEOUT_S = 10.0


def _known_keys(keys: list[str], dask_scheduler) -> list[str]:  # type: ignore[no-untyped-def]
    """(On the scheduler.) Which of `keys` it holds to run or running (not given up on)."""
    return [key for key in keys if key in dask_scheduler.tasks and dask_scheduler.tasks[key].state != "erred"]


def engine_reachable(address: str, timeout: float = 2.0) -> bool:
    """Whether something listens at a scheduler's address (``tcp://host:port``)."""
    parts = urlsplit(address)
    if parts.scheme not in ("tcp", "tls") or parts.hostname is None or parts.port is None:
        return False
    try:
        with socket.create_connection((parts.hostname, parts.port), timeout=timeout):
            return True
    except OSError:
        return False


def task_key(job_id: str) -> str:
    return f"job-{job_id}"


class SlotReservation:
    """A job slot held by an upload being read (`JobRunner.reserve`); released once."""

    def __init__(self, runner: JobRunner) -> None:
        self._runner: JobRunner | None = runner

    def release(self) -> None:
        runner, self._runner = self._runner, None
        if runner is not None:
            runner._unreserve()


class JobRunner:
    """Submits jobs to the job engine (`settings.job_scheduler`, or a local cluster this
    process starts with its first job) and reaps the jobs the engine lost."""

    def __init__(self, settings: Settings, sessions: sessionmaker[Session]) -> None:
        self.settings = settings
        self._sessions = sessions
        self._lock = threading.Lock()
        # Job slots held by uploads being read (`reserve`), not yet rows.
        self._reserve_lock = threading.Lock()
        self._reserved = 0
        self._cluster = None  # the local cluster, when this process owns one
        self._client = None
        self._stop = threading.Event()
        self._reaper = threading.Thread(target=self._reap_every, name="job-reaper", daemon=True)

    @property
    def owns_engine(self) -> bool:
        return self.settings.job_scheduler is None

    def start(self) -> None:
        """Fail the jobs a dead engine left queued or running, remove uploads of jobs that
        will never run, and start reaping."""
        self.reap()
        uploads = self.settings.data_dir / "uploads"
        if uploads.is_dir():
            with self._sessions() as session:
                active = store.active_ids(session)
            for folder in uploads.iterdir():
                if folder.name not in active:
                    shutil.rmtree(folder, ignore_errors=True)
        self._reaper.start()

    def client(self):  # type: ignore[no-untyped-def]  (distributed.Client)
        """The engine's client, connecting (or starting the local cluster) on first use;
        Busy (503) when the scheduler cannot be reached."""
        with self._lock:
            if self._client is not None and not self.owns_engine and self._client.status in ("closing", "closed"):
                # It gave up reconnecting to a scheduler that was away (restarted): anew.
                self._client = None
            if self._client is None:
                from distributed import Client

                try:
                    if self.owns_engine:
                        self._cluster = local_cluster(self.settings)
                        self._client = Client(self._cluster, set_as_default=False)
                        log.info("local job cluster at %s", self._cluster.scheduler_address)
                    else:
                        # TLS with the deployment's certificates for a tls:// scheduler.
                        security = engine_security(self.settings, self.settings.job_scheduler)
                        self._client = Client(self.settings.job_scheduler, timeout=CONNECT_TIMEOUT_S,
                                              set_as_default=False, security=security)
                except (OSError, TimeoutError, EngineSetupError) as exc:
                    raise Busy(f"the job engine at {self.settings.job_scheduler} cannot be reached ({exc}); "
                               "try again later") from None
            return self._client

    @property
    def address(self) -> str | None:
        """The scheduler's address once connected (the local cluster's once started)."""
        with self._lock:
            return None if self._client is None else self._client.scheduler.address

    def reserve(self, max_active: int) -> SlotReservation:
        """Hold one of the `max_active` job slots while a job's upload is read, before any
        of it is: TooMany (429) when the jobs queued or running in the database (every
        process's) and this process's other reservations fill them. Release it once the
        job is stored (`submit` counts the slots again, under the table lock) or refused."""
        with self._reserve_lock:
            with self._sessions() as session:
                active = store.count_active(session)
            if active + self._reserved >= max_active:
                raise TooMany(f"{active} jobs are queued or running and {self._reserved} more are being uploaded "
                              f"(the limit is {max_active}); try again later")
            self._reserved += 1
        return SlotReservation(self)

    def _unreserve(self) -> None:
        with self._reserve_lock:
            self._reserved -= 1

    def submit(self, session: Session, kind: str, params: BaseModel, *, environment_id: int | None = None,
               job_id: str | None = None, max_active: int | None = None) -> Job:
        """Store a job of `kind` (a registered kind; `params` of its handler's model) and
        hand it to the engine. With `max_active`, TooMany (429) when that many jobs are
        queued or running."""
        from distributed import fire_and_forget

        handler = handler_for(kind)
        if not isinstance(params, handler.params):
            raise TypeError(f"{kind} jobs take {handler.params.__name__}, not {type(params).__name__}")
        client = self.client()
        job = store.create(session, kind, params, engine=client.scheduler.address, environment_id=environment_id,
                           job_id=job_id, max_active=max_active)
        # The row, not this future, is the job's truth: the task runs whether or not this
        # process is still there to hear of it.
        fire_and_forget(client.submit(run_job, job.id, handler, key=task_key(job.id), pure=False,
                                      resources={JOB_RESOURCE: 1}))
        return job

    def reap(self) -> list[str]:
        """Fail the jobs the engine lost; their ids. A running job whose worker fell silent
        for `job_lease_s`; a queued or running job its scheduler no longer holds (this
        process's), or whose scheduler is gone (another's, unreachable)."""
        with self._sessions() as session:
            lost = store.fail_silent(session, self.settings.job_lease_s)
            by_engine = store.active_by_engine(session, SUBMIT_GRACE_S)
        gone: list[str] = []
        for engine, jobs in by_engine.items():
            held, asked = self._held(engine, [task_key(job_id) for job_id, _ in jobs])
            if held is not None:
                # A young job its own scheduler does not hold yet may be on its way there.
                gone += [job_id for job_id, young in jobs if task_key(job_id) not in held and not (asked and young)]
        if gone:
            with self._sessions() as session:
                store.fail(session, gone, "the job engine this job was given to is gone (its scheduler stopped "
                           "or restarted); submit it again", stage="interrupted")
        self._remove_uploads(lost + gone)
        if lost or gone:
            log.warning("failed %d job(s) the engine lost", len(lost) + len(gone))
        return lost + gone

    def _held(self, engine: str, keys: list[str]) -> tuple[set[str] | None, bool]:
        """Which of `keys` the scheduler at `engine` holds, and whether it was asked: it is
        when it is this process's engine; another that listens cannot be asked (None);
        where nothing listens, nothing is held."""
        with self._lock:
            client = self._client if self._client is not None and self._client.scheduler.address == engine else None
        if client is not None:
            try:
                return set(client.run_on_scheduler(_known_keys, keys)), True
            except Exception:  # noqa: BLE001  (the scheduler went away: see whether anything listens)
                log.warning("the job scheduler at %s did not answer", engine)
        return (None if engine_reachable(engine) else set()), False

    def _reap_every(self) -> None:
        interval = min(self.settings.job_lease_s / 3, 10.0)
        while not self._stop.wait(interval):
            try:
                self.reap()
            except Exception:  # noqa: BLE001  (a busy database or scheduler: next round)
                log.warning("job reaper round failed", exc_info=True)

    def _remove_uploads(self, job_ids: Iterable[str]) -> None:
        for job_id in job_ids:
            shutil.rmtree(store.uploads_dir(self.settings.data_dir, job_id), ignore_errors=True)

    def shutdown(self) -> None:
        """Stop reaping and disconnect. A local cluster this process owns stops with it:
        its queued and running jobs are failed, saying so."""
        self._stop.set()
        if self._reaper.is_alive():
            self._reaper.join(15)
        with self._lock:
            client, cluster, self._client, self._cluster = self._client, self._cluster, None, None
        if client is None:
            return
        address = client.scheduler.address
        if cluster is not None:
            with self._sessions() as session:
                ids = [job_id for job_id, _ in store.active_by_engine(session, 0.0).get(address, [])]
                store.fail(session, ids, "the server shut down while this job was queued or running",
                           stage="interrupted")
            self._remove_uploads(ids)
        client.close()
        if cluster is not None:
            cluster.close()
