"""Marker cards: code families, layout JSON vs rendered PNG, SVG, PDF sheets, id lists."""

from __future__ import annotations

import json
import math
import re
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest

from app.core.markers import (
    CODE_ORIGIN,
    CODE_SIZE,
    DEFAULT_FAMILY,
    DISC_CENTRES,
    DISC_RADIUS,
    FAMILIES,
    card_svg,
    code_outline,
    get_family,
    marker_layout,
    min_rotation_distance,
    parse_id_list,
    render_card,
)
from app.services.marker_sheets import MAX_SIZE_MM, MIN_SIZE_MM, sheet_grid, sheet_pdf

# --------------------------------------------------------------------------------------
# Code families
# --------------------------------------------------------------------------------------


def _all_rotations(codes: np.ndarray) -> np.ndarray:
    """(4, N, n, n): every code in every rotation."""
    return np.stack([np.rot90(codes, k, axes=(1, 2)) for k in range(4)])


def test_family_sizes() -> None:
    assert FAMILIES == ("fido3x3", "fido4x4")
    assert DEFAULT_FAMILY == "fido3x3"
    assert len(get_family("fido3x3")) == 60
    assert len(get_family("fido4x4")) == 282


@pytest.mark.parametrize("name", ["fido3x3", "fido4x4"])
def test_family_distance_property(name: str) -> None:
    fam = get_family(name)
    n = fam.cells
    assert fam.codes.shape == (len(fam), n, n)
    assert fam.codes.dtype == np.uint8
    assert set(np.unique(fam.codes)) <= {0, 1}
    assert min_rotation_distance(fam.codes) >= fam.min_distance


@pytest.mark.parametrize("name", ["fido3x3", "fido4x4"])
def test_no_code_equals_a_rotation(name: str) -> None:
    fam = get_family(name)
    rots = _all_rotations(fam.codes).reshape(4 * len(fam), -1)
    # 4N distinct words: no code equals a rotation of another code or of itself.
    assert len({row.tobytes() for row in rots}) == 4 * len(fam)


def test_min_rotation_distance_detects_bad_sets() -> None:
    sym = np.zeros((1, 3, 3), np.uint8)
    sym[0, 1, 1] = 1  # centre cell only: rotationally symmetric
    assert min_rotation_distance(sym) == 0
    a = np.zeros((3, 3), np.uint8)
    a[0, 0] = 1
    assert min_rotation_distance(np.stack([a, np.rot90(a)])) == 0  # same code, turned
    assert min_rotation_distance(a[None]) == 2  # corner cell vs its own rotations


def test_3x3_single_misread_is_rejected() -> None:
    """Every one-cell flip of every code in every rotation is not a codeword."""
    fam = get_family("fido3x3")
    rots = _all_rotations(fam.codes).reshape(-1, 9)
    words = {row.tobytes() for row in rots}
    for row in rots:
        for cell in range(9):
            flipped = row.copy()
            flipped[cell] ^= 1
            assert flipped.tobytes() not in words


def test_4x4_single_misread_is_corrected() -> None:
    """A one-cell flip has exactly one codeword-rotation at distance 1, the right one."""
    fam = get_family("fido4x4")
    bits = _all_rotations(fam.codes).reshape(-1, 16).astype(np.int64)  # (4N, 16)
    words = bits @ (1 << np.arange(16))  # as 16-bit integers
    popcount = np.array([bin(v).count("1") for v in range(1 << 16)])
    flips = (words[:, None] ^ (1 << np.arange(16))[None, :]).ravel()  # (4N * 16,)
    dist = popcount[flips[:, None] ^ words[None, :]]  # (16*4N, 4N) Hamming distances
    nearest = dist.argmin(axis=1)
    assert (dist.min(axis=1) == 1).all()
    assert np.array_equal(nearest, np.repeat(np.arange(words.size), 16))
    assert (np.sort(dist, axis=1)[:, 1] >= fam.min_distance - 1).all()


def test_3x3_is_the_greedy_lexicode() -> None:
    """Recompute the 3x3 family with a naive loop: same codes, same order."""
    accepted: list[np.ndarray] = []
    for v in range(1 << 9):
        g = np.array([(v >> i) & 1 for i in range(9)], np.uint8).reshape(3, 3)
        rots = [np.rot90(g, k) for k in range(4)]
        if any(int((g != r).sum()) < 2 for r in rots[1:]):
            continue
        if any(int((r != a).sum()) < 2 for a in accepted for r in rots):
            continue
        accepted.append(g)
    assert np.array_equal(np.array(accepted), get_family("fido3x3").codes)


