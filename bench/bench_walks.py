"""The card-only survey on walks that look like real filming, per walk type.

Each walk type is one of the simulator's named example walks (`app.sim.examples.WALKS`):
the bench's survey walk (two loops round the bench room), a hand-held loop near the
middle of the bench room looking out at its walls, a hand-held pan on one spot (no
baseline), and the same loop in a room of 10 cards spread round photo walls (one or two
cards in most frames, or none) and round plain painted walls. For each, over several rooms
(seeds), the walk is rendered, the detector runs on every frame as the survey job runs
it (``Detector.for_survey``: blob candidates too, fitted disc centres), and the survey (``app.core.survey.survey``, cards
only) maps the room. A tracking walk through the same room is then tracked with the
surveyed map and with the true one (as ``bench/bench_survey.py`` does).

Run: ``.venv/bin/python bench/bench_walks.py [--frames 300] [--rooms 8] [--walks bench pan ...]
[--quick]`` (markdown tables; ``--quick``: 2 rooms, 150-frame walks, 40-frame tracking
walks).

A card counts as seen in a frame when the truth has it whole in the image, facing the
camera at cos > 0.3 and with discs over 4 px; it should be mapped when seen in at least
10 frames whose viewing directions span at least 5 degrees. A pan's views all come from
one point, so none of its cards qualifies: the pan's row also counts the cards seen in 10
frames from any direction.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core.detection import Detector, load_default_classifier, warm_up  # noqa: E402
from app.core.survey import FeatureObservations, SurveyError, survey  # noqa: E402
from app.sim import WALKS, ExampleWalk, FrameTruth, Scene, camera_walk, frame_truth, render_walk, walk_speeds  # noqa: E402
from bench.walk_runs import detect_and_track_features, detect_frames, map_fit, track_errors  # noqa: E402

#: A card counts as mapped-worthy when seen in this many frames over this many degrees.
MIN_FRAMES, MIN_SPAN_DEG = 10, 5.0

#: Short names of the survey's warnings, by a phrase of their text (first match).
WARNING_KINDS = (
    ("could not be surveyed", "not surveyed"),
    ("parts of the map are not seen together", "disconnected parts"),
    ("fewer than", "few views"),
    ("too narrow", "narrow"),
    ("only turned on one spot", "pure pan"),
    ("focal length", "lens"),
    ("were ignored", "detections ignored"),
)


def seen(truth: FrameTruth) -> set[int]:
    """The cards a detector should find in a frame: whole in the image, facing the camera
    at cos > 0.3 (72 degrees), discs over 4 px."""
    return {t.id for t in truth.targets if t.visible and t.facing_cos > 0.3 and t.disc_diameter_px > 4.0}


def widest_angle_deg(centres: np.ndarray, point: np.ndarray) -> float:
    """The widest angle at `point` between two of the camera centres (N, 3), degrees."""
    rays = centres - point
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    return float(np.degrees(np.arccos(np.clip((rays @ rays.T).min(), -1.0, 1.0))))


def cards_to_map(scene: Scene, truths: list[FrameTruth], min_span_deg: float) -> set[int]:
    """The cards seen in at least `MIN_FRAMES` frames whose viewing directions span at
    least `min_span_deg`."""
    frames: dict[int, list[np.ndarray]] = {}
    for truth in truths:
        for card in seen(truth):
            frames.setdefault(card, []).append(truth.pose.position)
    centres = {t.id: t.discs.mean(axis=0) for t in scene.targets}
    return {card for card, positions in frames.items()
            if len(positions) >= MIN_FRAMES and widest_angle_deg(np.array(positions), centres[card]) >= min_span_deg}



@dataclass
class RoomRun:
    """One walk through one room: what the survey made of it."""

    seed: int
    tracks: str  # "cards": the card-only survey; "features": with feature tracks beside the cards
    n_frames: int
    n_with_card: int  # frames in which the detector found a card
    recall: float  # cards found / cards seen, over every frame
    to_map: set[int]  # cards seen in MIN_FRAMES frames over MIN_SPAN_DEG
    seen_often: set[int]  # cards seen in MIN_FRAMES frames, any directions
    mapped: set[int] = field(default_factory=set)
    n_registered: int = 0
    focal_pct: float = float("nan")
    disc_rms_mm: float = float("nan")
    wall_s: float = 0.0
    warnings: list[str] = field(default_factory=list)
    failure: str | None = None
    e_true: np.ndarray = field(default_factory=lambda: np.zeros(0))  # tracking errors, m
    e_surv: np.ndarray = field(default_factory=lambda: np.zeros(0))
    n_located_full: int = 0  # tracking frames located with the whole true map
    error_over_std: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per disc, after a rigid fit



def run_walk(walk: ExampleWalk, seed: int, n_frames: int, survey_detector: Detector,
             tracking: tuple[list, list, Scene], kinds: list[str]) -> list[RoomRun]:  # type: ignore[type-arg]
    """Render, detect and feature-track one walk, survey it with each kind of track
    (``kinds``: cards, features); track the room's tracking walk with each map."""
    room = walk.walk(seed, n_frames)
    desc = f"{walk.name} room {seed}"
    features: FeatureObservations | None = None
    track_s = 0.0
    if "features" in kinds:
        frames, truths, detect_s, features, track_s = detect_and_track_features(
            survey_detector, room.frames(walk.room.camera), n_frames, desc)
    else:
        frames, truths, detect_s = detect_frames(survey_detector, room.frames(walk.room.camera), n_frames, desc)
    should = [seen(t) for t in truths]
    found = sum(len(s & {t.id for t in f}) for s, f in zip(should, frames, strict=True))
    return [_survey_run(walk, room.scene, seed, kind, frames, truths, should, found,
                        detect_s + (track_s if kind == "features" else 0.0),
                        features if kind == "features" else None, tracking) for kind in kinds]


