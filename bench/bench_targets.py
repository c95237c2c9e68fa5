"""The targets stage alone (app.core.detection.targets.assemble_targets): proposals, survivors of
each check and time per sub-stage, on rendered 640x480 frames of each condition, fed
either the true discs plus simulated false candidates (``simulate_candidates``: code
cells, card corners, random points, dark texture spots) or the real candidate stage's
output (``find_candidates`` with the default classifier; its time is not counted here).
As in ``Detector.detect``, the stage is given the frame's ``cv2.pyrDown`` pyramid (the
candidate stage builds it anyway), so its time is not counted either.

Columns: proposals / quick / verified / identified are mean quadrilaterals per frame
after grouping, the 16-sample quick check, the full photometric check and
identification; completed: of the identified, the mean per frame found by completing a
card from three discs (``COMPLETE_MAX``); rate is found-with-the-right-id-and-all-discs-within-2-px over the
counted targets (as bench/bench_detect.py); false = detections that are no target;
group / verify / refine / identify / complete are median wall ms per frame (one thread);
total is the median (and p90) of the thread's CPU ms per frame, which other processes on
the machine do not inflate.

Run: ``.venv/bin/python bench/bench_targets.py`` (~1 min), ``--frames 20`` for a quick look.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from app.core.detection import assemble_targets, find_candidates, load_default_classifier  # noqa: E402
from app.core.detection.candidates import pyramid  # noqa: E402
from app.sim.candidates import simulate_candidates  # noqa: E402
from bench.bench_detect import EMPTY, Stats, draw_frame, score_frame  # noqa: E402
from app.sim.truth import truth_cards  # noqa: E402

CONDITIONS = ("default", "far", "blur", "dark", "clutter", "clean", EMPTY)
STAGES = ("group", "verify", "refine", "identify", "complete")
COUNTS = ("proposals", "quick", "verified", "identified", "completed")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=60, help="frames per condition (default 60)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--conditions", default=",".join(CONDITIONS))
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    classifier = load_default_classifier()
    conditions = [c for c in args.conditions.split(",") if c]
    rows = []
    with tqdm(total=len(conditions) * args.frames, desc="frames", unit="fr", file=sys.stderr) as bar:
        for condition in conditions:
            acc = {src: {"stats": Stats(), "ms": {k: [] for k in (*STAGES, "total")},
                         "n": {k: [] for k in COUNTS}, "cands": []} for src in ("simulated", "real")}
            for i in range(args.frames):
                image, truth = draw_frame(args.seed, condition, i, None)
                cards = truth_cards(truth, None)
                rng = np.random.default_rng([args.seed, i, 7])
                sources = {"simulated": simulate_candidates(image, truth.targets, rng),
                           "real": find_candidates(image, classifier)}
                levels = pyramid(image)
                for src, cand in sources.items():
                    a = acc[src]
                    timing: dict[str, float] = {}
                    counts: dict[str, int] = {}
                    start = time.thread_time()
                    found = assemble_targets(image, cand, timing=timing, counts=counts, pyramid=levels)
                    a["ms"]["total"].append((time.thread_time() - start) * 1e3)
                    for k in STAGES:
                        a["ms"][k].append(timing[k])
                    for k in COUNTS:
                        a["n"][k].append(counts[k])
                    a["cands"].append(len(cand))
                    score_frame(a["stats"], [(t.id, t.discs) for t in found], cards, clean=condition == "clean")
                bar.update()
            for src, a in acc.items():
                rows.append((condition, src, a))
    print(f"## Targets stage alone, 640x480, {args.frames} frames per condition, seed {args.seed}\n")
    print("| condition | candidates | cand/frame | proposals | quick | verified | identified | completed | rate "
          "| false | wrong ids | group ms | verify ms | refine ms | identify ms | complete ms | total CPU ms (median) "
          "| total CPU ms (p90) |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for condition, src, a in rows:
        s = a["stats"]
        rate = "-" if not s.targets else f"{100 * s.rate:.1f}%"
        n = {k: np.mean(v) for k, v in a["n"].items()}
        ms = {k: np.median(v) for k, v in a["ms"].items()}
        print(f"| {condition} | {src} | {np.mean(a['cands']):.0f} | {n['proposals']:.1f} | {n['quick']:.1f} "
              f"| {n['verified']:.1f} | {n['identified']:.2f} | {n['completed']:.2f} | {rate} | {s.false} "
              f"| {s.wrong_ids} "
              f"| {ms['group']:.3f} | {ms['verify']:.3f} | {ms['refine']:.3f} | {ms['identify']:.3f} "
              f"| {ms['complete']:.3f} "
              f"| {ms['total']:.3f} | {np.percentile(a['ms']['total'], 90):.3f} |")


if __name__ == "__main__":
    main()
