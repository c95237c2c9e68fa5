"""Camera degradations: geometry preserved by blur, photometric behaviour, presets."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from app.sim.degrade import (
    PRESETS,
    Degradation,
    DegradationRanges,
    Specular,
    ThinLens,
    defocus,
    defocus_kernel,
    depth_defocus,
    exposure,
    gamma,
    jpeg,
    lighting_gradient,
    motion_blur,
    motion_blur_kernel,
    occlude,
    polygon_coverage,
    sensor_noise,
    specular_highlight,
    to_uint8,
    vignette,
)

# --------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------


def render_disc(shape: tuple[int, int], cx: float, cy: float, r: float, ss: int = 16) -> np.ndarray:
    """Black disc on white, grey level = 1 - area coverage from ss x ss supersampling.

    Pixel centres at integer coordinates (pixel j spans [j - 0.5, j + 0.5]).
    """
    h, w = shape
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    xs = (np.arange(w)[:, None] + sub[None, :]).ravel()
    ys = (np.arange(h)[:, None] + sub[None, :]).ravel()
    inside = ((xs[None, :] - cx) ** 2 + (ys[:, None] - cy) ** 2) <= r * r
    cover = inside.reshape(h, ss, w, ss).mean(axis=(1, 3))
    return (1.0 - cover).astype(np.float32)


def dark_centroid(img: np.ndarray) -> tuple[float, float]:
    """Centroid weighted by darkness (1 - grey level)."""
    wgt = 1.0 - img.astype(np.float64)
    ys, xs = np.indices(img.shape)
    s = wgt.sum()
    return float((wgt * xs).sum() / s), float((wgt * ys).sum() / s)


def second_moments(img: np.ndarray) -> tuple[float, float, float]:
    """(var_major, var_minor, angle of the major axis in [0, pi)) of a non-negative image."""
    wgt = img.astype(np.float64) / img.sum()
    ys, xs = np.indices(img.shape)
    mx, my = (wgt * xs).sum(), (wgt * ys).sum()
    cxx = (wgt * (xs - mx) ** 2).sum()
    cyy = (wgt * (ys - my) ** 2).sum()
    cxy = (wgt * (xs - mx) * (ys - my)).sum()
    evals, evecs = np.linalg.eigh(np.array([[cxx, cxy], [cxy, cyy]]))
    major = evecs[:, 1]
    return float(evals[1]), float(evals[0]), float(math.atan2(major[1], major[0]) % math.pi)


def angle_diff(a: float, b: float) -> float:
    """Distance between two undirected angles (mod pi)."""
    d = (a - b) % math.pi
    return min(d, math.pi - d)


DISC = dict(cx=40.37, cy=37.71, r=9.3)


@pytest.fixture(scope="module")
def disc_img() -> np.ndarray:
    return render_disc((80, 84), DISC["cx"], DISC["cy"], DISC["r"])


# --------------------------------------------------------------------------------------
# Blur: geometry preserved
# --------------------------------------------------------------------------------------


def test_rendered_disc_centroid_is_its_centre(disc_img: np.ndarray) -> None:
    cx, cy = dark_centroid(disc_img)
    assert abs(cx - DISC["cx"]) < 0.01 and abs(cy - DISC["cy"]) < 0.01


@pytest.mark.parametrize(
    ("length", "angle"),
    [(0.4, 0.0), (1.0, 0.3), (2.5, 1.0), (5.0, 0.0), (7.3, math.pi / 4), (12.0, 2.2), (9.7, -0.7)],
)
def test_motion_blur_preserves_centroid_and_mean(disc_img, length, angle) -> None:
    out = motion_blur(disc_img, length, angle)
    assert out.dtype == np.float32 and out.shape == disc_img.shape
    c0, c1 = dark_centroid(disc_img), dark_centroid(out)
    assert abs(c1[0] - c0[0]) < 0.02 and abs(c1[1] - c0[1]) < 0.02
    assert abs(c1[0] - DISC["cx"]) < 0.02 and abs(c1[1] - DISC["cy"]) < 0.02
    assert abs(float(out.mean()) - float(disc_img.mean())) < 1e-4
    assert not np.allclose(out, disc_img)


@pytest.mark.parametrize("radius", [0.7, 1.5, 3.2, 6.0])
def test_defocus_preserves_centroid_and_mean(disc_img, radius) -> None:
    out = defocus(disc_img, radius)
    c0, c1 = dark_centroid(disc_img), dark_centroid(out)
    assert abs(c1[0] - c0[0]) < 0.02 and abs(c1[1] - c0[1]) < 0.02
    assert abs(float(out.mean()) - float(disc_img.mean())) < 1e-4
    assert not np.allclose(out, disc_img)


@pytest.mark.parametrize(
    ("length", "angle"), [(5.0, 0.0), (9.0, 0.6), (12.0, 2.0), (6.5, math.pi / 2)]
)
def test_motion_blur_of_a_point_spreads_along_angle_with_length(length, angle) -> None:
    img = np.zeros((61, 61), dtype=np.float32)
    img[30, 30] = 1.0
    out = motion_blur(img, length, angle)
    assert abs(float(out.sum()) - 1.0) < 1e-4
    var_major, var_minor, theta = second_moments(out)
    assert angle_diff(theta, angle) < math.radians(1.0)
    # A uniform smear of length L has variance L^2 / 12 along the line. The bilinear
    # splat (= averaging bilinearly shifted copies) adds at most 1/6 px^2 per axis:
    # 1/6 along and across a diagonal line, 1/6 along and 0 across an axis-aligned one.
    assert -1e-3 < var_minor < 1 / 6 + 1e-2
    assert -1e-3 < var_major - length**2 / 12 < 1 / 6 + 1e-2
    assert abs(math.sqrt(12.0 * var_major) - length) < 0.2


def test_motion_blur_fractional_lengths_interpolate() -> None:
    vars_ = [second_moments(motion_blur_kernel(L, 0.4))[0] for L in (3.0, 3.25, 3.5, 3.75, 4.0)]
    assert all(b > a for a, b in zip(vars_, vars_[1:]))


@pytest.mark.parametrize("length", [0.0, 0.3, 2.0, 7.7])
def test_blur_kernels_are_centred_symmetric_normalised(length) -> None:
    for k in (motion_blur_kernel(length, 0.9), defocus_kernel(length)):
        assert k.shape[0] == k.shape[1] and k.shape[0] % 2 == 1
        assert abs(float(k.sum()) - 1.0) < 1e-6
        np.testing.assert_allclose(k, k[::-1, ::-1], atol=1e-7)  # point symmetry
        assert (k >= 0).all()


def test_defocus_kernel_area_and_isotropy() -> None:
    k = defocus_kernel(4.0)
    var_major, var_minor, _ = second_moments(k)
    assert abs(var_major - var_minor) < 0.02
    assert abs(var_major - (4.0**2 / 4 + 1 / 12)) < 0.1  # disc r^2/4 plus pixel box


def test_zero_blur_is_identity(disc_img) -> None:
    np.testing.assert_array_equal(motion_blur(disc_img, 0.0, 1.0), disc_img)
    np.testing.assert_array_equal(defocus(disc_img, 0.0), disc_img)


# --------------------------------------------------------------------------------------
# Photometric
# --------------------------------------------------------------------------------------


def test_exposure_and_gamma_monotonic() -> None:
    ramp = np.linspace(0.0, 1.0, 256, dtype=np.float32)[None, :].repeat(4, axis=0)
    for gain, offset in [(0.06, 0.0), (0.2, 0.01), (1.0, 0.0), (2.0, -0.05)]:
        out = exposure(ramp, gain, offset)
        assert (np.diff(out, axis=1) >= 0).all()
        assert out.min() >= 0 and out.max() <= 1
    np.testing.assert_allclose(exposure(ramp, 0.1)[0, -1], 0.1, atol=1e-6)
    assert exposure(ramp, 2.0)[0, 200] == 1.0  # saturates
    for g in (0.5, 0.8, 1.0, 1.6, 2.2):
        out = gamma(ramp, g)
        assert (np.diff(out, axis=1) >= 0).all()
        assert out[0, 0] == 0.0 and out[0, -1] == 1.0
    assert gamma(ramp, 0.5)[0, 128] > ramp[0, 128] > gamma(ramp, 2.0)[0, 128]
    # Monotonic in the parameter too.
    assert exposure(ramp, 0.5)[0, 100] < exposure(ramp, 0.8)[0, 100]


def test_lighting_gradient_and_vignette() -> None:
    flat = np.full((60, 80), 0.8, dtype=np.float32)
    out = lighting_gradient(flat, 0.5, 0.0)  # falls off toward +x
    np.testing.assert_allclose(out[:, 0], 0.8, atol=1e-6)
    np.testing.assert_allclose(out[:, -1], 0.4, atol=1e-6)
    assert (np.diff(out[0]) <= 1e-7).all()
    down = lighting_gradient(flat, 0.5, math.pi / 2)  # falls off toward +y
    assert down[0, 40] > down[-1, 40]
    np.testing.assert_allclose(lighting_gradient(flat, 0.0, 1.0), flat)
    v = vignette(flat, 0.4)
    assert abs(float(v[30, 40]) - 0.8) < 0.01
    np.testing.assert_allclose(v[0, 0], 0.8 * 0.6, atol=1e-5)
    np.testing.assert_allclose(v, v[::-1, ::-1], atol=1e-6)


def test_specular_highlight() -> None:
    img = np.full((50, 60), 0.3, dtype=np.float32)
    out = specular_highlight(img, (20.0, 25.0), 5.0, 1.0)
    assert abs(float(out[25, 20]) - 1.0) < 1e-6  # saturates toward white
    assert abs(float(out[0, 59]) - 0.3) < 1e-3  # soft, local
    assert (out >= img - 1e-7).all() and out.max() <= 1.0
    ell = specular_highlight(img, (30.0, 25.0), 8.0, 0.8, aspect=0.3, angle=0.0)
    assert ell[25, 38] > ell[33, 30]  # elongated along x


@pytest.mark.parametrize(("read", "shot"), [(0.01, 0.0), (0.03, 0.0), (0.0, 2e-3), (0.02, 4e-3)])
def test_noise_has_requested_sigma(read, shot) -> None:
    level = 0.5
    flat = np.full((256, 256), level, dtype=np.float32)
    out = sensor_noise(flat, np.random.default_rng(1), read, shot)
    expected = math.sqrt(read**2 + shot * level)
    assert abs(float(out.std()) / expected - 1.0) < 0.03
    assert abs(float(out.mean()) - level) < 3 * expected / 256
    assert out.dtype == np.float32 and out.min() >= 0 and out.max() <= 1
    np.testing.assert_array_equal(flat, level)  # input untouched


def test_noise_is_deterministic_for_seed() -> None:
    flat = np.full((32, 32), 0.1, dtype=np.float32)
    a = sensor_noise(flat, np.random.default_rng(7), 0.01, 1e-3)
    b = sensor_noise(flat, np.random.default_rng(7), 0.01, 1e-3)
    np.testing.assert_array_equal(a, b)


def test_jpeg(disc_img) -> None:
    out = jpeg(disc_img, 30)
    assert out.shape == disc_img.shape and out.dtype == np.float32
    assert out.min() >= 0 and out.max() <= 1
    assert np.abs(out - disc_img).max() > 1.0 / 255
    hi = jpeg(disc_img, 95)
    assert np.abs(hi - disc_img).mean() < np.abs(out - disc_img).mean()
    with pytest.raises(ValueError):
        jpeg(disc_img, 0)


def test_to_uint8() -> None:
    a = np.array([[-0.2, 0.0, 0.5, 1.0 / 255 * 3.4, 1.0, 1.7]], dtype=np.float32)
    np.testing.assert_array_equal(to_uint8(a), [[0, 0, 128, 3, 255, 255]])
    assert to_uint8(a).dtype == np.uint8


# --------------------------------------------------------------------------------------
# Occlusion
# --------------------------------------------------------------------------------------


def shoelace(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


@pytest.mark.parametrize(
    "poly",
    [
        [[10.3, 10.2], [50.7, 12.1], [45.2, 40.9], [12.2, 35.5]],
        [[20.25, 20.5], [23.5, 20.5], [21.7, 24.1]],  # small triangle
        [[30, 5], [55, 30], [40, 30], [40, 55], [20, 55], [20, 30], [5, 30]],  # non-convex
    ],
)
def test_occlusion_mask_covers_polygon_area(poly) -> None:
    poly = np.asarray(poly, dtype=np.float64)
    img = np.ones((64, 64), dtype=np.float32)
    out, mask = occlude(img, poly, 0.25)
    assert mask.dtype == np.float32 and mask.min() >= 0 and mask.max() <= 1
    assert abs(float(mask.sum()) / shoelace(poly) - 1.0) < 0.02
    np.testing.assert_allclose(out, 1.0 - 0.75 * mask, atol=1e-6)


def test_occlusion_square_is_exact_and_texture() -> None:
    mask = polygon_coverage((8, 8), [[1, 1], [4, 1], [4, 4], [1, 4]])
    assert float(mask.sum()) == pytest.approx(9.0, abs=1e-5)
    assert mask[2, 2] == 1.0 and mask[1, 1] == 0.25 and mask[0, 0] == 0.0
    img = np.ones((40, 40), dtype=np.float32)
    patch = np.array([[0.0, 0.5], [0.5, 0.0]], dtype=np.float32)
    poly = np.array([[4.5, 4.5], [30.5, 4.5], [30.5, 30.5], [4.5, 30.5]])
    out, m = occlude(img, poly, patch)
    assert out[10, 10] in (0.0, 0.5) and set(np.unique(out[6:29, 6:29])) == {0.0, 0.5}
    np.testing.assert_array_equal(out[m == 0], 1.0)
    full_tex = np.random.default_rng(0).random((40, 40)).astype(np.float32)
    out2, _ = occlude(img, poly, full_tex)
    np.testing.assert_array_equal(out2[10:20, 10:20], full_tex[10:20, 10:20])


def test_occlusion_partly_outside_image() -> None:
    square = [[-10, -10], [10, -10], [10, 10], [-10, 10]]
    out, mask = occlude(np.ones((20, 20), np.float32), square, 0)
    assert float(mask.sum()) == pytest.approx(10.5 * 10.5, abs=1e-4)  # clipped to the image


# --------------------------------------------------------------------------------------
# Degradation / ranges / presets
# --------------------------------------------------------------------------------------


def test_presets_present() -> None:
    assert set(PRESETS) == {"none", "default", "blur", "dark", "bright", "full"}
    assert DegradationRanges.preset("dark") is PRESETS["dark"] is DegradationRanges.DARK
    assert DegradationRanges.preset("bright") is DegradationRanges.BRIGHT and DegradationRanges.BRIGHT.gain[0] > 1
    with pytest.raises(KeyError):
        DegradationRanges.preset("nope")


def test_identity_preset_returns_input(disc_img) -> None:
    rng = np.random.default_rng(3)
    for _ in range(5):
        deg = PRESETS["none"].sample(rng)
        assert deg == Degradation()
        out = deg.apply(disc_img, rng)
        assert out.dtype == np.float32 and out is not disc_img
        np.testing.assert_allclose(out, disc_img, atol=np.finfo(np.float32).eps)
    as64 = disc_img.astype(np.float64)
    np.testing.assert_allclose(Degradation().apply(as64, rng), as64, atol=1e-7)


def test_sample_deterministic_and_in_ranges() -> None:
    for name, ranges in PRESETS.items():
        a = [ranges.sample(np.random.default_rng(42)) for _ in range(2)]
        assert a[0] == a[1], name
        rng = np.random.default_rng(5)
        seen_blur = seen_jpeg = seen_spec = 0
        for _ in range(300):
            d = ranges.sample(rng)
            assert ranges.gain[0] <= d.gain <= ranges.gain[1]
            assert ranges.offset[0] <= d.offset <= ranges.offset[1]
            assert ranges.gamma[0] <= d.gamma <= ranges.gamma[1]
            assert ranges.read_sigma[0] <= d.read_sigma <= ranges.read_sigma[1]
            assert ranges.shot_scale[0] <= d.shot_scale <= ranges.shot_scale[1]
            if d.gradient_strength:
                assert d.gradient_strength <= ranges.gradient_strength[1]
            if d.vignette:
                assert ranges.vignette[0] <= d.vignette <= ranges.vignette[1]
            if d.blur_length:
                seen_blur += 1
                assert ranges.blur_length[0] <= d.blur_length <= ranges.blur_length[1]
                assert ranges.blur_angle[0] <= d.blur_angle <= ranges.blur_angle[1]
            if d.defocus_radius:
                assert d.defocus_radius <= ranges.defocus_radius[1]
            if d.jpeg_quality is not None:
                seen_jpeg += 1
                assert ranges.jpeg_quality[0] <= d.jpeg_quality <= ranges.jpeg_quality[1]
            if d.specular is not None:
                seen_spec += 1
                s = d.specular
                assert ranges.specular_strength[0] <= s.strength <= ranges.specular_strength[1]
                lo, hi = ranges.specular_radius_rel
                assert lo <= s.radius_rel <= hi
                assert all(0.0 <= c <= 1.0 for c in s.centre_rel)
        # Probabilities are honoured roughly (300 draws; loose bounds).
        assert abs(seen_blur / 300 - ranges.p_blur) < 0.1 or ranges.blur_length[1] == 0
        assert abs(seen_jpeg / 300 - ranges.p_jpeg) < 0.1
        assert abs(seen_spec / 300 - ranges.p_specular) < 0.1


def test_preset_specifics() -> None:
    rng = np.random.default_rng(11)
    for _ in range(50):
        b = PRESETS["blur"].sample(rng)
        assert 5.0 <= b.blur_length <= 12.0 and 0.0 <= b.blur_angle <= math.pi
        d = PRESETS["dark"].sample(rng)
        assert 0.06 <= d.gain <= 0.2 and 0.005 <= d.read_sigma <= 0.02 and d.shot_scale > 0
        m = PRESETS["default"].sample(rng)
        assert 0.7 <= m.gain <= 1.2 and m.blur_length <= 2.0
        assert m.jpeg_quality is None or 80 <= m.jpeg_quality <= 95


def test_apply_output_range_and_dtype(disc_img) -> None:
    rng = np.random.default_rng(9)
    for name in ("default", "blur", "dark", "full"):
        for _ in range(8):
            deg = PRESETS[name].sample(rng)
            out = deg.apply(disc_img, rng)
            assert out.dtype == np.float32 and out.shape == disc_img.shape
            assert np.isfinite(out).all() and out.min() >= 0.0 and out.max() <= 1.0
    # Everything at once, including out-of-range input values.
    everything = Degradation(
        gain=1.8, offset=0.05, gradient_strength=0.6, gradient_angle=1.0, vignette=0.4,
        gamma=0.7, read_sigma=0.03, shot_scale=2e-3, blur_length=6.5, blur_angle=0.3,
        defocus_radius=2.0, jpeg_quality=40, specular=Specular((0.5, 0.5), 0.2, 1.2, 0.5, 0.3),
    )  # fmt: skip
    out = everything.apply(disc_img * 1.5 - 0.2, rng)
    assert out.dtype == np.float32 and out.min() >= 0.0 and out.max() <= 1.0


def test_apply_order_blur_keeps_centroid_before_noise(disc_img) -> None:
    # Geometry-only degradations through apply() keep the disc centre.
    deg = Degradation(defocus_radius=1.5, blur_length=8.0, blur_angle=0.8)
    c = dark_centroid(deg.apply(disc_img, np.random.default_rng(0)))
    assert abs(c[0] - DISC["cx"]) < 0.02 and abs(c[1] - DISC["cy"]) < 0.02


def test_to_dict_round_trip_json() -> None:
    rng = np.random.default_rng(123)
    for _ in range(20):
        d = PRESETS["full"].sample(rng)
        doc = json.loads(json.dumps(d.to_dict()))
        assert Degradation.from_dict(doc) == d
    d = Degradation(jpeg_quality=np.int64(70), gain=np.float32(0.5))
    assert type(d.jpeg_quality) is int and type(d.gain) is float


def test_validation() -> None:
    with pytest.raises(ValueError):
        Degradation(gamma=0.0)
    with pytest.raises(ValueError):
        Degradation(jpeg_quality=101)
    with pytest.raises(ValueError):
        DegradationRanges(gain=(1.0, 0.5))
    with pytest.raises(ValueError):
        DegradationRanges(p_blur=1.5)
    with pytest.raises(ValueError):
        motion_blur(np.zeros((4, 4, 3), np.float32), 2.0, 0.0)
    with pytest.raises(ValueError):
        defocus(np.zeros((4, 4), np.float32), -1.0)


def test_tiny_defocus_radius_is_the_identity_not_nan() -> None:
    from app.sim.degrade import defocus

    img = np.random.default_rng(0).random((20, 20), dtype=np.float32)
    out = defocus(img, 0.04)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out, img, atol=1e-6)


def test_thin_lens_blur_grows_away_from_the_focus() -> None:
    lens = ThinLens(focal_length_mm=50.0, f_number=2.0, focus_m=2.0)
    radius = lens.blur_radius_px(np.array([2.0, 4.0, 1.0]), focal_px=1000.0)
    # At the focus nothing; at 4 m: (f/N) f |d - s| / (d (s - f)), in pixels, halved.
    np.testing.assert_allclose(radius, [0.0, 0.5 * 0.025 * 0.05 * 2.0 / (4.0 * 1.95) * 1000.0 / 0.05,
                                        0.5 * 0.025 * 0.05 * 1.0 / (1.0 * 1.95) * 1000.0 / 0.05])
    with pytest.raises(ValueError):
        ThinLens(focal_length_mm=50.0, f_number=2.0, focus_m=0.01)


def test_depth_defocus_blurs_what_is_out_of_focus_only() -> None:
    img = np.zeros((64, 128), np.float32)
    img[:, ::8] = 1.0  # thin lines everywhere
    depth = np.full(img.shape, 2.0)
    depth[:, 64:] = 6.0  # the right half far behind the focus
    lens = ThinLens(focal_length_mm=50.0, f_number=2.0, focus_m=2.0)
    out = depth_defocus(img, depth, lens, focal_px=1000.0)
    np.testing.assert_allclose(out[:, 8:56], img[:, 8:56], atol=1e-6)  # in focus: untouched
    assert out[:, 72:120].max() < 0.5 and abs(out[:, 72:120].mean() - img[:, 72:120].mean()) < 0.01  # spread, kept
