"""The survey on walks that look like real filming, per walk type: is the map complete,
is it right, and does it say so when it is not?

Each walk type is one of the simulator's named example walks (`app.sim.examples.WALKS`):
the bench's survey walk (two loops round the bench room), a hand-held loop near the
middle of the bench room looking out at its walls (*centre_loop*), a hand-held pan on one
spot (no baseline), the same loop in a room of 10 cards spread round photo walls (one or
two cards in most frames, or none: *sparse*) and round plain painted walls (*plain*), in
a furnished room, and in the bench room with one long wall bare (*bare_wall*: its cards
taken off and the wall painted plain, so that for about a third of each turn the camera
sees neither a card nor texture to track; the same room, less that wall, and the same
walk as *centre_loop* for the same seed). For each, over several rooms (seeds), the walk
is rendered, the detector runs on every frame as the survey job runs it
(``Detector.for_survey``: blob candidates too, fitted disc centres), the feature tracker
follows the walls through the same frames (the detected cards left out), and the survey
(``app.core.survey.survey``) maps the room with the cards alone (*cards*) and with the
feature tracks beside them (*features*). A tracking walk through the same room is then
tracked with the surveyed map and with the true one (as ``bench/bench_survey.py`` does).

Run: ``.venv/bin/python bench/bench_walks.py [--rooms 16] [--frames 300] [--walks bench pan ...]
[--tracks cards|features|both] [--no-floor] [--quick] [--exact-discs PX]`` (markdown tables on
stdout, one row per room last; ``--quick``: 2 rooms, 150-frame walks, 40-frame tracking walks;
``--exact-discs``: the detected disc centres replaced by the true ones plus noise, to see
what the detector's bias costs).

A card counts as seen in a frame when the truth has it whole in the image, facing the
camera at cos > 0.3 and with discs over 4 px; it should be mapped when seen in at least
10 frames whose viewing directions span at least 5 degrees. A pan's views all come from
one point, so none of its cards qualifies: the pan's row also counts the cards seen in 10
frames from any direction.

A mapped card is *wrong* when one of its discs lies more than 5 cm from the truth, or
more than 3 of its reported ``std_m``, after a similarity fit of the map to the truth
that the wrong cards do not pull (``walk_runs.check_map``); it is *named* when one of the
survey's typed map warnings lists it. A survey that raises ``SurveyError`` is *refused*:
no map, and no wrong card. The *floor* is where the survey's final bundle adjustment
settles from the truth with the same observations (``walk_runs.survey_floor``, as
``bench/bench_survey_floor.py``'s detected-discs variant; with the cards alone for the
card-only survey).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core.detection import (
    DetectedTarget,
    Detector,
    load_default_classifier,
    warm_up,
)
from app.core.geometry import Camera
from app.core.survey import FeatureObservations, SurveyError, SurveyResult, survey
from app.core.survey.features import texture_warning
from app.sim import (
    WALKS,
    ExampleWalk,
    FrameTruth,
    Scene,
    camera_walk,
    frame_truth,
    render_walk,
    walk_speeds,
)
from app.sim.examples import BareWallRoom
from bench.walk_runs import (
    WRONG_M,
    check_map,
    detect_and_track_features,
    detect_frames,
    disc_rms_mm,
    survey_floor,
    track_errors,
)

#: A card counts as mapped-worthy when seen in this many frames over this many degrees.
MIN_FRAMES, MIN_SPAN_DEG = 10, 5.0
#: A focal length off by more than this (percent) needs a lens warning.
FOCAL_TOLERANCE_PCT = 0.5
#: What |error| / std_m of an honest std_m looks like: the 95th percentile of the square
#: root of chi-square(3) / 3.
HONEST_95 = 1.61

#: Short names of the survey's warnings that are not typed map warnings, by a phrase of
#: their text (first match); the typed ones go by their kind.
WARNING_KINDS = (
    ("could not be surveyed", "not surveyed"),
    ("parts of the map are not seen together", "disconnected parts"),
    ("fewer than", "few views"),
    ("too narrow", "narrow"),
    ("only turned on one spot", "pure pan"),
    ("focal length", "lens"),
    ("principal point", "lens"),
    ("were ignored", "detections ignored"),
)
#: A warning about the lens (its focal length, principal point or calibration) mentions one of these.
LENS_PHRASES = ("focal", "lens")


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


def lens_warned(result: SurveyResult) -> bool:
    """Whether the survey warned about the lens: a warning whose text or kind mentions its
    focal length or the lens."""
    texts = [*result.warnings, *(str(getattr(w.kind, "value", w.kind)) for w in result.map_warnings)]
    return any(phrase in text.lower() for text in texts for phrase in LENS_PHRASES)


def warning_kinds(result: SurveyResult) -> list[str]:
    """The kind of each of the survey's warnings: the typed map warnings' own, the others'
    by `WARNING_KINDS`."""
    typed = {w.message for w in result.map_warnings}
    kinds = [str(getattr(w.kind, "value", w.kind)) for w in result.map_warnings]
    kinds += [next((name for phrase, name in WARNING_KINDS if phrase in text), "other")
              for text in result.warnings if text not in typed]
    return kinds


@dataclass
class RoomRun:
    """One walk through one room: what the survey made of it."""

    seed: int
    tracks: str  # "cards": the card-only survey; "features": with feature tracks beside the cards
    n_frames: int
    n_with_card: int  # frames in which the detector found a card of the room
    recall: float  # cards found / cards seen, over every frame
    to_map: set[int]  # cards seen in MIN_FRAMES frames over MIN_SPAN_DEG
    seen_often: set[int]  # cards seen in MIN_FRAMES frames, any directions
    before_s: float = 0.0  # detection (and with feature tracks, feature tracking)
    survey_s: float = 0.0
    refusal: str | None = None  # the SurveyError's message
    crash: str | None = None  # any other exception the survey raised
    mapped: set[int] = field(default_factory=set)
    n_registered: int = 0
    card_frames_lost: int = 0  # frames with a card of the room detected that did not register
    focal_pct: float = float("nan")
    lens_warned: bool = False
    wrong: set[int] = field(default_factory=set)
    wrong_named: set[int] = field(default_factory=set)
    wrong_far: set[int] = field(default_factory=set)  # wrong cards with a disc over WRONG_M off
    disc_rms_mm: float = float("nan")  # every mapped card of the room, after the robust fit
    floor_mm: float = float("nan")  # the floor of the same cards
    floor_failure: str | None = None
    warnings: list[str] = field(default_factory=list)
    kinds: list[str] = field(default_factory=list)
    error_over_std: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per disc, after a rigid fit
    e_true: np.ndarray = field(default_factory=lambda: np.zeros(0))  # tracking errors, m
    e_surv: np.ndarray = field(default_factory=lambda: np.zeros(0))
    n_located_full: int = 0  # tracking frames located with the whole true map

    @property
    def ok(self) -> bool:
        """Whether the survey made a map."""
        return self.refusal is None and self.crash is None

    @property
    def floor_ratio(self) -> float:
        """Disc RMS over the floor's."""
        return self.disc_rms_mm / self.floor_mm if self.floor_mm > 0 else float("nan")

    @property
    def focal_unwarned(self) -> bool:
        """A focal length off by more than `FOCAL_TOLERANCE_PCT` with no lens warning."""
        return self.ok and abs(self.focal_pct) > FOCAL_TOLERANCE_PCT and not self.lens_warned


