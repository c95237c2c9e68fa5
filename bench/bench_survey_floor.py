"""How close to the truth the survey's own optimum lies: the floor a survey can reach.

For each walk type and room, the walk is rendered, the detector runs on every frame as
the survey job runs it (``Detector.for_survey``: blob candidates too, fitted disc centres) and the feature tracker follows the
walls (the detected cards left out), as ``bench/bench_walks.py`` does. Then, instead of
surveying, the survey's state is set to the truth (every frame that observes something at
its true pose, every card at its true discs, the true lens), the feature points are
triangulated from it, and the final bundle adjustment (``app.core.survey.reconstruction.adjust``,
lens free) runs from there (``bench.walk_runs.survey_floor``, which the walks benchmark
shares). Where it settles is the optimum of the observations themselves: no survey from
these observations can be expected nearer the truth. Three variants tell which
observations set the floor:

* *detected discs, tracked features*: the observations a survey has;
* *exact discs, tracked features*: the disc observations replaced by the true discs'
  projections (so only the feature tracks' errors remain);
* *detected discs, exact features*: the feature observations replaced by their
  triangulated points' true projections (so only the discs' errors remain).

The figure is the disc RMS after the best similarity transform to the true discs (mm),
as in the walks benchmark, over the cards the detector saw in 2 frames or more.

Run: ``.venv/bin/python bench/bench_survey_floor.py [--rooms 2] [--frames 300]
[--walks centre_loop sparse bench]`` (markdown table).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core.detection import Detector, load_default_classifier, warm_up
from app.sim import WALKS, ExampleWalk
from bench.walk_runs import detect_and_track_features, disc_rms_mm, survey_floor

VARIANTS = ("detected discs, tracked features", "exact discs, tracked features", "detected discs, exact features")


def floor_mm(walk: ExampleWalk, seed: int, n_frames: int, detector: Detector) -> tuple[dict[str, float], int]:
    """Disc RMS (mm) where the final bundle adjustment settles from the truth, per variant;
    and the number of cards."""
    room = walk.walk(seed, n_frames)
    camera = walk.room.camera
    frames, truths, _, tracked, _ = detect_and_track_features(detector, room.frames(camera), n_frames,
                                                              f"{walk.name} room {seed}")
    true_discs = {t.id: t.discs for t in room.scene.targets}
    out: dict[str, float] = {}
    n_cards = 0
    for variant in VARIANTS:
        discs = survey_floor(frames, truths, camera, walk.room.marker_size_m, true_discs, tracked,
                             exact_discs=variant.startswith("exact discs"),
                             exact_features=variant.endswith("exact features"))
        out[variant] = disc_rms_mm(discs, true_discs)
        n_cards = len(discs)
    return out, n_cards


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=300, help="frames of each walk (30 a second)")
    parser.add_argument("--rooms", type=int, default=2, help="rooms (seeds 0 .. rooms - 1) per walk type")
    parser.add_argument("--walks", nargs="+", choices=list(WALKS), default=["bench", "centre_loop", "sparse"],
                        help="walk types")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    detector = Detector.for_survey(load_default_classifier())
    warm_up()
    started = time.perf_counter()
    rows = []
    for name in args.walks:
        for seed in range(args.rooms):
            figures, n_cards = floor_mm(WALKS[name], seed, args.frames, detector)
            rows.append((name, seed, n_cards, figures))
    print(f"\nThe survey's floor: {args.frames}-frame walks, rooms 0-{args.rooms - 1}; "
          f"{time.perf_counter() - started:.0f} s in all\n")
    print("| walk | room | cards | " + " | ".join(f"disc RMS from the truth, {v} (mm)" for v in VARIANTS) + " |")
    print("|---|---|---|" + "---|" * len(VARIANTS))
    for name, seed, n_cards, figures in rows:
        print(f"| {name} | {seed} | {n_cards} | " + " | ".join(f"{figures[v]:.2f}" for v in VARIANTS) + " |")


if __name__ == "__main__":
    main()
