"""Simulated disc candidates: what the candidate stage might report on a rendered frame,
drawn from the frame's ground truth, to exercise the target stages (grouping,
verification, refinement, identification, completion) without the learned classifier
(tests and bench/bench_targets.py)."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from app.core.geometry import apply_homographies, homographies
from app.core.markers import CODE_ORIGIN, CODE_SIZE, DEFAULT_FAMILY, get_family
from app.sim.scenes import TargetTruth

__all__ = ["simulate_candidates"]


def simulate_candidates(
    gray: np.ndarray,
    targets: Sequence[TargetTruth],
    rng: np.random.Generator,
    family: str = DEFAULT_FAMILY,
    n_random: int = 30,
    n_texture: int = 30,
    code_cells: bool = True,
    card_corners: bool = True,
    jitter_px: float = 1.0,
    radius_factor: tuple[float, float] = (0.7, 1.4),
) -> np.ndarray:
    """Disc candidates as the candidate stage might report them, from a frame's truth.

    Every visible disc within ±`jitter_px` and its radius off by a random factor, plus
    false candidates: the black code cells of every card (through its own homography),
    card corners, random points and dark texture spots of `gray`; in random order.

    Parameters
    ----------
    gray : ndarray
        The rendered frame, greyscale (for the texture spots and the image size).
    targets : sequence of TargetTruth
        The frame's targets (any objects with ``id``, ``discs_px`` (4, 2),
        ``disc_visible`` (4,) and ``disc_diameter_px``).
    rng : numpy.random.Generator
        The random stream every draw comes from.
    family : str
        The code family of the cards (for their code cells).
    n_random : int
        Random false candidates anywhere in the image.
    n_texture : int
        False candidates on dark texture spots (at most this many).
    code_cells : bool
        A false candidate on every black code cell.
    card_corners : bool
        A false candidate near each card corner.
    jitter_px : float
        Largest offset of a disc's candidate from the true centre, per axis.
    radius_factor : tuple of float
        Range of the random factor on a disc's true radius.

    Returns
    -------
    ndarray of float32, shape (N, 4)
        Rows ``[u, v, radius, score]`` in full-resolution pixels.
    """
    rows: list[list[float]] = []
    fam = get_family(family)
    n = fam.cells
    step = CODE_SIZE / n
    for t in targets:
        discs = np.asarray(t.discs_px, np.float64)
        vis = np.asarray(t.disc_visible, bool)
        r = 0.5 * float(t.disc_diameter_px)
        for k in range(4):
            if vis[k] and np.isfinite(discs[k]).all():
                u, v = discs[k] + rng.uniform(-jitter_px, jitter_px, 2)
                rows.append([u, v, r * rng.uniform(*radius_factor), rng.uniform(0.5, 1.0)])
        if not np.isfinite(discs).all():
            continue
        hs = homographies(discs[None])
        extra = []
        if code_cells and 0 <= int(t.id) < len(fam):
            code = fam.code(int(t.id))
            rr, cc = np.nonzero(code)
            extra.append(np.stack([CODE_ORIGIN + (cc + 0.5) * step, CODE_ORIGIN + (rr + 0.5) * step], 1))
        if card_corners:
            extra.append(np.array([[0.03, 0.03], [0.97, 0.03], [0.97, 0.97], [0.03, 0.97]]))
        if extra:
            p = apply_homographies(hs, np.concatenate(extra))[0]
            for u, v in p:
                rows.append([u, v, r * 0.45 * rng.uniform(*radius_factor), rng.uniform(0.0, 0.8)])
    h, w = gray.shape[:2]
    for _ in range(n_random):
        rows.append([rng.uniform(0, w - 1), rng.uniform(0, h - 1), float(np.exp(rng.uniform(np.log(2), np.log(25)))),
                     rng.uniform(0.0, 0.8)])
    if n_texture:
        g = cv2.GaussianBlur(np.asarray(gray, np.float32), (0, 0), 2.0)
        mins = (g <= cv2.erode(g, np.ones((5, 5), np.uint8))) & (g < cv2.blur(g, (15, 15)) - 3)
        ys, xs = np.nonzero(mins)
        if ys.size:
            pick = rng.choice(ys.size, size=min(n_texture, ys.size), replace=False)
            for y, x in zip(ys[pick], xs[pick], strict=True):
                rows.append([x + rng.uniform(-0.5, 0.5), y + rng.uniform(-0.5, 0.5),
                             rng.uniform(2.0, 12.0), rng.uniform(0.0, 0.8)])
    out = np.array(rows, np.float32).reshape(-1, 4)
    return out[rng.permutation(out.shape[0])]
