"""Surveys (a job: video or images in, map out) and alignment of a map to the world."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response, status
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field

from app.deps import ImageMemoryDep, JobsDep, RowId, SessionDep, SettingsDep, UploadsInFlightDep
from app.routers.json_bodies import JsonBodyRoute
from app.routers.preconditions import IfMatchDep, map_etag_reply, set_map_etag
from app.routers.responses import (JOB_QUEUE_FULL, MAP_CHANGED, NO_MAP, UPLOAD_TOO_LARGE, UPLOADS_BUSY, invalid,
                                   not_found, problem)
from app.routers.uploads import form_fields, multipart_doc, receive_job_upload
from app.schemas import AlignmentRequest, AlignmentResult, JobOut
from app.services import alignments, surveys

router = APIRouter(prefix="/environments", tags=["surveys"], route_class=JsonBodyRoute)
_404 = not_found("environment")
_422 = invalid("The request does not validate, or does not fit the environment")


class SurveyForm(BaseModel):
    """The text fields of a survey's form."""

    marker_size_m: float | None = Field(None, description="Printed card side; default: the environment's.")
    intrinsics: str | None = Field(None, description='JSON {"width","height","K","dist"}: fixes the camera.')
    max_frames: int | None = Field(None, description="Frames to use, evenly spaced (default from settings).")
    feature_tracks: bool = Field(True, description=(
        "Track the scene's own points (the walls' texture) beside the cards and register frames through them: "
        "frames that see one card or none, and cards never filmed together, join the map. The map still holds "
        "the cards only. On by default; false: the cards alone. Walls with too little texture to track leave "
        "the map resting on the cards alone, with a warning (kind `plain walls`)."))
    readout_ms: float | None = Field(None, description=(
        "The camera's rolling shutter: time from the first row's read to the last's, ms (phones: 10-30). Each "
        "frame's discs and points are then moved to its middle row's moment, with the camera's motion from the "
        "neighbouring frames. A video only (its frame rate); at most a frame. Default: a global shutter."))


_SURVEY_FILES = {
    "video": {"type": "string", "format": "binary", "description": "Calibration video: MP4, MOV or AVI."},
    "images": {"type": "array", "items": {"type": "string", "format": "binary"},
               "description": "Or: JPEG/PNG frames, in order (one size)."},
}


@router.post(
    "/{environment_id}/survey",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=JobOut,
    summary="Survey an environment from a video",
    responses={**_404, **UPLOAD_TOO_LARGE, **problem(415, "Not a supported video or image"), **_422,
               **JOB_QUEUE_FULL, **UPLOADS_BUSY},
    openapi_extra=multipart_doc(SurveyForm, _SURVEY_FILES),
)
async def start_survey(
    environment_id: RowId,
    request: Request,
    response: Response,
    session: SessionDep,
    settings: SettingsDep,
    runner: JobsDep,
    memory: ImageMemoryDep,
    in_flight: UploadsInFlightDep,
) -> JobOut | JSONResponse:
    """Survey the environment from a video of it (or a set of images): structure from
    motion gives the camera's focal length, principal point and distortion and the 3D
    position of every disc. Returns the job (202, ``Location: /jobs/{id}``); on success
    it replaces the environment's map in one transaction. A full job queue (429) or
    uploads in flight over the server's limit (503) are refused before the upload is
    read, with ``Retry-After``."""

    def submit(upload: surveys.SurveyUpload, fields: dict[str, str], job_id: str) -> JobOut:
        form = form_fields(SurveyForm, fields)
        return surveys.submit_survey(session, runner, settings, environment_id, upload, job_id=job_id,
                                     marker_size_m=form.marker_size_m, intrinsics=form.intrinsics,
                                     max_frames=form.max_frames, feature_tracks=form.feature_tracks,
                                     readout_ms=form.readout_ms)

    job = await receive_job_upload(
        request, settings, runner, in_flight, admit=lambda: surveys.check_environment(session, environment_id),
        target=lambda folder: surveys.SurveyUpload(folder, settings, memory), submit=submit)
    if isinstance(job, JobOut):
        response.headers["Location"] = f"/jobs/{job.id}"
    return job


@router.post(
    "/{environment_id}/alignment",
    response_model=AlignmentResult,
    summary="Align the map to the world",
    responses={**map_etag_reply("The fit and the map aligned"), **_404, **_422, **NO_MAP, **MAP_CHANGED},
)
def align_map(environment_id: RowId, spec: AlignmentRequest, session: SessionDep, response: Response,
              if_match: IfMatchDep) -> AlignmentResult:
    """Move the map into world coordinates: a similarity transform (scale, rotation,
    translation) fitted to three or more discs with known world positions (residuals in
    the reply), or one target chosen as the origin with its plane as z = 0. The fit is
    made on the map as it is when the alignment is stored; with ``If-Match``, only if
    that map is at the revision named (else 412)."""
    aligned = alignments.align(session, environment_id, spec, if_match=if_match)
    set_map_etag(response, aligned.revision)
    return aligned.result
