"""Marker ("target") cards: layout, identification code families, raster and SVG output.

A target is a square white card with four black discs at the corners of a smaller
square and an n x n binary identification code in the middle (Claus & Fitzgibbon,
WACV 2005, section 3). Everything here is in card units: the card spans 0..1, origin
at its top-left corner, x to the right, y down (docs/map-format.md). Discs are numbered
0 top-left, 1 top-right, 2 bottom-right, 3 bottom-left as printed.

Pure numpy/OpenCV; no I/O.
"""

from __future__ import annotations

import functools
import operator
import re
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "CODE_ORIGIN",
    "CODE_SIZE",
    "DEFAULT_FAMILY",
    "DISC_CENTRES",
    "DISC_RADIUS",
    "FAMILIES",
    "MarkerFamily",
    "MarkerLayout",
    "card_svg",
    "code_outline",
    "get_family",
    "marker_layout",
    "min_rotation_distance",
    "parse_id_list",
    "render_card",
]

# --------------------------------------------------------------------------------------
# Card layout (card units).
#
# Why these numbers:
# * The discs are as large as the card allows. The detector classifies 12x12 pixel
#   windows, so the farthest distance at which a target is still found is set by the
#   disc's size in pixels; every bit of disc radius buys range.
# * Each disc keeps a white margin so that it is seen as a dark blob on white: 0.075
#   (= 0.6 r) to the card edge and ~0.087 (= 0.7 r) to the nearest corner of the code
#   area. Less margin and the disc merges with the background or the code at range.
# * The code is a centred 0.30 square. For 3x3 a cell is 0.10 = 0.4 of a disc diameter,
#   so the code stays readable about as far away as the discs are still detectable
#   (the 4x4 family trades some of that reading range for more IDs).
# --------------------------------------------------------------------------------------

#: Disc centres, index order 0 top-left, 1 top-right, 2 bottom-right, 3 bottom-left.
DISC_CENTRES: np.ndarray = np.array(
    [[0.2, 0.2], [0.8, 0.2], [0.8, 0.8], [0.2, 0.8]], dtype=np.float64
)
DISC_CENTRES.setflags(write=False)
#: Disc radius, card units.
DISC_RADIUS: float = 0.125
#: Top-left corner (x and y) of the code area, and its side.
CODE_ORIGIN: float = 0.35
CODE_SIZE: float = 0.30

#: The code families, by name.
FAMILIES: tuple[str, ...] = ("fido3x3", "fido4x4")
DEFAULT_FAMILY: str = "fido3x3"

# name -> (cells per side, minimum Hamming distance over all rotations)
_FAMILY_PARAMS: dict[str, tuple[int, int]] = {
    "fido3x3": (3, 2),  # a single misread cell always gives a non-codeword: rejected
    "fido4x4": (4, 4),  # corrects one misread cell, detects up to three
}

_MAX_RENDER_PX = 8192
_MIN_RENDER_PX = 8
_MAX_ID_LIST = 1000


# --------------------------------------------------------------------------------------
# Code families
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)  # eq=False: ndarray fields make generated __eq__ useless
class MarkerFamily:
    """A set of n x n binary codes, unambiguous under the four card rotations.

    Attributes
    ----------
    name : str
        One of `FAMILIES`.
    cells : int
        Cells per side of the code, n.
    min_distance : int
        Least Hamming distance between any two codes in any rotation, and between a
        code and its own rotations.
    codes : (N, n, n) ndarray of uint8
        The codes, read-only; a black cell is 1; code i belongs to target id i.
    """

    name: str
    cells: int
    min_distance: int
    codes: np.ndarray  # (N, n, n) uint8, read-only; black cell = 1

    def __len__(self) -> int:
        return int(self.codes.shape[0])

    def code(self, marker_id: int) -> np.ndarray:
        """The code of one target.

        Parameters
        ----------
        marker_id : int
            Target id, 0..N-1.

        Returns
        -------
        (n, n) ndarray of uint8
            Read-only; rows top to bottom as printed upright, black = 1.

        Raises
        ------
        KeyError
            If `marker_id` is not an integer in 0..N-1.
        """
        i = _as_id(marker_id)
        if i is None or not 0 <= i < len(self):
            raise KeyError(f"marker id {marker_id!r} not in family {self.name} (0..{len(self) - 1})")
        return self.codes[i]


