"""The initial lens, from the cards alone (survey step 1).

A card is a planar square: with square pixels and the principal point at the image
centre, each tilted card's homography gives Zhang's two constraints on the focal length.
`focal_from_cards` solves them in closed form over every card of every frame (robust,
trimmed); `lens_from_cards` then finds the maximum-likelihood focal length and radial
distortion k1 over the cards (each card its own pose), since the closed form alone is
biased by detector noise. The bundle adjustment refines the lens later, from the map.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from app.core.geometry import Camera
from app.core.markers import DISC_CENTRES
from app.core.survey.state import Tracks


def focal_from_cards(cards_px: Sequence[np.ndarray], width: int, height: int) -> float | None:
    """Focal length from the homographies of many planar square cards, in closed form.

    Zhang's constraints with square pixels, no skew and the principal point at the
    image centre: for H = [h1 h2 h3] (card plane -> centred pixels) and w = 1/f^2,

        (h11 h12 + h21 h22) w + h31 h32 = 0,
        (h11^2 + h21^2 - h12^2 - h22^2) w + h31^2 - h32^2 = 0.

    A card seen head-on gives 0 = 0 (no information) and weighs nothing in the joint
    least squares; equations that disagree (a bad detection) are trimmed iteratively.

    Parameters
    ----------
    cards_px : sequence of (4, 2) ndarray
        Disc centres (px, printed order) of every card in every frame.
    width, height : int
        The image size, px.

    Returns
    -------
    float or None
        The focal length (px); None when the cards do not determine it (all seen
        head-on, too few) or it comes out beyond any real lens.
    """
    scale = float(max(width, height))
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    model = DISC_CENTRES.astype(np.float32)
    a_list, b_list = [], []
    for quad in cards_px:
        q = ((np.asarray(quad, np.float64) - centre) / scale).astype(np.float32)
        try:
            H = cv2.getPerspectiveTransform(model, q)
        except cv2.error:
            continue
        if not np.isfinite(H).all():
            continue
        # Normalise so that the equations of near and far cards weigh alike.
        H = H / np.sqrt((H[:2, :2] ** 2).sum() / 2)
        h1, h2 = H[:, 0], H[:, 1]
        a_list += [h1[0] * h2[0] + h1[1] * h2[1], h1[0] ** 2 + h1[1] ** 2 - h2[0] ** 2 - h2[1] ** 2]
        b_list += [h1[2] * h2[2], h1[2] ** 2 - h2[2] ** 2]
    if len(a_list) < 4:
        return None
    a, b = np.array(a_list), -np.array(b_list)  # a w = b
    keep = np.ones(len(a), bool)
    w = 0.0
    for _ in range(5):
        if (a[keep] ** 2).sum() <= 1e-18:
            return None
        w = float((a[keep] * b[keep]).sum() / (a[keep] ** 2).sum())
        r = a * w - b
        mad = 1.4826 * np.median(np.abs(r[keep])) + 1e-12
        new = np.abs(r) < 3 * mad
        if new.sum() < 4 or np.array_equal(new, keep):
            break
        keep = new
    if not np.isfinite(w) or w <= 0:
        return None
    f = scale / np.sqrt(w)
    # Lenses from fisheye-ish (~140 deg) to long (~10 deg): outside is a failed estimate.
    return f if 0.2 * scale < f < 6.0 * scale else None


def _rotations(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of rotation vectors w (N, 3) (Rodrigues, batched)."""
    angle = np.linalg.norm(w, axis=1)
    k = w / np.where(angle > 0, angle, 1.0)[:, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def _card_residuals(quads: np.ndarray, model: np.ndarray, R: np.ndarray, t: np.ndarray, f: float, k1: float,
                    centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (N, 8) of planar cards (``model`` (4, 3), poses R (N, 3, 3), t (N, 3))
    seen by a lens (f, k1, principal point ``centre``), and their Jacobian (N, 8, 8)
    over a rotation applied on the left, the translation, f and k1."""
    a = np.einsum("nij,kj->nki", R, model)  # (N, 4, 3): R @ model
    X = a + t[:, None, :]
    z = X[..., 2]
    x, y = X[..., 0] / z, X[..., 1] / z
    r2 = x * x + y * y
    d = 1 + k1 * r2
    res = np.stack([f * x * d + centre[0], f * y * d + centre[1]], axis=-1) - quads  # (N, 4, 2)
    dx = np.stack([1 / z, np.zeros_like(z), -x / z], axis=-1)
    dy = np.stack([np.zeros_like(z), 1 / z, -y / z], axis=-1)
    dd = 2 * k1 * (x[..., None] * dx + y[..., None] * dy)
    gu = f * (d[..., None] * dx + x[..., None] * dd)  # d u / d X
    gv = f * (d[..., None] * dy + y[..., None] * dd)
    J = np.empty((len(quads), 4, 2, 8))
    # A small rotation w moves a by w x a: d u / d w = a x (d u / d X).
    J[:, :, 0, :3], J[:, :, 1, :3] = np.cross(a, gu), np.cross(a, gv)
    J[:, :, 0, 3:6], J[:, :, 1, 3:6] = gu, gv
    J[:, :, 0, 6], J[:, :, 1, 6] = x * d, y * d
    J[:, :, 0, 7], J[:, :, 1, 7] = f * x * r2, f * y * r2
    return res.reshape(-1, 8), J.reshape(-1, 8, 8)


def _refine_cards(quads: np.ndarray, model: np.ndarray, centre: np.ndarray, th: np.ndarray, R: np.ndarray,
                  t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every card's pose for the lens ``th`` (f, k1) by damped Gauss-Newton (each card its
    own damping), from (R, t) (updated in place); with the residuals and Jacobian there."""
    r, J = _card_residuals(quads, model, R, t, th[0], th[1], centre)
    cost = (r**2).sum(axis=1)
    lam = np.full(len(quads), 1e-3)
    for _ in range(20):
        A = J[:, :, :6]
        H = A.transpose(0, 2, 1) @ A
        H = H + lam[:, None, None] * (np.eye(6) * (np.diagonal(H, axis1=1, axis2=2)[:, None, :] + 1e-12))
        step = -np.linalg.solve(H, np.einsum("nij,ni->nj", A, r)[..., None])[..., 0]
        new_R, new_t = _rotations(step[:, :3]) @ R, t + step[:, 3:]
        new_r, new_J = _card_residuals(quads, model, new_R, new_t, th[0], th[1], centre)
        new_cost = (new_r**2).sum(axis=1)
        better = new_cost < cost  # (NaN: behind the camera, refused)
        gain = np.where(better, cost - new_cost, 0.0)
        R[better], t[better], r[better], J[better], cost[better] = (
            new_R[better], new_t[better], new_r[better], new_J[better], new_cost[better])
        lam = np.where(better, np.maximum(lam / 10, 1e-9), lam * 10)
        if not (gain > 1e-10 * cost).any():
            break
    return R, t, r, J


def _fit_cards(quads: np.ndarray, model: np.ndarray, centre: np.ndarray, th: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every card's better tilt for the lens ``th``: both IPPE poses, refined; the card
    poses (R, t), residuals and Jacobian of the better one."""
    K = np.array([[th[0], 0, centre[0]], [0, th[0], centre[1]], [0, 0, 1.0]])
    dist = np.array([th[1], 0.0, 0.0, 0.0, 0.0])
    R, t = np.tile(np.eye(3), (2, len(quads), 1, 1)), np.zeros((2, len(quads), 3))
    t[:, :, 2] = np.nan  # no pose (refused below)
    for i, q in enumerate(quads):
        try:
            _, rvecs, tvecs, _ = cv2.solvePnPGeneric(model, q, K, dist, flags=cv2.SOLVEPNP_IPPE)
        except cv2.error:
            continue
        for k, (rvec, tvec) in enumerate(zip(rvecs[:2], tvecs[:2], strict=False)):
            R[k, i], t[k, i] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        if len(rvecs) == 1:
            R[1, i], t[1, i] = R[0, i], t[0, i]
    tilts = [_refine_cards(quads, model, centre, th, R[k], t[k]) for k in range(2)]
    first = (tilts[0][2] ** 2).sum(axis=1) <= (tilts[1][2] ** 2).sum(axis=1)
    return tuple(np.where(first.reshape((-1,) + (1,) * (a.ndim - 1)), a, b)  # type: ignore[return-value]
                 for a, b in zip(tilts[0], tilts[1], strict=True))


def _lens_normal_equations(r: np.ndarray, J: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normal equations (2x2, 2) of the lens with the card poses eliminated (Schur
    complement), over the cards ``keep``."""
    A, B, rk = J[keep, :, :6], J[keep, :, 6:], r[keep]
    U = A.transpose(0, 2, 1) @ A + 1e-12 * np.eye(6)
    W = A.transpose(0, 2, 1) @ B
    UiW = np.linalg.solve(U, W)
    S = np.einsum("nij,nik->jk", B, B) - np.einsum("nij,nik->jk", W, UiW)
    g = np.einsum("nij,ni->j", B, rk) - np.einsum("nij,ni->j", UiW, np.einsum("nij,ni->nj", A, rk))
    return S, g


def _fitting_cards(r: np.ndarray, keep: np.ndarray | None) -> np.ndarray:
    """Cards that fit no worse than 5 times the typical one (of ``keep``). The others are
    misread, have a wrong disc, or are a folded projection from outside the field: left
    in, they pull k1 far off (+1.5)."""
    card_rms = np.sqrt((r**2).mean(axis=1))
    ok = np.isfinite(card_rms)
    base = ok if keep is None else keep & ok
    typical = float(np.median(card_rms[base])) if base.any() else 0.0
    return ok & (card_rms < max(5 * typical, 1e-3))


def lens_from_cards(cards_px: Sequence[np.ndarray], width: int, height: int, focal: float,
                    max_cards: int = 1000) -> tuple[float, float] | None:
    """Focal length and radial distortion k1 from many planar square cards, by maximum
    likelihood: every card a planar square with its own pose, one lens for all (Zhang's
    refinement, principal point at the image centre), from the closed-form ``focal``.

    Why: the closed form is biased by detector noise, and strongly (small far cards:
    their perspective terms are mostly noise; f +8 % at 0.03 px, +40 % at 0.1 px in the
    bench room), and it ignores the distortion. The survey's start and every frame
    registered against it would inherit the wrong lens (cameras 0.3-0.5 m off at 6 m),
    and the bundle adjustment settle in a wrong minimum (f 871 px for 820). The
    reprojection error has no such bias (bench room, 0.03 px: 822 px, k1 -0.105 for
    -0.12).

    Variable projection: for a lens, each card's pose is fitted on its own (both tilts
    tried: a small card's two tilts fit alike; all cards at once, Gauss-Newton); the
    lens then takes a Newton step on that profile cost (normal equations with the card
    poses eliminated). A joint step that moves poses linearly crawls: the cost of a
    small card is far from quadratic in its tilt. Cards that fit far worse than the
    others (misread, a wrong disc, a folded projection) are trimmed.

    Parameters
    ----------
    cards_px : sequence of (4, 2) ndarray
        Disc centres (px, printed order) of every card in every frame.
    width, height : int
        The image size, px.
    focal : float
        The start: the closed-form focal length (`focal_from_cards`), px.
    max_cards : int
        At most this many cards, evenly over the video (a bound on the time, ~1 s).

    Returns
    -------
    (float, float) or None
        The focal length (px) and k1; None when the cards do not determine the focal
        length (all seen head-on, too few) or it comes out beyond any real lens.
    """
    quads = np.asarray([q for q in cards_px if np.isfinite(q).all()], np.float64).reshape(-1, 4, 2)
    if len(quads) > max_cards:
        quads = quads[np.linspace(0, len(quads) - 1, max_cards).round().astype(int)]
    if len(quads) < 4:
        return None
    model = np.c_[DISC_CENTRES, np.zeros(4)].astype(np.float64)  # card units: scale is free
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])

    theta = np.array([float(focal), 0.0])  # f, k1
    R, t, r, J = _fit_cards(quads, model, centre, theta)
    keep = _fitting_cards(r, None)
    for _ in range(3):  # fit, trim the cards that do not fit, fit again
        if keep.sum() < 4:
            return None
        cost = float((r[keep] ** 2).sum())
        lam = 1e-4
        for _ in range(30):
            S, g = _lens_normal_equations(r, J, keep)
            try:
                step = -np.linalg.solve(S + lam * np.diag(np.diag(S) + 1e-12), g)
            except np.linalg.LinAlgError:
                return None
            new = theta + step
            if 0.2 * focal < new[0] < 5 * focal and abs(new[1]) < 2:
                new_R, new_t, new_r, new_J = _refine_cards(quads, model, centre, new, R.copy(), t.copy())
                new_cost = float((new_r[keep] ** 2).sum())
                if new_cost < cost:
                    done = cost - new_cost < 1e-7 * cost or abs(step[0]) < 1e-6 * theta[0]
                    theta, R, t, r, J, cost = new, new_R, new_t, new_r, new_J, new_cost
                    lam = max(lam / 10, 1e-9)
                    if done:
                        break
                    continue
            lam *= 10
            if lam > 1e4:
                break
        # A card's better tilt may have changed with the lens: both again.
        R, t, r, J = _fit_cards(quads, model, centre, theta)
        new_keep = _fitting_cards(r, keep)
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    # The cards must determine f (not all head-on): its standard deviation from the
    # reduced normal equations, the noise level from the residuals (2 dof per card).
    S, _ = _lens_normal_equations(r, J, keep)
    sigma2 = float((r[keep] ** 2).sum()) / max(2 * int(keep.sum()) - 2, 1)
    try:
        var_f = float(np.linalg.inv(S)[0, 0]) * sigma2
    except np.linalg.LinAlgError:
        return None
    f, k1 = float(theta[0]), float(theta[1])
    if not (np.isfinite(f) and np.isfinite(k1) and np.isfinite(var_f)) or np.sqrt(max(var_f, 0.0)) > 0.05 * f:
        return None
    scale = float(max(width, height))
    return (f, k1) if 0.2 * scale < f < 6.0 * scale else None


@dataclass(frozen=True)
class CardsLens:
    """What the cards' own shapes say of the lens."""

    closed_form_px: float | None  # `focal_from_cards`; None: the cards do not determine it
    fitted: tuple[float, float] | None  # `lens_from_cards`: (focal length px, k1); None: not determined


def cards_lens(tracks: Tracks, width: int, height: int) -> CardsLens:
    """The lens the cards' own shapes give: `focal_from_cards`, then `lens_from_cards`.

    Parameters
    ----------
    tracks : Tracks
        The observations: every view is a card.
    width, height : int
        The image size, px.

    Returns
    -------
    CardsLens
        The closed-form focal length and the maximum-likelihood lens, each None when the
        cards do not determine it.
    """
    cards = tracks.uv.reshape(-1, 4, 2)
    focal = focal_from_cards(cards, width, height)
    return CardsLens(focal, lens_from_cards(cards, width, height, focal) if focal is not None else None)


def initial_camera(tracks: Tracks, width: int, height: int, intrinsics: Camera | None,
                   warnings: list[str], lens: CardsLens | None = None) -> Camera:
    """The camera the survey starts from (step 1).

    Parameters
    ----------
    tracks : Tracks
        The observations: every view is a card.
    width, height : int
        The image size, px.
    intrinsics : Camera or None
        A known camera (returned as it is), else the lens is found from the cards.
    warnings : list of str
        Warnings for the user; appended to when the cards do not determine the focal
        length.
    lens : CardsLens, optional
        The cards' lens (`cards_lens`) when the caller has it already.

    Returns
    -------
    Camera
        The given camera; or the lens of `lens_from_cards` (principal point at the image
        centre, k1 only), or of `focal_from_cards` when the maximum-likelihood fit
        fails, or a typical ~60 degree lens when the cards are all seen head-on.
    """
    if intrinsics is not None:
        return intrinsics
    if lens is None:
        lens = cards_lens(tracks, width, height)
    if lens.fitted is not None:
        focal, k1 = lens.fitted
    elif lens.closed_form_px is not None:
        focal, k1 = lens.closed_form_px, 0.0
    else:
        # Start from a typical ~60 degree lens; the bundle adjustment refines it.
        focal, k1 = 0.85 * max(width, height), 0.0
        warnings.append("the cards did not determine an initial focal length (all seen head-on?); "
                        "started from a typical lens")
    return Camera.pinhole(focal, width, height, dist=[k1, 0.0, 0.0, 0.0, 0.0])
