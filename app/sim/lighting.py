"""Lamps in the scene: light that falls off with distance, shades each card unevenly
and glints on glossy paper.

The renderer draws each surface's reflectance (its texture: white paper about 0.9,
black ink about 0.05) as if every surface were lit alike. `shade` lights it: each pixel
sees a surface point (`app.sim.surfaces`) whose irradiance is the bounced light of the
room (`Lighting.ambient`, the same everywhere) plus each lamp's direct light, which
falls off with the square of the distance and with the cosine of its incidence
(Lambert): a card lit at 45 degrees by a lamp 1.5 m away is some 30 % brighter at its
near edge than at its far one. The cards' paper may be glossy (`Lighting.gloss`): it also reflects each lamp
as a Blinn-Phong highlight, as bright on black ink as on white paper, which washes the
code out where it falls and clips the paper's white. The frame is then exposed as a
camera's automatic exposure would: its median brightness set to `Lighting.key`.

Not modelled: shadows (no surface hides a lamp from another), the colour of the light,
the bounce light's own gradients (the ambient term is uniform), and a lamp seen in the
frame (lamps are points, not drawn).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.sim.surfaces import Surfaces

__all__ = ["Lamp", "Lighting", "ceiling_lamps", "irradiance", "shade"]


@dataclass(frozen=True)
class Lamp:
    """A point light.

    Attributes
    ----------
    position : tuple of float
        Map coordinates, metres.
    intensity : float
        Radiant intensity in the lighting's units: the irradiance it gives a surface 1 m
        away facing it.
    """

    position: tuple[float, float, float]
    intensity: float = 1.0


@dataclass(frozen=True)
class Lighting:
    """The lamps of a scene and how its cards reflect them.

    Attributes
    ----------
    lamps : tuple of Lamp
    ambient : float
        Irradiance of the bounced light, uniform, in the lamps' units.
    gloss : float
        Specular reflectance of the cards' paper (0: matte): the highlight's peak, as a
        fraction of the lamp's irradiance at the card.
    shininess : float
        Blinn-Phong exponent of the highlight: higher is a smaller, sharper glint.
    key : float
        The frame's median brightness after the automatic exposure, as a fraction of
        the unlit render's (1: as rendered).
    """

    lamps: tuple[Lamp, ...]
    ambient: float = 0.1
    gloss: float = 0.0
    shininess: float = 40.0
    key: float = 1.0

    def __post_init__(self) -> None:
        if not self.lamps and self.ambient <= 0:
            raise ValueError("a lighting needs a lamp or some ambient light")
        if self.ambient < 0 or self.gloss < 0 or self.shininess <= 0 or self.key <= 0:
            raise ValueError(f"ambient and gloss must be >= 0, shininess and key > 0: {self}")


def ceiling_lamps(size: tuple[float, float, float], rows: int = 2, cols: int = 2, below_m: float = 0.1,
                  intensity: float = 1.0, ambient: float = 0.1, gloss: float = 0.0, shininess: float = 40.0
                  ) -> Lighting:
    """A room lit by a grid of lamps under its ceiling, one in the middle of each cell.

    Parameters
    ----------
    size : tuple of float
        (W, D, H) of the box room, metres.
    rows, cols : int
        Lamps along the room's depth and width.
    below_m : float
        How far below the ceiling the lamps hang, metres.
    intensity, ambient, gloss, shininess : float
        As `Lamp` and `Lighting`.

    Returns
    -------
    Lighting
    """
    w, d, h = size
    lamps = tuple(Lamp(((i + 0.5) * w / cols, (j + 0.5) * d / rows, h - below_m), intensity)
                  for j in range(rows) for i in range(cols))
    return Lighting(lamps, ambient=ambient, gloss=gloss, shininess=shininess)


def irradiance(points: np.ndarray, normals: np.ndarray, lighting: Lighting) -> np.ndarray:
    """The irradiance of surface points: bounce light plus each lamp's direct light.

    Parameters
    ----------
    points, normals : (..., 3) ndarray
        Surface points (map coordinates) and their unit normals.
    lighting : Lighting

    Returns
    -------
    (...) ndarray
    """
    total = np.full(points.shape[:-1], lighting.ambient)
    for lamp in lighting.lamps:
        to_lamp = np.asarray(lamp.position, np.float64) - points
        r2 = np.einsum("...k,...k->...", to_lamp, to_lamp)
        cos = np.einsum("...k,...k->...", to_lamp, normals) / np.sqrt(r2)
        total += lamp.intensity * np.maximum(cos, 0.0) / r2
    return total


def _highlight(points: np.ndarray, normals: np.ndarray, eye: np.ndarray, lighting: Lighting) -> np.ndarray:
    """The glossy reflection of every lamp at surface points seen from `eye`."""
    view = eye - points
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    total = np.zeros(points.shape[:-1])
    for lamp in lighting.lamps:
        to_lamp = np.asarray(lamp.position, np.float64) - points
        r2 = np.einsum("...k,...k->...", to_lamp, to_lamp)
        light = to_lamp / np.sqrt(r2)[..., None]
        half = light + view
        half /= np.linalg.norm(half, axis=-1, keepdims=True)
        lit = np.einsum("...k,...k->...", light, normals) > 0
        facing = np.maximum(np.einsum("...k,...k->...", half, normals), 0.0)
        total += np.where(lit, lamp.intensity / r2 * facing**lighting.shininess, 0.0)
    return lighting.gloss * total


def shade(image: np.ndarray, surfaces: Surfaces, lighting: Lighting, eye: np.ndarray) -> np.ndarray:
    """Light a rendered frame: each pixel's reflectance times its surface's irradiance,
    the glossy cards' highlights added, then the frame exposed to `lighting.key`.

    Parameters
    ----------
    image : (height, width) ndarray
        The render, reflectance in [0, 1].
    surfaces : Surfaces
        What each pixel sees (`cast_surfaces`), from the camera centre `eye`.
    lighting : Lighting
    eye : (3,) ndarray
        The camera centre, map coordinates.

    Returns
    -------
    (height, width) ndarray of float32
        Linear brightness, 1 being the unlit render's white; above 1 clips later, as a
        sensor does.
    """
    seen = np.isfinite(surfaces.depth)
    points = np.where(seen[..., None], surfaces.points, 0.0)
    normals = np.where(seen[..., None], surfaces.normals, (0.0, 0.0, 1.0))
    light = np.where(seen, irradiance(points, normals, lighting), lighting.ambient)
    lit = image * light
    if lighting.gloss > 0 and surfaces.card.any():
        at = surfaces.card
        lit[at] += _highlight(points[at], normals[at], np.asarray(eye, np.float64), lighting)
    reference = float(np.median(light[seen])) if seen.any() else 1.0
    return (lit * (lighting.key / max(reference, 1e-12))).astype(np.float32)