def _as_id(value: Any) -> int | None:
    """An integer id, or None for bools and non-integers (they are never valid ids)."""
    if isinstance(value, bool):
        return None
    try:
        return operator.index(value)
    except TypeError:
        return None


def _rotation_permutation(n: int) -> np.ndarray:
    """perm such that bits of the code rotated by 90 degrees = bits[perm] (row-major)."""
    return np.rot90(np.arange(n * n).reshape(n, n)).ravel()


@functools.cache
def _lexicode(n: int, d: int) -> np.ndarray:
    """Greedy lexicode under rotation: (N, n, n) uint8.

    Candidates v = 0 .. 2^(n*n)-1 in order, cell (r, c) = bit (r*n + c) of v. Accept v
    if it is at distance >= d from its own three non-trivial rotations and from every
    rotation of every accepted code. Vectorised: keep an "allowed" mask over all
    candidates and, on accepting a code, knock out everything within distance < d of
    any of its rotations. Same result as the naive loop, but 4x4 takes milliseconds.
    """
    nbits = n * n
    values = np.arange(1 << nbits, dtype=np.int64)
    shifts = np.arange(nbits, dtype=np.int64)
    bits = ((values[:, None] >> shifts) & 1).astype(np.uint8)  # (2^nbits, nbits)
    popcount = bits.sum(axis=1, dtype=np.int64)
    weights = np.int64(1) << shifts
    rot1 = bits[:, _rotation_permutation(n)] @ weights  # every code rotated by 90 deg
    rotations = [values, rot1]
    for _ in range(2):
        rotations.append(rot1[rotations[-1]])  # compose lookups: k+1 quarter turns
    rot = np.stack(rotations)  # rot[k, v] = v rotated by k * 90 degrees

    allowed = np.ones(values.shape, dtype=bool)
    for k in (1, 2, 3):
        allowed &= popcount[values ^ rot[k]] >= d  # no (near) rotational symmetry
    accepted: list[int] = []
    start = 0
    while True:
        nz = np.flatnonzero(allowed[start:])
        if nz.size == 0:
            break
        v = start + int(nz[0])
        accepted.append(v)
        for k in range(4):
            allowed &= popcount[values ^ rot[k, v]] >= d
        start = v + 1
    codes = bits[np.array(accepted, dtype=np.int64)].reshape(-1, n, n).copy()
    codes.setflags(write=False)
    return codes


@functools.cache
def get_family(name: str) -> MarkerFamily:
    """The code family called `name` (built once, then cached).

    Parameters
    ----------
    name : str
        One of `FAMILIES`.

    Returns
    -------
    MarkerFamily

    Raises
    ------
    KeyError
        If the family is unknown.
    """
    if name not in _FAMILY_PARAMS:
        raise KeyError(f"unknown marker family {name!r}; known: {', '.join(FAMILIES)}")
    n, d = _FAMILY_PARAMS[name]
    return MarkerFamily(name=name, cells=n, min_distance=d, codes=_lexicode(n, d))


def min_rotation_distance(codes: np.ndarray) -> int:
    """Minimum Hamming distance over all pairs of distinct codes in all 4 rotations, and
    over each code against its own three non-trivial rotations.

    Independent of the search in `_lexicode` (plain np.rot90 and pairwise comparison),
    so tests can check the property rather than trust the construction.

    Parameters
    ----------
    codes : (N, n, n) array_like
        Binary codes.

    Returns
    -------
    int
        The least distance, in cells (n * n + 1 when there is nothing to compare).

    Raises
    ------
    ValueError
        If `codes` is not (N, n, n).
    """
    codes = np.asarray(codes, dtype=np.uint8)
    if codes.ndim != 3 or codes.shape[1] != codes.shape[2]:
        raise ValueError("codes must have shape (N, n, n)")
    m = codes.shape[0]
    flat = [np.rot90(codes, k, axes=(1, 2)).reshape(m, -1).astype(np.int16) for k in range(4)]
    best = codes.shape[1] ** 2 + 1
    base = flat[0]
    for k in range(4):
        # dist[i, j] = Hamming(code i, code j rotated by k)
        dist = (base[:, None, :] != flat[k][None, :, :]).sum(axis=2)
        if k == 0:
            np.fill_diagonal(dist, best)  # a code vs itself unrotated is not a pair
        if dist.size:
            best = min(best, int(dist.min()))
    return int(best)


