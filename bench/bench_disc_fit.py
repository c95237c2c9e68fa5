"""Disc centres on the survey bench's room walks: the detector's centroids (what /track
uses) against the fitted centres (`app.core.detection.disc_fit`, what the survey uses), on the same
detections, against the renderer's truth.

Frames: every 10th pose of the 1000-frame calibration walks of bench_survey's rooms
(`--seeds`), rendered with default degradations (sampled afresh: not bench_survey's
frames, the same rooms and places). Prints the error (px per axis, RMS) by the minor
semi-axis of the disc's image, the error of each card's mean (the common shift of its
four discs, which a survey cannot average away within a view), that mean's systematic
part toward the card's near side by how obliquely the card is seen (it repeats from
view to view, so a survey cannot average it away either), the tails, and the time.

Every frame is also rendered a second time with another draw of its sensor noise (same
pose, same degradation, same clean image) and fitted from the same detections: half the
mean squared difference of the two fits is the part of the error that the images' noise
causes (random), the rest is the fit's model against the renderer (systematic, the same
in both draws). The random part, fitted as a + c / b^2 over the minor semi-axis b, is
what the fit would be left with if its model were exact (a least-squares fit of the
pixels: about as little as any estimator gets from these images);
`bench_survey --noise-floor a c` surveys with it.

Run: ``.venv/bin/python bench/bench_disc_fit.py [--seeds 0 1] [--step 10]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

# This checkout's package, whichever one the environment has installed.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core.detection import Detector, fit_disc_centres, load_default_classifier, warm_up  # noqa: E402
from app.core.geometry import disc_axes, homographies  # noqa: E402
from app.sim import BENCH_CAMERA, BENCH_ROOM, degrade, render_frame  # noqa: E402

BINS = [0.0, 1.5, 2.0, 2.5, 3.0, 4.0, 6.0, 100.0]
FACING_BINS = [0.3, 0.5, 0.7, 0.85, 1.01]


def bin_label(lo: float, hi: float) -> str:
    """A BINS row's label."""
    return f"minor semi-axis {lo:g}-{hi:g} px" if hi < 100 else f"minor semi-axis >= {lo:g} px"


def toward_near_side(discs: np.ndarray) -> np.ndarray:
    """Unit image vectors (T, 2) from each card's middle toward its near side (where
    perspective makes its discs larger), from its four disc centres (T, 4, 2)."""
    axes = disc_axes(discs)
    size = axes[..., 0] * axes[..., 1]
    g = ((size - size.mean(axis=1, keepdims=True))[..., None] * (discs - discs.mean(axis=1, keepdims=True))).sum(1)
    return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)


