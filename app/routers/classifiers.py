"""Classifiers: list, inspect, train a new one from a site's own images (a job), and
delete one that nothing uses."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response, status
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field

from app.deps import ImageMemoryDep, JobsDep, RowId, SessionDep, SettingsDep, UploadsInFlightDep
from app.routers.json_bodies import JsonBodyRoute
from app.routers.responses import JOB_QUEUE_FULL, UPLOAD_TOO_LARGE, UPLOADS_BUSY, invalid, not_found, problem
from app.routers.uploads import form_fields, multipart_doc, receive_job_upload
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


class TrainingForm(BaseModel):
    """The text fields of a training form."""

    name: Name = Field(description="A name for the new classifier.")
    base_classifier_id: int | None = Field(None, description="Classifier to adapt; default if omitted.")
    family: str = Field("fido3x3", description="Marker family of the cards in the images.")


_TRAINING_FILES = {
    "images": {"type": "array", "items": {"type": "string", "format": "binary"},
               "description": "JPEG/PNG frames of the site with targets in view."},
}


@router.post("", status_code=status.HTTP_202_ACCEPTED, response_model=JobOut,
             summary="Train a classifier on a site's images",
             responses={**UPLOAD_TOO_LARGE, **problem(415, "An image is not a JPEG or PNG"), **_422, **_404,
                        **JOB_QUEUE_FULL, **UPLOADS_BUSY},
             openapi_extra=multipart_doc(TrainingForm, _TRAINING_FILES, required=("images",)))
async def train_classifier(
    request: Request,
    response: Response,
    session: SessionDep,
    settings: SettingsDep,
    runner: JobsDep,
    memory: ImageMemoryDep,
    in_flight: UploadsInFlightDep,
) -> JobOut | JSONResponse:
    """Adapt a classifier to a site's own images (odd lighting, odd cameras): targets
    the current detector finds and verifies become positives, the candidates it
    rejects become hard negatives. Returns the job (202, ``Location: /jobs/{id}``); its
    result names the new classifier. A full job queue (429) or uploads in flight over
    the server's limit (503) are refused before the upload is read, with ``Retry-After``."""

    def submit(upload: training.TrainingUpload, fields: dict[str, str], job_id: str) -> JobOut:
        form = form_fields(TrainingForm, fields)
        return training.submit_training(session, runner, settings, upload, job_id=job_id, name=form.name,
                                        base_classifier_id=form.base_classifier_id, family=form.family)

    job = await receive_job_upload(
        request, settings, runner, in_flight, admit=lambda: None,
        target=lambda folder: training.TrainingUpload(folder, settings, memory), submit=submit)
    if isinstance(job, JobOut):
        response.headers["Location"] = f"/jobs/{job.id}"
    return job
