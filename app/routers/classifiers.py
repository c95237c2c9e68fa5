"""Classifiers: list, inspect, train a new one from a site's own images (a job), and
delete one that nothing uses."""

from __future__ import annotations

from functools import partial
from typing import Annotated

import anyio
from fastapi import APIRouter, File, Form, Response, UploadFile, status

from app.deps import ImageMemoryDep, JobsDep, RowId, SessionDep, SettingsDep
from app.routers.json_bodies import JsonBodyRoute
from app.routers.responses import JOB_QUEUE_FULL, UPLOAD_TOO_LARGE, invalid, not_found, problem
from app.routers.uploads import read_upload
from app.schemas import ClassifierOut, JobOut, Name
from app.services import classifiers, training

router = APIRouter(prefix="/classifiers", tags=["classifiers"], route_class=JsonBodyRoute)
_404 = not_found("classifier")
_422 = invalid()


@router.get("", response_model=list[ClassifierOut], summary="List the classifiers")
def list_classifiers(session: SessionDep) -> list[ClassifierOut]:
    """Every classifier, oldest first: the default one, installed at the first start, and the trained ones."""
    return classifiers.list_all(session)


@router.get("/{classifier_id}", response_model=ClassifierOut, summary="Get a classifier",
            responses={**_404, **_422})
def get_classifier(classifier_id: RowId, session: SessionDep) -> ClassifierOut:
    """One classifier: where it comes from and how it was trained."""
    return classifiers.get(session, classifier_id)


@router.delete(
    "/{classifier_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    summary="Delete a classifier",
    responses={**_404, **_422, **problem(409, (
        "The classifier is the default, an environment detects with it (the reply names them) or a queued or "
        "running job will use it"))},
)
def delete_classifier(classifier_id: RowId, session: SessionDep) -> None:
    """Delete a classifier nothing uses. The default classifier stays, and so does one
    that an environment detects with: give those environments another classifier first
    (``PATCH /environments/{id}``)."""
    classifiers.delete(session, classifier_id)


@router.post("", status_code=status.HTTP_202_ACCEPTED, response_model=JobOut,
             summary="Train a classifier on a site's images",
             responses={**UPLOAD_TOO_LARGE, **problem(415, "An image is not a JPEG or PNG"), **_422, **_404,
                        **JOB_QUEUE_FULL})
async def train_classifier(
    response: Response,
    session: SessionDep,
    settings: SettingsDep,
    runner: JobsDep,
    memory: ImageMemoryDep,
    images: Annotated[list[UploadFile], File(description="JPEG/PNG frames of the site with targets in view.")],
    name: Annotated[Name, Form(description="A name for the new classifier.")],
    base_classifier_id: Annotated[int | None, Form(description="Classifier to adapt; default if omitted.")] = None,
    family: Annotated[str, Form(description="Marker family of the cards in the images.")] = "fido3x3",
) -> JobOut:
    """Adapt a classifier to a site's own images (odd lighting, odd cameras): targets
    the current detector finds and verifies become positives, the candidates it
    rejects become hard negatives. Returns the job (202, ``Location: /jobs/{id}``); its
    result names the new classifier."""
    blobs = [await read_upload(upload, settings.max_image_bytes) for upload in images]
    # Every image is decoded to check it: off the event loop.
    job = await anyio.to_thread.run_sync(partial(
        training.submit_training, session, runner, settings, memory, images=blobs, name=name,
        base_classifier_id=base_classifier_id, family=family))
    response.headers["Location"] = f"/jobs/{job.id}"
    return job
