"""Printable A4 sheets of targets (GET /markers/sheet.pdf), drawn as vectors with reportlab.

Each card is drawn at exactly the requested side, with a dashed cut line around it and
its family and ID printed below the card, inside the cut line (so the label stays with
the card and marks its bottom edge). The card itself has no printed edge: it is the
white square the discs sit in, and the cut line runs a few millimetres outside it so
that a crooked cut cannot eat the white margin the detector reads around the discs;
each page says so (`cut_note`). Every page carries a footer with the card side and a
100 mm scale bar, because a printer that "fits to page" silently changes the scale of
the whole survey.
"""

from __future__ import annotations

import io
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from reportlab.lib.pagesizes import A4
from reportlab.lib.units import mm
from reportlab.pdfbase.pdfmetrics import stringWidth
from reportlab.pdfgen.canvas import FILL_NON_ZERO, Canvas

from app.core.markers import DISC_CENTRES, MarkerLayout, code_outline, get_family, marker_layout

PAGE_W_MM: float = A4[0] / mm  # 210
PAGE_H_MM: float = A4[1] / mm  # 297
PAGE_MARGIN_MM: float = 10.0
CUT_OFFSET_MM: float = 3.0  # cut line distance from the card edge (left, top, right)
LABEL_BAND_MM: float = 8.0  # cut line distance below the card: room for the label
GAP_MM: float = 4.0  # between neighbouring cut lines, so each card is cut on its own
FOOTER_MM: float = 16.0  # footer text and scale bar at the bottom of each page

#: Smallest card side: below this the 4x4 code cells get close to a millimetre.
MIN_SIZE_MM: float = 15.0
#: Largest card side that fits on A4 portrait with margins and the cut line.
MAX_SIZE_MM: float = 180.0
MAX_CARDS: int = 1000

_LABEL_FONT = ("Helvetica", 7.0)
_FOOTER_FONT = ("Helvetica", 7.5)
_GREY_CUT = 0.6
_GREY_TEXT = 0.3


@dataclass(frozen=True)
class SheetGrid:
    """How cards of one size tile an A4 page."""

    cols: int
    rows: int

    @property
    def per_page(self) -> int:
        return self.cols * self.rows


def _cell_mm(size_mm: float) -> tuple[float, float]:
    """Width and height taken by one card with its cut line (without the gap)."""
    return size_mm + 2 * CUT_OFFSET_MM, size_mm + CUT_OFFSET_MM + LABEL_BAND_MM