def test_family_lookup_errors_and_immutability() -> None:
    fam = get_family("fido3x3")
    assert get_family("fido3x3") is fam  # cached
    with pytest.raises(KeyError):
        get_family("aruco")
    for bad in (-1, len(fam), True, 1.0):
        with pytest.raises(KeyError):
            fam.code(bad)  # type: ignore[arg-type]
    assert np.array_equal(fam.code(np.int64(3)), fam.codes[3])
    with pytest.raises(ValueError):
        fam.codes[0, 0, 0] = 1
    with pytest.raises(KeyError):
        marker_layout("fido3x3", 60)


# --------------------------------------------------------------------------------------
# Layout and rendering
# --------------------------------------------------------------------------------------


def test_layout_geometry_constants() -> None:
    assert DISC_CENTRES.shape == (4, 2)
    # Order TL, TR, BR, BL in image coordinates (y down).
    assert np.allclose(DISC_CENTRES, [[0.2, 0.2], [0.8, 0.2], [0.8, 0.8], [0.2, 0.8]])
    assert DISC_RADIUS == 0.125 and CODE_ORIGIN == 0.35 and CODE_SIZE == 0.30
    # White margins: disc to card edge and disc to the nearest code corner.
    assert DISC_CENTRES.min() - DISC_RADIUS >= 0.6 * DISC_RADIUS - 1e-12
    corner_gap = math.hypot(CODE_ORIGIN - 0.2, CODE_ORIGIN - 0.2) - DISC_RADIUS
    assert corner_gap >= 0.65 * DISC_RADIUS


def test_layout_json() -> None:
    layout = marker_layout("fido4x4", 17)
    doc = layout.to_dict()
    assert set(doc) == {"id", "family", "discs", "disc_radius", "code"}
    assert json.loads(json.dumps(doc)) == doc  # plain Python types only
    assert doc["id"] == 17 and doc["family"] == "fido4x4"
    assert doc["discs"] == [[0.2, 0.2], [0.8, 0.2], [0.8, 0.8], [0.2, 0.8]]
    assert doc["disc_radius"] == 0.125
    assert doc["code"] == get_family("fido4x4").codes[17].tolist()
    assert all(type(v) is int for row in doc["code"] for v in row)


