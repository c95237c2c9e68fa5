"""POST /detect: targets (and optionally every candidate disc) in one image."""

from __future__ import annotations

from functools import partial
from typing import Annotated

import anyio
from fastapi import APIRouter, Query, Request

from app.deps import DetectorsDep, ImageMemoryDep, ImageThreadsDep, SessionDep, SettingsDep
from app.routers.json_bodies import JsonBodyRoute
from app.routers.uploads import IMAGE_BODY_DOC, read_image_body
from app.schemas import DetectResponse, Problem
from app.services import detection

router = APIRouter(tags=["detection"], route_class=JsonBodyRoute)


@router.post(
    "/detect",
    response_model=DetectResponse,
    openapi_extra=IMAGE_BODY_DOC,
    responses={413: {"model": Problem}, 415: {"model": Problem}, 422: {"model": Problem}, 503: {"model": Problem}},
)
async def detect(
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    detectors: DetectorsDep,
    memory: ImageMemoryDep,
    threads: ImageThreadsDep,
    candidates: Annotated[bool, Query(description="Also return every disc that passed the classifier.")] = False,
    classifier_id: Annotated[int | None, Query(description="Classifier to use; default if omitted.")] = None,
    family: Annotated[str, Query(description="Marker family of the cards.")] = "fido3x3",
) -> DetectResponse:
    """Find and identify the targets in a JPEG or PNG image."""
    data = await read_image_body(request, settings.max_image_bytes)
    # Decoding and detection hold the CPU: off the event loop, on the images' own threads.
    return await anyio.to_thread.run_sync(
        partial(detection.detect, session, detectors, settings, memory, data, classifier_id=classifier_id,
                family=family, with_candidates=candidates), limiter=threads)
