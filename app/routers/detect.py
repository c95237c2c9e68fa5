"""POST /detect: targets (and optionally every candidate disc) in one image."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request

from app.deps import ImageWorkersDep, SettingsDep
from app.routers.json_bodies import JsonBodyRoute
from app.routers.uploads import IMAGE_BODY_DOC, read_image_body
from app.schemas import DetectResponse, Problem

router = APIRouter(tags=["detection"], route_class=JsonBodyRoute)


@router.post(
    "/detect",
    response_model=DetectResponse,
    openapi_extra=IMAGE_BODY_DOC,
    responses={413: {"model": Problem}, 415: {"model": Problem}, 422: {"model": Problem}, 503: {"model": Problem}},
)
async def detect(
    request: Request,
    settings: SettingsDep,
    workers: ImageWorkersDep,
    candidates: Annotated[bool, Query(description="Also return every disc that passed the classifier.")] = False,
    classifier_id: Annotated[int | None, Query(description="Classifier to use; default if omitted.")] = None,
    family: Annotated[str, Query(description="Marker family of the cards.")] = "fido3x3",
) -> DetectResponse:
    """Find and identify the targets in a JPEG or PNG image."""
    with workers.admitted():
        data = await read_image_body(request, settings.max_image_bytes)
        return await workers.detect(data, classifier_id=classifier_id, family=family, with_candidates=candidates)
