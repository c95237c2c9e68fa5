"""Identification by nine samples: which card is it, and which of its discs is which?

The code is read through the refined homography (the mean of each code cell's samples,
`verification._measure`), normalised by the card's own black (discs) and white levels,
and fitted by every code of the family in all four rotations, each as it reads through
a few amounts of blur (a far card's 2 px cells are never read as clean black and white,
`_blurred_templates`), and a card whose white is clipped also through the clip
(`CODE_SATURATION`); a read whose best fit is poor, or that another code or rotation
fits nearly as well, is refused (`_decode`). The rotation of the best fit gives the
printed order of the discs (0 top-left, 1 top-right, 2 bottom-right, 3 bottom-left, the
card upright as its code defines: `_PRINTED_ORDER`).

This quick read is what the detector checks the whole-card read (`code_reader`) against:
where the two name the same code the card is settled cheaply, and a whole-card read the
nine samples contradict is refused.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from app.core.detection._frame import Pyramid, as_gray
from app.core.detection.verification import _measure, _plan
from app.core.geometry import homographies
from app.core.markers import CODE_ORIGIN, CODE_SIZE, DEFAULT_FAMILY, DISC_CENTRES, DISC_RADIUS, get_family

__all__ = [
    "CLIPPED_WHITE_GREY",
    "CODE_BLUR_CELLS",
    "CODE_FIT_MAX",
    "CODE_GAP_MIN",
    "CODE_SATURATION",
    "CodeMatch",
    "decode_cells",
    "identify",
]

#: Identification by template fit: the cells read (normalised: discs 0, card white 1)
#: are compared with every code of the family in every rotation, each as it would read
#: through an isotropic blur of `CODE_BLUR_CELLS` cell widths (sigma; a far card's 2 px
#: cells, the optics, the pyramid level), white around the code and black discs at the
#: corners. A read is accepted when the best fit's summed squared error is at most
#: `CODE_FIT_MAX` and every other (code, rotation) fits worse by at least `CODE_GAP_MIN`.
#: Set on simulator frames (true geometry, 1400 cards): true fits stay below 0.15 for
#: 99%+ of default/far/dark cards; no wrong id at any gap >= 0.1.
CODE_BLUR_CELLS = (0.0, 0.25, 0.4, 0.55, 0.7)
CODE_FIT_MAX = 0.15
CODE_GAP_MIN = 0.15
#: Clipped white: a brightly lit card's paper saturates the sensor, and the blur's grey
#: between a black cell and white paper saturates with it, so a blurred read is
#: brighter than a linear blur predicts. For a card whose white reads at least
#: `CLIPPED_WHITE_GREY` (of 255), each blurred template is also taken through the clip,
#: ``min(1, s * read)`` for each ``s`` here (1: no clipping): white exposed at s times
#: the sensor's full scale. Other cards are read against the linear templates alone:
#: the clipped ones would make codes alike that a linear read tells apart (bench_detect:
#: a far and two blurred cards lost when every read had them).
CODE_SATURATION = (1.0, 1.5, 2.5)
CLIPPED_WHITE_GREY = 245.0

#: `_PRINTED_ORDER[s][j]`: the quadrilateral vertex (j - s) % 4 that is card disc j.
_PRINTED_ORDER = (np.arange(4)[None, :] - np.arange(4)[:, None]) % 4


@dataclass(frozen=True)
class CodeMatch:
    """A code read and matched (`decode_cells`).

    Parameters
    ----------
    id : int
        The code's id in its family.
    shift : int
        Vertex shift s: vertex m of the quadrilateral read is the card's disc
        (m + s) % 4 in printed order.
    fit : float
        Summed squared error of the best template fit (cells normalised to black 0,
        white 1).
    gap : float
        How much worse the best other (code, rotation) fits.
    """

    id: int
    shift: int
    fit: float
    gap: float


def identify(gray: np.ndarray, discs: np.ndarray, family: str = DEFAULT_FAMILY
             ) -> tuple[int, np.ndarray, CodeMatch] | None:
    """Read and match the code of one card.

    Parameters
    ----------
    gray : ndarray
        The frame: uint8 greyscale (other types and BGR are converted).
    discs : ndarray, shape (4, 2)
        The card's disc centres in full-resolution pixels, in the layout's orientation
        (clockwise on screen), starting at any disc.
    family : str
        The code family to match against.

    Returns
    -------
    tuple of (int, ndarray, CodeMatch) or None
        The id, `discs` reordered to printed order (0 top-left, 1 top-right,
        2 bottom-right, 3 bottom-left) and the match; None when the code is not read
        unambiguously or `discs` is not finite.
    """
    gray = as_gray(gray)
    q = np.asarray(discs, np.float64).reshape(1, 4, 2)
    if not np.isfinite(q).all():
        return None
    hs = homographies(q)
    m = _measure(Pyramid(gray), hs, get_family(family).cells)
    match = decode_cells(m.cells[0], family, float(m.white[0]))
    if match is None:
        return None
    return match.id, _reorder(q[0], match.shift), match


def decode_cells(cells: np.ndarray, family: str = DEFAULT_FAMILY, white: float | None = None) -> CodeMatch | None:
    """Match the code cells read off a card against every code of `family` in every
    rotation, each as it reads through a few amounts of blur (`CODE_BLUR_CELLS`), and
    through the clip too when the card's white is clipped (`CODE_SATURATION`).

    Parameters
    ----------
    cells : ndarray, shape (n, n) or (n*n,)
        Code cell values normalised to black 0 and white 1, read row-major through the
        quadrilateral's homography.
    family : str
        The code family (its codes have n x n cells).
    white : float, optional
        The card's white level in grey levels (`CLIPPED_WHITE_GREY` or more: clipped);
        None: not clipped.

    Returns
    -------
    CodeMatch or None
        The best match; None when the read is ambiguous: the best fit's summed squared
        error above `CODE_FIT_MAX`, or another code (or rotation) within `CODE_GAP_MIN`
        of it.
    """
    ok, ids, shifts, fit, gap = _decode(np.asarray(cells, np.float32).reshape(1, -1), family,
                                        None if white is None else np.array([white]))
    if not ok[0]:
        return None
    return CodeMatch(id=int(ids[0]), shift=int(shifts[0]), fit=float(fit[0]), gap=float(gap[0]))


def _reorder(quad: np.ndarray, shift: int) -> np.ndarray:
    """A quadrilateral's rows (4, ...) in printed order, for vertex shift `shift` (vertex
    m is card disc (m + shift) % 4)."""
    return quad[_PRINTED_ORDER[shift]]


@functools.cache
def _rotation_perms(n: int) -> np.ndarray:
    """perm[s] (4, n*n): the cell read at row-major position p, when the quadrilateral's
    vertex m is the card's disc (m + s) % 4, is printed cell perm[s][p].

    Shifting the vertex order by one is the card turned by 90 degrees about its centre:
    layout point (x, y) -> (1 - y, x) takes disc m to disc m + 1.
    """
    step = CODE_SIZE / n
    rc = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2)
    xy = np.stack([CODE_ORIGIN + (rc[:, 1] + 0.5) * step, CODE_ORIGIN + (rc[:, 0] + 0.5) * step], 1)
    perms = []
    for s in range(4):
        p = xy.copy()
        for _ in range(s):
            p = np.stack([1.0 - p[:, 1], p[:, 0]], 1)
        col = np.rint((p[:, 0] - CODE_ORIGIN) / step - 0.5).astype(int)
        row = np.rint((p[:, 1] - CODE_ORIGIN) / step - 0.5).astype(int)
        perms.append(row * n + col)
    return np.array(perms)


@functools.cache
def _templates(family: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T, n*n) float32 templates (black = 0, white = 1, as the normalised image reads),
    and the id and vertex shift of each: every code in every rotation."""
    fam = get_family(family)
    flat = fam.codes.reshape(len(fam), -1)
    perms = _rotation_perms(fam.cells)
    tmpl = np.concatenate([1.0 - flat[:, perms[s]] for s in range(4)]).astype(np.float32)
    ids = np.tile(np.arange(len(fam)), 4)
    shifts = np.repeat(np.arange(4), len(fam))
    return tmpl, ids, shifts


