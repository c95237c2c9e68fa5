"""POST /detect: targets (and optionally every candidate disc) in one image."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request
from starlette.concurrency import run_in_threadpool

from app.deps import DetectorsDep, SessionDep, SettingsDep
from app.routers.uploads import IMAGE_BODY_DOC, read_image_body
from app.schemas import DetectResponse, Problem
from app.services import detection

router = APIRouter(tags=["detection"])


@router.post(
    "/detect",
    response_model=DetectResponse,
    openapi_extra=IMAGE_BODY_DOC,
    responses={413: {"model": Problem}, 415: {"model": Problem}, 422: {"model": Problem}},
)
async def detect(
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    detectors: DetectorsDep,
    candidates: Annotated[bool, Query(description="Also return every disc that passed the classifier.")] = False,
    classifier_id: Annotated[int | None, Query(description="Classifier to use; default if omitted.")] = None,
    family: Annotated[str, Query(description="Marker family of the cards.")] = "fido3x3",
) -> DetectResponse:
    """Find and identify the targets in a JPEG or PNG image."""
    data = await read_image_body(request, settings.max_image_bytes)
    # Decoding and detection hold the CPU: off the event loop.
    return await run_in_threadpool(detection.detect, session, detectors, settings, data,
                                   classifier_id=classifier_id, family=family, with_candidates=candidates)