def _survey_run(walk: ExampleWalk, scene: Scene, seed: int, kind: str, frames: list, truths: list[FrameTruth],  # type: ignore[type-arg]
                should: list[set[int]], found: int, before_s: float, features: FeatureObservations | None,
                tracking: tuple[list, list, Scene]) -> RoomRun:  # type: ignore[type-arg]
    """Survey one detected walk with one kind of track and measure the map."""
    camera = walk.room.camera
    run = RoomRun(seed, kind, len(frames), sum(bool(f) for f in frames),
                  found / max(sum(len(s) for s in should), 1),
                  cards_to_map(scene, truths, MIN_SPAN_DEG), cards_to_map(scene, truths, 0.0))
    start = time.perf_counter()
    try:
        result = survey(frames, camera.width, camera.height, walk.room.marker_size_m, features=features)
    except SurveyError as e:
        run.failure, run.wall_s = str(e), before_s + time.perf_counter() - start
        return run
    run.wall_s = before_s + time.perf_counter() - start
    run.mapped, run.n_registered, run.warnings = {t.id for t in result.targets}, result.n_registered, result.warnings
    run.focal_pct = 100 * (result.camera.fx / camera.fx - 1)
    truth = {t.id: t.discs for t in scene.targets}
    similar, errors = map_fit(result, truth)
    run.disc_rms_mm = 1000 * float(np.sqrt(np.mean(errors**2)))
    # The reported uncertainties against the errors: std_m is relative to one rigid
    # motion of the whole metric map, so the map is taken to the truth by a rigid fit.
    run.error_over_std = map_fit(result, truth, with_scale=False)[1] / np.concatenate([t.std_m for t in result.targets])
    # Tracking: the surveyed map with the surveyed camera against the true map of the same
    # cards with the true camera, on the frames both locate; and how many frames the whole
    # true map locates.
    t_frames, t_truths, _ = tracking
    surveyed = {t.id: t.discs for t in result.targets}
    e_true = track_errors(t_frames, t_truths, {i: truth[i] for i in surveyed}, camera)
    e_surv = track_errors(t_frames, t_truths, surveyed, result.camera, similar)
    both = np.isfinite(e_true) & np.isfinite(e_surv)
    run.e_true, run.e_surv = e_true[both], e_surv[both]
    run.n_located_full = int(np.isfinite(track_errors(t_frames, t_truths, truth, camera)).sum())
    return run


def warning_counts(runs: list[RoomRun]) -> str:
    """How many warnings of each kind the survey gave, over the rooms."""
    counts: Counter[str] = Counter()
    for run in runs:
        for text in run.warnings:
            counts[next((name for phrase, name in WARNING_KINDS if phrase in text), "other")] += 1
    return ", ".join(f"{name} {n}" for name, n in counts.most_common()) or "none"


