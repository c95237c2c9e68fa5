"""Printable marker cards: catalogue, layout JSON, PNG, SVG and A4 PDF sheets."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Query, Response

from app.routers.json_bodies import JsonBodyRoute
from app.routers.responses import invalid, not_found
from app.schemas import MarkerCatalogue, MarkerLayoutOut
from app.services import markers
from app.services.marker_sheets import MAX_SIZE_MM, MIN_SIZE_MM

router = APIRouter(prefix="/markers", tags=["markers"], route_class=JsonBodyRoute)

Family = Annotated[str, Query(description="Code family, e.g. fido3x3 (default) or fido4x4.")]
MarkerId = Annotated[int, Path(description="Marker id within the family (404 outside it).")]
_404 = not_found("marker id or family")
_422 = invalid()


@router.get("", response_model=MarkerCatalogue, summary="List the marker families")
def list_families() -> MarkerCatalogue:
    """Marker families and how many ids each holds."""
    return markers.catalogue()


# Declared before "/{marker_id}" so that "sheet.pdf", "3.png" and "3.svg" reach them.
@router.get(
    "/sheet.pdf",
    response_class=Response,
    summary="Print a sheet of cards",
    responses={200: {"content": {"application/pdf": {}}, "description": "A4 pages of cards"}, **_404, **_422},
)
def sheet_pdf(
    ids: Annotated[str, Query(max_length=2000, description='The card ids, e.g. "0-11" or "0,3,5-7".')],
    size_mm: Annotated[float, Query(ge=MIN_SIZE_MM, le=MAX_SIZE_MM, description="Card side in millimetres.")],
    family: Family = "fido3x3",
) -> Response:
    """A4 pages of cards with cut lines, ids and a scale bar to check the print size
    (print at 100 %)."""
    pdf = markers.sheet(family, ids, size_mm)
    return Response(
        pdf,
        media_type="application/pdf",
        headers={"Content-Disposition": f'inline; filename="fidotrack-{family}.pdf"'},
    )


@router.get(
    "/{marker_id}.png",
    response_class=Response,
    summary="Get a card as PNG",
    responses={200: {"content": {"image/png": {}}, "description": "The card, square"}, **_404, **_422},
)
def marker_png(
    marker_id: MarkerId,
    px: Annotated[int, Query(ge=16, le=4096, description="Side of the image in pixels.")] = 800,
    family: Family = "fido3x3",
) -> Response:
    """The card alone, its edges at the image edges."""
    return Response(markers.png(family, marker_id, px), media_type="image/png")


@router.get(
    "/{marker_id}.svg",
    response_class=Response,
    summary="Get a card as SVG",
    responses={200: {"content": {"image/svg+xml": {}}, "description": "The card, square"}, **_404, **_422},
)
def marker_svg(
    marker_id: MarkerId,
    size_mm: Annotated[float | None, Query(ge=MIN_SIZE_MM, le=2000, description=(
        "Side of the card in millimetres, as the SVG declares it for printing (default 100)."))] = None,
    family: Family = "fido3x3",
) -> Response:
    """The card as vector graphics, its edges at the image edges."""
    return Response(markers.svg(family, marker_id, size_mm), media_type="image/svg+xml")


@router.get("/{marker_id}", response_model=MarkerLayoutOut, summary="Get a card's layout",
            responses={**_404, **_422})
def marker_layout(marker_id: MarkerId, family: Family = "fido3x3") -> MarkerLayoutOut:
    """Disc centres, disc radius and code of a card, in card units (0..1, y down)."""
    return markers.layout_out(family, marker_id)
