"""Identification (app.core.detection.identification): codes read in every rotation give
the id and the printed disc order, ambiguous or unreadable codes are refused, and
motion-blurred codes are read by the smear templates (never as a wrong id)."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.detection import identification as ident
from app.core.detection import targets as tg
from app.core.markers import DEFAULT_FAMILY, get_family, marker_layout, render_card
from app.sim import degrade


def test_identification_in_every_rotation_gives_the_printed_order(clean_frames: list) -> None:
    n = 0
    for image, truth in clean_frames:
        for t in truth.targets:
            if not t.visible:
                continue
            for s in range(4):  # the quadrilateral may start at any disc
                got = ident.identify(image, np.roll(t.discs_px, s, axis=0))
                assert got is not None
                tid, discs, match = got
                assert tid == t.id
                assert np.allclose(discs, t.discs_px)  # printed order: 0 TL, 1 TR, 2 BR, 3 BL
                assert match.gap >= ident.CODE_GAP_MIN
                n += 1
    assert n >= 16


def test_identification_of_rotated_cards() -> None:
    # A printed card rolled by 0, 90, 180 and 270 degrees in the image (fronto-parallel):
    # the id and the printed disc order come out whatever the roll.
    fam = get_family(DEFAULT_FAMILY)
    for marker_id in (0, 7, len(fam) - 1):
        card = render_card(marker_layout(DEFAULT_FAMILY, marker_id), 240)
        canvas = np.full((320, 320), 128, np.uint8)
        canvas[40:280, 40:280] = card
        # printed disc centres (printed order) in canvas pixels (pixel centres at integers)
        base = 40 + np.array([[0.2, 0.2], [0.8, 0.2], [0.8, 0.8], [0.2, 0.8]]) * 240 - 0.5
        for k in range(4):
            img = np.ascontiguousarray(np.rot90(canvas, k))  # counter-clockwise by 90 k
            pts = base.copy()
            for _ in range(k):  # where np.rot90 moves pixel (x, y): (y, 319 - x)
                pts = np.stack([pts[:, 1], 319 - pts[:, 0]], axis=1)
            for s in range(4):
                got = ident.identify(img, np.roll(pts, s, axis=0))
                assert got is not None, f"id {marker_id} rotated {90 * k}"
                tid, discs, _ = got
                assert tid == marker_id
                assert np.allclose(discs, pts, atol=1e-6)


def test_ambiguous_or_unreadable_codes_are_refused() -> None:
    tmpl, ids, shifts = ident._templates(DEFAULT_FAMILY)
    # a clean code is read, with its id and rotation
    for row in (0, 5, len(tmpl) - 1):
        m = ident.decode_cells(tmpl[row])
        assert m is not None and m.id == ids[row] and m.shift == shifts[row]
    # every cell grey: unreadable
    assert ident.decode_cells(np.full(9, 0.5)) is None
    # halfway between two codes (or rotations) at the family's distance: ambiguous
    dist = (tmpl[:, None, :] != tmpl[None, :, :]).sum(axis=2)
    np.fill_diagonal(dist, 99)
    a, b = np.unravel_index(np.argmin(dist), dist.shape)
    assert ident.decode_cells(0.5 * (tmpl[a] + tmpl[b])) is None
    # noise far beyond any blur: refused
    rng = np.random.default_rng(5)
    refused = sum(ident.decode_cells(rng.uniform(-0.5, 1.5, 9)) is None for _ in range(200))
    assert refused >= 190


def _smeared_card(marker_id: int, px: int, length: float, angle: float) -> tuple[np.ndarray, np.ndarray]:
    img = np.full((px + 80, px + 80), 90, np.uint8)
    img[40 : 40 + px, 40 : 40 + px] = render_card(marker_layout(DEFAULT_FAMILY, marker_id), px)
    discs = np.asarray(marker_layout(DEFAULT_FAMILY, marker_id).discs, np.float64) * px - 0.5 + 40
    blurred = degrade.motion_blur(img, length, angle)  # float: a frame is uint8
    return np.clip(np.rint(blurred), 0, 255).astype(np.uint8), discs


def test_motion_blurred_codes_are_read_by_the_smear_templates(monkeypatch: pytest.MonkeyPatch) -> None:
    """A small card smeared by more than two cell widths: fitted with the smears, the
    whole card's code is read where the isotropic fit and the nine samples do not agree,
    and never as a wrong one."""
    found = {True: 0, False: 0}
    for marker_id in range(0, 60, 5):
        for angle in (0.3, 1.1, 2.0, 2.7):
            img, discs = _smeared_card(marker_id, 32, 8.0, angle)
            cand = np.column_stack([discs, np.full(4, 0.125 * 32), np.ones(4)])
            for on in (True, False):
                monkeypatch.setattr(tg, "SMEARED_MAX_READS", 4 if on else 0)  # the driver's budget per frame
                out = tg.assemble_targets(img, cand)
                assert all(t.id == marker_id for t in out)
                found[on] += any(t.id == marker_id for t in out)
    assert found[True] > found[False], found


def test_small_cards_with_clipped_white_paper_are_read() -> None:
    # A brightly lit card 10 m off (4 px discs) with its paper clipped to white: the blur
    # between black cells and the paper clips with it, which a linear blur never
    # predicts. Read through the clipped templates, most such cards are found (without
    # them, fewer than half), and none as another card.
    from app.core.detection import Detector, load_default_classifier
    from app.core.geometry import Camera, Pose
    from app.sim.scenes import PlacedTarget, Scene, render_frame, single_frame_scene

    camera = Camera.pinhole(800.0, 640, 480)
    detector = Detector(load_default_classifier())
    rng = np.random.default_rng(3)
    found = wrong = 0
    for _ in range(20):
        scene = single_frame_scene(rng, camera, n_targets=1, distance_m=(10.0, 10.0), tilt_deg=(0, 0),
                                   marker_size_m=0.2)
        card = scene.targets[0]
        centre, roll = card.point(np.array([[0.5, 0.5]]))[0], rng.uniform(0, np.pi / 2)
        x, y = np.array([np.cos(roll), np.sin(roll), 0.0]), np.array([-np.sin(roll), np.cos(roll), 0.0])
        rolled = PlacedTarget(card.id, card.family, 0.2, centre - 0.1 * (x + y), x, y)
        image, _ = render_frame(Scene(scene.background, [rolled]), camera, Pose(np.eye(3), np.zeros(3)), rng,
                                degrade.Degradation(gain=2.0, read_sigma=0.005))
        ids = [t.id for t in detector.detect(image).targets]
        found += card.id in ids
        wrong += sum(i != card.id for i in ids)
    assert found >= 14 and wrong == 0, (found, wrong)


def test_small_cards_rolled_45_degrees_with_faint_codes_are_found() -> None:
    # A card 12 m off (3.3 px discs) turned about 45 degrees in its plane, seen through
    # haze or glare (contrast 0.3-1): its neighbouring discs fall in the corners of each
    # disc's 12x12 window and lower the disc's blob score, so the level-0 threshold the
    # classifier is trained at (0.25) keeps about half of them. The survey's thorough
    # detector runs it at 0.18: more cards are found, and none as another card.
    from app.core.detection import Detector, load_default_classifier
    from app.core.geometry import Camera, Pose
    from app.sim.scenes import PlacedTarget, Scene, render_frame, single_frame_scene

    camera = Camera.pinhole(800.0, 640, 480)
    classifier = load_default_classifier()
    live, thorough = Detector(classifier), Detector(classifier, thorough=True)
    rng = np.random.default_rng(11)
    found = {False: 0, True: 0}
    wrong = 0
    for _ in range(50):
        scene = single_frame_scene(rng, camera, n_targets=1, distance_m=(12.0, 12.0), tilt_deg=(0, 0),
                                   marker_size_m=0.2)
        card = scene.targets[0]
        centre, roll = card.point(np.array([[0.5, 0.5]]))[0], np.deg2rad(45.0 + rng.uniform(-5.0, 5.0))
        x, y = np.array([np.cos(roll), np.sin(roll), 0.0]), np.array([-np.sin(roll), np.cos(roll), 0.0])
        rolled = PlacedTarget(card.id, card.family, 0.2, centre - 0.1 * (x + y), x, y)
        gain = rng.uniform(0.3, 1.0)
        image, _ = render_frame(Scene(scene.background, [rolled]), camera, Pose(np.eye(3), np.zeros(3)), rng,
                                degrade.Degradation(gain=gain, offset=rng.uniform(0.0, 1.0 - gain), read_sigma=0.01,
                                                    jpeg_quality=90))
        for careful, detector in ((False, live), (True, thorough)):
            ids = [t.id for t in detector.detect(image).targets]
            found[careful] += card.id in ids
            wrong += sum(i != card.id for i in ids)
    assert found[True] >= 42 and found[True] >= found[False] + 6 and wrong == 0, (found, wrong)  # 46 and 36 of 50