# --------------------------------------------------------------------------------------
# Layout
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class MarkerLayout:
    """Geometry of one card in card units (0..1, origin top-left, x right, y down).

    Attributes
    ----------
    id : int
        Target id.
    family : str
        Code family name.
    discs : (4, 2) ndarray
        Disc centres in disc order: 0 top-left, 1 top-right, 2 bottom-right,
        3 bottom-left as printed.
    disc_radius : float
        Disc radius, card units.
    code : (n, n) ndarray of uint8
        The identification code, rows top to bottom as printed upright; black = 1.
    """

    id: int
    family: str
    discs: np.ndarray  # (4, 2) disc centres, order TL, TR, BR, BL
    disc_radius: float
    code: np.ndarray  # (n, n) uint8, rows top to bottom as printed upright; black = 1

    def to_dict(self) -> dict[str, Any]:
        """The JSON document of GET /markers/{id}.

        Returns
        -------
        dict
            ``id``, ``family``, ``discs``, ``disc_radius`` and ``code``, as plain
            Python types.
        """
        return {
            "id": int(self.id),
            "family": str(self.family),
            "discs": [[float(x), float(y)] for x, y in self.discs],
            "disc_radius": float(self.disc_radius),
            "code": [[int(v) for v in row] for row in self.code],
        }

    @property
    def cells(self) -> int:
        """Cells per side of the code."""
        return int(self.code.shape[0])


def marker_layout(family: str, marker_id: int) -> MarkerLayout:
    """The layout of one target's card.

    Parameters
    ----------
    family : str
        One of `FAMILIES`.
    marker_id : int
        Target id within the family.

    Returns
    -------
    MarkerLayout

    Raises
    ------
    KeyError
        If the family or the id is unknown.
    """
    fam = get_family(family)
    code = fam.code(marker_id)
    return MarkerLayout(
        id=int(operator.index(marker_id)),
        family=fam.name,
        discs=DISC_CENTRES,
        disc_radius=DISC_RADIUS,
        code=code,
    )


def code_outline(code: np.ndarray) -> list[list[tuple[float, float]]]:
    """Closed loops (card units) outlining the union of the black code cells.

    Each cell contributes its four edges clockwise (in y-down coordinates); edges shared
    by two black cells cancel. What remains is the boundary of the union: outer loops
    clockwise, holes counter-clockwise, so a single path filled with the non-zero rule
    draws the code with no seams between touching cells (SVG, PDF).

    Parameters
    ----------
    code : (n, n) array_like
        A code, black = 1.

    Returns
    -------
    list of list of (float, float)
        The loops' corners in card units; the first point is not repeated at the end.
    """
    code = np.asarray(code)
    n = code.shape[0]
    edges: dict[tuple[int, int], list[tuple[int, int]]] = {}
    edge_set: set[tuple[tuple[int, int], tuple[int, int]]] = set()
    for r in range(n):
        for c in range(n):
            if not code[r, c]:
                continue
            # grid vertices as (x, y) integer pairs, clockwise with y down
            quad = [(c, r), (c + 1, r), (c + 1, r + 1), (c, r + 1)]
            for a, b in zip(quad, quad[1:] + quad[:1]):
                if (b, a) in edge_set:
                    edge_set.remove((b, a))
                else:
                    edge_set.add((a, b))
    for a, b in edge_set:
        edges.setdefault(a, []).append(b)
    for outs in edges.values():
        outs.sort()  # deterministic output where two loops touch at a corner
    loops: list[list[tuple[float, float]]] = []
    step = CODE_SIZE / n
    while edges:
        start = min(edges)
        loop = [start]
        cur = start
        while True:
            outs = edges[cur]
            nxt = outs.pop(0)
            if not outs:
                del edges[cur]
            if nxt == start:
                break
            loop.append(nxt)
            cur = nxt
        loop = _drop_collinear(loop)
        loops.append([(CODE_ORIGIN + x * step, CODE_ORIGIN + y * step) for x, y in loop])
    return loops