def _round_components(img: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Centroid and area of the 4 largest round dark blobs (not code cells).

    Round = fills pi/4 of a square bounding box and has circularity 4 pi A / P^2 well
    above a square's (a blob of code cells can be larger than a disc, and 7 of 9 cells
    fill ~pi/4 of their box too, so area or fill alone do not tell them apart).
    """
    binary = (img < 128).astype(np.uint8)
    n, labels, stats, cents = cv2.connectedComponentsWithStats(binary, connectivity=8)
    blobs = []
    for i in range(1, n):
        x, y, w, h, area = stats[i]
        mask = (labels[y:y + h, x:x + w] == i).astype(np.uint8)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        perimeter = sum(cv2.arcLength(c, True) for c in contours)
        circularity = 4 * math.pi * area / perimeter**2  # pixel contour: disc ~0.9, square ~0.8
        fill = area / float(w * h)
        if abs(w - h) <= 2 and abs(fill - math.pi / 4) < 0.03 and circularity > 0.86:
            blobs.append((cents[i], float(area)))
    blobs.sort(key=lambda b: -b[1])
    return blobs[:4]


@pytest.mark.parametrize(("family", "marker_id"), [("fido3x3", 0), ("fido3x3", 41),
                                                   ("fido4x4", 7), ("fido4x4", 281)])
def test_png_matches_layout_json(family: str, marker_id: int) -> None:
    px = 800
    layout = marker_layout(family, marker_id)
    doc = layout.to_dict()
    img = render_card(layout, px)
    assert img.shape == (px, px) and img.dtype == np.uint8
    assert img[0, 0] == 255 and img[-1, -1] == 255  # card edges are white

    expected = np.array(doc["discs"]) * px - 0.5
    r_px = doc["disc_radius"] * px
    blobs = _round_components(img)
    assert len(blobs) == 4
    for centre, area in blobs:
        err = np.linalg.norm(expected - centre, axis=1)
        assert err.min() < 0.5
        assert abs(math.sqrt(area / math.pi) / r_px - 1.0) < 0.01

    # Intensity-weighted centroid (sub-pixel, anti-aliasing included) in a window
    # around each disc, and the disc area from the summed darkness.
    half = int(math.ceil(r_px + 6))
    for ex, ey in expected:
        x0, y0 = int(round(ex)) - half, int(round(ey)) - half
        win = 255.0 - img[y0:y0 + 2 * half + 1, x0:x0 + 2 * half + 1].astype(np.float64)
        ys, xs = np.mgrid[y0:y0 + win.shape[0], x0:x0 + win.shape[1]]
        cx, cy = (win * xs).sum() / win.sum(), (win * ys).sum() / win.sum()
        assert math.hypot(cx - ex, cy - ey) < 0.05
        assert abs(win.sum() / 255.0 / (math.pi * r_px**2) - 1.0) < 0.01


@pytest.mark.parametrize("px", [97, 333, 1001])
def test_weighted_centroid_at_odd_sizes(px: int) -> None:
    """Disc centres land on x * px - 0.5 even when that is not on a pixel corner."""
    layout = marker_layout("fido3x3", 5)
    img = render_card(layout, px)
    r_px = DISC_RADIUS * px
    half = int(math.ceil(r_px + 1))  # stays clear of the code area's corner
    for ex, ey in DISC_CENTRES * px - 0.5:
        x0, y0 = int(round(ex)) - half, int(round(ey)) - half
        win = 255.0 - img[y0:y0 + 2 * half + 1, x0:x0 + 2 * half + 1].astype(np.float64)
        ys, xs = np.mgrid[y0:y0 + win.shape[0], x0:x0 + win.shape[1]]
        cx, cy = (win * xs).sum() / win.sum(), (win * ys).sum() / win.sum()
        assert math.hypot(cx - ex, cy - ey) < 0.05


def _read_code(img: np.ndarray, n: int) -> np.ndarray:
    px = img.shape[0]
    step = CODE_SIZE / n
    centres = (CODE_ORIGIN + (np.arange(n) + 0.5) * step) * px - 0.5
    idx = np.rint(centres).astype(int)
    return (img[np.ix_(idx, idx)] < 128).astype(np.uint8)


@pytest.mark.parametrize(("family", "marker_id", "px"), [
    ("fido3x3", 0, 800), ("fido3x3", 13, 517), ("fido3x3", 59, 200),
    ("fido4x4", 0, 800), ("fido4x4", 140, 517), ("fido4x4", 281, 240),
])
def test_png_code_reads_back(family: str, marker_id: int, px: int) -> None:
    layout = marker_layout(family, marker_id)
    img = render_card(layout, px)
    assert np.array_equal(_read_code(img, layout.code.shape[0]), layout.code)


@pytest.mark.parametrize("px", [7, 8193, 100.0, True, "800"])
def test_render_rejects_bad_px(px: object) -> None:
    with pytest.raises(ValueError):
        render_card(marker_layout("fido3x3", 0), px)  # type: ignore[arg-type]


def test_render_extremes_are_quick_enough() -> None:
    assert render_card(marker_layout("fido3x3", 0), 8).shape == (8, 8)
    img = render_card(marker_layout("fido4x4", 3), 4096)
    assert img.shape == (4096, 4096)


# --------------------------------------------------------------------------------------
# SVG
# --------------------------------------------------------------------------------------

_SVG = "{http://www.w3.org/2000/svg}"


def _fill_outline(loops: list[list[tuple[float, float]]], px: int) -> np.ndarray:
    """Rasterise outline loops (card units), black on white like render_card."""
    img = np.full((px, px), 255, np.uint8)
    polys = [np.rint(np.array(loop) * px).astype(np.int32) for loop in loops]
    if polys:
        cv2.fillPoly(img, polys, 0)
    return img


def test_svg_document() -> None:
    layout = marker_layout("fido3x3", 7)
    text = card_svg(layout, "150mm")
    root = ET.fromstring(text.encode())
    assert root.tag == f"{_SVG}svg"
    assert root.get("width") == "150mm" and root.get("height") == "150mm"
    vb = [float(v) for v in root.get("viewBox", "").split()]
    assert vb[:2] == [0, 0] and vb[2] == vb[3]
    circles = root.findall(f"{_SVG}circle")
    assert len(circles) == 4
    scale = vb[2]
    got = np.array([[float(c.get("cx")), float(c.get("cy"))] for c in circles]) / scale
    assert np.allclose(got, DISC_CENTRES)
    assert all(float(c.get("r")) / scale == pytest.approx(DISC_RADIUS) for c in circles)

    # The code path, filled, shows exactly the code's black cells.
    paths = root.findall(f"{_SVG}path")
    assert len(paths) == 1
    loops = [
        [(float(x) / scale, float(y) / scale)
         for x, y in re.findall(r"([-\d.]+)[ ,]([-\d.]+)", sub)]
        for sub in paths[0].get("d", "").split("Z") if sub.strip()
    ]
    assert np.array_equal(_read_code(_fill_outline(loops, 600), 3), layout.code)

    with pytest.raises(ValueError):
        card_svg(layout, '100mm" onload="x')


@pytest.mark.parametrize("pattern", [
    [[1, 1, 1], [1, 0, 1], [1, 1, 1]],  # ring: a hole
    [[1, 0, 1], [0, 1, 0], [1, 0, 1]],  # cells touching only at corners
    [[0, 0, 0], [0, 0, 0], [0, 0, 0]],
])
def test_code_outline_patterns(pattern: list[list[int]]) -> None:
    code = np.array(pattern, np.uint8)
    loops = code_outline(code)
    assert np.array_equal(_read_code(_fill_outline(loops, 600), 3), code)


def test_code_outline_every_family_code() -> None:
    for name in FAMILIES:
        fam = get_family(name)
        for code in fam.codes[:: max(1, len(fam) // 40)]:
            img = _fill_outline(code_outline(code), 400)
            assert np.array_equal(_read_code(img, fam.cells), code)


# --------------------------------------------------------------------------------------
# PDF sheets
# --------------------------------------------------------------------------------------


def _page_count(pdf: bytes) -> int:
    return len(re.findall(rb"/Type\s*/Page\b(?!s)", pdf))


def test_sheet_pdf_pages_and_progress() -> None:
    calls: list[tuple[int, int]] = []
    pdf = sheet_pdf("fido3x3", list(range(12)), 150.0, progress=lambda d, t: calls.append((d, t)))
    assert pdf.startswith(b"%PDF")
    assert _page_count(pdf) == 12  # one 150 mm card per A4 page
    assert calls == [(k, 12) for k in range(1, 13)]
    assert b"/Subtype /Image" not in pdf  # vector, not a raster

    assert sheet_grid(60.0).per_page == 6
    assert _page_count(sheet_pdf("fido3x3", list(range(12)), 60.0)) == 2
    assert _page_count(sheet_pdf("fido4x4", list(range(282)), MIN_SIZE_MM)) >= 1
    assert sheet_grid(MAX_SIZE_MM).per_page == 1
    # Reproducible bytes (no timestamps), so responses can be cached.
    assert sheet_pdf("fido3x3", [1, 2], 80) == sheet_pdf("fido3x3", [1, 2], 80)


@pytest.mark.parametrize("size", [MIN_SIZE_MM - 1, MAX_SIZE_MM + 1, 0, -50, 1000,
                                  float("nan"), float("inf"), "big"])
def test_sheet_pdf_rejects_bad_size(size: object) -> None:
    with pytest.raises(ValueError, match="size_mm"):
        sheet_pdf("fido3x3", [0], size)  # type: ignore[arg-type]


def test_sheet_pdf_rejects_bad_ids() -> None:
    with pytest.raises(KeyError):
        sheet_pdf("fido3x3", [0, 60], 100)
    with pytest.raises(KeyError):
        sheet_pdf("fido3x3", [-1], 100)
    with pytest.raises(KeyError):
        sheet_pdf("nope", [0], 100)
    with pytest.raises(ValueError):
        sheet_pdf("fido3x3", [], 100)


# --------------------------------------------------------------------------------------
# ID lists
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(("text", "ids"), [
    ("0-11", list(range(12))),
    ("0,3,5-7", [0, 3, 5, 6, 7]),
    (" 4 , 2 ", [4, 2]),
    ("7", [7]),
    ("9-9", [9]),
    ("10 - 12", [10, 11, 12]),
    ("0-999", list(range(1000))),
])
def test_parse_id_list(text: str, ids: list[int]) -> None:
    assert parse_id_list(text) == ids


@pytest.mark.parametrize(("text", "message"), [
    ("", "empty"),
    ("   ", "empty"),
    ("a", "bad id"),
    ("1,,2", "bad id"),
    ("-3", "bad id"),
    ("1.5", "bad id"),
    ("1-2-3", "bad id"),
    ("7-5", "reversed"),
    ("0-1000", "too many"),
    ("0-99999999999", "too many"),
    ("0-5,3", "more than once"),
])
def test_parse_id_list_errors(text: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_id_list(text)