def walk_row(walk: ExampleWalk, runs: list[RoomRun]) -> str:
    """The summary row of one walk type over its rooms."""
    ok = [r for r in runs if r.failure is None]
    frames = sum(r.n_frames for r in runs)
    registered = sum(r.n_registered for r in runs)
    to_map = sum(len(r.to_map) for r in runs)
    mapped = sum(len(r.mapped & r.to_map) for r in runs)
    often = sum(len(r.seen_often) for r in runs)
    mapped_often = sum(len(r.mapped & r.seen_often) for r in runs)
    e_true = np.concatenate([r.e_true for r in ok]) if ok else np.zeros(0)
    e_surv = np.concatenate([r.e_surv for r in ok]) if ok else np.zeros(0)
    located = sum(len(r.e_surv) for r in ok)
    located_full = sum(r.n_located_full for r in runs)
    focal = f"{max(abs(r.focal_pct) for r in ok):.3f} %" if ok else "-"
    rms = (f"{np.median([r.disc_rms_mm for r in ok]):.2f} / {max(r.disc_rms_mm for r in ok):.2f}" if ok else "-")
    tracking = (f"{1000 * np.median(e_true):.2f} / {1000 * np.median(e_surv):.2f} ({located} / {located_full})"
                if len(e_true) else "-")
    return (f"| {walk.name} | {runs[0].tracks} | {registered} / {frames} ({100 * registered / frames:.0f} %) "
            f"| {sum(r.n_with_card for r in runs)} | {100 * np.mean([r.recall for r in runs]):.1f} % "
            f"| {mapped} / {to_map} | {mapped_often} / {often} | {focal} | {rms} | {tracking} "
            f"| {np.mean([r.wall_s for r in runs]):.1f} | {len(runs) - len(ok)} "
            f"| {np.mean([len(r.warnings) for r in ok]) if ok else 0:.1f}: {warning_counts(ok)} |")


