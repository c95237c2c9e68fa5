"""Surveys (a job: video or images in, map out) and alignment of a map to the world."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, File, Form, Response, UploadFile, status

from app.deps import ImageMemoryDep, JobsDep, RowId, SessionDep, SettingsDep
from app.routers.json_bodies import JsonBodyRoute
from app.routers.responses import JOB_QUEUE_FULL, NO_MAP, UPLOAD_TOO_LARGE, invalid, not_found, problem
from app.schemas import AlignmentRequest, AlignmentResult, JobOut
from app.services import alignments, surveys
from app.settings import MAX_SURVEY_FILES

router = APIRouter(prefix="/environments", tags=["surveys"], route_class=JsonBodyRoute)
_404 = not_found("environment")
_422 = invalid("The request does not validate, or does not fit the environment")


@router.post(
    "/{environment_id}/survey",
    status_code=status.HTTP_202_ACCEPTED,
    # The form parser's own default (1000 files) would refuse a survey of more images than
    # that with a bare 400 before the service's limit (`max_survey_images`) is applied.
    form_limits={"max_files": MAX_SURVEY_FILES + 1},
    response_model=JobOut,
    summary="Survey an environment from a video",
    responses={**_404, **UPLOAD_TOO_LARGE, **problem(415, "Not a supported video or image"), **_422,
               **JOB_QUEUE_FULL},
)
def start_survey(
    environment_id: RowId,
    response: Response,
    session: SessionDep,
    settings: SettingsDep,
    runner: JobsDep,
    memory: ImageMemoryDep,
    video: Annotated[UploadFile | None, File(description="Calibration video: MP4, MOV or AVI.")] = None,
    images: Annotated[list[UploadFile] | None, File(description="Or: JPEG/PNG frames, in order (one size).")] = None,
    marker_size_m: Annotated[float | None, Form(description="Printed card side; default: the environment's.")] = None,
    intrinsics: Annotated[str | None, Form(description='JSON {"width","height","K","dist"}: fixes the camera.')] = None,
    max_frames: Annotated[int | None, Form(description="Frames to use, evenly spaced (default from settings).")] = None,
    feature_tracks: Annotated[bool, Form(description=(
        "Also track the scene's own points (the walls' texture) and register frames through them: frames that "
        "see one card or none, and cards never filmed together, join the map. The map still holds the cards "
        "only."))] = False,
) -> JobOut:
    """Survey the environment from a video of it (or a set of images): structure from
    motion gives the camera's focal length, principal point and distortion and the 3D
    position of every disc. Returns the job (202, ``Location: /jobs/{id}``); on success
    it replaces the environment's map in one transaction."""
    job = surveys.submit_survey(
        session, runner, settings, memory, environment_id,
        video=video.file if video is not None else None,
        images=[upload.file for upload in images or []],
        marker_size_m=marker_size_m, intrinsics=intrinsics, max_frames=max_frames, feature_tracks=feature_tracks,
    )
    response.headers["Location"] = f"/jobs/{job.id}"
    return job


@router.post(
    "/{environment_id}/alignment",
    response_model=AlignmentResult,
    summary="Align the map to the world",
    responses={**_404, **_422, **NO_MAP},
)
def align_map(environment_id: RowId, spec: AlignmentRequest, session: SessionDep) -> AlignmentResult:
    """Move the map into world coordinates: a similarity transform (scale, rotation,
    translation) fitted to three or more discs with known world positions (residuals in
    the reply), or one target chosen as the origin with its plane as z = 0."""
    return alignments.align(session, environment_id, spec)
