"""FastAPI dependencies, as annotated types (``SessionDep``, ``SettingsDep``)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy import Engine
from sqlalchemy.orm import Session

from app.services.detection import DetectorCache
from app.services.jobs import JobRunner
from app.services.metrics import Metrics
from app.settings import Settings


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_engine(request: Request) -> Engine:
    return request.app.state.engine


def get_session(request: Request) -> Iterator[Session]:
    with request.app.state.sessionmaker() as session:
        yield session


def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


def get_detectors(request: Request) -> DetectorCache:
    return request.app.state.detectors


def get_jobs(request: Request) -> JobRunner:
    return request.app.state.jobs


SettingsDep = Annotated[Settings, Depends(get_settings)]
EngineDep = Annotated[Engine, Depends(get_engine)]
SessionDep = Annotated[Session, Depends(get_session)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
DetectorsDep = Annotated[DetectorCache, Depends(get_detectors)]
JobsDep = Annotated[JobRunner, Depends(get_jobs)]
