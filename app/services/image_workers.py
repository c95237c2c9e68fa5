"""``/detect`` (its JSON reply and its drawn image) and ``/locate`` in worker processes of
their own.

Their images are whole frames sent by any client at any rate: in the web process they
would share its interpreter (the GIL) and its cores with the ``/track`` streams, which
then lost most of their frame rate under a burst of ``/detect`` requests. In
``image_workers`` processes at a lower OS priority (``image_workers_nice``), they take
the cores only when tracking leaves them idle. Each worker has its own database
sessions, detectors and maps (loaded once, as the web process's); the image memory
budget is shared with the web process.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from typing import TypeVar

from sqlalchemy.orm import Session, sessionmaker

from app import logs
from app.core.detection import warm_up
from app.db import make_engine, make_sessionmaker
from app.schemas import DetectResponse, LocateResponse, TrackConfig
from app.services import detection
from app.services.detection import DetectorCache
from app.services.errors import Busy
from app.services.images import MemoryBudget, limit_compute_threads
from app.services.tracking import TrackingService
from app.settings import Settings

T = TypeVar("T")
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Worker:
    """A worker process's services, made once when it starts."""

    settings: Settings
    memory: MemoryBudget
    sessions: sessionmaker[Session]
    detectors: DetectorCache
    tracking: TrackingService


_worker: _Worker | None = None


def _start_worker(settings: Settings, memory: MemoryBudget, nice: int) -> None:
    global _worker
    try:
        os.nice(nice)
    except (AttributeError, OSError) as exc:  # not a Unix, or not allowed: the same priority then
        log.debug("the image worker keeps its priority (%s)", exc)
    logs.configure(settings.log_format, settings.log_level)
    limit_compute_threads(settings.compute_threads)
    sessions = make_sessionmaker(make_engine(settings.resolved_database_url, settings.sqlite_busy_timeout_ms))
    detectors = DetectorCache()
    warm_up()
    _worker = _Worker(settings, memory, sessions, detectors,
                      TrackingService(detectors=detectors, sessions=sessions, settings=settings, memory=memory))


def _in_worker(request_id: str | None, function: Callable[..., T], *args: object) -> T:
    assert _worker is not None, "the image worker was not started"
    token = logs.request_id.set(request_id)
    try:
        return function(_worker, *args)
    finally:
        logs.request_id.reset(token)


def _detect(worker: _Worker, data: bytes, classifier_id: int | None, family: str, with_candidates: bool
            ) -> DetectResponse:
    with worker.sessions() as session:
        return detection.detect(session, worker.detectors, worker.settings, worker.memory, data,
                                classifier_id=classifier_id, family=family, with_candidates=with_candidates)


def _detect_drawn(worker: _Worker, data: bytes, classifier_id: int | None, family: str) -> bytes:
    with worker.sessions() as session:
        return detection.detect_drawn(session, worker.detectors, worker.settings, worker.memory, data,
                                      classifier_id=classifier_id, family=family)


def _locate(worker: _Worker, environment_id: int, data: bytes, config: TrackConfig) -> LocateResponse:
    return worker.tracking.locate(environment_id, data, config)


class ImageWorkers:
    """The worker processes of ``/detect`` and ``/locate``. At most ``max_image_requests``
    are in at once, from before their bodies are read until their replies; more are
    refused (503) rather than queued with their bodies in memory. A worker that dies
    (killed, out of memory) is replaced; the requests it held get 503."""

    def __init__(self, settings: Settings, memory: MemoryBudget) -> None:
        self.settings = settings
        self.memory = memory
        self.max_requests = settings.max_image_requests
        self.in_flight = 0
        self._executor = self._new_executor()

    def _new_executor(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(self.settings.image_workers, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_start_worker,
                                   initargs=(self.settings, self.memory, self.settings.image_workers_nice))

    @contextmanager
    def admitted(self) -> Iterator[None]:
        """One image request, from before its body is read until its reply: Busy when
        `max_requests` are in already. (Used on the event loop only: no lock.)"""
        if self.in_flight >= self.max_requests:
            raise Busy(f"the server is processing {self.in_flight} images already; retry")
        self.in_flight += 1
        try:
            yield
        finally:
            self.in_flight -= 1

    async def detect(self, data: bytes, *, classifier_id: int | None, family: str, with_candidates: bool
                     ) -> DetectResponse:
        return await self._run(_detect, data, classifier_id, family, with_candidates)

    async def detect_drawn(self, data: bytes, *, classifier_id: int | None, family: str) -> bytes:
        """The image as a PNG with its detections drawn (`detection.detect_drawn`)."""
        return await self._run(_detect_drawn, data, classifier_id, family)

    async def locate(self, environment_id: int, data: bytes, config: TrackConfig) -> LocateResponse:
        return await self._run(_locate, environment_id, data, config)

    async def _run(self, function: Callable[..., T], *args: object) -> T:
        executor = self._executor
        call = partial(_in_worker, logs.request_id.get(), function, *args)
        try:
            return await asyncio.get_running_loop().run_in_executor(executor, call)
        except BrokenProcessPool:
            log.error("an image worker died; starting new ones")
            if self._executor is executor:
                executor.shutdown(wait=False, cancel_futures=True)  # its other workers are stopped too
                self.memory.release_others()
                self._executor = self._new_executor()
            raise Busy("the image worker processing this request stopped; retry") from None

    def shutdown(self) -> None:
        self._executor.shutdown(wait=True, cancel_futures=True)
