"""KLT's parts: the forward-backward check drops points whose patch changed, new corners
keep their distance from the live points and stay out of excluded regions."""

from __future__ import annotations

import numpy as np

from app.core.features import FeatureSettings
from app.core.features.klt import flow, flow_image, seed_points
from app.core.features.masks import allowed_mask
from tests.core.features.conftest import film, texture, transfer, view


def test_the_forward_backward_check_drops_points_whose_patch_was_replaced(plane: np.ndarray) -> None:
    settings = FeatureSettings()
    views = [view(300, 200, 0), view(305, 203, 1)]
    a, b = film(plane, views)
    # Something else passes in front of a 160 x 120 px part of the second frame.
    b[150:270, 200:360] = texture(9, 480, 640)[150:270, 200:360]
    uv = seed_points(a, allowed_mask(a.shape, None, 8), np.zeros((0, 2)), 500, settings)
    moved, ok = flow(flow_image(a), flow_image(b), uv, settings)
    covered = (uv[:, 0] > 200 + 12) & (uv[:, 0] < 360 - 12) & (uv[:, 1] > 150 + 12) & (uv[:, 1] < 270 - 12)
    clear = (uv[:, 0] < 200 - 25) | (uv[:, 0] > 360 + 25) | (uv[:, 1] < 150 - 25) | (uv[:, 1] > 270 + 25)
    assert covered.sum() >= 15 and clear.sum() >= 100
    assert ok[covered].mean() <= 0.1
    assert ok[clear].mean() >= 0.95
    # Beyond the reach of `flow_image`'s shading (20 px) from the change and from the
    # image's border, the points land within a few hundredths of a pixel of the truth.
    far = (uv[:, 0] < 200 - 32) | (uv[:, 0] > 360 + 32) | (uv[:, 1] < 150 - 32) | (uv[:, 1] > 270 + 32)
    far &= np.all((uv > 32) & (uv < [640 - 32, 480 - 32]), axis=1)
    err = np.linalg.norm(moved[ok & far] - transfer(views, 0, 1, uv[ok & far]), axis=1)
    assert (ok & far).sum() >= 100 and np.percentile(err, 95) < 0.05


def test_a_point_moved_far_is_found_from_its_predicted_place(plane: np.ndarray) -> None:
    settings = FeatureSettings()
    views = [view(300, 200, 0), view(400, 260, 0)]  # 117 px in one frame: beyond the pyramid's reach
    a, b = film(plane, views)
    uv = seed_points(a, allowed_mask(a.shape, None, 8), np.zeros((0, 2)), 300, settings)
    truth = transfer(views, 0, 1, uv)
    inside = np.all((truth > 20) & (truth < [620, 460]), axis=1)
    moved, ok = flow(flow_image(a), flow_image(b), uv[inside], settings, guess=uv[inside] + [-98.0, -61.0])
    assert ok.mean() >= 0.9
    assert np.median(np.linalg.norm(moved[ok] - truth[inside][ok], axis=1)) < 0.1


def test_new_corners_keep_their_distance_and_stay_in_the_allowed_region(plane: np.ndarray) -> None:
    settings = FeatureSettings(min_distance_px=10.0)
    image = film(plane, [view(300, 200, 0)])[0]
    exclude = np.zeros(image.shape, bool)
    exclude[100:300, 250:450] = True
    live = np.array([[100.0, 100.0], [500.0, 400.0]])
    uv = seed_points(image, allowed_mask(image.shape, exclude, 8), live, 400, settings)
    assert len(uv) > 100
    xy = np.round(uv).astype(int)
    assert not exclude[xy[:, 1], xy[:, 0]].any()
    assert np.all((uv >= 8 - 0.5) & (uv <= [640 - 8, 480 - 8]))
    everything = np.vstack([live, uv])
    d = np.linalg.norm(everything[:, None] - everything[None], axis=2) + np.eye(len(everything)) * 1e9
    # Corners are placed whole pixels apart before their subpixel refinement moves them (< 1 px each).
    assert d.min() >= 10.0 - 2.0


def test_a_blank_or_noisy_plain_frame_gives_no_corners() -> None:
    settings = FeatureSettings()
    rng = np.random.default_rng(0)
    allowed = allowed_mask((480, 640), None, 8)
    for image in (np.zeros((480, 640), np.uint8), np.full((480, 640), 200, np.uint8),
                  np.clip(np.rint(150 + rng.normal(0, 2.0, (480, 640))), 0, 255).astype(np.uint8)):
        assert len(seed_points(image, allowed, np.zeros((0, 2)), 500, settings)) == 0
