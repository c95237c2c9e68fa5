"""FastAPI dependencies, as annotated types (``SessionDep``, ``SettingsDep``, ...): the
application's shared state, for HTTP routes and WebSockets alike. The getters of shared
objects are ``async``: FastAPI runs a plain ``def`` dependency in a worker thread, a hop
per request for an attribute lookup."""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Path
from pydantic import BeforeValidator
from sqlalchemy import Engine
from sqlalchemy.orm import Session
from starlette.requests import HTTPConnection

from app.services.image_workers import ImageWorkers
from app.services.images import MemoryBudget
from app.services.jobs import JobRunner
from app.services.keys import VerifiedKeys
from app.services.metrics import Metrics
from app.services.streaming import TrackStreams
from app.services.uploads import UploadsInFlight
from app.settings import Settings


async def get_settings(connection: HTTPConnection) -> Settings:
    return connection.app.state.settings


async def get_engine(connection: HTTPConnection) -> Engine:
    return connection.app.state.engine


def get_session(connection: HTTPConnection) -> Iterator[Session]:
    with connection.app.state.sessionmaker() as session:
        yield session


async def get_metrics(connection: HTTPConnection) -> Metrics:
    return connection.app.state.metrics


async def get_jobs(connection: HTTPConnection) -> JobRunner:
    return connection.app.state.jobs


async def get_image_memory(connection: HTTPConnection) -> MemoryBudget:
    return connection.app.state.image_memory


async def get_image_workers(connection: HTTPConnection) -> ImageWorkers:
    return connection.app.state.image_workers


async def get_verified_keys(connection: HTTPConnection) -> VerifiedKeys:
    return connection.app.state.verified_keys


async def get_track_streams(connection: HTTPConnection) -> TrackStreams:
    return connection.app.state.track_streams


async def get_uploads_in_flight(connection: HTTPConnection) -> UploadsInFlight:
    return connection.app.state.uploads_in_flight


_ROW_ID = re.compile(r"[1-9][0-9]{0,17}")


def _row_id(value: object) -> object:
    if isinstance(value, str) and not _ROW_ID.fullmatch(value):
        raise ValueError("must be a positive whole number in plain digits")
    return value


#: A stored row's id in a URL path: plain digits only. An int path parameter alone would
#: also take "1 ", "+1" and "01" for row 1, so that a mistyped URL (a stray space) acts on
#: a row all the same.
RowId = Annotated[int, BeforeValidator(_row_id), Path()]

SettingsDep = Annotated[Settings, Depends(get_settings)]
EngineDep = Annotated[Engine, Depends(get_engine)]
SessionDep = Annotated[Session, Depends(get_session)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
JobsDep = Annotated[JobRunner, Depends(get_jobs)]
VerifiedKeysDep = Annotated[VerifiedKeys, Depends(get_verified_keys)]
ImageMemoryDep = Annotated[MemoryBudget, Depends(get_image_memory)]
#: The processes of /detect and /locate (apart from /track's threads).
ImageWorkersDep = Annotated[ImageWorkers, Depends(get_image_workers)]
TrackStreamsDep = Annotated[TrackStreams, Depends(get_track_streams)]
#: The bytes of the uploads this process is reading.
UploadsInFlightDep = Annotated[UploadsInFlight, Depends(get_uploads_in_flight)]
