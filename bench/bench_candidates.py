"""Disc candidates (stage 1 + condensed 1-NN + NMS) with the shipped default classifier:
training statistics, per-condition recall, false candidates and single-threaded speed.

Run: ``.venv/bin/python bench/bench_candidates.py [--frames 100] [--seed 1]``
(prints markdown tables). Frames come from ``scenes.scenario_frame`` with seeds the
classifier was not trained or calibrated on. A disc counts when it is visible (the
simulator's flag, minus discs hidden behind a nearer card) and at least 4 px across.
"""

from __future__ import annotations

import os

# Single-threaded throughout: BLAS (stage 2 is a matrix product) and OpenCV.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core.detection import candidates as cand  # noqa: E402
from app.core.detection import warm_up  # noqa: E402
from app.learning import training  # noqa: E402

CONDITIONS = ("default", "far", "blur", "dark", "clutter")


def _fmt(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def training_table(classifier: cand.DiscClassifier) -> str:
    s = classifier.stats
    rows = [
        ("Stage 1 false negatives, held-out disc windows (1b screen; paper: ~1%)", s.get("screen_fn_rate_heldout")),
        ("Stage 1+2 false negatives, held-out disc windows", s.get("heldout_fn_rate_stage1_and_2")),
        ("Disc recall of stages 1+2 on the calibration frames", s.get("calibration_disc_recall_stage1_and_2")),
        ("Stage 1a rejection factor, marker-free photos", s.get("stage1a_rejection_factor")),
        ("Stage 1 rejection factor, marker-free photos (paper: ~3000)", s.get("stage1_rejection_factor")),
        ("All windows / reported candidates, marker-free photos", s.get("candidate_rejection_factor")),
        ("Stage 2 condensation: examples -> Hart -> Gates (paper: 27,558 -> 382)",
         f"{s.get('condensation_examples')} -> {s.get('condensation_hart_prototypes')} -> "
         f"{s.get('condensation_prototypes')}"),
        ("Held-out agreement, condensed vs full 1-NN (windows stage 2 sees)",
         s.get("heldout_agreement_condensed_vs_full")),
        ("Held-out accuracy, full 1-NN / condensed", f"{_fmt(s.get('heldout_full_1nn_accuracy'))} / "
                                                     f"{_fmt(s.get('heldout_condensed_accuracy'))}"),
        ("Training windows: discs / non-discs", f"{s.get('positive_windows')} / {s.get('negative_windows')}"),
    ]
    lines = ["| training statistic (shipped classifier) | value |", "|---|---|"]
    lines += [f"| {name} | {_fmt(value)} |" for name, value in rows]
    return "\n".join(lines)


def _frames(name: str, n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        image, truth = training.safe_scenario_frame(name, rng)
        visible = training.visible_discs(truth)
        vis_set = {(round(u, 6), round(v, 6)) for u, v, _ in visible}
        # Targets whose four discs are all visible: the later stages need all four.
        whole = [t.discs_px for t in truth.targets
                 if all((round(float(u), 6), round(float(v), 6)) in vis_set for u, v in t.discs_px)]
        out.append((image, visible, training.all_discs(truth), whole))
    return out


def evaluate(classifier: cand.DiscClassifier, name: str, n: int, seed: int) -> dict[str, float]:
    frames = _frames(name, n, seed)
    for image, *_ in frames[:3]:
        cand.find_candidates(image, classifier)  # warm-up
    ms: list[float] = []
    ms_stage1: list[float] = []
    n_cand: list[int] = []
    n_false: list[int] = []
    discs = hit = hit_loose = targets = targets_ok = 0
    radius_ratio: list[float] = []
    for image, visible, every, whole in frames:
        # Best of three runs per frame: the machine is shared, and the best run is the
        # one nothing else interrupted.
        runs = []
        for _ in range(3):
            start = time.perf_counter()
            found = cand.find_candidates(image, classifier)
            runs.append((time.perf_counter() - start) * 1e3)
        ms.append(min(runs))
        runs = []
        for _ in range(3):
            start = time.perf_counter()
            cand.stage1_windows(image, classifier)
            runs.append((time.perf_counter() - start) * 1e3)
        ms_stage1.append(min(runs))
        n_cand.append(len(found))
        far = np.ones(len(found), bool)
        for u, v, d in every:
            far &= np.hypot(found[:, 0] - u, found[:, 1] - v) > 0.75 * d
        n_false.append(int(far.sum()))
        for u, v, d in visible:
            if d < 4.0:
                continue
            discs += 1
            if len(found) == 0:
                continue
            dist = np.hypot(found[:, 0] - u, found[:, 1] - v)
            j = int(np.argmin(dist))
            hit += dist[j] <= 1.5
            hit_loose += dist[j] <= 0.25 * d
            if dist[j] <= 0.25 * d:
                radius_ratio.append(float(found[j, 2] / (0.5 * d)))
        for pts in whole:
            targets += 1
            if len(found) and all(np.hypot(found[:, 0] - u, found[:, 1] - v).min() <= 0.25 * d
                                  for (u, v), d in zip(pts, [_diameter(visible, p) for p in pts])):
                targets_ok += 1
    rr = np.asarray(radius_ratio) if radius_ratio else np.ones(1)
    return {
        "discs": discs,
        "recall": hit / max(discs, 1),
        "recall_loose": hit_loose / max(discs, 1),
        "targets": targets,
        "target_rate": targets_ok / max(targets, 1),
        "candidates": float(np.mean(n_cand)),
        "false": float(np.mean(n_false)),
        "ms": float(np.median(ms)),
        "ms_stage1": float(np.median(ms_stage1)),
        "ms_p90": float(np.percentile(ms, 90)),
        "radius": f"{np.median(rr):.2f} [{np.percentile(rr, 5):.2f}, {np.percentile(rr, 95):.2f}]",
    }


def _diameter(visible: np.ndarray, point: np.ndarray) -> float:
    j = int(np.argmin(np.hypot(visible[:, 0] - point[0], visible[:, 1] - point[1])))
    return float(visible[j, 2])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    classifier = cand.load_default_classifier()
    warm_up()  # compile (or load) the detector's kernels before anything is timed

    print("## Disc candidates: training\n")
    print(training_table(classifier))
    print(f"\nStage 2: {classifier.prototypes.shape[0]} prototypes "
          f"({int((classifier.labels == 1).sum())} discs); thresholds: blob "
          f"{', '.join(f'{t:.2f}' for t in classifier.blob_thresholds)}, screen {classifier.screen_threshold:.3f}, "
          f"1-NN {classifier.nn_threshold:.3f}.\n")

    print(f"## Disc candidates per condition ({args.frames} frames each, 640x480, single thread, "
          "time = best of 3 runs per frame)\n")
    print("| condition | discs | recall @1.5 px | recall @d/4 | targets | all 4 discs @d/4 | candidates / frame"
          " | false / frame | radius / true: median [5%, 95%] | ms median (stage 1) | ms p90 |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for k, name in enumerate(CONDITIONS):
        r = evaluate(classifier, name, args.frames, args.seed * 1000 + k)
        print(f"| {name} | {r['discs']} | {r['recall']:.4f} | {r['recall_loose']:.4f} | {r['targets']} | "
              f"{r['target_rate']:.4f} | {r['candidates']:.0f} | {r['false']:.0f} | {r['radius']} | "
              f"{r['ms']:.2f} ({r['ms_stage1']:.2f}) | {r['ms_p90']:.2f} |")
    r = evaluate(classifier, "empty", args.frames, args.seed * 1000 + 99)
    print(f"| empty (no markers) | 0 | - | - | 0 | - | {r['candidates']:.0f} | {r['false']:.0f} | - | "
          f"{r['ms']:.2f} ({r['ms_stage1']:.2f}) | {r['ms_p90']:.2f} |")


if __name__ == "__main__":
    main()