def sheet_grid(size_mm: float) -> SheetGrid:
    """Columns and rows of cards of side `size_mm` on one A4 portrait page."""
    cell_w, cell_h = _cell_mm(size_mm)
    avail_w = PAGE_W_MM - 2 * PAGE_MARGIN_MM
    avail_h = PAGE_H_MM - 2 * PAGE_MARGIN_MM - FOOTER_MM
    cols = int((avail_w + GAP_MM) // (cell_w + GAP_MM))
    rows = int((avail_h + GAP_MM) // (cell_h + GAP_MM))
    return SheetGrid(cols=max(cols, 0), rows=max(rows, 0))


def _check_size(size_mm: float) -> float:
    if isinstance(size_mm, bool):
        raise ValueError("size_mm must be a number of millimetres")
    try:
        size = float(size_mm)
    except (TypeError, ValueError):
        raise ValueError(f"size_mm must be a number of millimetres, got {size_mm!r}") from None
    if not math.isfinite(size) or not MIN_SIZE_MM <= size <= MAX_SIZE_MM:
        raise ValueError(
            f"size_mm must be between {MIN_SIZE_MM:g} and {MAX_SIZE_MM:g} mm for A4 pages "
            f"(got {size_mm!r}): larger cards do not fit on the page with a cut line, "
            "smaller ones print code cells too small to read"
        )
    return size


def sheet_pdf(
    family: str,
    ids: Sequence[int],
    size_mm: float,
    progress: Callable[[int, int], None] | None = None,
) -> bytes:
    """A PDF of A4 portrait pages holding the cards `ids` of `family`, side `size_mm`.

    Raises KeyError for an unknown family or an id outside it, ValueError for a size
    that does not fit (see MIN_SIZE_MM, MAX_SIZE_MM) or an empty/oversized id list.
    `progress(done, total)` is called after each card.
    """
    fam = get_family(family)  # KeyError for unknown families
    size = _check_size(size_mm)
    ids = list(ids)
    if not ids:
        raise ValueError("no marker ids given")
    if len(ids) > MAX_CARDS:
        raise ValueError(f"too many cards: at most {MAX_CARDS} per sheet")
    layouts = [marker_layout(fam.name, i) for i in ids]  # KeyError before any drawing

    grid = sheet_grid(size)
    per_page = grid.per_page
    n_pages = -(-len(layouts) // per_page)
    cell_w, cell_h = _cell_mm(size)
    # Centre the grid horizontally; fill from the top margin down.
    grid_w = grid.cols * cell_w + (grid.cols - 1) * GAP_MM
    left = (PAGE_W_MM - grid_w) / 2
    top = PAGE_H_MM - PAGE_MARGIN_MM

    buf = io.BytesIO()
    # invariant: no timestamp or random document id, so equal requests give equal bytes
    canvas = Canvas(buf, pagesize=A4, invariant=1)
    canvas.setTitle(f"fidotrack {fam.name} targets, card side {size:.1f} mm")
    canvas.setAuthor("fidotrack")
    canvas.setCreator("fidotrack")
    total = len(layouts)
    for page in range(n_pages):
        chunk = layouts[page * per_page:(page + 1) * per_page]
        for k, layout in enumerate(chunk):
            row, col = divmod(k, grid.cols)
            # Card top-left corner in mm, page coordinates y up.
            x0 = left + CUT_OFFSET_MM + col * (cell_w + GAP_MM)
            y_top = top - CUT_OFFSET_MM - row * (cell_h + GAP_MM)
            _draw_card(canvas, layout, x0, y_top, size)
            if progress is not None:
                progress(page * per_page + k + 1, total)
        _draw_footer(canvas, fam.name, size, page + 1, n_pages)
        canvas.showPage()
    canvas.save()
    return buf.getvalue()


def _draw_card(canvas: Canvas, layout: MarkerLayout, x0_mm: float, y_top_mm: float,
               size_mm: float) -> None:
    """One card, its cut line and its label; card top-left at (x0_mm, y_top_mm)."""
    s = size_mm * mm
    x0 = x0_mm * mm
    y_top = y_top_mm * mm

    def page_xy(u: float, v: float) -> tuple[float, float]:
        # card units (y down) -> PDF points (y up)
        return x0 + u * s, y_top - v * s

    canvas.saveState()
    # The paper is the white of the card; only black is printed.
    canvas.setFillGray(0.0)
    for u, v in layout.discs:
        cx, cy = page_xy(float(u), float(v))
        canvas.circle(cx, cy, float(layout.disc_radius) * s, stroke=0, fill=1)
    loops = code_outline(layout.code)
    if loops:
        path = canvas.beginPath()
        for loop in loops:
            path.moveTo(*page_xy(*loop[0]))
            for u, v in loop[1:]:
                path.lineTo(*page_xy(u, v))
            path.close()
        # One non-zero-filled path: touching cells merge without seams.
        canvas.drawPath(path, stroke=0, fill=1, fillMode=FILL_NON_ZERO)

    # Dashed grey cut line, a few mm outside the card so a wobbly cut does not eat it.
    canvas.setStrokeGray(_GREY_CUT)
    canvas.setLineWidth(0.4)
    canvas.setDash(2 * mm, 1.5 * mm)
    canvas.rect(
        x0 - CUT_OFFSET_MM * mm,
        y_top - s - LABEL_BAND_MM * mm,
        s + 2 * CUT_OFFSET_MM * mm,
        s + (CUT_OFFSET_MM + LABEL_BAND_MM) * mm,
        stroke=1,
        fill=0,
    )
    canvas.setDash()

    # Label below the card (also marks which edge is the bottom).
    font, font_size = _LABEL_FONT
    canvas.setFillGray(_GREY_TEXT)
    label = f"{layout.family}  id {int(layout.id)}"
    font_size = min(font_size, _fit_font(label, font, s))
    canvas.setFont(font, font_size)
    canvas.drawCentredString(x0 + s / 2, y_top - s - (LABEL_BAND_MM - 2.5) * mm, label)
    canvas.restoreState()


def _fit_font(text: str, font: str, width_pt: float) -> float:
    """Largest font size (pt) at which `text` fits in `width_pt`."""
    w1 = stringWidth(text, font, 1.0)
    return width_pt / w1 if w1 > 0 else 12.0


def cut_note(size_mm: float) -> str:
    """The page's line on where to cut, and why not on the card's edge."""
    return (
        f"Cut on the dashed lines, {CUT_OFFSET_MM:g} mm outside each {size_mm:.1f} mm card ({LABEL_BAND_MM:g} mm "
        "below: its label), so that a crooked cut keeps the white the detector needs around the discs."
    )


def _draw_footer(canvas: Canvas, family: str, size_mm: float, page: int, pages: int) -> None:
    """Footer: scale reminder text and a 100 mm ruler with ticks every 10 mm."""
    canvas.saveState()
    font, font_size = _FOOTER_FONT
    x = PAGE_MARGIN_MM * mm
    avail = (PAGE_W_MM - 2 * PAGE_MARGIN_MM) * mm
    text = (
        f"fidotrack {family} \u2014 card side {size_mm:.1f} mm (disc centres "
        f"{size_mm * float(DISC_CENTRES[1, 0] - DISC_CENTRES[0, 0]):.1f} mm apart): check with "
        "the ruler below that your printer did not scale (print at 100% / actual size)"
    )
    canvas.setFillGray(0.0)
    canvas.setFont(font, min(font_size, _fit_font(text, font, avail)))
    canvas.drawString(x, (PAGE_MARGIN_MM + 10) * mm, text)
    note = cut_note(size_mm)
    canvas.setFont(font, min(font_size, _fit_font(note, font, avail)))
    canvas.drawString(x, (PAGE_MARGIN_MM + 13.5) * mm, note)

    # Scale bar: 0..100 mm, major ticks every 10 mm, minor every 5 mm.
    y = (PAGE_MARGIN_MM + 4) * mm
    canvas.setStrokeGray(0.0)
    canvas.setLineWidth(0.5)
    canvas.line(x, y, x + 100 * mm, y)
    for t in range(0, 101, 5):
        h = 3.0 if t % 50 == 0 else 2.0 if t % 10 == 0 else 1.2
        canvas.line(x + t * mm, y, x + t * mm, y + h * mm)
    canvas.setFont(font, 6.5)
    for t in (0, 50, 100):
        canvas.drawCentredString(x + t * mm, y - 3 * mm, f"{t}")
    canvas.drawString(x + 103 * mm, y - 0.8 * mm, "100 mm")
    canvas.drawRightString(x + avail, y - 0.8 * mm, f"page {page} / {pages}")
    canvas.restoreState()
