"""Camera degradations for the scene simulator.

Every function takes a rendered greyscale image (H x W, float, values in [0, 1]) and
explicit parameters (plus a `numpy.random.Generator` where randomness is needed) and
returns a new float32 image; inputs are never modified.

Conventions (same as `app.core.markers.render_card`):

* pixel centres at integer coordinates, centre of the top-left pixel at (0, 0), x to the
  right, y down; pixel (row i, column j) covers [j - 0.5, j + 0.5] x [i - 0.5, i + 0.5];
* angles in radians from +x towards +y (clockwise as displayed, since y points down).

Geometry is never shifted: blur kernels are point-symmetric about their centre pixel, so
the intensity-weighted centroid of a symmetric blob (a disc seen face-on) is unchanged
and ground-truth disc centres stay valid after blurring.

`Degradation` is one sampled set of parameters (JSON-able via `to_dict`) and
`DegradationRanges` the distribution it is sampled from; `PRESETS` holds the named ones.

Pure numpy/OpenCV; no I/O.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import cv2
import numpy as np

Range = tuple[float, float]

__all__ = [
    "BLUR",
    "BRIGHT",
    "DARK",
    "DEFAULT",
    "FULL",
    "NONE",
    "PRESETS",
    "Degradation",
    "DegradationRanges",
    "Specular",
    "ThinLens",
    "defocus",
    "defocus_kernel",
    "depth_defocus",
    "exposure",
    "gamma",
    "jpeg",
    "lighting_gradient",
    "motion_blur",
    "motion_blur_kernel",
    "occlude",
    "polygon_coverage",
    "sensor_noise",
    "specular_highlight",
    "to_uint8",
    "vignette",
]


# --------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------


def _as_image(img: np.ndarray) -> np.ndarray:
    """A float32 2-D copy of `img` (copy so callers can never alias our output)."""
    a = np.array(img, dtype=np.float32, copy=True)
    if a.ndim != 2:
        raise ValueError(f"expected a 2-D greyscale image, got shape {a.shape}")
    return a


def _check(cond: bool, message: str) -> None:
    if not cond:
        raise ValueError(message)


def _finite(value: float, name: str) -> float:
    v = float(value)
    _check(math.isfinite(v), f"{name} must be finite, got {value!r}")
    return v


def _pixel_grid(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Broadcastable pixel-centre coordinates (x of shape (1, W), y of shape (H, 1))."""
    h, w = shape
    return (
        np.arange(w, dtype=np.float32)[None, :],
        np.arange(h, dtype=np.float32)[:, None],
    )


# --------------------------------------------------------------------------------------
# Photometric: exposure, tone curve, illumination
# --------------------------------------------------------------------------------------


def exposure(img: np.ndarray, gain: float, offset: float = 0.0) -> np.ndarray:
    """Exposure: ``img * gain + offset``, clipped to [0, 1] (the sensor saturates).

    Parameters
    ----------
    img : (H, W) ndarray
        Grey levels in [0, 1].
    gain : float
        Multiplier, >= 0: ~0.06..2 (dark frames 0.06-0.2, > 1 blows out white paper).
    offset : float, optional
        Black level / veiling flare (positive lifts the blacks).

    Returns
    -------
    (H, W) ndarray of float32

    Raises
    ------
    ValueError
        If `gain` is negative or a value is not finite.
    """
    gain = _finite(gain, "gain")
    offset = _finite(offset, "offset")
    _check(gain >= 0.0, f"gain must be >= 0, got {gain}")
    out = _as_image(img)
    out *= np.float32(gain)
    out += np.float32(offset)
    return np.clip(out, 0.0, 1.0, out=out)


def gamma(img: np.ndarray, g: float) -> np.ndarray:
    """Tone curve ``img ** g``, standing in for the unknown camera response curve.

    Parameters
    ----------
    img : (H, W) ndarray
        Grey levels in [0, 1].
    g : float
        Exponent > 0: 1 is the identity, < 1 brightens mid-tones, > 1 darkens them.

    Returns
    -------
    (H, W) ndarray of float32

    Raises
    ------
    ValueError
        If `g` is not positive and finite.
    """
    g = _finite(g, "g")
    _check(g > 0.0, f"gamma exponent must be > 0, got {g}")
    out = np.clip(_as_image(img), 0.0, 1.0)  # negative bases would give NaN
    if g == 1.0:
        return out
    return np.power(out, np.float32(g), out=out)


def lighting_gradient(img: np.ndarray, strength: float, angle: float) -> np.ndarray:
    """Uneven illumination: multiply by a linear ramp falling off in direction `angle`.

    The factor is 1 on the brightest image edge and 1 - strength on the opposite one.
    It only darkens, so white paper does not saturate here; the overall level is set by
    `exposure`. Deterministic, so `Degradation.to_dict` fully describes it.

    Parameters
    ----------
    img : (H, W) ndarray
        Grey levels in [0, 1].
    strength : float
        Darkening at the darkest edge, in [0, 1].
    angle : float
        Direction of the fall-off, radians from +x towards +y.

    Returns
    -------
    (H, W) ndarray of float32

    Raises
    ------
    ValueError
        If `strength` is outside [0, 1] or a value is not finite.
    """
    strength = _finite(strength, "strength")
    angle = _finite(angle, "angle")
    _check(0.0 <= strength <= 1.0, f"strength must be in [0, 1], got {strength}")
    out = _as_image(img)
    if strength == 0.0:
        return out
    h, w = out.shape
    c, s = math.cos(angle), math.sin(angle)
    x, y = _pixel_grid((h, w))
    proj = (x - 0.5 * (w - 1)) * np.float32(c) + (y - 0.5 * (h - 1)) * np.float32(s)
    half = 0.5 * (abs(c) * (w - 1) + abs(s) * (h - 1))  # max |proj| over the image
    p = proj / np.float32(half) if half > 0 else np.zeros_like(proj)  # -1 .. 1
    factor = 1.0 - np.float32(strength) * 0.5 * (1.0 + p)
    out *= factor
    return np.clip(out, 0.0, 1.0, out=out)


