"""Frames decoded smaller: the decoder's reduced JPEGs and their pixel convention, the
frame's share of the memory budget, the crops and the reduction chosen from a
prediction."""

from __future__ import annotations

import os

import cv2
import numpy as np
import pytest

from app.core.geometry import Camera, Pose
from app.core.geometry.regions import (
    MapTargets,
    PredictedTarget,
    Region,
    decode_reduction,
    disc_diameters,
    predict_in_view,
    reduce_regions,
)
from app.core.imagecodec import ImageError, _count_sos, decode_gray, read_header, reduced_size
from app.services import images
from app.settings import Settings


def _blob_jpeg(width: int, height: int, centre: tuple[float, float], sigma: float = 12.0) -> bytes:
    """A dark Gaussian blob on grey at a subpixel `centre` (pixel centres at integers)."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    dark = np.exp(-((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / (2 * sigma**2))
    image = np.clip(np.rint(200.0 - 150.0 * dark), 0, 255).astype(np.uint8)
    return cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 98])[1].tobytes()


def _dark_centroid(gray: np.ndarray) -> np.ndarray:
    weight = np.clip(200.0 - gray.astype(np.float64), 0, None)
    y, x = np.mgrid[0 : gray.shape[0], 0 : gray.shape[1]]
    return np.array([(weight * x).sum(), (weight * y).sum()]) / weight.sum()


@pytest.mark.parametrize("factor", [2, 4, 8])
def test_a_reduced_jpeg_keeps_its_pixels_where_the_camera_scaling_puts_them(factor: int) -> None:
    centre = (401.3, 233.7)
    data = _blob_jpeg(803, 517, centre)
    whole = decode_gray(data, 10**8)
    small = decode_gray(data, 10**8, reduction=factor)
    assert small.shape == (-(-517 // factor), -(-803 // factor)) and small.flags.c_contiguous
    assert (small.shape[1], small.shape[0]) == reduced_size(803, 517, factor)
    # Pixel i of the reduced frame is centred on (i + 0.5) * factor - 0.5 of the image.
    back = (_dark_centroid(small) + 0.5) * factor - 0.5
    assert np.allclose(_dark_centroid(whole), centre, atol=0.02)
    assert np.allclose(back, centre, atol=0.1)  # (i * factor would be off by (factor - 1) / 2)


def test_reductions_other_than_the_decoders_are_refused() -> None:
    data = _blob_jpeg(64, 48, (30.0, 20.0), sigma=4.0)
    with pytest.raises(ValueError):
        decode_gray(data, 10**8, reduction=3)
    png = cv2.imencode(".png", np.full((48, 64), 90, np.uint8))[1].tobytes()
    assert decode_gray(png, 10**8, reduction=2).shape == (48, 64)  # PNGs are decoded whole


def test_a_truncated_jpeg_is_refused_at_every_reduction() -> None:
    data = _blob_jpeg(320, 240, (100.0, 100.0))
    cut = data[: len(data) // 2] + b"\xff\xd9"
    for factor in (1, 2, 4):
        with pytest.raises(ImageError):
            decode_gray(cut, 10**8, reduction=factor)


def test_counting_scans_agrees_with_the_bytes() -> None:
    rng = np.random.default_rng(5)
    for n in range(300):
        chunks = [rng.integers(0, 256, int(rng.integers(0, 40)), dtype=np.uint8).tobytes(),
                  b"\xff\xda" * int(rng.integers(0, 3)), os.urandom(int(rng.integers(0, 5))), b"\xff"]
        data = b"".join(chunks[: 1 + n % 4])
        for start in (0, 1, 5):
            assert _count_sos(data, start) == data.count(b"\xff\xda", start)
    real = _blob_jpeg(200, 100, (50.0, 50.0))
    assert read_header(real).width == 200


def test_decoded_frame_reduces_what_the_caller_asks_within_the_budget(settings: Settings) -> None:
    memory = images.MemoryBudget(10**9)
    data = _blob_jpeg(640, 360, (320.0, 180.0))
    header = images.frame_header(data, settings)  # the size, before any pixel is decoded
    assert (header.width, header.height) == (640, 360)
    with images.decoded_frame(data, settings, memory, header=header, reduction=2) as frame:
        assert frame.reduction == 2
        assert (frame.width, frame.height) == (640, 360) and frame.gray.shape == (180, 320)
        assert memory.held == images.cost_bytes(header, True, 2) < images.cost_bytes(header, True)
    assert memory.held == 0
    # Reduced below the detector's window: decoded whole.
    tiny = _blob_jpeg(80, 60, (40.0, 30.0), sigma=5.0)
    with images.decoded_frame(tiny, settings, memory, reduction=4) as frame:
        assert frame.reduction == 1 and frame.gray.shape == (60, 80)
    with pytest.raises(ValueError), images.decoded_frame(data, settings, memory, reduction=3):
        pass
    with images.decoded(data, settings, memory) as gray:  # the plain path: whole
        assert gray.shape == (360, 640)


def test_reduced_crops_cover_the_frames_crops_on_the_grid() -> None:
    regions = [Region(8, 16, 200, 136, (1,)), Region(600, 400, 1280, 720, (2, 3))]
    for factor in (2, 4):
        width, height = reduced_size(1280, 720, factor)
        out = reduce_regions(regions, factor, width, height)
        for r in regions:
            # Every frame pixel of the crop lies in a reduced crop's pixels.
            assert any(o.x0 * factor <= r.x0 and o.y0 * factor <= r.y0 and min(o.x1 * factor, 1280) >= r.x1
                       and min(o.y1 * factor, 720) >= r.y1 and set(r.ids) <= set(o.ids) for o in out)
        for o in out:
            assert o.x0 % 8 == 0 and o.y0 % 8 == 0 and o.x1 <= width and o.y1 <= height
    assert reduce_regions(regions, 1, 1280, 720) == regions


def _target(discs: list[list[float]]) -> PredictedTarget:
    d = np.array(discs, np.float64)
    return PredictedTarget(1, d, (d[:, 0].min(), d[:, 1].min(), d[:, 0].max(), d[:, 1].max()))


def test_the_reduction_follows_the_smallest_disc_on_the_frame_and_the_frames_size() -> None:
    def square(x: float, y: float, side: float) -> PredictedTarget:
        return _target([[x, y], [x + side, y], [x + side, y + side], [x, y + side]])

    # Disc diameter 0.25 / 0.6 of the disc square's side.
    assert np.allclose(disc_diameters([square(0, 0, 60.0)]), [25.0])
    big, small = square(100, 100, 60.0), square(900, 100, 24.0)  # discs of 25 and 10 px
    assert decode_reduction([big], 1920, 1080, 5.0, (1, 2, 4)) == 4
    assert decode_reduction([big, small], 1920, 1080, 5.0, (1, 2, 4)) == 2
    assert decode_reduction([big], 1920, 1080, 5.0, (1, 2, 4), min_side=360) == 2  # 270 rows at 1/4: too few
    assert decode_reduction([big], 640, 480, 5.0, (1, 2, 4), min_side=360) == 1
    assert decode_reduction([], 1920, 1080, 5.0, (1, 2, 4)) == 1  # nothing predicted: nothing known
    off = square(3000, 100, 24.0)  # beyond the frame's edge: does not count
    assert decode_reduction([big, off], 1920, 1080, 5.0, (1, 2, 4)) == 4


def test_in_view_prediction_is_what_the_regions_are_planned_from() -> None:
    camera = Camera.pinhole(1640.0, 1280, 720)
    uv = np.array([[0.2, 0.2], [0.8, 0.2], [0.8, 0.8], [0.2, 0.8]]) - 0.5
    targets = MapTargets.from_discs({5: np.c_[0.2 * uv, np.full(4, 2.0)]})
    predicted = predict_in_view(targets, camera, Pose.identity())
    assert [t.id for t in predicted] == [5]
    # 0.12 m between discs at 2 m through f = 1640 px: 98 px, discs of 41 px.
    assert np.allclose(disc_diameters(predicted), 0.25 / 0.6 * 1640 * 0.12 / 2.0, rtol=0.02)
