"""The survey on footage recorded as frames and as a phone's video, side by side.

People film a room with a phone's camera app: what reaches the survey is H.264 video,
not a stack of stills. For each room (`app.sim.examples.BENCH_ROOM`, seeds) the same
calibration walk (the same poses, lighting, noise and blur) is rendered twice: stored
frame by frame as the degradation preset says (half the frames as JPEG at quality
80-95: today's benches), and recorded as a phone records video (`app.sim.video.record`:
H.264 through libx264 at a phone's bits per pixel, the preset's JPEG left out). On
each, the survey job's detector (fitted disc centres) and the survey, self-calibrating
and with the true intrinsics; then the room's tracking walk (frames, as a `/track`
client sends them) is tracked with each surveyed map.

Columns: *disc-centre error*: the detected disc centres against the true projections
(px; every disc of every card detected whole and identified, median / 90th percentile);
*cards found*: cards found per card seen whole (facing the camera by more than 0.3,
discs over 4 px); *focal error*, *principal point*: the self-calibrated camera against
the true one; *disc RMS*: the map against the truth after the best similarity (mm), self-
calibrated and with the true intrinsics, and their ratio; the principal point's error
comes with the survey's own standard deviation (the larger of x and y), and in units of
it (the worst room: at most 2 if the deviation is honest); *correlation time*: how many
consecutive observations of a disc the survey counts as one independent measurement
(`SurveyResult.correlation_time`: its covariance is widened by it); *NEES*: the tracking
walk's normalised squared position errors with the self-calibrated map, its `std_m`
included (median; chi-square with 3 degrees of freedom: 2.37 if honest); *|error| / std_m*:
each surveyed disc's error after the best rigid motion over its reported `std_m`
(median; 0.89 if honest). The standard
deviations and the NEES are also given as if every observation were independent (the
covariance not widened: the same map and poses, only its uncertainty divided back).

A walk filmed with an exposure (``--walk centre_loop``, ``pan``, ``sparse``, ``plain``) can
also be rendered along its exposure's path (``--recordings frames "frames, blur along
the path"``): each frame the mean of renders through the exposure, against the straight
smear the other recordings use. Any walk can also be filmed through a cinema lens's depth
of field (``"frames, cine lens depth of field"``: `app.sim.examples.CINE_LENS`, 32 mm at
f/2.8 focused at 2.5 m, each pixel blurred by its depth's blur circle), or lit by lamps
under the ceiling (``"frames, lamps"``: `ExampleRoom.lamps`, light falling off with
distance, cards shaded across their faces; ``"frames, lamps and glossy cards"``: the cards'
paper glossy, `app.sim.examples.GLOSSY_PAPER`); the tracking walk stays evenly lit. The
furnished room's walk (``--walk furnished``) has cards on boards seen at grazing angles.
``"frames, rolling shutter"`` reads each frame's rows out one after another over
``--readout-ms`` (20 ms, a phone's; `app.sim.shutter`), the survey walk and the tracking
walk alike; the truth is the mid-readout pose. ``"frames, rolling shutter, modelled"`` is
the same footage surveyed and tracked with the readout modelled (`survey`'s ``shutter``,
/track's ``rolling_shutter`` config, `app.core.geometry.rolling`); both also track the
tracking walk with the true map. *tracking error*: the tracking walk's position errors
(median, mm).

Run: ``.venv/bin/python bench/bench_recording.py [--seeds 0 1 2 3] [--frames 300]
[--bits-per-pixel 0.28] [--walk bench] [--recordings frames "phone video"]`` (markdown
tables).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core.detection import DetectedTarget, Detector, load_default_classifier, warm_up  # noqa: E402
from app.core.survey import SurveyError, SurveyResult, survey  # noqa: E402
from app.sim import (  # noqa: E402
    CINE_LENS,
    GLOSSY_PAPER,
    WALKS,
    ExampleWalk,
    FrameTruth,
    PhoneVideo,
    draw_walk,
    render_walk,
)
from app.core.geometry import RollingShutter  # noqa: E402
from app.sim.walks import FPS  # noqa: E402
from bench.walk_runs import JointMapCovariance, detect_frames, map_fit, track_walk  # noqa: E402

RECORDINGS = ("frames", "phone video", "frames, blur along the path", "frames, cine lens depth of field",
              "frames, lamps", "frames, lamps and glossy cards", "frames, rolling shutter",
              "frames, rolling shutter, modelled")
#: A phone's readout, first row to last (seconds): 1080p sensors read out in 15-30 ms.
READOUT_S = 0.020


@dataclass
class Run:
    """One room recorded one way: what the detector and the survey made of it."""

    seed: int
    recording: str
    disc_errors_px: np.ndarray  # every disc of every card detected whole and identified
    found: int  # cards found among those seen whole
    seen: int
    focal_pct: float
    principal_px: float
    principal_std_px: float  # the survey's own 1 sigma, the larger of x and y
    disc_rms_mm: float
    disc_rms_true_intrinsics_mm: float
    nees: np.ndarray
    track_errors_mm: np.ndarray  # the tracking walk's position errors
    seconds: float
    correlation_time: float  # the survey's observations per independent one (its covariance is widened by it)
    nees_independent: np.ndarray  # NEES with std_m as if every observation were independent
    refused: bool  # the self-calibrating survey refused the footage: the rest is the true lens's map
    error_over_std: np.ndarray  # each disc's error after the best rigid motion over its std_m
    # Through a rolling shutter: the tracking walk tracked with the true map (the readout
    # modelled or not, as the recording); empty for the other recordings.
    true_map_track_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # NEES with the map's uncertainty from the survey's joint covariance of its discs,
    # the cards apart (each card's own block) and whole; empty through a rolling shutter.
    nees_cards_apart: np.ndarray = field(default_factory=lambda: np.zeros(0))
    nees_joint: np.ndarray = field(default_factory=lambda: np.zeros(0))


def seen_whole(truth: FrameTruth) -> dict[int, np.ndarray]:
    """The cards a detector should find in a frame, with their true disc projections."""
    return {t.id: t.discs_px for t in truth.targets
            if t.visible and not t.occluded and t.facing_cos > 0.3 and t.disc_diameter_px > 4.0}


def disc_errors(frames: list[list[DetectedTarget]], truths: list[FrameTruth]) -> tuple[np.ndarray, int, int]:
    """Distances (px) of the detected disc centres from the true ones, and the cards
    found and seen whole."""
    errors, found, seen = [], 0, 0
    for detected, truth in zip(frames, truths, strict=True):
        should = seen_whole(truth)
        seen += len(should)
        for t in detected:
            if t.id in should:
                found += 1
                errors.append(np.linalg.norm(t.discs - should[t.id], axis=1))
    return (np.concatenate(errors) if errors else np.zeros(0)), found, seen


def disc_rms_mm(result: SurveyResult, truth: dict[int, np.ndarray]) -> float:
    """The surveyed discs against the true ones after the best similarity, mm."""
    return 1000 * float(np.sqrt(np.mean(map_fit(result, truth)[1] ** 2)))


def run_room(walk: ExampleWalk, seed: int, n_frames: int, n_tracking: int, video: PhoneVideo,
             detector: Detector, survey_detector: Detector, recordings: list[str], readout_s: float) -> list[Run]:
    """Each recording of one room's walk, surveyed and tracked with."""
    camera = walk.room.camera
    scene = walk.walk(seed, n_frames).scene

    def tracking_walk(rolling: bool) -> tuple[list[list[DetectedTarget]], list[FrameTruth]]:
        """The room's tracking walk, through a global or a rolling shutter (the same
        poses and noise either way)."""
        rng = np.random.default_rng([seed, 1])
        drawn = draw_walk(rng, scene.room_size, n_tracking, "tracking")
        frames, truths, _ = detect_frames(
            detector, render_walk(scene, camera, drawn.poses, rng,
                                  readouts=drawn.readouts(readout_s) if rolling else None),
            n_tracking, f"room {seed}: tracking walk{', rolling shutter' if rolling else ''}")
        return frames, truths

    tracking = {False: tracking_walk(False)}
    truth = {t.id: t.discs for t in scene.targets}
    recorded: dict[str, tuple[list[list[DetectedTarget]], list[FrameTruth], float]] = {}
    runs = []
    for recording in recordings:
        rolling = recording.startswith("frames, rolling shutter")
        # The survey and the tracking model the readout (the survey's rolling_shutter,
        # /track's config), or take every frame as read at one instant.
        shutter = RollingShutter.from_seconds(readout_s, FPS) if recording.endswith(", modelled") else None
        if rolling not in tracking:
            tracking[rolling] = tracking_walk(rolling)
        t_frames, t_truths = tracking[rolling]
        footage = recording.removesuffix(", modelled")
        if footage not in recorded:
            # The same walk drawn afresh: the same poses, degradations and noise.
            room = walk.walk(seed, n_frames)
            lighting = None
            if footage.startswith("frames, lamps"):
                lighting = walk.room.lamps(GLOSSY_PAPER if footage.endswith("glossy cards") else 0.0)
            recorded[footage] = detect_frames(
                survey_detector, room.frames(camera, video=video if footage == "phone video" else None,
                                             follow_path=footage == "frames, blur along the path",
                                             lens=CINE_LENS if footage == "frames, cine lens depth of field" else None,
                                             lighting=lighting, readout_s=readout_s if rolling else None),
                n_frames, f"room {seed}: {footage}")
        frames, truths, detect_s = recorded[footage]
        errors, found, seen = disc_errors(frames, truths)
        start = time.perf_counter()
        result: SurveyResult | None = None
        try:
            result = survey(frames, camera.width, camera.height, walk.room.marker_size_m, shutter=shutter)
        except SurveyError as refusal:
            print(f"room {seed}, {recording}: self-calibration refused: {refusal}", file=sys.stderr)
        seconds = detect_s + time.perf_counter() - start
        fixed = survey(frames, camera.width, camera.height, walk.room.marker_size_m, intrinsics=camera,
                       shutter=shutter)
        # A refused survey (its lens check) tells the user to give the intrinsics: that
        # map is the one tracked with.
        refused = result is None
        if result is None:
            result = fixed
        cam = result.camera
        rigid, rigid_errors = map_fit(result, truth, with_scale=False)
        error_over_std = rigid_errors / np.concatenate([t.std_m for t in result.targets])
        discs = {t.id: t.discs for t in result.targets}
        track_errors, nees = track_walk(t_frames, t_truths, discs, cam, rigid, {t.id: t.std_m for t in result.targets},
                                        shutter)
        # The same map with the uncertainty it would report if the observations were
        # independent (the covariance is widened by the correlation time, nothing else).
        narrow = 1.0 / np.sqrt(result.correlation_time)
        nees_independent = track_walk(t_frames, t_truths, discs, cam, rigid,
                                      {t.id: t.std_m * narrow for t in result.targets}, shutter)[1]
        # The map's uncertainty as the survey's joint covariance holds it, not as /track
        # has it (each card off as a whole by its std_m, the same in every direction).
        nees_apart, nees_joint = np.zeros(0), np.zeros(0)
        if shutter is None and not rolling and result.disc_covariance is not None:
            nees_apart, nees_joint = (
                track_walk(t_frames, t_truths, discs, cam, rigid, joint=JointMapCovariance.of(result, apart))[1]
                for apart in (True, False))
        true_map = np.zeros(0)
        if rolling:
            true_map = track_walk(t_frames, t_truths, truth, camera, shutter=shutter)[0]
            true_map = 1000 * true_map[np.isfinite(true_map)]
        runs.append(Run(seed, recording, errors, found, seen, 100 * (cam.fx / camera.fx - 1),
                        float(np.hypot(cam.cx - camera.cx, cam.cy - camera.cy)),
                        float(np.max(result.intrinsics_std[1:3])) if result.intrinsics_std is not None else np.nan,
                        disc_rms_mm(result, truth), disc_rms_mm(fixed, truth), nees[np.isfinite(nees)],
                        1000 * track_errors[np.isfinite(track_errors)], seconds,
                        result.correlation_time, nees_independent[np.isfinite(nees_independent)], refused,
                        error_over_std[np.isfinite(error_over_std)], true_map,
                        nees_apart[np.isfinite(nees_apart)], nees_joint[np.isfinite(nees_joint)]))
    return runs


