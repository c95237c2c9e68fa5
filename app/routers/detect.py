"""POST /detect: targets (and optionally every candidate disc) in one image, as JSON or
drawn over the image."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request, Response

from app.deps import ImageWorkersDep, SettingsDep
from app.routers.json_bodies import JsonBodyRoute
from app.routers.responses import IMAGE_REFUSED, invalid, not_found
from app.routers.uploads import IMAGE_BODY_DOC, read_image_body
from app.schemas import DetectResponse

router = APIRouter(tags=["detection"], route_class=JsonBodyRoute)


@router.post(
    "/detect",
    response_model=DetectResponse,
    summary="Detect the targets in an image",
    openapi_extra=IMAGE_BODY_DOC,
    responses={
        200: {"description": "The targets as JSON; with ?draw=true the image as a PNG with the detections drawn.",
              "content": {"image/png": {"schema": {"type": "string", "format": "binary"}}}},
        **not_found("classifier"),
        **IMAGE_REFUSED,
        **invalid("The request does not validate, or the image cannot be used (corrupt, too small) or the family "
                  "is unknown"),
    },
)
async def detect(
    request: Request,
    settings: SettingsDep,
    workers: ImageWorkersDep,
    candidates: Annotated[bool, Query(description="Also return every disc that passed the classifier.")] = False,
    classifier_id: Annotated[int | None, Query(description="Classifier to use; default if omitted.")] = None,
    family: Annotated[str, Query(description="Marker family of the cards.")] = "fido3x3",
    draw: Annotated[bool, Query(description=(
        "Reply with the image instead (image/png, its size): each target's disc quadrilateral in green, its discs "
        "in red (disc 0 with a dot) and its id, and every candidate disc in amber."))] = False,
) -> DetectResponse | Response:
    """Find and identify the targets in a JPEG or PNG image: their ids, disc centres
    and confidence, or (``draw``) the image with them drawn, to check by eye what the
    detector sees."""
    with workers.admitted():
        data = await read_image_body(request, settings.max_image_bytes)
        if draw:
            png = await workers.detect_drawn(data, classifier_id=classifier_id, family=family)
            return Response(png, media_type="image/png")
        return await workers.detect(data, classifier_id=classifier_id, family=family, with_candidates=candidates)