def vignette(img: np.ndarray, strength: float) -> np.ndarray:
    """Radial lens fall-off: factor ``1 - strength * (r / r_corner)^2``, centred on the image.

    A quadratic is the leading term of the cos^4 law.

    Parameters
    ----------
    img : (H, W) ndarray
        Grey levels in [0, 1].
    strength : float
        Darkening in the corners, in [0, 1].

    Returns
    -------
    (H, W) ndarray of float32

    Raises
    ------
    ValueError
        If `strength` is outside [0, 1] or not finite.
    """
    strength = _finite(strength, "strength")
    _check(0.0 <= strength <= 1.0, f"strength must be in [0, 1], got {strength}")
    out = _as_image(img)
    if strength == 0.0:
        return out
    h, w = out.shape
    x, y = _pixel_grid((h, w))
    cx, cy = 0.5 * (w - 1), 0.5 * (h - 1)
    r2_corner = cx * cx + cy * cy
    if r2_corner == 0:
        return out
    r2 = (x - np.float32(cx)) ** 2 + (y - np.float32(cy)) ** 2
    out *= 1.0 - np.float32(strength / r2_corner) * r2
    return np.clip(out, 0.0, 1.0, out=out)


def specular_highlight(
    img: np.ndarray,
    centre_xy: tuple[float, float],
    radius_px: float,
    strength: float,
    *,
    aspect: float = 1.0,
    angle: float = 0.0,
) -> np.ndarray:
    """Additive soft glare blob, as off glossy paper, saturating toward white.

    glare = min(strength * G, 1) with G an elliptical Gaussian: sigma `radius_px` along
    direction `angle` and `radius_px * aspect` across it. out = img + (1 - img) * glare,
    so the result never exceeds 1 and, unlike plain addition, a black disc under the
    glare is washed out toward white as on real paper.

    Parameters
    ----------
    img : (H, W) ndarray
        Grey levels in [0, 1].
    centre_xy : tuple of float
        Centre of the blob, pixels (x, y).
    radius_px : float
        Gaussian sigma along `angle`, pixels, > 0.
    strength : float
        Peak glare, >= 0; above 1 widens a fully blown-out core.
    aspect : float, optional
        Sigma across `angle` over sigma along it, in (0, 1].
    angle : float, optional
        Direction of the long axis, radians from +x towards +y.

    Returns
    -------
    (H, W) ndarray of float32

    Raises
    ------
    ValueError
        If a parameter is out of range or not finite.
    """
    cx, cy = (_finite(v, "centre_xy") for v in centre_xy)
    radius_px = _finite(radius_px, "radius_px")
    strength = _finite(strength, "strength")
    aspect = _finite(aspect, "aspect")
    angle = _finite(angle, "angle")
    _check(radius_px > 0.0, f"radius_px must be > 0, got {radius_px}")
    _check(strength >= 0.0, f"strength must be >= 0, got {strength}")
    _check(0.0 < aspect <= 1.0, f"aspect must be in (0, 1], got {aspect}")
    out = np.clip(_as_image(img), 0.0, 1.0)
    if strength == 0.0:
        return out
    x, y = _pixel_grid(out.shape)
    dx, dy = x - np.float32(cx), y - np.float32(cy)
    c, s = np.float32(math.cos(angle)), np.float32(math.sin(angle))
    u = (dx * c + dy * s) / np.float32(radius_px)
    v = (-dx * s + dy * c) / np.float32(radius_px * aspect)
    glare = np.minimum(np.float32(strength) * np.exp(-0.5 * (u * u + v * v)), 1.0)
    out += (1.0 - out) * glare
    return np.clip(out, 0.0, 1.0, out=out)


# --------------------------------------------------------------------------------------
# Sensor
# --------------------------------------------------------------------------------------