def noise_floor(first: np.ndarray, second: np.ndarray, b: np.ndarray, fitted: np.ndarray,
                first_mean: np.ndarray, second_mean: np.ndarray) -> None:
    """Print the fitted error (px per axis) split into its random part (half the mean
    squared difference of two noise draws) and its systematic part, by minor semi-axis
    b, and the random part fitted as a + c / b^2."""
    print("\nThe fitted centres' error: the images' noise (random: two noise draws of every frame) "
          "and the fit's model (systematic: the rest), px per axis RMS, discs fitted in both draws\n")
    print("| discs | n | total | random | systematic |")
    print("|---|---|---|---|---|")

    def row(label: str, x: np.ndarray, y: np.ndarray) -> float:
        total = float(np.sqrt(np.mean((x**2 + y**2) / 2)))
        random = float(np.sqrt(np.mean((x - y) ** 2) / 2))
        print(f"| {label} | {len(x)} | {total:.4f} | {random:.4f} | {np.sqrt(max(total**2 - random**2, 0)):.4f} |")
        return random

    centres, randoms, counts = [], [], []
    for lo, hi in zip(BINS[:-1], BINS[1:], strict=True):
        m = fitted & (b >= lo) & (b < hi)
        if m.sum() > 1:
            randoms.append(row(bin_label(lo, hi), first[m], second[m]))
            centres.append(float(np.mean(1 / b[m] ** 2)))
            counts.append(int(m.sum()))
    row("all", first[fitted], second[fitted])
    row("card's mean of its four discs", first_mean, second_mean)
    # Weighted least squares of the bins' random RMS on their mean 1 / b^2.
    A = np.stack([np.ones(len(centres)), centres], axis=1) * np.sqrt(counts)[:, None]
    a, c = np.linalg.lstsq(A, np.array(randoms) * np.sqrt(counts), rcond=None)[0]
    print(f"\nrandom part ~ {a:.4f} + {c:.4f} / b^2 px per axis (bench_survey.py --noise-floor {a:.4f} {c:.4f})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--step", type=int, default=10, help="every step-th frame of the 1000-frame walk")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    detector = Detector(load_default_classifier())
    warm_up()
    centroid, fitted, refitted, minor, was_fitted, both, facing, near = [], [], [], [], [], [], [], []
    fit_s, n_frames = 0.0, 0
    ranges = degrade.PRESETS["default"]
    for seed in args.seeds:
        room = BENCH_ROOM.walk(seed, 1000, kind="calibration")  # bench_survey's room, walk and rendering
        scene, walk, rng = room.scene, room.poses[:: args.step], room.rng
        # The second noise draws have their own stream, so the first frames are render_walk's.
        noise_rng = np.random.default_rng([seed, 2])
        for pose in tqdm(walk, desc=f"room {seed}", unit="frame"):
            degradation = ranges.sample(rng)
            image, truth = render_frame(scene, BENCH_CAMERA, pose, rng, degradation)
            again, _ = render_frame(scene, BENCH_CAMERA, pose, noise_rng, degradation)
            n_frames += 1
            by_id = {t.id: t for t in truth.targets}
            found = [t for t in detector.detect(image).targets if t.id in by_id]
            if not found:
                continue
            discs = np.array([t.discs for t in found])
            start = time.perf_counter()
            cards = homographies(discs)
            fit = fit_disc_centres(image, discs, cards)
            fit_s += time.perf_counter() - start
            refit = fit_disc_centres(again, discs, cards)  # the same detections' homographies
            true = np.array([by_id[t.id].discs_px for t in found])
            centroid.append(discs - true)
            fitted.append(fit.centres - true)
            refitted.append(refit.centres - true)
            minor.append(disc_axes(discs)[..., 1])
            was_fitted.append(fit.fitted)
            both.append(fit.fitted & refit.fitted)
            facing.append([by_id[t.id].facing_cos for t in found])
            near.append(toward_near_side(true))
    c, f = np.concatenate(centroid), np.concatenate(fitted)
    b, ok = np.concatenate(minor).ravel(), np.concatenate(was_fitted).ravel()
    ce, fe = c.reshape(-1, 2), f.reshape(-1, 2)

    def rms(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean(x**2))) if x.size else float("nan")

    print(f"\nDisc centres, rooms {args.seeds}, every {args.step}th frame of the 1000-frame calibration walks "
          f"({n_frames} frames, {len(c)} card views, {ce.shape[0]} discs, {100 * ok.mean():.1f}% fitted), "
          "default degradations, error against the renderer's truth (px per axis, RMS)\n")
    cn, fn = np.hypot(*ce.T), np.hypot(*fe.T)
    print("| discs | n | centroid (/track): RMS / median 2-D | fitted (survey): RMS / median 2-D "
          "| ratio fitted / centroid: RMS / median |")
    print("|---|---|---|---|---|")

    def row(label: str, m: np.ndarray) -> None:
        c_rms, f_rms, c_med, f_med = rms(ce[m]), rms(fe[m]), np.median(cn[m]), np.median(fn[m])
        print(f"| {label} | {m.sum()} | {c_rms:.4f} / {c_med:.4f} | {f_rms:.4f} / {f_med:.4f} "
              f"| {f_rms / c_rms:.2f} / {f_med / c_med:.2f} |")

    for lo, hi in zip(BINS[:-1], BINS[1:], strict=True):
        m = (b >= lo) & (b < hi)
        if m.sum():
            row(bin_label(lo, hi), m)
    row("all", np.ones(len(b), bool))
    cm, fm = c.mean(axis=1), f.mean(axis=1)
    print(f"| card's mean of its four discs (RMS) | {len(c)} | {rms(cm):.4f} | {rms(fm):.4f} | {rms(fm) / rms(cm):.2f} |")
    cos, g = np.concatenate(facing), np.concatenate(near)
    c_near, f_near = 1000 * (cm * g).sum(1), 1000 * (fm * g).sum(1)
    for lo, hi in zip(FACING_BINS[:-1], FACING_BINS[1:], strict=True):
        m = (cos >= lo) & (cos < hi)
        if m.sum() > 1:
            def se(x: np.ndarray) -> str:
                return f"{x[m].mean():+.2f} +- {x[m].std() / np.sqrt(m.sum()):.2f}"
            print(f"| card's mean toward its near side (mean +- s.e., mpx), seen at cos {lo:g}-{min(hi, 1):g} "
                  f"| {m.sum()} | {se(c_near)} | {se(f_near)} | |")
    for q in (0.9, 0.99):
        print(f"| 2-D error, {round(100 * q)}th percentile | {len(cn)} | {np.quantile(cn, q):.4f} "
              f"| {np.quantile(fn, q):.4f} | {np.quantile(fn, q) / np.quantile(cn, q):.2f} |")
    r = np.concatenate(refitted)
    twice = np.concatenate(both)  # (cards, 4): fitted in both draws
    whole = twice.all(axis=1)
    noise_floor(fe, r.reshape(-1, 2), b, twice.ravel(), fm[whole], r.mean(axis=1)[whole])
    print(f"\nfit time: {1000 * fit_s / n_frames:.1f} ms per frame ({1000 * fit_s / max(len(c), 1):.2f} ms per card)")


if __name__ == "__main__":
    main()