def run_walk(walk: ExampleWalk, seed: int, n_frames: int, survey_detector: Detector,
             tracking: tuple[list, list, Scene], kinds: list[str], floor: bool,
             exact_discs_px: float | None = None) -> list[RoomRun]:  # type: ignore[type-arg]
    """Render, detect and feature-track one walk, survey it with each kind of track
    (``kinds``: cards, features); track the room's tracking walk with each map. With
    ``exact_discs_px``, each detected card's disc centres are replaced by the true discs'
    projections plus Gaussian noise of that many px (the detector's bias taken out)."""
    room = walk.walk(seed, n_frames)
    desc = f"{walk.name} room {seed}"
    features: FeatureObservations | None = None
    track_s = 0.0
    if "features" in kinds:
        frames, truths, detect_s, features, track_s = detect_and_track_features(
            survey_detector, room.frames(walk.room.camera), n_frames, desc)
    else:
        frames, truths, detect_s = detect_frames(survey_detector, room.frames(walk.room.camera), n_frames, desc)
    if exact_discs_px is not None:
        frames = exact_discs(frames, truths, room.scene, walk.room.camera, exact_discs_px, seed)
    should = [seen(t) for t in truths]
    found = sum(len(s & {t.id for t in f}) for s, f in zip(should, frames, strict=True))
    return [_survey_run(walk, room.scene, seed, kind, frames, truths, should, found,
                        detect_s + (track_s if kind == "features" else 0.0),
                        features if kind == "features" else None, tracking, floor) for kind in kinds]


