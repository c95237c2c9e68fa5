"""Marker cards for the API and the command line: layout, PNG, SVG and PDF sheets."""

from __future__ import annotations

from collections.abc import Callable

import cv2

from app.core import markers as core
from app.schemas import MarkerCatalogue, MarkerFamilyOut, MarkerLayoutOut
from app.services import marker_sheets
from app.services.errors import Invalid, NotFound


def catalogue() -> MarkerCatalogue:
    families = [core.get_family(name) for name in core.FAMILIES]
    return MarkerCatalogue(
        default_family=core.DEFAULT_FAMILY,
        families=[
            MarkerFamilyOut(name=f.name, cells=f.cells, min_distance=f.min_distance, count=len(f))
            for f in families
        ],
    )


def layout(family: str, marker_id: int) -> core.MarkerLayout:
    try:
        return core.marker_layout(family, marker_id)
    except KeyError:
        raise NotFound(_unknown(family, marker_id)) from None


def layout_out(family: str, marker_id: int) -> MarkerLayoutOut:
    return MarkerLayoutOut.model_validate(layout(family, marker_id).to_dict())


def png(family: str, marker_id: int, px: int) -> bytes:
    card = core.render_card(layout(family, marker_id), px)
    ok, encoded = cv2.imencode(".png", card)
    assert ok, "PNG encoding of a uint8 image cannot fail"
    return encoded.tobytes()


def svg(family: str, marker_id: int, size_mm: float | None) -> str:
    size = f"{size_mm:g}mm" if size_mm is not None else "100mm"
    return core.card_svg(layout(family, marker_id), size)


def sheet(
    family: str,
    ids_text: str,
    size_mm: float,
    progress: Callable[[int, int], None] | None = None,
) -> bytes:
    try:
        ids = core.parse_id_list(ids_text)
    except ValueError as exc:
        raise Invalid(f"ids: {exc}") from None
    for marker_id in ids:
        layout(family, marker_id)  # 404 for the first id outside the family
    try:
        return marker_sheets.sheet_pdf(family, ids, size_mm, progress)
    except ValueError as exc:
        raise Invalid(f"size_mm: {exc}") from None


def _unknown(family: str, marker_id: int) -> str:
    try:
        count = len(core.get_family(family))
    except KeyError:
        return f"unknown marker family {family!r}; known: {', '.join(core.FAMILIES)}"
    return f"marker {marker_id} is not in family {family} (ids 0..{count - 1})"