def sensor_noise(
    img: np.ndarray, rng: np.random.Generator, read_sigma: float, shot_scale: float
) -> np.ndarray:
    """Poisson shot noise plus Gaussian read noise, clipped to [0, 1].

    Variance at signal level x is read_sigma^2 + shot_scale * x: shot_scale is the
    variance per unit signal, i.e. 1 / (electrons that make white). The shot part is a
    true Poisson draw (signal / shot_scale photo-electrons) because dark frames have few
    electrons per pixel, where a Gaussian approximation is poor.

    Parameters
    ----------
    img : (H, W) ndarray
        Grey levels in [0, 1].
    rng : numpy.random.Generator
        Draws the noise.
    read_sigma : float
        Standard deviation of the read noise, grey levels, >= 0.
    shot_scale : float
        Shot-noise variance per unit signal, >= 0.

    Returns
    -------
    (H, W) ndarray of float32

    Raises
    ------
    ValueError
        If a parameter is negative or not finite.
    """
    read_sigma = _finite(read_sigma, "read_sigma")
    shot_scale = _finite(shot_scale, "shot_scale")
    _check(read_sigma >= 0.0, f"read_sigma must be >= 0, got {read_sigma}")
    _check(shot_scale >= 0.0, f"shot_scale must be >= 0, got {shot_scale}")
    out = np.clip(_as_image(img), 0.0, 1.0)
    if shot_scale >= 1e-7:
        electrons = rng.poisson(out.astype(np.float64) / shot_scale)
        out = (electrons * shot_scale).astype(np.float32)
    elif shot_scale > 0.0:
        # Over ~1e7 electrons Poisson is Gaussian to any precision that matters, and
        # numpy's Poisson sampler refuses such rates.
        noise = rng.normal(0.0, 1.0, size=out.shape) * np.sqrt(out * shot_scale)
        out = (out + noise).astype(np.float32)
    if read_sigma > 0.0:
        out += rng.normal(0.0, read_sigma, size=out.shape).astype(np.float32)
    return np.clip(out, 0.0, 1.0, out=out)


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Quantise grey levels to 8 bits (clip, then round half to even).

    Parameters
    ----------
    img : ndarray
        Grey levels in [0, 1].

    Returns
    -------
    ndarray of uint8
        0..255, same shape.
    """
    a = np.asarray(img, dtype=np.float32)
    return np.rint(np.clip(a, 0.0, 1.0) * np.float32(255.0)).astype(np.uint8)


def jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    """JPEG artefacts: encode with OpenCV and decode again.

    Quantises to 8 bits first, as a real camera pipeline would.

    Parameters
    ----------
    img : (H, W) ndarray
        Grey levels in [0, 1].
    quality : int
        JPEG quality, 1..100.

    Returns
    -------
    (H, W) ndarray of float32
        Grey levels in [0, 1].

    Raises
    ------
    ValueError
        If `quality` is not an integer in 1..100.
    """
    if isinstance(quality, bool) or not float(quality).is_integer():
        raise ValueError(f"quality must be an integer, got {quality!r}")
    q = int(quality)
    _check(1 <= q <= 100, f"quality must be in 1..100, got {q}")
    u8 = to_uint8(_as_image(img))
    ok, buf = cv2.imencode(".jpg", u8, [cv2.IMWRITE_JPEG_QUALITY, q])
    if not ok:  # pragma: no cover - OpenCV only fails on invalid input
        raise RuntimeError("JPEG encoding failed")
    dec = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return dec.astype(np.float32) / np.float32(255.0)


# --------------------------------------------------------------------------------------
# Optics: blur kernels (centred, point-symmetric, normalised)
# --------------------------------------------------------------------------------------


def motion_blur_kernel(length_px: float, angle_rad: float) -> np.ndarray:
    """Normalised (2k+1)^2 float32 kernel of a straight smear `length_px` long.

    The continuous segment from -L/2 to +L/2 through the kernel centre is sampled densely
    (16 samples per pixel of length, symmetric about the centre) and each sample is
    splatted bilinearly. That gives anti-aliased sub-pixel endpoints, so fractional and
    sub-pixel lengths blur by exactly the right amount, and an exactly point-symmetric
    kernel, so the blur never moves a centroid. Second moment along the smear is
    L^2 / 12 (the uniform motion) plus ~1/6 from the pixel footprint of the splat.

    Parameters
    ----------
    length_px : float
        Length of the smear, pixels, >= 0.
    angle_rad : float
        Its direction, radians from +x towards +y.

    Returns
    -------
    (2k + 1, 2k + 1) ndarray of float32
        Sums to 1; k = ceil(length_px / 2) + 1.

    Raises
    ------
    ValueError
        If `length_px` is negative or a value is not finite.
    """
    length = _finite(length_px, "length_px")
    angle = _finite(angle_rad, "angle_rad")
    _check(length >= 0.0, f"length_px must be >= 0, got {length}")
    half = int(math.ceil(0.5 * length)) + 1
    size = 2 * half + 1
    kernel = np.zeros((size, size), dtype=np.float64)
    if length == 0.0:
        kernel[half, half] = 1.0
        return kernel.astype(np.float32)
    n = max(16, int(math.ceil(16 * length)))
    t = ((np.arange(n, dtype=np.float64) + 0.5) / n - 0.5) * length  # symmetric about 0
    xs = half + t * math.cos(angle)
    ys = half + t * math.sin(angle)
    x0 = np.floor(xs).astype(np.int64)
    y0 = np.floor(ys).astype(np.int64)
    fx, fy = xs - x0, ys - y0
    for dy, wy in ((0, 1.0 - fy), (1, fy)):
        for dx, wx in ((0, 1.0 - fx), (1, fx)):
            np.add.at(kernel, (y0 + dy, x0 + dx), wx * wy)
    kernel /= kernel.sum()
    return kernel.astype(np.float32)


def defocus_kernel(radius_px: float) -> np.ndarray:
    """Normalised anti-aliased pillbox (uniform disc of radius `radius_px`), centred.

    Each kernel pixel holds its area coverage by the disc, from a 16 x 16 grid of
    sub-samples placed symmetrically, so the kernel is exactly point-symmetric. Radii
    below ~0.5 px fit inside the centre pixel and give (nearly) the identity: a blur
    circle smaller than a pixel does not blur.

    Parameters
    ----------
    radius_px : float
        Radius of the blur circle, pixels, >= 0.

    Returns
    -------
    (2k + 1, 2k + 1) ndarray of float32
        Sums to 1; k = ceil(radius_px) + 1.

    Raises
    ------
    ValueError
        If `radius_px` is negative or not finite.
    """
    r = _finite(radius_px, "radius_px")
    _check(r >= 0.0, f"radius_px must be >= 0, got {r}")
    half = int(math.ceil(r)) + 1
    size = 2 * half + 1
    if r < 1.0 / 32:  # smaller than the sub-sample spacing: no sample falls inside

        kernel = np.zeros((size, size), dtype=np.float32)
        kernel[half, half] = 1.0
        return kernel
    ss = 16
    sub = (np.arange(ss, dtype=np.float64) + 0.5) / ss - 0.5  # symmetric sub-offsets
    coords = (np.arange(size, dtype=np.float64)[:, None] - half + sub[None, :]).ravel()
    inside = (coords[:, None] ** 2 + coords[None, :] ** 2) <= r * r  # (size*ss)^2
    kernel = inside.reshape(size, ss, size, ss).mean(axis=(1, 3))
    if kernel.sum() == 0.0:  # the blur circle missed every sub-sample: no blur
        kernel[half, half] = 1.0
    kernel /= kernel.sum()
    return kernel.astype(np.float32)


def _filter(img: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    # Odd-sized kernel, default anchor = its centre: no shift. filter2D correlates, which
    # equals convolution here because the kernels are point-symmetric. REFLECT keeps the
    # image mean at the borders (no dark frame from zero padding).
    return cv2.filter2D(img, cv2.CV_32F, kernel, borderType=cv2.BORDER_REFLECT)


def motion_blur(img: np.ndarray, length_px: float, angle_rad: float) -> np.ndarray:
    """Linear motion blur, centred (it moves no centroid).

    Parameters
    ----------
    img : (H, W) ndarray
        Grey levels.
    length_px : float
        Length of the smear, pixels.
    angle_rad : float
        Its direction, radians from +x towards +y.

    Returns
    -------
    (H, W) ndarray of float32
    """
    out = _as_image(img)
    if float(length_px) == 0.0:
        _finite(angle_rad, "angle_rad")
        return out
    return _filter(out, motion_blur_kernel(length_px, angle_rad))


def defocus(img: np.ndarray, radius_px: float) -> np.ndarray:
    """Out-of-focus blur: convolution with an anti-aliased pillbox (`defocus_kernel`).

    Parameters
    ----------
    img : (H, W) ndarray
        Grey levels.
    radius_px : float
        Radius of the blur circle, pixels.

    Returns
    -------
    (H, W) ndarray of float32
    """
    out = _as_image(img)
    if float(radius_px) == 0.0:
        return out
    return _filter(out, defocus_kernel(radius_px))


@dataclass(frozen=True)
class ThinLens:
    """A lens's depth of field: the thin-lens blur of what is nearer or farther than the
    focus.

    A point at depth ``d`` (along the optical axis) images as a disc of diameter
    ``(f / N) * f * |d - s| / (d * (s - f))`` on the sensor (focal length ``f``, f-number
    ``N``, focus distance ``s``); in pixels, times ``focal_px / f``.

    Attributes
    ----------
    focal_length_mm : float
        The lens's real focal length (a phone's main camera: about 4-7 mm; a 35 mm lens
        on a cinema camera's Super 35 sensor gives 640 px across at f 820 px).
    f_number : float
        Its aperture, f / N.
    focus_m : float
        The distance it is focused at, metres.
    """

    focal_length_mm: float
    f_number: float
    focus_m: float

    def __post_init__(self) -> None:
        for name in ("focal_length_mm", "f_number", "focus_m"):
            _check(math.isfinite(getattr(self, name)) and getattr(self, name) > 0, f"{name} must be positive")
        _check(self.focus_m * 1000.0 > self.focal_length_mm, "the focus must be beyond the focal length")

    def blur_radius_px(self, depth_m: np.ndarray, focal_px: float) -> np.ndarray:
        """The radius of the blur circle of points at these depths, pixels.

        Parameters
        ----------
        depth_m : ndarray
            Depths along the optical axis, metres (positive).
        focal_px : float
            The camera's focal length in pixels.

        Returns
        -------
        ndarray
            Same shape as `depth_m`.
        """
        f = self.focal_length_mm / 1000.0
        d = np.maximum(np.asarray(depth_m, np.float64), f * 1.001)
        return 0.5 * (focal_px / self.f_number) * np.abs(d - self.focus_m) / (d * (self.focus_m - f)) * f


def depth_defocus(img: np.ndarray, depth_m: np.ndarray, lens: ThinLens, focal_px: float,
                  levels: int = 8) -> np.ndarray:
    """Out-of-focus blur that follows each pixel's depth (`ThinLens`).

    The image is blurred with ``levels`` pillboxes from no blur to the largest radius
    in it, and each pixel takes the two levels around its own radius, linearly. A blur
    that varies across a tilted card moves its discs' centroids as a real lens does;
    the edges between near and far surfaces are not modelled (a box room's walls and
    the cards on them have none).

    Parameters
    ----------
    img : (H, W) ndarray
        Grey levels.
    depth_m : (H, W) ndarray
        Each pixel's depth along the optical axis, metres.
    lens : ThinLens
    focal_px : float
        The camera's focal length, pixels.
    levels : int, optional
        Blur levels (at least 2).

    Returns
    -------
    (H, W) ndarray of float32
    """
    out = _as_image(img)
    _check(depth_m.shape == out.shape, f"depth map {depth_m.shape} does not match the image {out.shape}")
    _check(levels >= 2, "levels must be at least 2")
    radius = lens.blur_radius_px(depth_m, focal_px)
    largest = float(radius.max())
    if largest < 0.05:
        return out
    position = radius / largest * (levels - 1)
    low = np.minimum(np.floor(position).astype(int), levels - 2)
    weight = (position - low).astype(np.float32)
    blurred = np.stack([defocus(out, r) for r in np.linspace(0.0, largest, levels)])
    rows, cols = np.indices(out.shape)
    return (1.0 - weight) * blurred[low, rows, cols] + weight * blurred[low + 1, rows, cols]


# --------------------------------------------------------------------------------------
# Occlusion
# --------------------------------------------------------------------------------------


def polygon_coverage(
    shape: tuple[int, int], polygon_xy: np.ndarray, supersample: int = 8
) -> np.ndarray:
    """Fraction of each pixel covered by a polygon (even-odd rule), float32 (H, W).

    Exact along x (each scan line's inside spans are intersected with the pixel columns
    analytically) and `supersample` scan lines per pixel row in y. Unlike cv2.fillPoly,
    which includes every sub-pixel an edge touches (a few % too much area on small
    shapes), this is unbiased: the mask sums to the polygon's area inside the image.

    Parameters
    ----------
    shape : tuple of int
        (H, W) of the mask.
    polygon_xy : (N, 2) ndarray
        Vertices in pixel coordinates (x, y), N >= 3.
    supersample : int, optional
        Scan lines per pixel row.

    Returns
    -------
    (H, W) ndarray of float32
        Coverage in [0, 1].

    Raises
    ------
    ValueError
        If the polygon is not finite (N >= 3, 2) or `supersample` < 1.
    """
    h, w = (int(v) for v in shape)
    poly = np.asarray(polygon_xy, dtype=np.float64)
    _check(poly.ndim == 2 and poly.shape[1] == 2 and poly.shape[0] >= 3,
           f"polygon_xy must have shape (N >= 3, 2), got {poly.shape}")
    _check(bool(np.isfinite(poly).all()), "polygon_xy must be finite")
    _check(supersample >= 1, "supersample must be >= 1")
    mask = np.zeros((h, w), dtype=np.float32)
    # Pixel-edge coordinates: column j spans [j, j + 1], row i spans [i, i + 1].
    px, py = poly[:, 0] + 0.5, poly[:, 1] + 0.5
    r0 = max(int(math.floor(py.min())), 0)
    r1 = min(int(math.ceil(py.max())), h)
    c0 = max(int(math.floor(px.min())), 0)
    c1 = min(int(math.ceil(px.max())), w)
    if r0 >= r1 or c0 >= c1:
        return mask
    ss = int(supersample)
    ys = (np.arange(r0 * ss, r1 * ss, dtype=np.float64) + 0.5) / ss  # scan lines (R,)
    xa, ya = px, py
    xb, yb = np.roll(px, -1), np.roll(py, -1)
    # Half-open rule so that a vertex on a scan line is counted once.
    crosses = ((ya[None, :] <= ys[:, None]) & (ys[:, None] < yb[None, :])) | (
        (yb[None, :] <= ys[:, None]) & (ys[:, None] < ya[None, :])
    )  # (R, E)
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = xa[None, :] + (ys[:, None] - ya[None, :]) * ((xb - xa) / (yb - ya))[None, :]
    xcross = np.sort(np.where(crosses, tx, np.inf), axis=1)  # inf (no crossing) last
    # Even-odd: inside between crossings 0-1, 2-3, ... A row's count is always even,
    # so unused slots pair inf with inf and contribute nothing.
    n_pairs = xcross.shape[1] // 2
    lo = xcross[:, 0 : 2 * n_pairs : 2]
    hi = xcross[:, 1 : 2 * n_pairs : 2]
    lo = np.where(np.isfinite(lo), lo, 0.0)
    hi = np.where(np.isfinite(hi), hi, 0.0)
    # Column coverage of [lo, hi] is G(hi) - G(lo) with G(x)_j = clip(x - j, 0, 1); G is
    # a step with one fractional column, so it is accumulated as a difference array and
    # integrated with one cumsum: memory O(rows x columns) however many edges there are.
    n_cols = c1 - c0
    diff = np.zeros((ys.size, n_cols + 2), dtype=np.float64)
    rows = np.broadcast_to(np.arange(ys.size)[:, None], lo.shape)
    for x, sign in ((hi, 1.0), (lo, -1.0)):
        xr = np.clip(x - c0, 0.0, float(n_cols))
        f = np.floor(xr)
        frac = xr - f
        fi = f.astype(np.int64)
        np.add.at(diff, (rows, fi), sign * (frac - 1.0))
        np.add.at(diff, (rows, fi + 1), -sign * frac)
    overlap = np.cumsum(diff[:, :n_cols], axis=1)  # (R, C); the +1 at column 0 cancels
    cover = overlap.reshape(r1 - r0, ss, c1 - c0).mean(axis=1)
    mask[r0:r1, c0:c1] = np.clip(cover, 0.0, 1.0)
    return mask


def occlude(
    img: np.ndarray, polygon_xy: np.ndarray, value_or_texture: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Cover a polygon (pixel coordinates, (N, 2) x/y) with a constant or a texture.

    `value_or_texture` is a grey level, an image of the same shape as `img`, or a smaller
    2-D patch tiled from the polygon's bounding-box corner (so the texture moves with
    the occluder). Edges are anti-aliased by area coverage.

    Parameters
    ----------
    img : (H, W) ndarray
        Grey levels in [0, 1].
    polygon_xy : (N, 2) ndarray
        The occluder's vertices, pixels (x, y).
    value_or_texture : float or ndarray
        What covers the polygon.

    Returns
    -------
    image : (H, W) ndarray of float32
        The occluded image.
    mask : (H, W) ndarray of float32
        Coverage in [0, 1], for ground truth (which discs are hidden).

    Raises
    ------
    ValueError
        If `value_or_texture` is neither a number nor a 2-D array.
    """
    out = _as_image(img)
    mask = polygon_coverage(out.shape, polygon_xy)
    tex_in = np.asarray(value_or_texture, dtype=np.float32)
    if tex_in.ndim == 0:
        fill: np.ndarray | np.float32 = np.float32(tex_in)
    elif tex_in.ndim == 2 and tex_in.shape == out.shape:
        fill = tex_in
    elif tex_in.ndim == 2 and tex_in.size > 0:
        poly = np.asarray(polygon_xy, dtype=np.float64)
        ox = int(math.floor(poly[:, 0].min() + 0.5))
        oy = int(math.floor(poly[:, 1].min() + 0.5))
        th, tw = tex_in.shape
        h, w = out.shape
        rows = (np.arange(h) - oy) % th
        cols = (np.arange(w) - ox) % tw
        fill = tex_in[rows[:, None], cols[None, :]]
    else:
        raise ValueError(
            f"value_or_texture must be a number or a 2-D array, got shape {tex_in.shape}"
        )
    out = out * (1.0 - mask) + fill * mask
    return np.clip(out, 0.0, 1.0).astype(np.float32), mask