def exact_discs(frames: list[list[DetectedTarget]], truths: list[FrameTruth], scene: Scene, camera: Camera,
                noise_px: float, seed: int) -> list[list[DetectedTarget]]:
    """The detected cards with their disc centres replaced by the true discs' projections
    in the frame plus Gaussian noise of ``noise_px``: what the survey would make of the
    same walk if the disc centres had no bias. Detections of ids not in the room are
    dropped."""
    truth = {t.id: t.discs for t in scene.targets}
    rng = np.random.default_rng([seed, 2])
    return [[replace(t, discs=camera.project_map(truth[t.id], ft.pose) + rng.normal(0, noise_px, (4, 2)))
             for t in detected if t.id in truth] for detected, ft in zip(frames, truths, strict=True)]


def _survey_run(walk: ExampleWalk, scene: Scene, seed: int, kind: str, frames: list, truths: list[FrameTruth],  # type: ignore[type-arg]
                should: list[set[int]], found: int, before_s: float, features: FeatureObservations | None,
                tracking: tuple[list, list, Scene], floor: bool) -> RoomRun:  # type: ignore[type-arg]
    """Survey one detected walk with one kind of track and measure the map."""
    camera = walk.room.camera
    truth = {t.id: t.discs for t in scene.targets}
    with_card = [any(t.id in truth for t in f) for f in frames]
    run = RoomRun(seed, kind, len(frames), sum(with_card), found / max(sum(len(s) for s in should), 1),
                  cards_to_map(scene, truths, MIN_SPAN_DEG), cards_to_map(scene, truths, 0.0), before_s=before_s)
    start = time.perf_counter()
    try:
        result = survey(frames, camera.width, camera.height, walk.room.marker_size_m, features=features)
    except SurveyError as e:
        run.refusal, run.survey_s = str(e), time.perf_counter() - start
        return run
    except Exception as e:  # noqa: BLE001 - a survey that breaks is measured, not the end of the run
        run.crash, run.survey_s = f"{type(e).__name__}: {e}", time.perf_counter() - start
        return run
    run.survey_s = time.perf_counter() - start
    run.mapped, run.warnings = {t.id for t in result.targets}, result.warnings
    run.n_registered, run.kinds = result.n_registered, warning_kinds(result)
    # The survey job adds the plain-walls warning to the survey's own (the job has the
    # tracks); so does this bench.
    plain = texture_warning(features, len(frames)) if features is not None else None
    if plain is not None:
        run.kinds.append(str(plain.kind.value))
    run.card_frames_lost = sum(c and p is None for c, p in zip(with_card, result.trajectory, strict=True))
    run.focal_pct = 100 * (result.camera.fx / camera.fx - 1)
    run.lens_warned = lens_warned(result)
    check = check_map(result, truth)
    run.wrong, run.wrong_named = check.wrong, check.wrong_named
    order = [t.id for t in result.targets]
    worst = {i: float(np.nanmax(e)) if np.isfinite(e).any() else np.inf
             for i, e in zip(order, check.errors_m.reshape(-1, 4), strict=True)}
    run.wrong_far = {i for i in check.wrong if worst[i] > WRONG_M}
    finite = np.isfinite(check.errors_m)
    run.disc_rms_mm = 1000 * float(np.sqrt(np.mean(check.errors_m[finite] ** 2))) if finite.any() else float("nan")
    # The reported uncertainties against the errors: std_m is relative to one rigid
    # motion of the whole metric map, so the map is taken to the truth by a rigid fit.
    run.error_over_std = check.rigid_errors_m / check.std_m
    if floor:
        try:
            optimum = survey_floor(frames, truths, camera, walk.room.marker_size_m, truth, features)
            run.floor_mm = disc_rms_mm(optimum, truth, [i for i in order if i in truth])
        except Exception as e:  # noqa: BLE001 - the floor rests on the survey's internals, which may move
            run.floor_failure = f"{type(e).__name__}: {e}"
    # Tracking: the surveyed map with the surveyed camera against the true map of the same
    # cards with the true camera, on the frames both locate; and how many frames the whole
    # true map locates.
    t_frames, t_truths, _ = tracking
    surveyed = {t.id: t.discs for t in result.targets if t.id in truth}
    e_true = track_errors(t_frames, t_truths, {i: truth[i] for i in surveyed}, camera)
    e_surv = track_errors(t_frames, t_truths, surveyed, result.camera, check.fit)
    both = np.isfinite(e_true) & np.isfinite(e_surv)
    run.e_true, run.e_surv = e_true[both], e_surv[both]
    run.n_located_full = int(np.isfinite(track_errors(t_frames, t_truths, truth, camera)).sum())
    return run


