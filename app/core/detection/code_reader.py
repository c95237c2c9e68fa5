"""Whole-card code reading: the card's image compared with the rendered image of every code.

The nine-sample reader (`identification`) reads the mean of a few samples in each code
cell. On a small card (discs of 3-5 px, code cells of 1.2-2 px) those samples straddle
the cells' edges and carry little signal. Here every pixel of the card takes part:

    I(p) = a + b * u_c(p) + g * beyond(p)

where u_c is the card printed with pattern c (white 1, ink 0) integrated over pixel p's
footprint and blurred by a point-spread function k, `beyond` the part of p's footprint
off the card (the unknown background, blurred the same way), and a, b, g are fitted by
least squares. The patterns are every code in every rotation and every pattern one cell
from a code (`_patterns`: no card carries those, so a card that fits one best is not
read). Because the model is linear in a, b, g, the fit of every pattern comes from one
small Gram matrix of the rendered channels (one per code cell, the white card, the
background and a constant) per blur, so all 496 patterns of `fido3x3` cost about what one does.

The blur is not known in advance. It is chosen from a set of point-spread functions
(`PSF_SIGMAS_PX` isotropic, `MOTION_LENGTHS_PX` x `MOTION_ANGLES` smears) by the same fit:
the four discs and the white around them, which every pattern shares, pin it down. A
caller that knows the blur (a bench with the simulator's truth) passes it instead.

A read is judged by its margin, how much worse the best other pattern fits than the best,
and its misfit, how much worse the best fits than a free card whose cells may take any
grey level; both in units of the free card's residual variance (the margin is then twice
the log-likelihood ratio under Gaussian noise of that variance). See `MIN_MARGIN` and
`MAX_FIT_PER_MARGIN`.

Pure numpy/OpenCV and compiled kernels (`_code_reader_kernels`); no I/O.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.special import ndtr

from app.core.detection import _code_reader_kernels as compiled
from app.core.detection._frame import Pyramid
from app.core.detection.identification import _templates
from app.core.markers import CODE_ORIGIN, CODE_SIZE, DISC_CENTRES, DISC_RADIUS, get_family

__all__ = [
    "MAX_FIT_PER_MARGIN",
    "MAX_SIDE_PX",
    "MIN_MARGIN",
    "MOTION_ANGLES",
    "MOTION_LENGTHS_PX",
    "MOTION_SIGMA_PX",
    "PSF_SIGMAS_PX",
    "QUICK_SIDE_PX",
    "QUICK_SIGMAS_PX",
    "SMEARED_MAX_READS",
    "CardReads",
    "gaussian_psf",
    "isotropic_psfs",
    "psf_set",
    "read_cards",
    "smear_psf",
]

#: Isotropic point-spread functions tried (Gaussian sigma, pixels of the level read; the
#: pixel's own footprint comes on top): optics, defocus, the pyramid's smoothing.
PSF_SIGMAS_PX = (0.0, 0.35, 0.55, 0.75, 1.0, 1.3, 1.7)
#: Straight smears tried (length in pixels, each at `MOTION_ANGLES` directions over a
#: half turn), each with a little isotropic blur (`MOTION_SIGMA_PX`).
MOTION_LENGTHS_PX = (3.0, 5.5, 9.0)
MOTION_ANGLES = 6
MOTION_SIGMA_PX = 0.35
#: At most this many cards of a frame get the full fit with the smears (about 3-4 ms each).
SMEARED_MAX_READS = 3
#: A card larger than this (side, pixels) is read on the pyramid level that brings it
#: below: its cells are big enough there, and the fit stays small.
MAX_SIDE_PX = 32.0
#: Pixels are read whose centres lie this far inside the card's edge (card units): the
#: background beyond the edge is modelled only as one level.
REGION_MARGIN = 0.06
#: A pixel of a clipped card at this grey level or above is saturated.
SATURATED_GREY = 254.0
#: The quick check of a card whose code the nine samples name: two isotropic blurs, the
#: card read on the pyramid level that keeps it under `QUICK_SIDE_PX`. A clear read of the
#: same code settles the card at a fraction of the full fit's cost (about 0.2 ms against 3-4).
QUICK_SIGMAS_PX = (0.45, 0.95)
QUICK_SIDE_PX = 20.0
QUICK_SUPERSAMPLE = 3
#: Sub-samples per pixel side for the pixel's footprint.
SUPERSAMPLE = 3
#: Acceptance: the margin (see the module's docstring) at least `MIN_MARGIN`, and the best
#: code's misfit (`CardReads.fit`) at most `MAX_FIT_PER_MARGIN` times the margin: the card
#: as read must lie nearer its code than the code lies to the next pattern. A printed card
#: keeps the ratio under 1.7 (bench_code_read, unclipped cards through their true discs);
#: dice, text and checkerboards in the code area go far above it. For a family whose
#: codes are d > 2 cells apart (`fido4x4`, which corrects a misread cell) the ratio allowed
#: is d - 1 times this.
MIN_MARGIN = 12.0
MAX_FIT_PER_MARGIN = 2.0


@dataclass(frozen=True)
class CardReads:
    """Whole-card reads of P cards (`read_cards`).

    Parameters
    ----------
    ok : ndarray of bool, shape (P,)
        Read and accepted.
    ids : ndarray of int, shape (P,)
        The best code's id (meaningful where `ok`).
    shifts : ndarray of int, shape (P,)
        Its vertex shift: vertex m of the quadrilateral read is the card's disc
        (m + shift) % 4 in printed order.
    margin : ndarray, shape (P,)
        How much worse the best other pattern (another code, this code turned, or a
        pattern one cell from a code) fits than the best, in units of the free card's
        residual variance; 0 where the card could not be read.
    fit : ndarray, shape (P,)
        How much worse the best code fits than a card whose cells may take any grey
        level, in the same units: small for a printed code, large for a pattern that is
        no code; inf where not read.
    psf : ndarray of int, shape (P,)
        Index of the best fit's point-spread function in the set used; -1 where not read.
    smeared : ndarray of bool, shape (P,)
        Tried against the smears (`psf_set`) as well.
    """

    ok: np.ndarray
    ids: np.ndarray
    shifts: np.ndarray
    margin: np.ndarray
    fit: np.ndarray
    psf: np.ndarray
    smeared: np.ndarray


def read_cards(pyr: Pyramid, hs: np.ndarray, family: str, psfs: Sequence[np.ndarray] | None = None,
               clipped: np.ndarray | None = None, known: np.ndarray | None = None,
               smeared: int | None = None) -> CardReads:
    """Read the codes of cards by fitting every code's rendered image to every pixel.

    A read is accepted on its margin and misfit (`MIN_MARGIN`, `MAX_FIT_PER_MARGIN`), and
    never when `known` names another code. By default a card whose code `known` names
    gets a quick check first (`QUICK_SIGMAS_PX`, the card at most `QUICK_SIDE_PX` wide),
    which settles it when the whole card names the same code clearly; any other card is
    fitted with every isotropic blur and the smears (`psf_set`, the card at most
    `MAX_SIDE_PX` wide): an isotropic fit of a smeared small card can name a wrong code
    clearly.

    Parameters
    ----------
    pyr : Pyramid
        The frame's pyramid.
    hs : ndarray, shape (P, 3, 3)
        Each card's homography, card units to full-resolution pixels, with vertex 0 at
        card disc 0 (the quadrilateral's order, as `identification` reads it).
    family : str
        The code family.
    psfs : sequence of ndarray, optional
        The point-spread functions to fit with instead (odd-sized, summing to 1, in
        pixels of the level each card is read on; a bench that knows the blur): one
        stage, accepted on margin and misfit.
    clipped : ndarray of bool, shape (P,), optional
        Cards whose white may clip at the sensor's full scale: a saturated pixel only
        says the card is at least that bright there.
    known : ndarray of int, shape (P, 2), optional
        Each card's (id, vertex shift) from another read (the nine samples,
        `identification`), or -1 where none.
    smeared : int, optional
        At most this many cards are fitted with the smears (None: every one that needs
        it); the others stay unread.

    Returns
    -------
    CardReads
    """
    hs = np.ascontiguousarray(hs, np.float64).reshape(-1, 3, 3)
    p = hs.shape[0]
    out = CardReads(ok=np.zeros(p, bool), ids=np.zeros(p, np.intp), shifts=np.zeros(p, np.intp),
                    margin=np.zeros(p), fit=np.full(p, np.inf), psf=np.full(p, -1, np.intp),
                    smeared=np.zeros(p, bool))
    if p == 0:
        return out
    tmpl, ids, shifts = _patterns(family)
    n2 = get_family(family).cells ** 2
    clipped = np.zeros(p, bool) if clipped is None else np.asarray(clipped, bool)
    known = np.full((p, 2), -1, np.intp) if known is None else np.asarray(known, np.intp).reshape(p, 2)
    # a family whose codes are d cells apart corrects a misread cell: its card may sit a cell
    # from its code, so its misfit may be that much larger against the margin
    fit_per_margin = MAX_FIT_PER_MARGIN * (get_family(family).min_distance - 1)
    full = (list(psfs) if psfs is not None else list(psf_set()), MAX_SIDE_PX, SUPERSAMPLE)
    quick = (list(isotropic_psfs(QUICK_SIGMAS_PX)), QUICK_SIDE_PX, QUICK_SUPERSAMPLE)
    left = p if smeared is None else smeared
    for q in range(p):
        named = known[q, 0] >= 0
        # the quick check can only settle a card whose code another read names
        stages = [quick, full] if named and psfs is None else [full]
        for stage, (kernels, max_side, sub) in enumerate(stages):
            last = stage == len(stages) - 1
            if last and psfs is None:
                if left <= 0:
                    break
                left -= 1
                out.smeared[q] = True
            patch = _card_patch(pyr, hs[q], n2, max(k.shape[0] for k in kernels) // 2, bool(clipped[q]), max_side,
                                sub)
            if patch is None:
                break
            fitted = _fit_codes(patch, kernels, tmpl)
            if fitted is None:
                break
            best, margin, fit, psf = fitted
            out.ids[q], out.shifts[q] = ids[best], shifts[best]
            out.margin[q], out.fit[q], out.psf[q] = margin, fit, psf
            same = named and ids[best] == known[q, 0] and shifts[best] == known[q, 1]
            clear = ids[best] >= 0 and margin >= MIN_MARGIN and fit <= fit_per_margin * margin
            if not last:
                if same and clear:
                    out.ok[q] = True
                    break
                continue
            out.ok[q] = clear and (same or not named)
    return out


# --------------------------------------------------------------------------------------
# Point-spread functions
# --------------------------------------------------------------------------------------


@functools.cache
def isotropic_psfs(sigmas: tuple[float, ...] = PSF_SIGMAS_PX) -> tuple[np.ndarray, ...]:
    """Isotropic point-spread functions.

    Parameters
    ----------
    sigmas : tuple of float
        Their Gaussian standard deviations, pixels (`PSF_SIGMAS_PX` by default).

    Returns
    -------
    tuple of ndarray
        Odd-sized float32 kernels summing to 1, in pixels.
    """
    return tuple(gaussian_psf(s) for s in sigmas)


@functools.cache
def psf_set() -> tuple[np.ndarray, ...]:
    """The point-spread functions `read_cards` tries by default: `PSF_SIGMAS_PX`, then
    `MOTION_LENGTHS_PX` x `MOTION_ANGLES` smears.

    Returns
    -------
    tuple of ndarray
        Odd-sized float32 kernels summing to 1, in pixels.
    """
    kernels = list(isotropic_psfs())
    for length in MOTION_LENGTHS_PX:
        for a in range(MOTION_ANGLES):
            kernels.append(smear_psf(length, math.pi * a / MOTION_ANGLES, MOTION_SIGMA_PX))
    return tuple(kernels)


def gaussian_psf(sigma: float) -> np.ndarray:
    """A Gaussian point-spread function integrated over each kernel pixel.

    Parameters
    ----------
    sigma : float
        Its standard deviation, pixels; 0 or less: the identity.

    Returns
    -------
    ndarray
        An odd-sized float32 kernel summing to 1.
    """
    if sigma <= 0:
        return np.ones((1, 1), np.float32)
    half = math.ceil(3 * sigma + 0.5)
    edges = np.arange(-half, half + 2) - 0.5
    one = np.diff(ndtr(edges / sigma))
    k = np.outer(one, one)
    return (k / k.sum()).astype(np.float32)


def smear_psf(length: float, angle: float, sigma: float) -> np.ndarray:
    """A straight smear blurred by a Gaussian, sampled on a 4x finer grid and summed into
    pixels.

    Parameters
    ----------
    length : float
        The smear's length, pixels.
    angle : float
        Its direction, radians from +x toward +y.
    sigma : float
        The Gaussian's standard deviation, pixels.

    Returns
    -------
    ndarray
        An odd-sized float32 kernel summing to 1, point-symmetric.
    """
    half = math.ceil(0.5 * length + 3 * sigma + 0.5)
    s = 4
    g = (np.arange((2 * half + 1) * s) + 0.5) / s - (half + 0.5)  # fine sample centres, pixels
    x, y = np.meshgrid(g, g)
    t = np.linspace(-0.5 * length, 0.5 * length, max(int(length * 4), 2))
    c, si = math.cos(angle), math.sin(angle)
    k = np.zeros_like(x)
    sig2 = max(sigma, 0.25 / s) ** 2
    for ti in t:
        k += np.exp(-0.5 * ((x - ti * c) ** 2 + (y - ti * si) ** 2) / sig2)
    k = k.reshape(2 * half + 1, s, 2 * half + 1, s).sum(axis=(1, 3))
    return (k / k.sum()).astype(np.float32)


# --------------------------------------------------------------------------------------
# The card's pixels and their channels
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Patch:
    """One card's pixels read: their values (P,), and the card rendered per channel at
    pixel resolution over the padded patch (H, W, n2 + 2): each code cell's area, the white
    card's, the background's; `rows`, `cols` the read pixels' places in it; `saturated`
    the places of the pixels at the sensor's full scale (a card whose white clips)."""

    y: np.ndarray
    channels: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    saturated: tuple[np.ndarray, np.ndarray] | None  # rows and columns of saturated pixels left out of `y`


