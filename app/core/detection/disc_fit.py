"""Disc centres by fitting a model of the printed card around each disc (for the survey).

The detector's centres (`refinement.refine_centres`: a darkness centroid in a window that
is the image of a circle around the disc) are fast, and within ~0.001 px on discs of
8 px and more seen face-on. On small or foreshortened discs the window cannot hold the
blurred disc without part of the card's edge (0.6 disc radii away on the card), the
background beyond it or the code: the centroid moves by 0.01-0.05 px, the same way in
every view from about the same place. A survey averages hundreds of views of each disc;
independent errors average out, these do not, and they end up in the map.

Here each such disc is fitted instead. The pixels of the disc's corner of the card (the
disc, the white around it, the card's two nearby edges and half a pixel beyond them; the
code area and a margin around it are left out) are modelled as

    I(p) = G + (A - G) * card(p) - B * ink(p)

(the blurred image of the printed card: blurring is linear, and the disc lies inside
the card, so the blurred disc is subtracted as it is; multiplied by the blurred card it
would lose ink near the card's edge and move thin discs outward by up to ~8 mpx under
a blur of 0.6 px), with ``ink = Phi(-d / s)`` and
``card = Phi(-(d_u - e_u) / s) * Phi(-(d_v - e_v) / s)``:

- d: the signed distance (pixels, first order) to the disc's image ellipse. Its shape
  and the offset of its centre from the projected disc centre come from the card's
  homography; its position is free (delta, 2 parameters).
- d_u, d_v: signed distances to the two card edges through the homography, each with a
  free offset e (a card is not flat: its edges need not lie where the homography of
  the disc centres puts them).
- A the white, B the disc's contrast, G the background, s the blur (pixel area and
  optics as one Gaussian).

Phi is the normal CDF: a blurred straight edge. It is exact for the card's edges and
symmetric about the centre for the disc, so a misfit of the disc's profile does not
move its centre.

A hand-held camera smears the frame over its exposure, often by more than a disc's
width. An isotropic blur cannot fit a smeared card, and the compromise it makes, with
the patch cut short on the code's side, moved the discs toward the card's middle: the
card's image shrank and a survey of one-sided views put the card 3-6 mm too far
(`bench/bench_disc_bias.py`). So the model is smeared too: ``ink`` and ``card`` are the
means of the printed card's images shifted by ``t v`` for `_SMEAR_T` points t along a
straight smear v (2 parameters, pixels; v = 0 is no smear). Pixels at the sensor's full
scale are left out (the model has no clipping). Gauss-Newton with Levenberg damping over
the 10 parameters, with analytic derivatives, all discs of a frame at once:

1. each disc is started with a short smear in two directions (`SMEAR_START_ANGLES`: the
   model is flat in v at v = 0) and goes on from the start that fits better;
2. the card's smear, the median of its discs' (their signs aligned), is held for each of
   its discs, which are fitted again: a disc's own smear is too loose a fit on a small
   disc;
3. a disc keeps the smeared fit only where it is clearly better than the unsmeared one
   (`SMEAR_EVIDENCE`) and the smear is at least `MIN_SMEAR_PX` long; otherwise the
   unsmeared fit (8 parameters) stands.

The code's cells are not modelled, and the pixels a smear carries their ink to are kept:
leaving them out would cut the patch short on the code's side and lose the disc's inner
edge (the survey's floor on the centre-loop walks is 1.9-4.2 mm with that cut, 1.5-2.2
mm without, `bench/bench_survey_floor.py`).

The result is the projection of the disc's centre: the homography's own, moved by the
fitted delta.

The model, its residuals and its normal equations are compiled (`_disc_fit_kernels`);
the rest is numpy. No I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.core.detection import _disc_fit_kernels as _kernels
from app.core.geometry import apply_homographies
from app.core.markers import CODE_ORIGIN, CODE_SIZE, DISC_CENTRES, DISC_RADIUS

__all__ = ["FIT_MAX_RADIUS_PX", "DiscFit", "fit_disc_centres"]

#: Discs whose image ellipse has a semi-major axis above this (px) keep the centroid:
#: there it is already within ~0.001 px, and the fit's patch would be large.
FIT_MAX_RADIUS_PX = 8.0
#: Pixels up to this far beyond the card's edge take part (px): its blurred ramp.
BEYOND_EDGE_PX = 0.5
#: Pixels within this of the code area (px, on both of its sides facing the disc) are
#: left out: the code's cells are not modelled.
CODE_MARGIN_PX = 0.5
ITERATIONS = 8
#: A fit that moves a centre further than this (px) from the detector's is not trusted.
MAX_SHIFT_PX = 0.5
MIN_PIXELS = 12
#: Pixels at or above this grey level are saturated (the white clipped).
SATURATED_GREY = 254.0
#: How far the patch reaches from the disc's centre toward the card's middle (card
#: units; its edges are 0.175 away on the other side). The blurred disc's inner tail
#: must be in it: at 0.2 discs of 2-3 px (minor semi-axis) under a blur of 0.8 px came
#: out 6 mpx too far inward, at 0.25 2 mpx (single cards rendered at supersample 4).
PATCH_INNER = 0.25
#: ... and toward its two nearby edges: past them (0.175), the edges' pixels being
#: limited by BEYOND_EDGE_PX.
PATCH_OUTER = 0.2
#: Where along the smear (fractions of its vector, centred) the printed card is sampled:
#: a straight smear of the exposure is the mean of the card's images shifted along it.
_SMEAR_T = (np.arange(5) + 0.5) / 5 - 0.5
_NO_SMEAR = np.zeros(1)
#: The longest smear fitted (px), the starts' length and directions, and the steps taken
#: from each start before the best goes on.
MAX_SMEAR_PX = 12.0
SMEAR_START_PX = 2.0
SMEAR_START_ANGLES = (0.0, np.pi / 2)
START_ITERATIONS = 3
#: Steps taken with the card's smear held.
HELD_ITERATIONS = 5
#: How much better (in units of the residual variance) the smeared fit must be than the
#: unsmeared one, on the same pixels, for its smear and centre to be kept.
SMEAR_EVIDENCE = 25.0
#: ... and its smear at least this long (px): shorter ones the Gaussian blur takes well enough.
MIN_SMEAR_PX = 3.0
#: (4, 2) per disc and card axis, the direction (+1 or -1 in card units) of the disc's
#: two nearby card edges.
_OUTWARD = np.where(DISC_CENTRES < 0.5, -1.0, 1.0)


@dataclass(frozen=True)
class DiscFit:
    """The disc fit of T cards (`fit_disc_centres`).

    Parameters
    ----------
    centres : ndarray, shape (T, 4, 2)
        Fitted disc centres in pixels; the given ones where not fitted.
    fitted : ndarray of bool, shape (T, 4)
        Which discs were fitted.
    blur_px : ndarray, shape (T, 4)
        The fitted blur s in pixels; NaN where not fitted.
    rms : ndarray, shape (T, 4)
        The residual RMS in grey levels; NaN where not fitted.
    smear_px : ndarray, shape (T, 4, 2)
        The fitted smear v in pixels (its sign is arbitrary); NaN where not fitted.
    """

    centres: np.ndarray
    fitted: np.ndarray
    blur_px: np.ndarray
    rms: np.ndarray
    smear_px: np.ndarray


def _disc_conics(hinv: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image ellipses of the card circles (`centre` (D, 2), DISC_RADIUS) under the
    inverse homographies `hinv` (D, 3, 3): centres (D, 2), shape matrices Q (D, 2, 2)
    with ``(x - m)^T Q (x - m) = 1`` on the ellipse, and which are real ellipses."""
    d = centre.shape[0]
    c0 = np.zeros((d, 3, 3))
    c0[:, 0, 0] = c0[:, 1, 1] = 1.0
    c0[:, :2, 2] = c0[:, 2, :2] = -centre
    c0[:, 2, 2] = (centre**2).sum(1) - DISC_RADIUS**2
    conic = hinv.transpose(0, 2, 1) @ c0 @ hinv
    a2, b2, c2 = conic[:, :2, :2], conic[:, :2, 2], conic[:, 2, 2]
    det = a2[:, 0, 0] * a2[:, 1, 1] - a2[:, 0, 1] * a2[:, 1, 0]
    ok = np.isfinite(det) & (np.abs(det) > 1e-300)
    a2 = np.where(ok[:, None, None], a2, np.eye(2))
    ainv = np.linalg.inv(a2)
    m = -(ainv @ b2[..., None])[..., 0]
    k = (b2[:, None, :] @ ainv @ b2[..., None])[:, 0, 0] - c2
    ok &= np.abs(k) > 1e-300
    q = a2 / np.where(ok, k, 1.0)[:, None, None]
    ok &= (q[:, 0, 0] > 0) & (q[:, 0, 0] * q[:, 1, 1] - q[:, 0, 1] * q[:, 1, 0] > 0) & np.isfinite(m).all(axis=1)
    return m, q, ok


