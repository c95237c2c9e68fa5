"""The whole-card code reader (`code_reader`): small cards the nine samples cannot read are
read right, and cards whose code area shows something that is no code (a pattern one cell
from a code, checkerboards, dice, text) are never named."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from app.core.detection import identification
from app.core.detection import targets as tg
from app.core.detection._frame import Pyramid
from app.core.detection.code_reader import read_cards
from app.core.detection.verification import _measure
from app.core.geometry import Camera, Pose, homographies
from app.core.markers import CODE_ORIGIN, CODE_SIZE, DEFAULT_FAMILY, get_family, marker_layout, render_card
from app.sim import degrade
from app.sim.scenes import render_frame, single_frame_scene
from app.sim.truth import truth_cards

SCALE = 8  # distractors are drawn this much finer than the card is shown, then averaged down


def test_small_blurred_compressed_cards_the_nine_samples_refuse_are_read_right() -> None:
    # Cards 10-13 m off (discs of 3.3-5 px), a little smear and defocus, JPEG at 85: read
    # through their true disc centres, as the detector reads them after refinement.
    camera = Camera.pinhole(800.0, 640, 480)
    rng = np.random.default_rng(11)
    refused = read_right = read_wrong = 0
    for _ in range(30):
        scene = single_frame_scene(rng, camera, n_targets=3, distance_m=(10.0, 13.0), tilt_deg=(0.0, 30.0),
                                   marker_size_m=0.2)
        image, truth = render_frame(scene, camera, Pose.identity(), rng, degrade.Degradation(
            blur_length=float(rng.uniform(0.5, 2.0)), blur_angle=float(rng.uniform(0, np.pi)),
            defocus_radius=0.6, read_sigma=0.005, jpeg_quality=85))
        cards = [c for c in truth_cards(truth, None) if c.counted and 3.3 <= c.disc_px < 5.0]
        if not cards:
            continue
        pyr = Pyramid(image)
        hs = homographies(np.stack([c.points for c in cards]))
        m = _measure(pyr, hs, 3)
        ok, ids, shifts, _, _ = identification._decode(m.cells, DEFAULT_FAMILY, m.white)
        known = np.where(ok[:, None], np.stack([ids, shifts], axis=1), -1)
        reads = read_cards(pyr, hs, DEFAULT_FAMILY, clipped=m.white >= identification.CLIPPED_WHITE_GREY,
                           known=known)
        for k, card in enumerate(cards):
            if ok[k]:
                continue
            refused += 1
            right = reads.ids[k] == card.id and reads.shifts[k] == 0
            read_right += bool(reads.ok[k] and right)
            read_wrong += bool(reads.ok[k] and not right)
    assert refused >= 15, refused  # the nine samples refuse many of these cards
    assert read_right >= 0.9 * refused and read_wrong == 0, (read_right, read_wrong, refused)


def _card_with(draw: object, px: int) -> np.ndarray:
    """A card `px` wide whose code area holds what `draw(canvas, x0, side)` draws (black on
    white, on a canvas `SCALE` times finer)."""
    big = render_card(marker_layout(DEFAULT_FAMILY, 0), px * SCALE).copy()
    x0, side = round(CODE_ORIGIN * px * SCALE), round(CODE_SIZE * px * SCALE)
    big[x0:x0 + side, x0:x0 + side] = 255
    draw(big, x0, side)  # type: ignore[operator]
    return cv2.resize(big, (px, px), interpolation=cv2.INTER_AREA)


def _cells(pattern: np.ndarray) -> object:
    def draw(img: np.ndarray, x0: int, side: int) -> None:
        n = pattern.shape[0]
        for r in range(n):
            for c in range(n):
                if pattern[r, c]:
                    img[x0 + r * side // n:x0 + (r + 1) * side // n, x0 + c * side // n:x0 + (c + 1) * side // n] = 0
    return draw


def _dice(pips: int) -> object:
    at = {1: [(1, 1)], 2: [(0, 0), (2, 2)], 3: [(0, 0), (1, 1), (2, 2)], 4: [(0, 0), (0, 2), (2, 0), (2, 2)],
          5: [(0, 0), (0, 2), (1, 1), (2, 0), (2, 2)], 6: [(0, 0), (1, 0), (2, 0), (0, 2), (1, 2), (2, 2)]}[pips]

    def draw(img: np.ndarray, x0: int, side: int) -> None:
        for r, c in at:
            cv2.circle(img, (x0 + (2 * c + 1) * side // 6, x0 + (2 * r + 1) * side // 6), side // 9, 0, -1)
    return draw


def _text(text: str) -> object:
    def draw(img: np.ndarray, x0: int, side: int) -> None:
        scale = side / 30.0 / max(len(text), 1)
        (w, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, max(1, side // 12))
        cv2.putText(img, text, (x0 + (side - w) // 2, x0 + (side + h) // 2), cv2.FONT_HERSHEY_SIMPLEX, scale, 0,
                    max(1, side // 12), cv2.LINE_AA)
    return draw


def _distractors() -> list[tuple[str, object]]:
    codes = get_family(DEFAULT_FAMILY).codes
    out: list[tuple[str, object]] = []
    for i in (0, 17, 33, 59):  # a code with one cell flipped: no code, in any rotation
        for cell in (0, 4, 7):
            pattern = codes[i].copy().ravel()
            pattern[cell] ^= 1
            out.append((f"code {i}, cell {cell} flipped", _cells(pattern.reshape(3, 3))))
    for n in (2, 4, 6):
        out.append((f"{n}x{n} checkerboard", _cells(np.indices((n, n)).sum(axis=0) % 2)))
    out += [(f"die {k}", _dice(k)) for k in range(1, 7)]
    out += [(f"text {t!r}", _text(t)) for t in ("A", "7", "K", "%", "fido")]
    out += [("blank", _cells(np.zeros((3, 3), int))), ("all black", _cells(np.ones((3, 3), int)))]
    return out


@pytest.mark.parametrize("px", [16, 20, 24, 32, 48])
def test_near_code_distractors_are_never_named(px: int) -> None:
    rng = np.random.default_rng(px)
    named: list[str] = []
    for name, draw in _distractors():
        card = _card_with(draw, px)
        img = np.full((px + 80, px + 80), 110, np.uint8)
        img[40:40 + px, 40:40 + px] = card
        discs = np.asarray(marker_layout(DEFAULT_FAMILY, 0).discs, np.float64) * px - 0.5 + 40
        for blur in ("none", "defocus", "smear"):
            shot = img
            if blur == "defocus":
                shot = degrade.defocus(img, 0.8)
            elif blur == "smear":
                shot = degrade.motion_blur(img, 3.0, float(rng.uniform(0, np.pi)))
            shot = np.clip(np.asarray(shot, np.float64) + rng.normal(0, 1.5, img.shape), 0, 255).astype(np.uint8)
            shot = cv2.imdecode(cv2.imencode(".jpg", shot, [cv2.IMWRITE_JPEG_QUALITY, 85])[1], cv2.IMREAD_GRAYSCALE)
            cand = np.column_stack([discs, np.full(4, 0.125 * px), np.ones(4)])
            named += [f"{name}, {blur}: id {t.id} (margin {t.read_margin:.0f})"
                      for t in tg.assemble_targets(shot, cand)]
    assert not named, named


def _channels_reference(hinv: np.ndarray, x0: int, y0: int, width: int, height: int, sub: int, n: int) -> np.ndarray:
    """numpy reference of `_code_reader_kernels.card_channels`."""
    xs = x0 - 0.5 + (np.arange(width * sub) + 0.5) / sub
    ys = y0 - 0.5 + (np.arange(height * sub) + 0.5) / sub
    x, y = np.meshgrid(xs, ys)
    w = hinv[2, 0] * x + hinv[2, 1] * y + hinv[2, 2]
    u = (hinv[0, 0] * x + hinv[0, 1] * y + hinv[0, 2]) / w
    v = (hinv[1, 0] * x + hinv[1, 1] * y + hinv[1, 2]) / w
    step = CODE_SIZE / n
    col, row = np.floor((u - CODE_ORIGIN) / step).astype(int), np.floor((v - CODE_ORIGIN) / step).astype(int)
    label = np.where((col >= 0) & (col < n) & (row >= 0) & (row < n), row * n + col, n * n)
    label = np.where((u >= 0) & (u <= 1) & (v >= 0) & (v <= 1), label, n * n + 1)
    disc = np.zeros(u.shape, bool)
    for c in np.asarray(marker_layout(DEFAULT_FAMILY, 0).discs):
        disc |= (u - c[0]) ** 2 + (v - c[1]) ** 2 <= 0.125**2
    pixel = (np.arange(height * sub) // sub)[:, None] * width + (np.arange(width * sub) // sub)[None, :]
    flat = pixel[~disc] * (n * n + 2) + label[~disc]
    return np.bincount(flat, minlength=height * width * (n * n + 2)).reshape(height, width, -1) / sub**2


@pytest.mark.parametrize("n", [3, 4])
def test_the_compiled_card_channels_match_the_numpy_reference(n: int) -> None:
    from app.core.detection._code_reader_kernels import card_channels
    from app.core.markers import DISC_CENTRES, DISC_RADIUS

    rng = np.random.default_rng(n)
    for _ in range(5):
        quad = np.array([[10, 12], [40, 9], [43, 41], [8, 38]], np.float64) + rng.normal(0, 2, (4, 2))
        hinv = np.linalg.inv(homographies(quad[None])[0])
        got = card_channels(hinv, -2, -3, 56, 54, 3, n, CODE_ORIGIN, CODE_SIZE, DISC_CENTRES, DISC_RADIUS)
        want = _channels_reference(hinv, -2, -3, 56, 54, 3, n)
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, atol=1e-6)
        assert got[..., :n * n].sum() > 0  # the code's cells are in the patch


def test_a_card_cut_by_the_image_border_is_still_read() -> None:
    # The card's margin runs off the image's left edge; its discs and code are inside.
    px = 60
    img = np.full((120, 120), 110, np.uint8)
    card = render_card(marker_layout(DEFAULT_FAMILY, 42), px)
    img[30:30 + px, 0:px - 3] = card[:, 3:]
    discs = np.asarray(marker_layout(DEFAULT_FAMILY, 42).discs, np.float64) * px - 0.5 + np.array([-3.0, 30.0])
    reads = read_cards(Pyramid(img), homographies(discs[None]), DEFAULT_FAMILY)
    assert reads.ok[0] and reads.ids[0] == 42 and reads.shifts[0] == 0
    cand = np.column_stack([discs, np.full(4, 0.125 * px), np.ones(4)])
    assert [t.id for t in tg.assemble_targets(img, cand)] == [42]


def test_a_4x4_card_is_read_and_a_misread_cell_is_corrected() -> None:
    # fido4x4 codes are four cells apart: a card with one cell printed wrong still reads
    # as its code, as the nine samples read it.
    px = 48
    for marker_id in (0, 77, 281):
        img = np.full((px + 80, px + 80), 110, np.uint8)
        img[40:40 + px, 40:40 + px] = render_card(marker_layout("fido4x4", marker_id), px)
        discs = np.asarray(marker_layout("fido4x4", marker_id).discs, np.float64) * px - 0.5 + 40
        reads = read_cards(Pyramid(img), homographies(discs[None]), "fido4x4")
        assert reads.ok[0] and reads.ids[0] == marker_id and reads.shifts[0] == 0
        code = get_family("fido4x4").codes[marker_id].copy()
        code[1, 2] ^= 1
        img[40:40 + px, 40:40 + px] = _card_with(_cells(code), px)
        reads = read_cards(Pyramid(img), homographies(discs[None]), "fido4x4")
        assert reads.ok[0] and reads.ids[0] == marker_id and reads.shifts[0] == 0


def _censored_reference(stack: np.ndarray, sr: np.ndarray, sc: np.ndarray, tmpl: np.ndarray, gram: np.ndarray,
                        contrast: np.ndarray, sse: np.ndarray, saturated: float) -> np.ndarray:
    """numpy reference of `_code_reader_kernels.censored_fits`: every (function,
    pattern) pair completed, each pattern's best total."""
    n_card = tmpl.shape[1]
    sat = stack[:, sr, sc].astype(np.float64)  # (K, S, n_card + 1)
    kk, tt = np.meshgrid(np.arange(sse.shape[0]), np.arange(sse.shape[1]), indexing="ij")
    kk, tt = kk.ravel(), tt.ravel()
    b = contrast[kk, tt]
    v = tmpl[tt]
    zu = np.einsum("mzc,mc->mz", gram[kk, :2, 2:2 + n_card], v)
    zz = gram[kk, :2, :2] + 1e-9 * np.eye(2)
    coef = np.linalg.solve(zz, (gram[kk, :2, -1] - b[:, None] * zu)[..., None])[..., 0]
    pred = coef[:, :1] + coef[:, 1:] * sat[kk, :, n_card] + b[:, None] * np.einsum("msc,mc->ms", sat[kk, :, :n_card], v)
    short = np.maximum(saturated - pred, 0.0)
    total = (sse[kk, tt] + (short**2).sum(axis=1)).reshape(sse.shape)
    return np.where(np.isfinite(sse), total, np.inf).min(axis=0)


