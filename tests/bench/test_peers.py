"""The peers of the detection benchmark (bench/peers.py) are measured fairly: their own
detector finds their artwork with the right id and the corners, reordered to our
TL, TR, BR, BL as printed, on the projected truth - under all four image rotations."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pupil_apriltags")

from app.sim import scenes  # noqa: E402
from app.sim.truth import truth_cards  # noqa: E402
from bench import peers  # noqa: E402

SEEDS = (1, 2)  # clean frames: fronto-parallel cards, no degradation, random roll


def _rot90(image: np.ndarray, points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.rot90(image, k)`` and the pixel coordinates of ``points`` in it."""
    points = np.array(points, np.float64)
    for _ in range(k):
        width = image.shape[1]
        image = np.rot90(image)
        points = np.column_stack([points[:, 1], width - 1 - points[:, 0]])
    return np.ascontiguousarray(image), points


@pytest.fixture(scope="module")
def detectors() -> dict[str, peers.PeerDetector]:
    return {
        "apriltag": peers.AprilTagDetector("AprilTag", peers.apriltag_artwork, quad_decimate=1.0),
        "aruco": peers.ArucoDetector("ArUco", peers.aruco_artwork, refinement="none"),
        "aruco-subpix": peers.ArucoDetector("ArUco subpix", peers.aruco_artwork, refinement="subpix"),
    }


# Corner tolerance: 1 px; ArUco without corner refinement reports the corners of its
# polygon approximation (pixel centres of the contour, up to ~1.1 px off on rotated cards),
# so it gets 1.5 px. A wrong corner order would be off by a card side (tens of pixels).
TOLERANCE_PX = {"apriltag": 1.0, "aruco": 1.5, "aruco-subpix": 1.0}


@pytest.mark.parametrize("name", ["apriltag", "aruco", "aruco-subpix"])
def test_own_detector_finds_artwork_with_corners_in_printed_order(detectors, name) -> None:
    detector = detectors[name]
    checked = 0
    for seed in SEEDS:
        image, truth = scenes.scenario_frame("clean", np.random.default_rng(seed), artwork=detector.artwork)
        cards = [c for c in truth_cards(truth, detector.artwork) if c.counted]
        assert cards
        for k in range(4):
            rotated, _ = _rot90(image, np.zeros((0, 2)), k)
            found = dict(detector.detect(rotated))
            for card in cards:
                _, expected = _rot90(image, card.points, k)
                assert card.id in found, (name, seed, k, card.id, sorted(found))
                error = np.linalg.norm(found[card.id] - expected, axis=1)
                assert error.max() < TOLERANCE_PX[name], (name, seed, k, card.id, error)
                checked += 1
            assert set(found) <= {c.id for c in truth.targets}, (name, seed, k, sorted(found))
    assert checked >= 8


def test_artwork_geometry() -> None:
    for artwork, cells in ((peers.apriltag_artwork(5), 8), (peers.aruco_artwork(55), 6)):
        tex = artwork.texture
        assert tex.shape == (scenes.CARD_TEXTURE_PX, scenes.CARD_TEXTURE_PX) and tex.dtype == np.float32
        lo, hi = 36, 444  # 0.075 and 0.925 of 480 texels
        assert set(np.unique(tex)) <= {0.0, 1.0}  # edges on texel edges: no partial texels
        assert (tex[:lo] == 1).all() and (tex[hi:] == 1).all() and (tex[:, :lo] == 1).all() and (tex[:, hi:] == 1).all()
        assert (tex[lo, lo:hi] == 0).all() and (tex[hi - 1, lo:hi] == 0).all()  # the black border
        assert (tex[lo:hi, lo] == 0).all() and (tex[lo:hi, hi - 1] == 0).all()
        assert (hi - lo) % cells == 0
        np.testing.assert_allclose(artwork.points_uv, [[0.075, 0.075], [0.925, 0.075], [0.925, 0.925], [0.075, 0.925]])


def test_aruco_dictionary_extends_4x4_50() -> None:
    import cv2

    ours = peers.aruco_dictionary()
    base = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    assert ours.bytesList.shape[0] == peers.N_IDS >= 50
    np.testing.assert_array_equal(ours.bytesList[:50], base.bytesList)
    assert ours.maxCorrectionBits == base.maxCorrectionBits


def test_blob_candidates_find_the_discs() -> None:
    image, truth = scenes.scenario_frame("clean", np.random.default_rng(3))
    cand = peers.blob_candidates(image)
    assert cand.ndim == 2 and cand.shape[1] == 4
    for target in truth.visible_targets():
        for disc in target.discs_px:
            nearest = np.linalg.norm(cand[:, :2] - disc, axis=1)
            i = int(np.argmin(nearest))
            assert nearest[i] < 0.5, (target.id, disc, nearest[i])
            assert cand[i, 2] == pytest.approx(target.disc_diameter_px / 2, rel=0.25)