def _kind_counts(runs: list[RoomRun]) -> str:
    """How many warnings of each kind the survey gave, over the rooms."""
    counts: Counter[str] = Counter(k for run in runs for k in run.kinds)
    return ", ".join(f"{name} {n}" for name, n in counts.most_common()) or "none"


def _median_worst(values: list[float], digits: int = 2) -> str:
    finite = [v for v in values if np.isfinite(v)]
    return f"{np.median(finite):.{digits}f} / {max(finite):.{digits}f}" if finite else "-"


def _ratio(runs: list[RoomRun]) -> np.ndarray:
    ratio = np.concatenate([r.error_over_std for r in runs if r.ok] or [np.zeros(0)])
    return ratio[np.isfinite(ratio)]


def walk_row(walk: ExampleWalk, runs: list[RoomRun]) -> str:
    """The summary row of one walk type and track kind over its rooms: is the map complete,
    is it right, does it say so."""
    ok = [r for r in runs if r.ok]
    frames = sum(r.n_frames for r in runs)
    registered = sum(r.n_registered for r in runs)
    with_card = sum(r.n_with_card for r in ok)
    to_map = sum(len(r.to_map) for r in runs)
    mapped = sum(len(r.mapped & r.to_map) for r in runs)
    often = sum(len(r.seen_often) for r in runs)
    mapped_often = sum(len(r.mapped & r.seen_often) for r in runs)
    named = sum(len(r.wrong_named) for r in ok)
    silent = sum(len(r.wrong - r.wrong_named) for r in ok)
    far = sum(len(r.wrong_far) for r in ok)
    focal = f"{max(abs(r.focal_pct) for r in ok):.3f} %" if ok else "-"
    ratio = _ratio(runs)
    refused = f"{sum(r.refusal is not None for r in runs)}" + (
        f" (+{sum(r.crash is not None for r in runs)} crashed)" if any(r.crash for r in runs) else "")
    return (f"| {walk.name} | {runs[0].tracks} | {registered} / {frames} ({100 * registered / frames:.0f} %) "
            f"| {sum(r.card_frames_lost for r in ok)} / {with_card} "
            f"| {mapped} / {to_map} ({100 * mapped / max(to_map, 1):.0f} %) | {mapped_often} / {often} "
            f"| {named} / {silent} ({far} over {100 * WRONG_M:g} cm) "
            f"| {focal} | {sum(r.focal_unwarned for r in runs)} "
            f"| {_median_worst([r.disc_rms_mm for r in ok])} | {_median_worst([r.floor_ratio for r in ok])} "
            f"| {np.median(ratio) if len(ratio) else float('nan'):.2f} "
            f"| {_median_worst([r.survey_s for r in runs], 1)} | {np.mean([r.before_s for r in runs]):.1f} "
            f"| {refused} | {np.mean([len(r.kinds) for r in ok]) if ok else 0:.1f}: {_kind_counts(ok)} |")


def detection_row(walk: ExampleWalk, runs: list[RoomRun]) -> str:
    """The detection and tracking row of one walk type and track kind."""
    ok = [r for r in runs if r.ok]
    e_true = np.concatenate([r.e_true for r in ok] or [np.zeros(0)])
    e_surv = np.concatenate([r.e_surv for r in ok] or [np.zeros(0)])
    located = sum(len(r.e_surv) for r in ok)
    located_full = sum(r.n_located_full for r in ok)
    tracking = (f"{1000 * np.median(e_true):.2f} / {1000 * np.median(e_surv):.2f} ({located} / {located_full})"
                if len(e_true) else "-")
    return (f"| {walk.name} | {runs[0].tracks} | {sum(r.n_with_card for r in runs)} / {sum(r.n_frames for r in runs)} "
            f"| {100 * np.mean([r.recall for r in runs]):.1f} % | {tracking} |")