def test_the_compiled_censored_fit_finds_the_two_best_patterns_of_the_numpy_reference() -> None:
    # A card whose white clips: the two best patterns, and their totals, as completing
    # every (function, pattern) pair would give them.
    from app.core.detection import _code_reader_kernels as compiled
    from app.core.detection.code_reader import _card_patch, _patterns, isotropic_psfs, psf_set

    px = 40
    img = np.full((px + 40, px + 40), 200, np.uint8)
    card = render_card(marker_layout(DEFAULT_FAMILY, 17), px).astype(np.float64)
    img[20:20 + px, 20:20 + px] = np.clip(card * 1.3 + 10, 0, 255).astype(np.uint8)  # white clipped at 255
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    discs = np.asarray(marker_layout(DEFAULT_FAMILY, 17).discs, np.float64) * px - 0.5 + 20
    tmpl, _, _ = _patterns(DEFAULT_FAMILY)
    for kernels in (list(isotropic_psfs((0.45, 0.95))), list(psf_set())[:9]):
        patch = _card_patch(Pyramid(img), homographies(discs[None])[0], 9, max(k.shape[0] for k in kernels) // 2,
                            True, 32.0)
        assert patch is not None and patch.saturated is not None and patch.saturated[0].size > 20
        stack = np.stack([cv2.filter2D(patch.channels, -1, k, borderType=cv2.BORDER_REPLICATE) for k in kernels])
        gram, sse, contrast, _ = compiled.pattern_fits(stack, patch.rows, patch.cols, patch.y, tmpl)
        got, _ = compiled.censored_fits(stack, *patch.saturated, tmpl, gram, contrast, sse, 254.0)
        want = _censored_reference(stack, *patch.saturated, tmpl, gram, contrast, sse, 254.0)
        assert list(np.argsort(got)[:2]) == list(np.argsort(want)[:2])
        np.testing.assert_allclose(np.sort(got)[:2], np.sort(want)[:2], rtol=1e-9)