@functools.cache
def _blurred_templates(family: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The predicted cell reads of every template under every blur of
    `CODE_BLUR_CELLS`: (B * T, n*n) float32 as they are, and (B * C * T, n*n) taken
    through each clip of `CODE_SATURATION` above 1; both in blocks of T templates, whose
    ids and vertex shifts (T,) come last. The read of a cell is
    the mean of its sub-samples (`_plan`), each the blurred card: a 9x9 grid of offsets
    with Gaussian weights, each offset looked up in the card layout."""
    tmpl, ids, shifts = _templates(family)
    n = get_family(family).cells
    plan = _plan(n)
    step = CODE_SIZE / n
    subs = plan.points[plan.cells]  # (n*n, S, 2)
    g = np.linspace(-2.0, 2.0, 9)
    preds = []
    for s in CODE_BLUR_CELLS:
        if s == 0:
            off, w = np.zeros((1, 2)), np.ones(1)
        else:
            x, y = np.meshgrid(g * s * step, g * s * step)
            w = np.exp(-0.5 * (x * x + y * y) / (s * step) ** 2).ravel()
            off, w = np.stack([x.ravel(), y.ravel()], 1), w / w.sum()
        p = subs[:, :, None, :] + off[None, None]  # (n*n, S, K, 2)
        col = np.floor((p[..., 0] - CODE_ORIGIN) / step).astype(int)
        row = np.floor((p[..., 1] - CODE_ORIGIN) / step).astype(int)
        inside = (col >= 0) & (col < n) & (row >= 0) & (row < n)
        cell = np.where(inside, row * n + col, -1)
        disc = np.zeros(cell.shape, bool)
        for c in DISC_CENTRES:
            disc |= ((p - c) ** 2).sum(-1) <= DISC_RADIUS**2
        ww = np.broadcast_to(w, cell.shape) / subs.shape[1]
        a = np.zeros((n * n, n * n))
        for cc in range(n * n):
            a[:, cc] = (ww * ((cell == cc) & ~disc)).sum(axis=(1, 2))
        b = (ww * ((cell < 0) & ~disc)).sum(axis=(1, 2))  # white card around the code
        preds.append(tmpl @ a.T + b)
    linear = np.concatenate(preds).astype(np.float32)
    clipped = np.concatenate([np.minimum(saturation * pred, 1.0) for pred in preds
                              for saturation in CODE_SATURATION if saturation != 1.0]).astype(np.float32)
    return linear, clipped, ids, shifts


def _decode(cells: np.ndarray, family: str, white: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vectorised `decode_cells`: for cells (P, n*n) normalised (black 0, white 1), and
    each card's white level (P,) in grey levels (None: none clipped): (ok (P,), id (P,),
    shift (P,), fit (P,) summed squared error of the best template, gap (P,) how much
    worse the best other (id, rotation) fits)."""
    linear, clipped, ids, shifts = _blurred_templates(family)
    tmpl, _, _ = _templates(family)
    n_t = tmpl.shape[0]
    cells = np.asarray(cells, np.float32).reshape(-1, linear.shape[1])
    p = cells.shape[0]
    if p == 0:
        z = np.zeros(0)
        return z.astype(bool), z.astype(int), z.astype(int), z, z
    # Every read against the linear templates; a card with clipped white against the
    # clipped ones as well (most frames have none: the hot path stays as it was).
    diff = cells[:, None, :] - linear[None]
    sse = np.einsum("ptk,ptk->pt", diff, diff).reshape(p, -1, n_t).min(axis=1)  # best blur per template
    bright = np.zeros(p, bool) if white is None else np.asarray(white) >= CLIPPED_WHITE_GREY
    if bright.any():
        diff = cells[bright][:, None, :] - clipped[None]
        sse_clipped = np.einsum("ptk,ptk->pt", diff, diff).reshape(int(bright.sum()), -1, n_t).min(axis=1)
        sse[bright] = np.minimum(sse[bright], sse_clipped)
    rows = np.arange(p)
    best = np.argmin(sse, axis=1)
    fit = sse[rows, best]
    sse[rows, best] = np.inf
    gap = sse.min(axis=1) - fit
    ok = np.isfinite(fit) & (fit <= CODE_FIT_MAX) & (gap >= CODE_GAP_MIN)
    return ok, ids[best], shifts[best], fit, gap
