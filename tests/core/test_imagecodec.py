"""Client images are decoded safely: sizes checked from the header before decoding."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest

from app.core.imagecodec import MAX_JPEG_SCANS, ImageError, decode_gray, read_header


def _encode(image: np.ndarray, ext: str) -> bytes:
    ok, data = cv2.imencode(ext, image)
    assert ok
    return data.tobytes()


def _giant_jpeg_header(width: int, height: int) -> bytes:
    """A tiny JPEG whose frame header claims a huge image."""
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 11, 8, height, width, 1) + b"\x01\x11\x00"
    return b"\xff\xd8" + sof + b"\xff\xda\x00\x08\x01\x01\x00\x00\x3f\x00" + b"\x00" * 600 + b"\xff\xd9"


def _giant_png_header(width: int, height: int) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    data = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + chunk + struct.pack(">I", zlib.crc32(chunk))
    idat = b"IDAT" + zlib.compress(b"\x00" * 100)
    end = b"IEND"
    return (data + struct.pack(">I", len(idat) - 4) + idat + struct.pack(">I", zlib.crc32(idat))
            + struct.pack(">I", 0) + end + struct.pack(">I", zlib.crc32(end)))


def test_header_sizes_match_the_image() -> None:
    image = np.random.default_rng(0).integers(0, 255, (37, 53, 3), dtype=np.uint8)
    for ext, fmt in ((".jpg", "jpeg"), (".png", "png")):
        header = read_header(_encode(image, ext))
        assert (header.format, header.width, header.height) == (fmt, 53, 37)


@pytest.mark.parametrize("make", [_giant_jpeg_header, _giant_png_header])
def test_giant_declared_size_is_refused_before_decoding(make) -> None:  # type: ignore[no-untyped-def]
    data = make(30000, 30000)
    assert len(data) < 1000
    with pytest.raises(ImageError) as refused:
        decode_gray(data, max_pixels=40_000_000)
    assert refused.value.kind == "too_large"


@pytest.mark.parametrize(
    "data,kind",
    [(b"", "empty"), (b"hello world", "unsupported"), (b"GIF89a....", "unsupported"),
     (b"\xff\xd8\xff\xe0\x00\x10JFIF", "corrupt"), (b"\x89PNG\r\n\x1a\n\x00\x00", "corrupt")],
)
def test_garbage_is_refused_with_a_reason(data: bytes, kind: str) -> None:
    with pytest.raises(ImageError) as refused:
        decode_gray(data, max_pixels=10**7)
    assert refused.value.kind == kind and str(refused.value)


@pytest.mark.parametrize("ext", [".jpg", ".png"])
def test_truncated_files_are_refused(ext: str) -> None:
    data = _encode(np.full((64, 64), 128, np.uint8), ext)
    with pytest.raises(ImageError):
        decode_gray(data[: len(data) // 2], max_pixels=10**7)


def test_grey_colour_alpha_and_16_bit_images_decode_to_8_bit_grey() -> None:
    grey = np.tile(np.arange(64, dtype=np.uint8) * 4, (32, 1))
    variants = {
        "grey png": _encode(grey, ".png"),
        "bgr jpeg": _encode(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR), ".jpg"),
        "bgra png": _encode(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGRA), ".png"),
        "16-bit png": _encode(grey.astype(np.uint16) * 257, ".png"),
    }
    for name, data in variants.items():
        decoded = decode_gray(data, max_pixels=10**6)
        assert decoded.dtype == np.uint8 and decoded.shape == (32, 64), name
        assert np.abs(decoded.astype(int) - grey).max() <= 3, name


def test_exif_orientation_is_ignored() -> None:
    """Pixels stay where the sensor put them (the camera's intrinsics refer to them),
    whatever a phone's EXIF orientation tag says."""
    image = np.zeros((32, 64, 3), np.uint8)
    image[:, :8] = 255  # a bright left edge
    jpeg = _encode(image, ".jpg")
    # APP1 Exif: little-endian TIFF, one IFD entry, Orientation (0x0112) = 6 (rotate 90 CW)
    tiff = b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 1) + struct.pack("<HHIHH", 0x0112, 3, 1, 6, 0) + b"\x00" * 4
    app1 = b"Exif\x00\x00" + tiff
    tagged = jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + jpeg[2:]
    decoded = decode_gray(tagged, max_pixels=10**6)
    assert decoded.shape == (32, 64)
    assert decoded[:, :6].mean() > 200 and decoded[:, 12:].mean() < 50


