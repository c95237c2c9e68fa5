"""The printed sheet, measured on the page as a printer would print it (rasterised with
PDFium): where each cut line runs relative to its card, and that the page says so."""

from __future__ import annotations

import re
from dataclasses import dataclass

import cv2
import numpy as np
import pypdfium2 as pdfium
import pytest

from app.core.markers import DISC_CENTRES, DISC_RADIUS
from app.services.marker_sheets import sheet_pdf

DPI = 400
PX_PER_MM = DPI / 25.4
#: Rasterised grey levels: the discs print black, the cut line grey (0.6), the paper white.
BLACK_BELOW, CUT_GREY = 64, (110, 225)


@dataclass(frozen=True)
class Box:
    x0: float
    y0: float
    x1: float
    y1: float  # pixels, x1 and y1 exclusive


def _render(pdf: bytes, page: int = 0) -> tuple[np.ndarray, str]:
    document = pdfium.PdfDocument(pdf)
    rendered = document[page].render(scale=DPI / 72, grayscale=True).to_numpy()
    text = document[page].get_textpage().get_text_range()
    return (rendered[..., 0] if rendered.ndim == 3 else rendered), text


def _first_card_discs(image: np.ndarray, size_mm: float) -> tuple[Box, Box, Box]:
    """The bounding boxes of discs 0 (top-left), 1 (top-right) and 3 (bottom-left) of the
    page's first card: the black blobs of a disc's size, the top-left one and its neighbours."""
    n, _, stats, _ = cv2.connectedComponentsWithStats((image < BLACK_BELOW).astype(np.uint8))
    diameter = 2 * DISC_RADIUS * size_mm * PX_PER_MM
    discs = [Box(x, y, x + w, y + h) for x, y, w, h, _ in stats[1:n]
             if abs(w - diameter) < 0.05 * diameter + 3 and abs(h - diameter) < 0.05 * diameter + 3]
    first = min(discs, key=lambda b: b.x0 + b.y0)
    spacing = (DISC_CENTRES[1, 0] - DISC_CENTRES[0, 0]) * size_mm * PX_PER_MM

    def near(dx: float, dy: float) -> Box:
        return min(discs, key=lambda b: abs(b.x0 - first.x0 - dx) + abs(b.y0 - first.y0 - dy))

    right, below = near(spacing, 0), near(0, spacing)
    assert abs(right.x0 - first.x0 - spacing) < 2 and abs(below.y0 - first.y0 - spacing) < 2  # printed to scale
    return first, right, below


def _nearest_line(outward: np.ndarray) -> float:
    """The distance (pixels) to the centre of the first dense run in a projection of grey
    pixels that starts at the card's edge and runs outward (a neighbour's line may follow)."""
    dense = outward >= 0.3 * outward.max()
    first = int(np.argmax(dense))
    last = first + int(np.argmin(dense[first:]))  # the run's end (exclusive)
    assert outward.max() > 0 and last - first < 0.5 * PX_PER_MM, "not a thin line"
    run = np.arange(first, last)
    return float(np.average(run, weights=outward[run])) + 0.5  # a pixel's centre


def cut_offsets_mm(image: np.ndarray, size_mm: float) -> dict[str, float]:
    """How far outside the first card's edge its cut line runs, on each side, in mm. The
    card has no printed edge: it lies DISC_CENTRES - DISC_RADIUS outside the discs."""
    d0, d1, d3 = _first_card_discs(image, size_mm)
    margin = (DISC_CENTRES[0, 0] - DISC_RADIUS) * size_mm * PX_PER_MM
    left, top = round(d0.x0 - margin), round(d0.y0 - margin)
    right, bottom = round(d1.x1 + margin), round(d3.y1 + margin)
    # The line's grey, away from anything darker (the edges of the discs and of the label's letters).
    darker = cv2.dilate((image < CUT_GREY[0]).astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    grey = ((image >= CUT_GREY[0]) & (image <= CUT_GREY[1]) & ~darker).astype(np.int64)
    reach = int(12 * PX_PER_MM)  # beyond the widest margin
    rows, cols = slice(top, bottom), slice(left, right)
    found = {
        "left": _nearest_line(grey[rows, left - reach:left].sum(axis=0)[::-1]),
        "right": _nearest_line(grey[rows, right:right + reach].sum(axis=0)),
        "top": _nearest_line(grey[top - reach:top, cols].sum(axis=1)[::-1]),
        "bottom": _nearest_line(grey[bottom:bottom + reach, cols].sum(axis=1)),
    }
    return {side: px / PX_PER_MM for side, px in found.items()}


@pytest.mark.parametrize("size_mm", [15.0, 50.0, 150.0])
def test_the_page_states_how_far_outside_the_card_its_cut_line_runs(size_mm: float) -> None:
    image, text = _render(sheet_pdf("fido3x3", list(range(4)), size_mm))
    measured = cut_offsets_mm(image, size_mm)
    stated = re.search(r"Cut on the dashed lines, ([\d.]+) mm outside each ([\d.]+) mm card \(([\d.]+) mm below",
                       " ".join(text.split()))
    assert stated is not None, text
    side_mm, below_mm = float(stated.group(1)), float(stated.group(3))
    assert float(stated.group(2)) == size_mm
    # What the page says is what it prints, to a tenth of a millimetre (the line is 0.14 mm wide).
    for side in ("left", "top", "right"):
        assert measured[side] == pytest.approx(side_mm, abs=0.1), measured
    assert measured["bottom"] == pytest.approx(below_mm, abs=0.1), measured
    # and a margin a crooked cut cannot eat: the detector reads the card's white up to its edge
    assert side_mm >= 2.0
