"""Classifiers: list, inspect, and train a new one from a site's own images (a job)."""

from __future__ import annotations

from functools import partial
from typing import Annotated

import anyio
from fastapi import APIRouter, File, Form, Response, UploadFile, status

from app.deps import ImageMemoryDep, JobsDep, RowId, SessionDep, SettingsDep
from app.routers.json_bodies import JsonBodyRoute
from app.routers.uploads import read_upload
from app.schemas import ClassifierOut, JobOut, Name, Problem
from app.services import classifiers, training

router = APIRouter(prefix="/classifiers", tags=["classifiers"], route_class=JsonBodyRoute)
_404 = {404: {"model": Problem, "description": "No such classifier"}}


@router.get("", response_model=list[ClassifierOut])
def list_classifiers(session: SessionDep) -> list[ClassifierOut]:
    return classifiers.list_all(session)


@router.get("/{classifier_id}", response_model=ClassifierOut, responses=_404)
def get_classifier(classifier_id: RowId, session: SessionDep) -> ClassifierOut:
    return classifiers.get(session, classifier_id)


@router.post("", status_code=status.HTTP_202_ACCEPTED, response_model=JobOut,
             responses={413: {"model": Problem}, 422: {"model": Problem}, **_404})
async def train_classifier(
    response: Response,
    session: SessionDep,
    settings: SettingsDep,
    runner: JobsDep,
    memory: ImageMemoryDep,
    images: Annotated[list[UploadFile], File(description="JPEG/PNG frames of the site with targets in view.")],
    name: Annotated[Name, Form()],
    base_classifier_id: Annotated[int | None, Form(description="Classifier to adapt; default if omitted.")] = None,
    family: Annotated[str, Form()] = "fido3x3",
) -> JobOut:
    """Adapt a classifier to a site's own images (odd lighting, odd cameras): targets
    the current detector finds and verifies become positives, the candidates it
    rejects become hard negatives. Returns the job (202, ``Location: /jobs/{id}``)."""
    blobs = [await read_upload(upload, settings.max_image_bytes) for upload in images]
    # Every image is decoded to check it: off the event loop.
    job = await anyio.to_thread.run_sync(partial(
        training.submit_training, session, runner, settings, memory, images=blobs, name=name,
        base_classifier_id=base_classifier_id, family=family))
    response.headers["Location"] = f"/jobs/{job.id}"
    return job