# --------------------------------------------------------------------------------------
# One sampled degradation
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Specular:
    """A glare blob in image-relative units, so a sampled one fits any resolution.

    Attributes
    ----------
    centre_rel : tuple of float
        (x, y) as fractions of (width - 1, height - 1).
    radius_rel : float
        Gaussian sigma as a fraction of min(height, width), > 0.
    strength : float
        Peak glare, >= 0.
    aspect, angle : float
        As in `specular_highlight` (angle in radians).
    """

    centre_rel: tuple[float, float]
    radius_rel: float
    strength: float
    aspect: float = 1.0
    angle: float = 0.0

    def __post_init__(self) -> None:
        cx, cy = (float(v) for v in self.centre_rel)
        object.__setattr__(self, "centre_rel", (cx, cy))
        for name in ("radius_rel", "strength", "aspect", "angle"):
            object.__setattr__(self, name, _finite(getattr(self, name), name))
        _check(self.radius_rel > 0.0, "specular radius_rel must be > 0")
        _check(self.strength >= 0.0, "specular strength must be >= 0")
        _check(0.0 < self.aspect <= 1.0, "specular aspect must be in (0, 1]")

    def in_pixels(self, shape: tuple[int, int]) -> tuple[tuple[float, float], float]:
        """The blob in pixels for an image of a given size.

        Parameters
        ----------
        shape : tuple of int
            (H, W) of the image.

        Returns
        -------
        centre : tuple of float
            (x, y), pixels.
        sigma : float
            Pixels.
        """
        h, w = shape
        centre = (self.centre_rel[0] * (w - 1), self.centre_rel[1] * (h - 1))
        return centre, self.radius_rel * min(h, w)

    def apply(self, img: np.ndarray) -> np.ndarray:
        """Add the glare to an image (`specular_highlight`).

        Parameters
        ----------
        img : (H, W) ndarray
            Grey levels in [0, 1].

        Returns
        -------
        (H, W) ndarray of float32
        """
        centre, radius = self.in_pixels(np.shape(img))
        return specular_highlight(
            img, centre, radius, self.strength, aspect=self.aspect, angle=self.angle
        )