def row(label: str, recording: str, runs: list[Run]) -> str:
    errors = np.concatenate([r.disc_errors_px for r in runs])
    tracked = np.concatenate([r.track_errors_mm for r in runs])
    fixed = np.median([r.disc_rms_true_intrinsics_mm for r in runs])
    refused = sum(r.refused for r in runs)
    common = (f"| {label} | {recording} | {np.median(errors):.3f} / {np.percentile(errors, 90):.3f} "
              f"| {100 * sum(r.found for r in runs) / max(sum(r.seen for r in runs), 1):.1f} % ")
    runs = [r for r in runs if not r.refused]
    if not runs:  # every room refused: only the true lens's map
        return (common + f"| refused | | | | (refused) / {fixed:.2f} | | | {np.median(tracked):.2f} "
                "(true lens's map) | |")
    nees = np.concatenate([r.nees for r in runs])
    nees_independent = np.concatenate([r.nees_independent for r in runs])
    worst = max(runs, key=lambda r: r.principal_px / r.principal_std_px)
    self_cal = np.median([r.disc_rms_mm for r in runs])
    fixed = np.median([r.disc_rms_true_intrinsics_mm for r in runs])
    return (common +
            f"| {max(abs(r.focal_pct) for r in runs):.3f} % | {max(r.principal_px for r in runs):.2f} "
            f"({max(r.principal_std_px for r in runs):.2f} / "
            f"{max(r.principal_std_px / np.sqrt(r.correlation_time) for r in runs):.2f}) "
            f"| {worst.principal_px / worst.principal_std_px:.2f} / "
            f"{worst.principal_px / worst.principal_std_px * np.sqrt(worst.correlation_time):.2f} "
            f"| {max(r.correlation_time for r in runs):.1f} "
            f"| {self_cal:.2f} / {fixed:.2f} ({self_cal / fixed:.2f}) "
            f"| {np.median(np.concatenate([r.error_over_std for r in runs])):.2f} "
            f"| {np.median(nees):.2f} / "
            f"{np.median(nees_independent):.2f} "
            f"| {np.median(tracked):.2f}{f' ({refused} refused: the true lens map)' if refused else ''} "
            f"| {np.mean([r.seconds for r in runs]):.1f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=300, help="calibration walk length")
    parser.add_argument("--tracking-frames", type=int, default=100)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3], help="rooms")
    parser.add_argument("--bits-per-pixel", type=float, default=PhoneVideo().bits_per_pixel,
                        help="the phone video's bits per pixel and frame")
    parser.add_argument("--walk", choices=list(WALKS), default="bench",
                        help="the example walk (app.sim.examples.WALKS); the bench room's survey walk by default")
    parser.add_argument("--recordings", nargs="+", choices=RECORDINGS, default=list(RECORDINGS[:2]),
                        help="how the walk is recorded; blur along the path needs a walk with an exposure "
                             "(centre_loop, pan, sparse, plain)")
    parser.add_argument("--readout-ms", type=float, default=1000 * READOUT_S,
                        help="the rolling shutter's readout, first row to last (ms)")
    args = parser.parse_args()
    walk = WALKS[args.walk]
    if "frames, blur along the path" in args.recordings and walk.exposure_s is None:
        parser.error(f"the {args.walk} walk has no exposure to blur along: pick centre_loop, pan, sparse or plain")
    cv2.setNumThreads(1)
    detector = Detector(classifier=load_default_classifier())
    warm_up()
    survey_detector = Detector.for_survey(detector.classifier)
    video = PhoneVideo(bits_per_pixel=args.bits_per_pixel)
    started = time.perf_counter()
    runs = [run for seed in args.seeds
            for run in run_room(walk, seed, args.frames, args.tracking_frames, video, detector, survey_detector,
                                args.recordings, args.readout_ms / 1000)]
    camera = walk.room.camera
    bit_rate = video.bit_rate(camera.width, camera.height, 30.0)
    print(f"\nRecording: the {walk.name} walk ({walk.room.name} room, {walk.kind}"
          f"{', hand-held' if walk.shake else ''}), {args.frames} frames at 30 a second, "
          f"{camera.width}x{camera.height}, f {camera.fx:g} px, k1 {camera.dist[0]:g}; phone video: H.264 (libx264, {video.preset}, Main, no B-frames, keyframe every "
          f"{video.keyframe_s:g} s) at {video.bits_per_pixel:g} bits per pixel ({bit_rate / 1e6:.1f} Mbit/s); "
          f"tracking walks of {args.tracking_frames} frames; {time.perf_counter() - started:.0f} s in all\n")
    print("| room | recording | disc-centre error, median / p90 (px) | cards found | focal error | "
          "principal point error (reported 1 sigma / as if independent) (px) | principal point error in sigmas "
          "(worst; / as if independent) | correlation time (observations) "
          "| disc RMS, self-calibrated / true intrinsics (mm) (ratio) | \\|error\\| / std_m, median "
          "| NEES, median (/ as if independent) | tracking error, median (mm) | detection + survey (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for seed in args.seeds:
        for recording in args.recordings:
            print(row(str(seed), recording, [r for r in runs if r.seed == seed and r.recording == recording]))
    for recording in args.recordings:
        print(row("all (worst focal and principal point)", recording, [r for r in runs if r.recording == recording]))
    rolled = [r for r in runs if len(r.true_map_track_mm)]
    if rolled:
        print(f"\nThe tracking walks through the rolling shutter ({args.readout_ms:g} ms) with the true map, "
              "median / p90 position error (mm):\n")
        print("| room | recording | position error, median / p90 (mm) |")
        print("|---|---|---|")
        for r in rolled:
            e = r.true_map_track_mm
            print(f"| {r.seed} | {r.recording} | {np.median(e):.2f} / {np.percentile(e, 90):.2f} |")
    joint = [r for r in runs if len(r.nees_joint)]
    if joint:
        print("\nNEES of the tracking walks with the surveyed map, by how the map's uncertainty is taken: "
              "median (share under 7.81; 2.37 and 95 % if honest):\n")
        print("| room | recording | each card off as a whole by its std_m (/track) | the survey's joint "
              "covariance, cards apart | the survey's joint covariance |")
        print("|---|---|---|---|---|")

        def cell(nees: np.ndarray) -> str:
            return f"{np.median(nees):.2f} ({100 * np.mean(nees < 7.81):.0f} %)"

        for recording in args.recordings:
            chosen = [r for r in joint if r.recording == recording]
            for r in chosen:
                print(f"| {r.seed} | {recording} | {cell(r.nees)} | {cell(r.nees_cards_apart)} | {cell(r.nees_joint)} |")
            if chosen:
                pooled = [np.concatenate([getattr(r, name) for r in chosen])
                          for name in ("nees", "nees_cards_apart", "nees_joint")]
                print(f"| all | {recording} | {' | '.join(cell(n) for n in pooled)} |")
    base = [r for r in runs if r.recording == args.recordings[0]]
    print()
    for recording in args.recordings[1:]:
        other = [r for r in runs if r.recording == recording]
        ratio = (np.median(np.concatenate([r.disc_errors_px for r in other]))
                 / np.median(np.concatenate([r.disc_errors_px for r in base])))
        print(f"{recording} / {args.recordings[0]}: disc-centre error (median) {ratio:.2f}, disc RMS (median over "
              f"rooms) {np.median([r.disc_rms_mm for r in other]) / np.median([r.disc_rms_mm for r in base]):.2f}")


if __name__ == "__main__":
    main()