def test_scan_markers_inside_a_comment_are_no_scans() -> None:
    # A comment (or an APPn block) may hold any bytes: FF DA there is no scan, and the
    # image decodes. Counted blindly, 100 of them made a baseline JPEG "101 scans".
    image = (np.arange(64 * 48, dtype=np.uint32).reshape(48, 64) % 251).astype(np.uint8)
    data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    sos = data.index(b"\xff\xda")
    payload = b"\xff\xda" * 100
    comment = b"\xff\xfe" + struct.pack(">H", len(payload) + 2) + payload
    patched = data[:sos] + comment + data[sos:]
    np.testing.assert_array_equal(decode_gray(patched, 10**6), decode_gray(data, 10**6))
    # while a file of many real scans is still refused
    many = data[:-2] + data[sos:-2] * (MAX_JPEG_SCANS + 1) + b"\xff\xd9"
    with pytest.raises(ImageError, match="scans"):
        decode_gray(many, 10**6)


def _photo_jpeg(progressive: bool = False) -> bytes:
    rng = np.random.default_rng(1)
    image = cv2.GaussianBlur(rng.integers(0, 255, (240, 320, 3), dtype=np.uint8), (0, 0), 2)
    params = [cv2.IMWRITE_JPEG_QUALITY, 90] + ([cv2.IMWRITE_JPEG_PROGRESSIVE, 1] if progressive else [])
    return cv2.imencode(".jpg", image, params)[1].tobytes()


@pytest.mark.parametrize("progressive", [False, True])
def test_a_jpeg_cut_short_and_given_an_end_marker_is_refused(progressive: bool) -> None:
    # The decoder would fill the missing rows with grey and say so only in a warning.
    data = _photo_jpeg(progressive)
    cut = data[: len(data) // 2] + b"\xff\xd9"
    with pytest.raises(ImageError, match="premature end") as refused:
        decode_gray(cut, 10**6)
    assert refused.value.kind == "corrupt"


def test_spare_bytes_before_the_end_marker_are_harmless() -> None:
    data = _photo_jpeg()
    padded = data[:-2] + b"\x55" * 7 + b"\xff\xd9"
    np.testing.assert_array_equal(decode_gray(padded, 10**6), decode_gray(data, 10**6))


@pytest.mark.parametrize("progressive", [False, True])
def test_jpeg_luma_is_what_opencv_decodes(progressive: bool) -> None:
    data = _photo_jpeg(progressive)
    expected = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(decode_gray(data, 10**6), expected)


def test_the_header_says_what_decoding_will_hold() -> None:
    baseline, progressive = read_header(_photo_jpeg()), read_header(_photo_jpeg(progressive=True))
    assert (baseline.channels, baseline.progressive) == (3, False)
    assert (progressive.channels, progressive.progressive) == (3, True)
    assert baseline.decode_bytes == 320 * 240  # a band at a time into the grey result
    assert progressive.decode_bytes == 320 * 240 * (1 + 2 * 3)  # every coefficient at once
    rgba16 = read_header(_encode(np.zeros((30, 40, 4), np.uint16), ".png"))
    assert (rgba16.channels, rgba16.sample_bytes) == (4, 2)
    assert rgba16.decode_bytes == 2 * 30 * 40 * 4 * 2 + 30 * 40


def test_a_jpeg_too_short_for_its_declared_size_is_refused_before_decoding() -> None:
    # Every 8x8 block costs at least a bit: 344 bytes cannot hold 6324x6324 pixels.
    data = _encode(np.zeros((32, 32), np.uint8), ".jpg")
    sof = data.index(b"\xff\xc0")
    bomb = data[: sof + 5] + struct.pack(">HH", 6324, 6324) + data[sof + 9 :]
    with pytest.raises(ImageError, match="needs at least") as refused:
        decode_gray(bomb, 40_000_000)
    assert refused.value.kind == "corrupt"
    # while flat images, the most compressible there are, pass
    for progressive in (0, 1):
        flat = cv2.imencode(".jpg", np.full((2000, 2000), 128, np.uint8),
                            [cv2.IMWRITE_JPEG_PROGRESSIVE, progressive])[1].tobytes()
        assert decode_gray(flat, 10**7).shape == (2000, 2000)