def _drop_collinear(loop: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """Remove vertices in the middle of a straight run (edges are axis-aligned)."""
    m = len(loop)
    keep = []
    for i, (x, y) in enumerate(loop):
        (px_, py_), (nx, ny) = loop[i - 1], loop[(i + 1) % m]
        if not ((px_ == x == nx) or (py_ == y == ny)):
            keep.append((x, y))
    return keep


# --------------------------------------------------------------------------------------
# Raster
# --------------------------------------------------------------------------------------

_SUPERSAMPLE = 16  # sub-samples per axis on disc boundary pixels: 256 coverage levels


def render_card(layout: MarkerLayout, px: int) -> np.ndarray:
    """The card as a greyscale image (white 255, black 0).

    The card edges are the image edges; the centre of the top-left pixel is at (0, 0),
    so card unit x is at pixel x * px - 0.5. Grey levels are the area coverage of each
    pixel: exact for the code cells (axis-aligned rectangles), 16x16 supersampled on the
    boundary pixels of the discs. That keeps each disc's intensity-weighted centroid on
    its layout centre to ~1e-3 px (~1e-2 px when the disc is only a few pixels across)
    and its summed darkness within 0.1% of pi r^2.

    Parameters
    ----------
    layout : MarkerLayout
    px : int
        Side of the image in pixels, 8..8192.

    Returns
    -------
    (px, px) ndarray of uint8

    Raises
    ------
    ValueError
        If `px` is not an integer in 8..8192.
    """
    if isinstance(px, bool) or not isinstance(px, (int, np.integer)):
        raise ValueError(f"px must be an integer, got {px!r}")
    px = int(px)
    if not _MIN_RENDER_PX <= px <= _MAX_RENDER_PX:
        raise ValueError(f"px must be in {_MIN_RENDER_PX}..{_MAX_RENDER_PX}, got {px}")

    coverage = np.zeros((px, px), dtype=np.float32)  # fraction of each pixel that is black
    _add_code_coverage(coverage, np.asarray(layout.code), px)
    for cx, cy in np.asarray(layout.discs, dtype=np.float64):
        _add_disc_coverage(coverage, cx * px, cy * px, float(layout.disc_radius) * px)
    np.clip(coverage, 0.0, 1.0, out=coverage)
    return np.rint(255.0 * (1.0 - coverage)).astype(np.uint8)


def _interval_overlap(lo: float, hi: float, px: int) -> np.ndarray:
    """Length of [lo, hi] (in pixel-edge units, pixel i spans [i, i+1]) inside each pixel."""
    edges = np.arange(px, dtype=np.float64)
    return np.clip(np.minimum(edges + 1.0, hi) - np.maximum(edges, lo), 0.0, 1.0)


def _add_code_coverage(coverage: np.ndarray, code: np.ndarray, px: int) -> None:
    """Exact area coverage of the code cells: coverage = Y^T @ code @ X (separable)."""
    n = code.shape[0]
    step = CODE_SIZE / n
    # Pixel-edge coordinates (card unit u -> u * px) of each cell's extent.
    ext = [((CODE_ORIGIN + i * step) * px, (CODE_ORIGIN + (i + 1) * step) * px) for i in range(n)]
    lo = max(int(np.floor(ext[0][0])), 0)
    hi = min(int(np.ceil(ext[-1][1])), px)
    over = np.stack([_interval_overlap(a, b, px)[lo:hi] for a, b in ext])  # (n, hi-lo)
    coverage[lo:hi, lo:hi] += (over.T @ code.astype(np.float64) @ over).astype(np.float32)


def _add_disc_coverage(coverage: np.ndarray, cx: float, cy: float, r: float) -> None:
    """Add a disc given in pixel-edge coordinates, only within its bounding box.

    Pixels whose square lies wholly inside or outside the circle get 1 or 0 from their
    centre distance; only the thin ring of boundary pixels is supersampled, which keeps
    time and memory proportional to the perimeter for large px.
    """
    h, w = coverage.shape
    x0 = max(int(np.floor(cx - r)) - 1, 0)
    x1 = min(int(np.ceil(cx + r)) + 1, w)
    y0 = max(int(np.floor(cy - r)) - 1, 0)
    y1 = min(int(np.ceil(cy + r)) + 1, h)
    if x0 >= x1 or y0 >= y1:
        return
    # Pixel centres in pixel-edge coordinates are at i + 0.5.
    xs = np.arange(x0, x1, dtype=np.float64) + 0.5 - cx
    ys = np.arange(y0, y1, dtype=np.float64) + 0.5 - cy
    dist = np.hypot(xs[None, :], ys[:, None])
    half_diag = np.sqrt(0.5)
    block = (dist + half_diag <= r).astype(np.float32)
    rows, cols = np.nonzero(np.abs(dist - r) < half_diag)
    if rows.size:
        s = _SUPERSAMPLE
        offs = (np.arange(s, dtype=np.float64) + 0.5) / s - 0.5  # symmetric in the pixel
        sx = xs[cols][:, None, None] + offs[None, None, :]
        sy = ys[rows][:, None, None] + offs[None, :, None]
        inside = (sx * sx + sy * sy) <= r * r
        block[rows, cols] = inside.reshape(rows.size, -1).mean(axis=1)
    coverage[y0:y1, x0:x1] += block


# --------------------------------------------------------------------------------------
# SVG
# --------------------------------------------------------------------------------------

_SVG_SIZE_RE = re.compile(r"^\d{1,5}(\.\d{1,4})?(mm|cm|in|pt|pc|px)?$")
_SVG_UNITS = 1000.0  # viewBox side: card unit 1 = 1000, so 3x3 cells are exact integers


def _fmt(v: float) -> str:
    return f"{v:.4f}".rstrip("0").rstrip(".")


def card_svg(layout: MarkerLayout, size: str = "100mm") -> str:
    """A standalone SVG document of the card.

    The code is one path outlining the union of its black cells (see `code_outline`),
    so touching cells show no hairline seams in any renderer.

    Parameters
    ----------
    layout : MarkerLayout
    size : str, optional
        Width and height of the document, a length such as "100mm" or "4in".

    Returns
    -------
    str
        The SVG document.

    Raises
    ------
    ValueError
        If `size` is not such a length.
    """
    if not isinstance(size, str) or not _SVG_SIZE_RE.match(size):
        raise ValueError(f"size must be a length like '100mm' or '4in', got {size!r}")
    u = _SVG_UNITS
    circles = "\n".join(
        f'  <circle cx="{_fmt(x * u)}" cy="{_fmt(y * u)}" r="{_fmt(layout.disc_radius * u)}" '
        f'fill="#000"/>'
        for x, y in np.asarray(layout.discs, dtype=np.float64)
    )
    d = " ".join(
        "M" + " L".join(f"{_fmt(x * u)} {_fmt(y * u)}" for x, y in loop) + " Z"
        for loop in code_outline(layout.code)
    )
    code_path = f'  <path d="{d}" fill="#000" fill-rule="nonzero"/>\n' if d else ""
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        f'<svg xmlns="http://www.w3.org/2000/svg" version="1.1" width="{size}" height="{size}" '
        f'viewBox="0 0 {_fmt(u)} {_fmt(u)}">\n'
        f"  <title>fidotrack {layout.family} target {int(layout.id)}</title>\n"
        f'  <rect x="0" y="0" width="{_fmt(u)}" height="{_fmt(u)}" fill="#fff"/>\n'
        f"{circles}\n"
        f"{code_path}"
        "</svg>\n"
    )


