"""The metric scale of the map (survey step 5): the least-squares scale that gives every
surveyed card its printed disc-to-disc distances (sides 0.6 s, diagonals 0.6 sqrt(2) s
for a card of side s). With the card prior on, the bundle adjustment has already made
the map metric and this factor is ~1; without it, it is the only source of scale."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.core.survey.cards import PAIR_UNITS, PAIRS
from app.core.survey.state import Reconstruction


@dataclass(frozen=True)
class MetricScale:
    """The scale applied to the map, and how well the cards then fit their printed size."""

    factor: float
    residual_m: float  # RMS of the card disc-distance residuals after scaling


def apply_metric_scale(rec: Reconstruction, targets: np.ndarray, marker_size_m: float) -> MetricScale:
    """Scale the map (points and camera positions) to the printed card size.

    Parameters
    ----------
    rec : Reconstruction
        The map; its points and translations are scaled in place.
    targets : ndarray of int
        The targets whose cards set the scale (placed, every disc).
    marker_size_m : float
        The printed card's side, metres.

    Returns
    -------
    MetricScale
        The factor applied and the cards' residual after it.
    """
    d = np.concatenate([np.linalg.norm(rec.X[4 * t + PAIRS[:, 0]] - rec.X[4 * t + PAIRS[:, 1]], axis=1)
                        for t in targets])
    L = np.tile(PAIR_UNITS * marker_size_m, len(targets))
    s = float((d * L).sum() / (d * d).sum())
    rec.X *= s
    rec.tvec *= s
    return MetricScale(s, float(np.sqrt(np.mean((s * d - L) ** 2))))