def _card_patch(pyr: Pyramid, h: np.ndarray, n2: int, pad: int, clipped: bool, max_side: float,
                sub: int = 3) -> _Patch | None:
    """The pixels of one card and its channels, on the pyramid level that keeps the card's
    side at most `max_side` pixels, each pixel's footprint sub-sampled `sub` x `sub` times;
    None when the card is degenerate or its code is not wholly in the image (the pixels of
    the card outside the image are left out)."""
    side = compiled.card_side(h)
    if not math.isfinite(side) or side <= 0:
        return None
    level = max(0, math.floor(math.log2(side / max_side)) + 1) if side > max_side else 0
    level = min(level, pyr.max_level)
    hl = h.copy()
    hl[:2] *= 0.5**level
    ok, hinv, x0, y0, width, height, rows, cols, values, sat_rows, sat_cols = compiled.card_pixels(
        pyr.get(level), hl, REGION_MARGIN, CODE_ORIGIN, CODE_SIZE, clipped, SATURATED_GREY)
    if not ok or rows.size < 12:
        return None
    # the channels over the patch padded by the kernel's reach, from sub^2 sub-samples of
    # every pixel's footprint
    channels = compiled.card_channels(hinv, x0 - pad, y0 - pad, width + 2 * pad, height + 2 * pad, sub,
                                      round(math.sqrt(n2)), CODE_ORIGIN, CODE_SIZE, DISC_CENTRES, DISC_RADIUS)
    return _Patch(y=values, channels=channels, rows=rows + pad, cols=cols + pad,
                  saturated=(sat_rows + pad, sat_cols + pad) if clipped else None)