def _image_lines(hinv: np.ndarray, lines_card: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Card lines (D, 3) as image lines (D, 3) scaled to signed pixel distances, negative
    on the side of the image points `inside` (D, 2)."""
    line = (hinv.transpose(0, 2, 1) @ lines_card[..., None])[..., 0]
    line /= np.maximum(np.hypot(line[:, 0], line[:, 1]), 1e-300)[:, None]
    side = line[:, 0] * inside[:, 0] + line[:, 1] * inside[:, 1] + line[:, 2]
    return line * np.where(side > 0, -1.0, 1.0)[:, None]


def fit_disc_centres(gray: np.ndarray, discs: np.ndarray, homographies: np.ndarray,
                     max_radius_px: float = FIT_MAX_RADIUS_PX) -> DiscFit:
    """Fit the disc centres of cards with a model of the card around each disc.

    A disc is fitted when its image ellipse's semi-major axis is at most
    `max_radius_px` and its patch lies in the image; a fit that moves the centre by
    `MAX_SHIFT_PX` or more, or rests on fewer than `MIN_PIXELS` pixels, is not
    trusted (the given centre stays).

    Parameters
    ----------
    gray : ndarray
        The frame, greyscale.
    discs : ndarray, shape (T, 4, 2)
        The detector's disc centres in pixels, in printed order.
    homographies : ndarray, shape (T, 3, 3)
        Card units to pixels, one per card (`app.core.geometry.homographies` of
        `discs`).
    max_radius_px : float
        Discs with a larger semi-major axis (pixels) keep their given centres.

    Returns
    -------
    DiscFit
        The centres, which were fitted, the blur and the residuals.
    """
    img = np.asarray(gray)
    cur = np.array(discs, np.float64).reshape(-1, 4, 2)
    t = cur.shape[0]
    centres, fitted = cur.copy(), np.zeros((t, 4), bool)
    blur, rms, smear = np.full((t, 4), np.nan), np.full((t, 4), np.nan), np.full((t, 4, 2), np.nan)
    out = DiscFit(centres, fitted, blur, rms, smear)
    if t == 0:
        return out
    card_hs = np.asarray(homographies, np.float64).reshape(t, 3, 3)
    hs = np.repeat(card_hs, 4, axis=0)  # (D, 3, 3)
    with np.errstate(all="ignore"):
        hinv = np.linalg.inv(hs)
    card_centre = np.tile(DISC_CENTRES, (t, 1))  # (D, 2)
    sign = np.tile(_OUTWARD, (t, 1))  # (D, 2)
    m, q, ok = _disc_conics(hinv, card_centre)
    semi_major = 1.0 / np.sqrt(np.maximum(np.linalg.eigvalsh(np.where(ok[:, None, None], q, np.eye(2)))[:, 0], 1e-12))
    ok &= semi_major <= max_radius_px
    # The patch: the image of the disc's corner of the card, out to its edges.
    span = np.array([[-PATCH_INNER, -PATCH_INNER], [PATCH_OUTER, -PATCH_INNER], [PATCH_OUTER, PATCH_OUTER],
                     [-PATCH_INNER, PATCH_OUTER]])  # (outward, outward) from the disc's centre
    corner_pts = DISC_CENTRES[:, None, :] + span[None] * _OUTWARD[:, None, :]
    corners = apply_homographies(card_hs, corner_pts.reshape(-1, 2)).reshape(t * 4, 4, 2)
    h, w = img.shape
    lo = np.floor(corners.min(axis=1) - BEYOND_EDGE_PX - 1.0)
    hi = np.ceil(corners.max(axis=1) + BEYOND_EDGE_PX + 1.0)
    ok &= np.isfinite(lo).all(axis=1) & np.isfinite(hi).all(axis=1)
    ok &= (lo[:, 0] >= 0) & (lo[:, 1] >= 0) & (hi[:, 0] < w) & (hi[:, 1] < h)
    rows = np.flatnonzero(ok)
    if rows.size == 0:
        return out
    n = rows.size
    lo, hi = lo[rows].astype(int), hi[rows].astype(int)
    side = int((hi - lo).max()) + 1
    offs = np.arange(side)
    xs = np.broadcast_to(lo[:, 0, None, None] + offs[None, None, :], (n, side, side))
    ys = np.broadcast_to(lo[:, 1, None, None] + offs[None, :, None], (n, side, side))
    within = (xs <= hi[:, 0, None, None]) & (ys <= hi[:, 1, None, None])
    xs, ys = xs.reshape(n, -1), ys.reshape(n, -1)
    within = within.reshape(n, -1)
    hinv_r, cc, sg = hinv[rows], card_centre[rows], sign[rows]
    mr, qr = m[rows], q[rows]

    # Which pixels take part: inside the card or just beyond its two nearby edges, on
    # the disc's corner of the card, and away from the code.
    one, zero = np.ones(n), np.zeros(n)
    edge_u = np.where(sg[:, 0] < 0, 0.0, 1.0)
    edge_v = np.where(sg[:, 1] < 0, 0.0, 1.0)
    line_u = _image_lines(hinv_r, np.stack([one, zero, -edge_u], axis=1), mr)
    line_v = _image_lines(hinv_r, np.stack([zero, one, -edge_v], axis=1), mr)
    code_mid = np.repeat(apply_homographies(card_hs, np.full((1, 2), CODE_ORIGIN + CODE_SIZE / 2))[:, 0], 4,
                         axis=0)[rows]
    code_u = np.where(sg[:, 0] < 0, CODE_ORIGIN, CODE_ORIGIN + CODE_SIZE)
    code_v = np.where(sg[:, 1] < 0, CODE_ORIGIN, CODE_ORIGIN + CODE_SIZE)
    cline_u = -_image_lines(hinv_r, np.stack([one, zero, -code_u], axis=1), code_mid)  # + toward the code
    cline_v = -_image_lines(hinv_r, np.stack([zero, one, -code_v], axis=1), code_mid)
    pxf, pyf = xs.astype(np.float64), ys.astype(np.float64)

    def dist(line: np.ndarray) -> np.ndarray:
        return line[:, 0, None] * pxf + line[:, 1, None] * pyf + line[:, 2, None]

    du_all, dv_all = dist(line_u), dist(line_v)
    near_code = (dist(cline_u) > -CODE_MARGIN_PX) & (dist(cline_v) > -CODE_MARGIN_PX)
    wx = hinv_r[:, 2, 0, None] * pxf + hinv_r[:, 2, 1, None] * pyf + hinv_r[:, 2, 2, None]
    ou = ((hinv_r[:, 0, 0, None] * pxf + hinv_r[:, 0, 1, None] * pyf + hinv_r[:, 0, 2, None]) / wx
          - cc[:, 0, None]) * sg[:, 0, None]
    ov = ((hinv_r[:, 1, 0, None] * pxf + hinv_r[:, 1, 1, None] * pyf + hinv_r[:, 1, 2, None]) / wx
          - cc[:, 1, None]) * sg[:, 1, None]
    use = (within & (du_all <= BEYOND_EDGE_PX) & (dv_all <= BEYOND_EDGE_PX)
           & (ou >= -PATCH_INNER) & (ov >= -PATCH_INNER)
           & ~near_code)

    # Pack each disc's pixels to the front of its row (padding has weight 0).
    count = use.sum(1)
    order = np.argsort(~use, axis=1, kind="stable")[:, : max(int(count.max()), 1)]
    take = lambda a: np.take_along_axis(a, order, axis=1)  # noqa: E731
    wgt = (np.arange(order.shape[1])[None, :] < count[:, None]).astype(np.float64)
    px, py = take(pxf), take(pyf)
    du, dv = take(du_all), take(dv_all)
    vals = take(img[np.minimum(ys, h - 1), np.minimum(xs, w - 1)].astype(np.float64))
    # A pixel at the sensor's full scale only says the card is at least that bright
    # there: the model has no clipping, so such pixels are left out.
    wgt *= vals < SATURATED_GREY
    count = wgt.sum(1).astype(int)

    nu, nv = np.ascontiguousarray(line_u[:, :2]), np.ascontiguousarray(line_v[:, :2])  # the edges' unit normals
    px, py, du, dv, vals = (np.ascontiguousarray(a) for a in (px, py, du, dv, vals))
    mr, qr = np.ascontiguousarray(mr), np.ascontiguousarray(qr)

    def normal_equations(theta: np.ndarray, ts: np.ndarray, with_jacobian: bool = True
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return _kernels.normal_equations(px, py, wgt, vals, du, dv, mr, qr, nu, nv, np.ascontiguousarray(theta), ts,
                                         with_jacobian)

    # Start: white and background from the pixels away from the disc, contrast from its
    # darkest pixel, the detector's centre, a typical blur.
    # The signed distance (px, first order) of each pixel to the disc's ellipse.
    x0, x1 = px - mr[:, 0, None], py - mr[:, 1, None]
    g0 = qr[:, 0, 0, None] * x0 + qr[:, 0, 1, None] * x1
    g1 = qr[:, 0, 1, None] * x0 + qr[:, 1, 1, None] * x1
    qq = x0 * g0 + x1 * g1
    d0 = (qq - np.sqrt(qq)) / (np.hypot(g0, g1) + 1e-12)
    use_b = wgt > 0

    def masked_mean(mask: np.ndarray, default: np.ndarray) -> np.ndarray:
        k = mask.sum(1)
        return np.where(k > 0, (vals * mask).sum(1) / np.maximum(k, 1), default)

    top = np.where(use_b, vals, -np.inf).max(1)
    white0 = masked_mean(use_b & (d0 > 1.0) & (du < -1.0) & (dv < -1.0), top)
    black0 = np.where(use_b & (d0 < 0), vals, np.inf).min(1)
    black0 = np.where(np.isfinite(black0), black0, np.where(use_b, vals, np.inf).min(1))
    back0 = masked_mean(use_b & ((du > 0.0) | (dv > 0.0)), white0)
    theta0 = np.zeros((n, 10))
    theta0[:, 2], theta0[:, 3], theta0[:, 4], theta0[:, 5] = white0, np.maximum(white0 - black0, 1.0), back0, 0.6

    def solve(theta: np.ndarray, iterations: int, lam: np.ndarray | None = None, ts: np.ndarray = _SMEAR_T,
              fixed_smear: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Levenberg-Marquardt from `theta`: the parameters, their cost and damping."""
        lam = np.full(n, 1e-3) if lam is None else lam
        eye = np.eye(10)[None]
        cost = normal_equations(theta, ts, False)[0]
        for _ in range(iterations):
            _, normal, rhs = normal_equations(theta, ts)
            if fixed_smear:
                normal[:, 8:10, :] = normal[:, :, 8:10] = 0.0
                rhs[:, 8:10] = 0.0
            diag = np.maximum(np.einsum("dii->di", normal), 1e-9)
            damped = normal + (lam[:, None] * diag)[:, :, None] * eye
            try:
                step = np.linalg.solve(damped, rhs[..., None])[..., 0]
            except np.linalg.LinAlgError:
                break
            trial = theta + step
            trial[:, 5] = np.clip(trial[:, 5], 0.15, 5.0)
            length = np.hypot(trial[:, 8], trial[:, 9])
            trial[:, 8:10] *= (np.minimum(length, MAX_SMEAR_PX) / np.maximum(length, 1e-12))[:, None]
            tcost = normal_equations(trial, ts, False)[0]
            better = tcost <= cost
            theta = np.where(better[:, None], trial, theta)
            cost = np.where(better, tcost, cost)
            lam = np.where(better, lam * 0.3, lam * 10.0)
        return theta, cost, lam

    # The model is the same for the smear v and -v, and flat in v at v = 0 (no step can
    # leave it): each disc is started with a short smear in each of two directions and
    # keeps the start that fits best after a few steps.
    best: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    for angle in SMEAR_START_ANGLES:
        start = theta0.copy()
        start[:, 8:10] = SMEAR_START_PX * np.array([np.cos(angle), np.sin(angle)])
        theta_k, cost_k, lam_k = solve(start, START_ITERATIONS)
        if best is None:
            best = (theta_k, cost_k, lam_k)
        else:
            better = cost_k < best[1]
            best = (np.where(better[:, None], theta_k, best[0]), np.where(better, cost_k, best[1]),
                    np.where(better, lam_k, best[2]))
    assert best is not None
    theta, cost, _ = solve(best[0], ITERATIONS - START_ITERATIONS, best[2])
    # One smear per card: the discs' own, their signs aligned, medianed; each disc is
    # fitted again with it held (a disc's own smear is too loose a fit on a small disc).
    card_of = rows // 4
    v = theta[:, 8:10].copy()
    for card in np.unique(card_of):
        mine = np.flatnonzero(card_of == card)
        ref = v[mine[np.argmax(np.hypot(v[mine, 0], v[mine, 1]))]]
        aligned = v[mine] * np.where(v[mine] @ ref < 0, -1.0, 1.0)[:, None]
        v[mine] = np.median(aligned, axis=0)
    held = theta.copy()
    held[:, 8:10] = v
    theta, cost, _ = solve(held, HELD_ITERATIONS, fixed_smear=True)
    # A smear is kept only where it fits clearly better than none: two more parameters
    # must not buy a worse centre on a sharp frame.
    sharp, cost_sharp, _ = solve(theta0.copy(), ITERATIONS, ts=_NO_SMEAR)
    dof = np.maximum(count - 10, 1)
    smeared = ((cost_sharp - cost) > SMEAR_EVIDENCE * cost / dof) & (np.hypot(theta[:, 8], theta[:, 9]) >= MIN_SMEAR_PX)
    theta = np.where(smeared[:, None], theta, sharp)
    cost = np.where(smeared, cost, cost_sharp)

    good = ((np.hypot(theta[:, 0], theta[:, 1]) < MAX_SHIFT_PX) & (theta[:, 3] > 0) & (count >= MIN_PIXELS)
            & np.isfinite(theta).all(axis=1))
    projected = apply_homographies(card_hs, DISC_CENTRES).reshape(-1, 2)[rows]
    new = projected + theta[:, :2]
    # Not trusted either: a result far from the detector's centre.
    good &= np.hypot(*(new - cur.reshape(-1, 2)[rows]).T) < MAX_SHIFT_PX
    sel = rows[good]
    centres.reshape(-1, 2)[sel] = new[good]
    fitted.reshape(-1)[sel] = True
    blur.reshape(-1)[sel] = theta[good, 5]
    rms.reshape(-1)[sel] = np.sqrt(cost[good] / count[good])
    smear.reshape(-1, 2)[sel] = theta[good, 8:10]
    return out