def room_row(walk: ExampleWalk, r: RoomRun) -> str:
    """One room's row."""
    head = f"| {walk.name} | {r.tracks} | {r.seed} "
    if not r.ok:
        what = f"refused: {r.refusal}" if r.refusal is not None else f"crashed: {r.crash}"
        return head + f"| {what} | | | | | | | | | {r.survey_s:.1f} |"
    ratio = r.error_over_std[np.isfinite(r.error_over_std)]
    wrong = f"{len(r.wrong_named)} / {len(r.wrong - r.wrong_named)}"
    if r.wrong:
        wrong += " (" + ", ".join(f"{i}{'' if i in r.wrong_named else '!'}" for i in sorted(r.wrong)) + ")"
    return (head + f"| {r.n_registered} / {r.n_frames} | {r.card_frames_lost} "
            f"| {len(r.mapped & r.to_map)} / {len(r.to_map)} | {wrong} | {r.focal_pct:+.3f} % "
            f"| {'yes' if r.lens_warned else 'no'} | {r.disc_rms_mm:.2f} | {r.floor_mm:.2f} "
            f"| {r.floor_ratio:.2f} | {np.median(ratio) if len(ratio) else float('nan'):.2f} "
            f"| {r.survey_s:.1f} |")


def describe(walk: ExampleWalk, seeds: list[int], n_frames: int) -> str:
    """A row on how the walk moves and what its frames see, from the truth alone."""
    speed, turn, counts, blur, cards = [], [], [], [], []
    for seed in seeds:
        room = walk.walk(seed, n_frames)
        cards.append(len(room.scene.targets))
        s, t = walk_speeds(room.poses)
        speed.append(s)
        turn.append(t)
        counts += [len(seen(frame_truth(walk.room.camera, p, room.scene))) for p in room.poses]
        blur += [b.length_px for b in room.blur] if room.blur else []
    share = np.bincount(np.minimum(counts, 3), minlength=4) / len(counts)
    s, t = np.concatenate(speed), np.concatenate(turn)
    room = walk.room
    n_cards = f"{min(cards)}" if min(cards) == max(cards) else f"{min(cards)}-{max(cards)}"
    walls = f"{room.walls} walls" + (", one bare" if isinstance(room, BareWallRoom) else "")
    return (f"| {walk.name} | {room.name}: {n_cards} cards, {room.cards}, {walls} "
            f"| {walk.kind}{', hand-held' if walk.shake else ''} | {np.median(s):.2f} / {s.max():.2f} "
            f"| {np.median(t):.0f} / {t.max():.0f} | " + " / ".join(f"{100 * x:.0f}" for x in share)
            + f" | {f'{np.median(blur):.1f} / {max(blur):.1f}' if blur else 'preset (0-2 px, half the frames)'} |")