# --------------------------------------------------------------------------------------
# The fit of every code
# --------------------------------------------------------------------------------------


@functools.cache
def _patterns(family: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The patterns a card is fitted with: every code of `family` in every rotation, then,
    for a family whose codes are two cells apart (a misread cell is refused, not
    corrected), every pattern one cell from one of them (no code: a card that fits one of
    these best is no printed card, or too unclear to tell; 256 for `fido3x3`, 496 in all).
    (T, n2 + 1) weights on the channels (code cells, then the white card) that make the
    printed card: 1 for a white cell and the card; the id (-1: no code) and vertex shift
    of each."""
    tmpl, ids, shifts = _templates(family)  # (T0, n2) white = 1 as read through the quadrilateral
    n2 = tmpl.shape[1]
    corrects = get_family(family).min_distance > 2  # a pattern one cell from a code reads as that code
    flips = np.zeros((0, n2), tmpl.dtype) if corrects else \
        np.abs(tmpl[:, None, :] - np.eye(n2, dtype=tmpl.dtype)[None]).reshape(-1, n2)
    every = np.concatenate([tmpl, flips]).astype(np.int64)
    keys = every @ (np.int64(1) << np.arange(n2, dtype=np.int64))
    _, first = np.unique(keys, return_index=True)
    first = np.sort(first)  # the codes (first in `every`) keep their places
    weights = np.concatenate([every[first], np.ones((first.size, 1), np.int64)], axis=1).astype(np.float64)
    pid = np.where(first < tmpl.shape[0], ids[np.minimum(first, tmpl.shape[0] - 1)], -1)
    pshift = np.where(first < tmpl.shape[0], shifts[np.minimum(first, tmpl.shape[0] - 1)], 0)
    return weights, pid, pshift


def _blur(channels: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """`channels` (H, W, C) float32 blurred by `kernel`: by its two factors where it is
    separable (a Gaussian; about 2.5 times faster), else whole."""
    if kernel.size == 1:
        return channels
    factors = _factors(kernel.shape, kernel.tobytes())
    if factors is not None:
        return cv2.sepFilter2D(channels, -1, factors[1], factors[0], borderType=cv2.BORDER_REPLICATE)
    return cv2.filter2D(channels, -1, kernel, borderType=cv2.BORDER_REPLICATE)


@functools.lru_cache(maxsize=256)
def _factors(shape: tuple[int, ...], data: bytes) -> tuple[np.ndarray, np.ndarray] | None:
    """The column and row factors of a rank-one kernel (its bytes, for the cache), or None."""
    kernel = np.frombuffer(data, np.float32).reshape(shape).astype(np.float64)
    u, sv, vt = np.linalg.svd(kernel)
    if sv.size > 1 and sv[1] > 1e-6 * sv[0]:
        return None
    col, row = u[:, 0] * math.sqrt(sv[0]), vt[0] * math.sqrt(sv[0])
    if col.sum() < 0:
        col, row = -col, -row
    return col.astype(np.float32), row.astype(np.float32)


def _fit_codes(patch: _Patch, kernels: list[np.ndarray], tmpl: np.ndarray
               ) -> tuple[int, float, float, int] | None:
    """The best pattern, its margin and misfit (`CardReads`) and its point-spread
    function, or None when no pattern fits with the paper brighter than the ink.

    The constant and the background's level are the same columns for every pattern, so
    they are projected out once per point-spread function (a Schur complement of the
    channels' Gram matrix); what is left of each pattern's fit is a one-column
    regression, ``sse = |y|^2 - (v.g)^2 / v.G.v`` over the projected Gram matrix G of
    the card's channels and their products g with the read. The free card (every cell
    any grey level) is the same regression over all channels at once."""
    n_card = tmpl.shape[1]  # code cells and the white card
    stack = np.stack([_blur(patch.channels, k) for k in kernels])  # (K, H, W, n_card + 1)
    gram, sse, contrast, free_k = compiled.pattern_fits(stack, patch.rows, patch.cols, patch.y, tmpl)
    n_p = patch.y.size
    if patch.saturated is not None and patch.saturated[0].size:
        # a saturated pixel is at least the full scale: a fit below it there pays the
        # shortfall squared (`compiled.censored_fits`)
        per_t, best_k = compiled.censored_fits(stack, *patch.saturated, tmpl, gram, contrast, sse, SATURATED_GREY)
    else:
        best_k = np.argmin(sse, axis=0)  # (T,) each pattern at its best point-spread function
        per_t = sse[best_k, np.arange(sse.shape[1])]
    order = np.argpartition(per_t, 1)[:2]
    best, second = (int(order[0]), int(order[1])) if per_t[order[0]] <= per_t[order[1]] else \
        (int(order[1]), int(order[0]))
    if not np.isfinite(per_t[best]):
        return None
    k = int(best_k[best])
    free = float(free_k[k])  # the free card at the best pattern's point-spread function: the noise floor
    var = max(free / max(n_p - n_card - 2, 1), 1e-3)
    # the misfit over the same pixels as the free card (the saturated ones left out)
    return best, float((per_t[second] - per_t[best]) / var), float(max(sse[k, best] - free, 0.0) / var), k
