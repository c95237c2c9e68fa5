"""A walk recorded as a phone's H.264 video: frame for frame, lossy as the bit rate says."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from app.sim import BENCH_ROOM, PhoneVideo, RoomWalk, record


def _walk() -> RoomWalk:
    """The first second of the bench's 300-frame walk: a camera moving as people film."""
    room = BENCH_ROOM.walk(0, 300)
    return dataclasses.replace(room, poses=room.poses[:30])


@pytest.fixture(scope="module")
def walk_frames() -> tuple[list[np.ndarray], list]:
    frames = list(_walk().frames(BENCH_ROOM.camera, degradation="none"))
    return [image for image, _ in frames], [truth for _, truth in frames]


def _psnr(a: list[np.ndarray], b: list[np.ndarray]) -> float:
    return float(np.median([cv2.PSNR(x, y) for x, y in zip(a, b, strict=True)]))


def test_every_frame_comes_back_in_order_and_lossy_as_the_bit_rate_says(walk_frames: tuple) -> None:
    images, _ = walk_frames
    phone = list(record(images, 30.0))
    assert len(phone) == len(images)
    assert all(p.dtype == np.uint8 and p.shape == (480, 640) for p in phone)
    # Each decoded frame is its own input's, not a neighbour's.
    for k in (0, 10, len(images) - 1):
        errors = [float(np.abs(phone[k].astype(float) - images[j]).mean()) for j in range(len(images))]
        assert int(np.argmin(errors)) == k
    generous = list(record(images, 30.0, PhoneVideo(bits_per_pixel=2.0)))
    starved = list(record(images, 30.0, PhoneVideo(bits_per_pixel=0.05)))
    psnr = {"starved": _psnr(images, starved), "phone": _psnr(images, phone), "generous": _psnr(images, generous)}
    assert 20.0 < psnr["starved"] < psnr["phone"] - 5 < psnr["generous"] - 10 < 50.0, psnr


def test_a_walk_rendered_as_video_keeps_its_truth(walk_frames: tuple) -> None:
    images, truths = walk_frames
    recorded = list(_walk().frames(BENCH_ROOM.camera, degradation="none", video=PhoneVideo()))
    assert [t.pose.position.tolist() for _, t in recorded] == [t.pose.position.tolist() for t in truths]
    assert all(not np.array_equal(image, original) for (image, _), original in zip(recorded, images, strict=True))


def test_frames_it_cannot_encode_are_refused() -> None:
    with pytest.raises(ValueError, match="even frame size"):
        list(record([np.zeros((49, 64), np.uint8)], 30.0))
    with pytest.raises(ValueError, match="differs from the first"):
        list(record([np.zeros((48, 64), np.uint8), np.zeros((48, 66), np.uint8)], 30.0))
    with pytest.raises(ValueError, match="uint8"):
        list(record([np.zeros((48, 64), np.float32)], 30.0))
    with pytest.raises(ValueError, match="bits_per_pixel"):
        PhoneVideo(bits_per_pixel=0.0)