# --------------------------------------------------------------------------------------
# ID lists
# --------------------------------------------------------------------------------------

_ID_ITEM_RE = re.compile(r"^(\d+)(?:\s*-\s*(\d+))?$")


def parse_id_list(text: str) -> list[int]:
    """Parse an id list such as "0-11" or "0,3,5-7".

    Range sizes are checked before expanding, so "0-999999999" fails fast instead of
    allocating.

    Parameters
    ----------
    text : str
        Comma-separated non-negative integers and inclusive ranges.

    Returns
    -------
    list of int
        The ids, in the order given.

    Raises
    ------
    ValueError
        With the offending part named, for empty input, garbage, reversed ranges,
        duplicates, or more than 1000 ids.
    """
    if not isinstance(text, str) or not text.strip():
        raise ValueError("id list is empty; expected e.g. '0-11' or '0,3,5-7'")
    ids: list[int] = []
    seen: set[int] = set()
    for part in text.split(","):
        item = part.strip()
        m = _ID_ITEM_RE.match(item)
        if m is None:
            raise ValueError(
                f"bad id list item {item!r}: expected a non-negative integer or a range "
                "like '5-7'"
            )
        lo = int(m.group(1))
        hi = int(m.group(2)) if m.group(2) is not None else lo
        if hi < lo:
            raise ValueError(f"reversed range {item!r}: write it as '{hi}-{lo}'")
        if len(ids) + (hi - lo + 1) > _MAX_ID_LIST:
            raise ValueError(f"too many ids: at most {_MAX_ID_LIST} per request")
        for i in range(lo, hi + 1):
            if i in seen:
                raise ValueError(f"id {i} is listed more than once")
            seen.add(i)
            ids.append(i)
    return ids