def print_tables(walks: list[ExampleWalk], kinds: list[str], runs: dict[tuple[str, str], list[RoomRun]]) -> None:
    """The summary tables, then a row per room (markdown)."""
    print("\n| walk | tracks | frames registered | frames with a card detected, not registered "
          f"| cards mapped / seen in {MIN_FRAMES}+ frames over {MIN_SPAN_DEG:g}+ deg "
          f"| mapped / seen in {MIN_FRAMES}+ frames | cards wrong: named / not named by a warning "
          f"| focal error, worst | focal error over {FOCAL_TOLERANCE_PCT:g} % without a lens warning (rooms) "
          "| disc RMS, median / worst (mm) | disc RMS / floor, median / worst | \\|error\\| / std_m, median "
          "| survey per room, median / worst (s) | detection + feature tracking per room (s) | refused "
          "| warnings per room: kinds over all rooms |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for walk in walks:
        for kind in kinds:
            print(walk_row(walk, runs[walk.name, kind]))
    for walk in walks:
        for kind in kinds:
            for r in runs[walk.name, kind]:
                if r.refusal is not None:
                    print(f"\n{walk.name} ({kind}), room {r.seed} refused: {r.refusal}")
                if r.crash is not None:
                    print(f"\n{walk.name} ({kind}), room {r.seed}: the survey crashed: {r.crash}")
                if r.floor_failure is not None:
                    print(f"\n{walk.name} ({kind}), room {r.seed}: no floor: {r.floor_failure}")
    print("\nDetection, and tracking a walk through the same room with the map:\n")
    print("| walk | tracks | frames with a card detected | cards found per card seen "
          "| tracking median, true / surveyed map (mm) (frames located: surveyed / whole true map) |")
    print("|---|---|---|---|---|")
    for walk in walks:
        for kind in kinds:
            print(detection_row(walk, runs[walk.name, kind]))
    print("\nThe discs' reported uncertainty against their error after a rigid fit to the truth: "
          "|error| / std_m is the square root of chi-square(3) / 3 if std_m is honest (median 0.89, "
          f"95 % under {HONEST_95}).\n")
    print(f"| walk | tracks | discs | \\|error\\| / std_m, median | share under {HONEST_95} |")
    print("|---|---|---|---|---|")
    for walk in walks:
        for kind in kinds:
            ratio = _ratio(runs[walk.name, kind])
            print(f"| {walk.name} | {kind} | {len(ratio)} | {np.median(ratio) if len(ratio) else float('nan'):.2f} "
                  f"| {np.mean(ratio < HONEST_95) if len(ratio) else float('nan'):.0%} |")
    print("\nOne row per room (wrong cards by id, ! where no warning names them):\n")
    print("| walk | tracks | room | registered | frames with a card, not registered | cards mapped / to map "
          "| cards wrong: named / not named | focal error | lens warning | disc RMS (mm) | floor (mm) "
          "| disc RMS / floor | \\|error\\| / std_m, median | survey (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for walk in walks:
        for kind in kinds:
            for r in runs[walk.name, kind]:
                print(room_row(walk, r))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=300, help="frames of each surveyed walk (30 a second)")
    parser.add_argument("--tracking-frames", type=int, default=100, help="frames of each room's tracking walk")
    parser.add_argument("--rooms", type=int, default=16, help="rooms (seeds 0 .. rooms - 1) per walk type")
    parser.add_argument("--walks", nargs="+", choices=list(WALKS), default=list(WALKS), help="walk types")
    parser.add_argument("--tracks", choices=["cards", "features", "both"], default="both",
                        help="survey with card tracks only, with feature tracks beside them, or both side by side")
    parser.add_argument("--no-floor", action="store_true", help="skip the floor (the survey's optimum) of each room")
    parser.add_argument("--quick", action="store_true", help="2 rooms, 150-frame walks, 40-frame tracking walks")
    parser.add_argument("--exact-discs", type=float, metavar="PX", default=None,
                        help="replace the detected disc centres by the true ones plus this much noise (px): "
                             "the survey without the detector's bias")
    args = parser.parse_args()
    if args.quick:
        args.rooms, args.frames, args.tracking_frames = 2, 150, 40
    kinds = ["cards", "features"] if args.tracks == "both" else [args.tracks]
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
            for run in run_walk(walk, seed, args.frames, survey_detector, tracking[key], kinds, not args.no_floor,
                                args.exact_discs):
                runs.setdefault((walk.name, run.tracks), []).append(run)
                # Each room's row as it comes, beside the progress bars: a long run tells early.
                tqdm.write(room_row(walk, run), file=sys.stderr)

    print(f"\nWalks: {args.frames} frames at 30 a second, rooms (seeds) {seeds[0]}-{seeds[-1]}, 640x480, "
          f"f 820 px, k1 -0.12, cards of 0.2 m; tracking walks of {args.tracking_frames} frames; "
          f"{time.perf_counter() - started:.0f} s in all\n")
    print("| walk | room | kind | speed, median / max (m/s) | turn, median / max (deg/s) "
          "| frames seeing 0 / 1 / 2 / 3+ cards (%) | motion blur, median / max (px) |")
    print("|---|---|---|---|---|---|---|")
    for walk in walks:
        print(describe(walk, seeds, args.frames))
    print_tables(walks, kinds, runs)


if __name__ == "__main__":
    main()