@dataclass(frozen=True)
class Degradation:
    """One sampled set of camera degradations; the defaults are the identity.

    Each field is the parameter of the function of the same stage: `exposure` (gain,
    offset), `lighting_gradient` (gradient_strength, gradient_angle), `vignette`,
    `gamma`, `sensor_noise` (read_sigma, shot_scale), `motion_blur` (blur_length,
    blur_angle), `defocus` (defocus_radius), `jpeg` (jpeg_quality, None: no JPEG) and
    `Specular` (None: no glare). Lengths in pixels, angles in radians.

    Raises
    ------
    ValueError
        If a parameter is out of its function's range.
    """

    gain: float = 1.0
    offset: float = 0.0
    gradient_strength: float = 0.0
    gradient_angle: float = 0.0
    vignette: float = 0.0
    gamma: float = 1.0
    read_sigma: float = 0.0
    shot_scale: float = 0.0
    blur_length: float = 0.0
    blur_angle: float = 0.0
    defocus_radius: float = 0.0
    jpeg_quality: int | None = None
    specular: Specular | None = None

    _FLOATS: ClassVar[tuple[str, ...]] = (
        "gain", "offset", "gradient_strength", "gradient_angle", "vignette", "gamma",
        "read_sigma", "shot_scale", "blur_length", "blur_angle", "defocus_radius",
    )  # fmt: skip

    def __post_init__(self) -> None:
        # Coerce numpy scalars to plain Python types so to_dict() is json.dumps-able and
        # equality/hashing behave; validate early so a bad sample fails where it is made.
        for name in self._FLOATS:
            object.__setattr__(self, name, _finite(getattr(self, name), name))
        _check(self.gain >= 0.0, "gain must be >= 0")
        _check(0.0 <= self.gradient_strength <= 1.0, "gradient_strength must be in [0, 1]")
        _check(0.0 <= self.vignette <= 1.0, "vignette must be in [0, 1]")
        _check(self.gamma > 0.0, "gamma must be > 0")
        for name in ("read_sigma", "shot_scale", "blur_length", "defocus_radius"):
            _check(getattr(self, name) >= 0.0, f"{name} must be >= 0")
        if self.jpeg_quality is not None:
            q = self.jpeg_quality
            _check(not isinstance(q, bool) and float(q).is_integer() and 1 <= q <= 100,
                   f"jpeg_quality must be None or an integer in 1..100, got {q!r}")
            object.__setattr__(self, "jpeg_quality", int(q))
        if isinstance(self.specular, Mapping):
            object.__setattr__(self, "specular", Specular(**self.specular))
        _check(self.specular is None or isinstance(self.specular, Specular),
               "specular must be None or a Specular")

    def apply(self, img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Apply in the order light meets the camera, skipping identity steps.

        Optics first (defocus, then motion blur: both act on the rendered geometry, and
        both are centroid-preserving), then illumination (lighting gradient, vignette,
        specular glare, exposure: smooth fields that nearly commute with the blur), then
        the sensor (noise on the exposed signal, then the tone curve), JPEG last as the
        camera's output.

        Parameters
        ----------
        img : (H, W) ndarray
            The rendered image, grey levels in [0, 1].
        rng : numpy.random.Generator
            Drawn from for the sensor noise only.

        Returns
        -------
        (H, W) ndarray of float32
            Grey levels in [0, 1].
        """
        out = np.clip(_as_image(img), 0.0, 1.0)
        if self.defocus_radius > 0.0:
            out = defocus(out, self.defocus_radius)
        if self.blur_length > 0.0:
            out = motion_blur(out, self.blur_length, self.blur_angle)
        if self.gradient_strength > 0.0:
            out = lighting_gradient(out, self.gradient_strength, self.gradient_angle)
        if self.vignette > 0.0:
            out = vignette(out, self.vignette)
        if self.specular is not None and self.specular.strength > 0.0:
            out = self.specular.apply(out)
        if self.gain != 1.0 or self.offset != 0.0:
            out = exposure(out, self.gain, self.offset)
        if self.read_sigma > 0.0 or self.shot_scale > 0.0:
            out = sensor_noise(out, rng, self.read_sigma, self.shot_scale)
        if self.gamma != 1.0:
            out = gamma(out, self.gamma)
        if self.jpeg_quality is not None:
            out = jpeg(out, self.jpeg_quality)
        return np.clip(out, 0.0, 1.0).astype(np.float32, copy=False)

    def to_dict(self) -> dict[str, Any]:
        """The parameters as a plain JSON-able dict for ground-truth files.

        Returns
        -------
        dict
            One key per field; round-trips through `from_dict`.
        """
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        if self.specular is not None:
            sp = dataclasses.asdict(self.specular)
            sp["centre_rel"] = list(self.specular.centre_rel)
            d["specular"] = sp
        return d

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Degradation:
        """The degradation of a `to_dict` document.

        Parameters
        ----------
        data : mapping
            Field names to values.

        Returns
        -------
        Degradation
        """
        spec = data.get("specular")
        kwargs = {k: v for k, v in data.items() if k != "specular"}
        return cls(**kwargs, specular=None if spec is None else Specular(**spec))


# --------------------------------------------------------------------------------------
# Distributions and presets
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DegradationRanges:
    """(lo, hi) ranges for every parameter and probabilities for the optional ones.

    gain and gamma are drawn log-uniformly (exposure works in stops and a tone-curve
    exponent of 0.8 is as far from 1 as 1.25); everything else uniformly. Gradient
    angle is uniform over a full turn and blur angle over `blur_angle` (a smear is
    symmetric, so [0, pi) covers every direction). The defaults are the identity.

    Each ``(lo, hi)`` field is the range of the `Degradation` field of the same name
    and each ``p_*`` the probability that an optional stage is on; the ``specular_*``
    ranges are those of `Specular`.

    Raises
    ------
    ValueError
        If a range is reversed or outside its parameter's domain, or a probability is
        outside [0, 1].
    """

    gain: Range = (1.0, 1.0)
    offset: Range = (0.0, 0.0)
    p_gradient: float = 0.0
    gradient_strength: Range = (0.0, 0.0)
    p_vignette: float = 0.0
    vignette: Range = (0.0, 0.0)
    gamma: Range = (1.0, 1.0)
    read_sigma: Range = (0.0, 0.0)
    shot_scale: Range = (0.0, 0.0)
    p_blur: float = 0.0
    blur_length: Range = (0.0, 0.0)
    blur_angle: Range = (0.0, math.pi)
    p_defocus: float = 0.0
    defocus_radius: Range = (0.0, 0.0)
    p_jpeg: float = 0.0
    jpeg_quality: tuple[int, int] = (95, 95)
    p_specular: float = 0.0
    specular_strength: Range = (0.5, 1.0)
    specular_radius_rel: Range = (0.05, 0.2)
    specular_aspect: Range = (0.3, 1.0)

    # Presets, filled in below the class (see also PRESETS).
    NONE: ClassVar[DegradationRanges]
    DEFAULT: ClassVar[DegradationRanges]
    BLUR: ClassVar[DegradationRanges]
    DARK: ClassVar[DegradationRanges]
    BRIGHT: ClassVar[DegradationRanges]
    FULL: ClassVar[DegradationRanges]

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name.startswith("p_"):
                p = _finite(value, f.name)
                _check(0.0 <= p <= 1.0, f"{f.name} must be in [0, 1], got {value!r}")
                object.__setattr__(self, f.name, p)
                continue
            lo, hi = (_finite(v, f.name) for v in value)
            _check(lo <= hi, f"{f.name}: lo must be <= hi, got {value!r}")
            if f.name == "jpeg_quality":
                _check(lo.is_integer() and hi.is_integer() and 1 <= lo and hi <= 100,
                       f"jpeg_quality must be integers in 1..100, got {value!r}")
                object.__setattr__(self, f.name, (int(lo), int(hi)))
            else:
                object.__setattr__(self, f.name, (lo, hi))
        _check(self.gain[0] > 0.0, "gain range must be > 0 (log-uniform)")
        _check(self.gamma[0] > 0.0, "gamma range must be > 0 (log-uniform)")
        _check(self.offset[0] >= -1.0 and self.offset[1] <= 1.0, "offset must be in [-1, 1]")
        _check(0.0 <= self.gradient_strength[0] and self.gradient_strength[1] <= 1.0,
               "gradient_strength must be in [0, 1]")
        _check(0.0 <= self.vignette[0] and self.vignette[1] <= 1.0,
               "vignette must be in [0, 1]")
        for name in ("read_sigma", "shot_scale", "blur_length", "defocus_radius",
                     "specular_strength"):
            _check(getattr(self, name)[0] >= 0.0, f"{name} must be >= 0")
        _check(self.specular_radius_rel[0] > 0.0, "specular_radius_rel must be > 0")
        _check(0.0 < self.specular_aspect[0] and self.specular_aspect[1] <= 1.0,
               "specular_aspect must be in (0, 1]")

    @classmethod
    def preset(cls, name: str) -> DegradationRanges:
        """A named preset.

        Parameters
        ----------
        name : {"none", "default", "blur", "dark", "bright", "full"}

        Returns
        -------
        DegradationRanges

        Raises
        ------
        KeyError
            If there is no preset of that name.
        """
        try:
            return PRESETS[name]
        except KeyError:
            raise KeyError(f"unknown preset {name!r}; known: {', '.join(PRESETS)}") from None

    def sample(self, rng: np.random.Generator) -> Degradation:
        """Draw one Degradation; deterministic for a given Generator state.

        Every value is drawn every time, in a fixed order, whether or not its option is
        switched on, so the stream (and hence the other parameters) does not depend on
        the probabilities.

        Parameters
        ----------
        rng : numpy.random.Generator

        Returns
        -------
        Degradation
        """

        def uni(r: Range) -> float:
            return float(rng.uniform(r[0], r[1]))

        def log_uni(r: Range) -> float:
            v = math.exp(rng.uniform(math.log(r[0]), math.log(r[1])))
            return float(min(max(v, r[0]), r[1]))  # exp(log(x)) may be off by an ulp

        def on(p: float) -> bool:
            return bool(rng.random() < p)

        gain = log_uni(self.gain)
        offset = uni(self.offset)
        use_gradient = on(self.p_gradient)
        gradient_strength = uni(self.gradient_strength)
        gradient_angle = float(rng.uniform(0.0, 2.0 * math.pi))
        use_vignette = on(self.p_vignette)
        vig = uni(self.vignette)
        g = log_uni(self.gamma)
        read_sigma = uni(self.read_sigma)
        shot_scale = uni(self.shot_scale)
        use_blur = on(self.p_blur)
        blur_length = uni(self.blur_length)
        blur_angle = uni(self.blur_angle)
        use_defocus = on(self.p_defocus)
        defocus_radius = uni(self.defocus_radius)
        use_jpeg = on(self.p_jpeg)
        quality = int(rng.integers(self.jpeg_quality[0], self.jpeg_quality[1] + 1))
        use_specular = on(self.p_specular)
        centre = (float(rng.random()), float(rng.random()))
        sp_radius = uni(self.specular_radius_rel)
        sp_strength = uni(self.specular_strength)
        sp_aspect = uni(self.specular_aspect)
        sp_angle = float(rng.uniform(0.0, math.pi))

        return Degradation(
            gain=gain,
            offset=offset,
            gradient_strength=gradient_strength if use_gradient else 0.0,
            gradient_angle=gradient_angle if use_gradient else 0.0,
            vignette=vig if use_vignette else 0.0,
            gamma=g,
            read_sigma=read_sigma,
            shot_scale=shot_scale,
            blur_length=blur_length if use_blur else 0.0,
            blur_angle=blur_angle if use_blur else 0.0,
            defocus_radius=defocus_radius if use_defocus else 0.0,
            jpeg_quality=quality if use_jpeg else None,
            specular=(
                Specular(centre, sp_radius, sp_strength, sp_aspect, sp_angle)
                if use_specular and sp_strength > 0.0
                else None
            ),
        )


#: Identity: sample() always returns Degradation() and apply() returns the input.
NONE = DegradationRanges()

#: Mild, everyday conditions: a decent camera indoors.
DEFAULT = DegradationRanges(
    gain=(0.7, 1.2),
    offset=(-0.02, 0.03),
    p_gradient=0.5,
    gradient_strength=(0.0, 0.3),
    p_vignette=0.5,
    vignette=(0.0, 0.2),
    gamma=(0.9, 1.1),
    read_sigma=(0.002, 0.01),
    shot_scale=(0.0, 2e-4),
    p_blur=0.5,
    blur_length=(0.0, 2.0),
    p_defocus=0.3,
    defocus_radius=(0.0, 1.0),
    p_jpeg=0.5,
    jpeg_quality=(80, 95),
)

#: Fast camera motion: a 5-12 px smear in any direction, nothing else.
BLUR = DegradationRanges(p_blur=1.0, blur_length=(5.0, 12.0))

#: Low light: 0.06-0.2 of normal exposure with read and shot noise.
DARK = DegradationRanges(
    gain=(0.06, 0.2),
    read_sigma=(0.005, 0.02),
    shot_scale=(2e-4, 1e-3),
)

#: Bright light: 1.5-2.5 times normal exposure, so the card's white paper (and lit walls)
#: clip at the sensor's full scale, with a little read noise.
BRIGHT = DegradationRanges(
    gain=(1.5, 2.5),
    read_sigma=(0.002, 0.008),
)

#: Everything, for training: the whole range of every parameter.
FULL = DegradationRanges(
    gain=(0.06, 2.0),
    offset=(-0.05, 0.1),
    p_gradient=0.5,
    gradient_strength=(0.0, 0.7),
    p_vignette=0.4,
    vignette=(0.0, 0.5),
    gamma=(0.6, 1.6),
    read_sigma=(0.0, 0.03),
    shot_scale=(0.0, 2e-3),
    p_blur=0.4,
    blur_length=(0.0, 12.0),
    p_defocus=0.3,
    defocus_radius=(0.0, 4.0),
    p_jpeg=0.5,
    jpeg_quality=(30, 95),
    p_specular=0.25,
    specular_strength=(0.3, 1.5),
    specular_radius_rel=(0.03, 0.25),
    specular_aspect=(0.3, 1.0),
)

DegradationRanges.NONE = NONE
DegradationRanges.DEFAULT = DEFAULT
DegradationRanges.BLUR = BLUR
DegradationRanges.DARK = DARK
DegradationRanges.BRIGHT = BRIGHT
DegradationRanges.FULL = FULL

#: The named presets, by name.
PRESETS: dict[str, DegradationRanges] = {
    "none": NONE,
    "default": DEFAULT,
    "blur": BLUR,
    "dark": DARK,
    "bright": BRIGHT,
    "full": FULL,
}