def describe(walk: ExampleWalk, seeds: list[int], n_frames: int) -> str:
    """A row on how the walk moves and what its frames see, from the truth alone."""
    speed, turn, counts, blur = [], [], [], []
    for seed in seeds:
        room = walk.walk(seed, n_frames)
        s, t = walk_speeds(room.poses)
        speed.append(s)
        turn.append(t)
        counts += [len(seen(frame_truth(walk.room.camera, p, room.scene))) for p in room.poses]
        blur += [b.length_px for b in room.blur] if room.blur else []
    share = np.bincount(np.minimum(counts, 3), minlength=4) / len(counts)
    s, t = np.concatenate(speed), np.concatenate(turn)
    room = walk.room
    return (f"| {walk.name} | {room.name}: {room.n_targets} cards, {room.cards}, {room.walls} walls "
            f"| {walk.kind}{', hand-held' if walk.shake else ''} | {np.median(s):.2f} / {s.max():.2f} "
            f"| {np.median(t):.0f} / {t.max():.0f} | " + " / ".join(f"{100 * x:.0f}" for x in share)
            + f" | {f'{np.median(blur):.1f} / {max(blur):.1f}' if blur else 'preset (0-2 px, half the frames)'} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=300, help="frames of each surveyed walk (30 a second)")
    parser.add_argument("--tracking-frames", type=int, default=100, help="frames of each room's tracking walk")
    parser.add_argument("--rooms", type=int, default=8, help="rooms (seeds 0 .. rooms - 1) per walk type")
    parser.add_argument("--walks", nargs="+", choices=list(WALKS), default=list(WALKS), help="walk types")
    parser.add_argument("--tracks", nargs="+", choices=["cards", "features"], default=["cards", "features"],
                        help="survey with card tracks only, with feature tracks beside them, or both side by side")
    parser.add_argument("--quick", action="store_true", help="2 rooms, 150-frame walks, 40-frame tracking walks")
    parser.add_argument("--details", action="store_true", help="a row per room as well")
    args = parser.parse_args()
    if args.quick:
        args.rooms, args.frames, args.tracking_frames = 2, 150, 40
    cv2.setNumThreads(1)
    detector = Detector(classifier=load_default_classifier())
    warm_up()  # the detector's compiled kernels: not part of the first frame's time
    survey_detector = Detector.for_survey(detector.classifier)
    seeds = list(range(args.rooms))
    walks = [WALKS[name] for name in args.walks]
    started = time.perf_counter()

    tracking: dict[tuple[str, int], tuple[list, list, Scene]] = {}  # type: ignore[type-arg]
    runs: dict[tuple[str, str], list[RoomRun]] = {}
    for walk in walks:
        for seed in seeds:
            key = (walk.room.name, seed)
            if key not in tracking:
                scene = walk.room.scene(seed)
                # Its own stream: the same tracking walk whatever the surveyed walk.
                rng = np.random.default_rng([seed, 1])
                poses = camera_walk(rng, walk.room.size, args.tracking_frames, "tracking")
                t_frames, t_truths, _ = detect_frames(detector, render_walk(scene, walk.room.camera, poses, rng),
                                                    len(poses), f"{walk.room.name} room {seed}: tracking walk")
                tracking[key] = (t_frames, t_truths, scene)
            for run in run_walk(walk, seed, args.frames, survey_detector, tracking[key], args.tracks):
                runs.setdefault((walk.name, run.tracks), []).append(run)

    print(f"\nWalks: {args.frames} frames at 30 a second, rooms (seeds) {seeds[0]}-{seeds[-1]}, 640x480, "
          f"f 820 px, k1 -0.12, cards of 0.2 m; tracking walks of {args.tracking_frames} frames; "
          f"{time.perf_counter() - started:.0f} s in all\n")
    print("| walk | room | kind | speed, median / max (m/s) | turn, median / max (deg/s) "
          "| frames seeing 0 / 1 / 2 / 3+ cards (%) | motion blur, median / max (px) |")
    print("|---|---|---|---|---|---|---|")
    for walk in walks:
        print(describe(walk, seeds, args.frames))
    print("\n| walk | tracks | frames registered | frames with a card detected | cards found per card seen "
          f"| cards mapped / seen in {MIN_FRAMES}+ frames over {MIN_SPAN_DEG:g}+ deg "
          f"| mapped / seen in {MIN_FRAMES}+ frames | focal error, worst | disc RMS, median / worst (mm) "
          "| tracking median, true / surveyed map (mm) (frames located: surveyed / whole true map) "
          "| detection + survey per room (s) | surveys failed | warnings per room: kinds over all rooms |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for walk in walks:
        for kind in args.tracks:
            print(walk_row(walk, runs[walk.name, kind]))
    for walk in walks:
        for kind in args.tracks:
            for r in runs[walk.name, kind]:
                if r.failure:
                    print(f"\n{walk.name} ({kind}), survey failed in room {r.seed}: {r.failure}")
    print("\nThe discs' reported uncertainty against their error after a rigid fit to the truth: "
          "|error| / std_m is the square root of chi-square(3) / 3 if std_m is honest (median 0.89, "
          "95 % under 1.61).\n")
    print("| walk | tracks | discs | \\|error\\| / std_m, median | share under 1.61 |")
    print("|---|---|---|---|---|")
    for walk in walks:
        for kind in args.tracks:
            ratio = np.concatenate([r.error_over_std for r in runs[walk.name, kind] if r.failure is None] or [[]])
            ratio = ratio[np.isfinite(ratio)]
            print(f"| {walk.name} | {kind} | {len(ratio)} | {np.median(ratio) if len(ratio) else float('nan'):.2f} "
                  f"| {np.mean(ratio < 1.61) if len(ratio) else float('nan'):.0%} |")
    if args.details:
        print("\n| walk | tracks | room | registered | cards mapped / to map | focal error | disc RMS (mm) | s |")
        print("|---|---|---|---|---|---|---|---|")
        for walk in walks:
            for kind in args.tracks:
                for r in runs[walk.name, kind]:
                    print(f"| {walk.name} | {kind} | {r.seed} | {r.n_registered} / {r.n_frames} "
                          f"| {len(r.mapped & r.to_map)} / {len(r.to_map)} | {r.focal_pct:+.3f} % "
                          f"| {r.disc_rms_mm:.2f} | {r.wall_s:.1f} |")


if __name__ == "__main__":
    main()
