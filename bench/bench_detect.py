"""Side-by-side detection benchmark: our learned detector, a plain
threshold-and-blob baseline on our cards, AprilTag 3 (tag36h11) and OpenCV ArUco (4x4),
on the same rendered 640x480 frames.

Every frame is drawn from its own seed (condition, frame index), once per artwork: our
card, the AprilTag card and the ArUco card, printed at the same size, carry the same
geometry, background and degradations (``scenario_frame(..., artwork=)``). See
``bench/peers.py`` for the artwork and the detector settings.

Measures, per detector and condition:

* rate: fraction of the true targets that are fully visible (all four reference points
  in the image, card facing the camera) and not covered by a nearer card, detected with
  the right id and all four points (our disc centres; a tag's outer corners) within 2 px;
* false /1000 fr: detections whose id is not in the frame and that are not on a true
  target, per 1000 frames (on the marker-free frames: every detection);
* wrong ids: detections on a true target (centre within half a card side of its centre)
  with an id that is not in the frame;
* off >2px: detections with the id of a counted target but a point more than 2 px off;
* RMS px: point error over the correct detections;
* per view bin: the rate by viewing cosine and imaged disc diameter, over every
  condition (`BINS_COS`, `BINS_DISC_PX`), each detector side by side;
* ms: median wall time per frame of ``detect`` on one thread (cv2.setNumThreads(1),
  BLAS/OpenMP at one thread, AprilTag nthreads=1). Rendering is not timed.

With ``--baseline DIR`` (a checkout of another version) that tree's live detector runs
on the same frames too (``peers.CheckoutDetector``), and the live detector's medians are
compared per condition with it and with AprilTag at decimate 2, and stage by stage
(``Detection.timing_ms``). The stage table's ``floor`` rows time, on the same frames,
what the candidate stage's design costs before its glue: stage 1a's pixel passes
(``candidates.scan_levels``) and the screen's and stage 2's matrix products.

Run: ``.venv/bin/python bench/bench_detect.py [--baseline DIR]`` (~10 min on 2 cores),
quick mode ``--frames 30 --empty-frames 100``. Prints markdown tables; progress on stderr.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import functools  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
import zlib  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from app.core.detection import candidates as cand  # noqa: E402
from app.sim import scenes  # noqa: E402
from app.sim.truth import TruthCard, truth_cards  # noqa: E402
from bench.peers import CheckoutDetector, Detection, PeerDetector, all_detectors  # noqa: E402

CONDITIONS = ("default", "far", "blur", "dark", "bright", "tiny", "grazing", "clutter")
CLEAN = "clean"  # fronto-parallel, no degradation: the centre-accuracy row
EMPTY = "empty"  # no marker: false targets
MATCH_PX = 2.0
CLEAN_MIN_DISC_PX = 8.0
#: Bin edges of the viewing cosine (the card's normal against the direction to the
#: camera: 1 face-on, 0 edge-on) and of the imaged disc diameter (px), for the rate per
#: bin over every condition; and the bar for a good view: a card seen at a cosine of 0.5
#: or more with discs of 3 px or more is to be found 99 % of the time.
BINS_COS = (0.0, 0.5, 0.7, 0.85, 1.01)
BINS_DISC_PX = (0.0, 3.0, 5.0, 8.0, np.inf)
GOOD_VIEW = (0.5, 3.0)
#: A bin is reported with at least this many targets.
MIN_BIN_TARGETS = 20
#: The row names of our live detector and of the same detector in another checkout (`--baseline`).
LIVE = "fidotrack (learned)"
BASELINE = "fidotrack (learned), baseline"


@dataclass
class Stats:
    frames: int = 0
    targets: int = 0  # counted (visible, unoccluded) true targets
    occluded: int = 0  # visible by the simulator's truth but covered by a nearer card
    correct: int = 0
    off: int = 0  # right id on a counted target, a point > 2 px off
    false: int = 0
    wrong_ids: int = 0
    duplicates: int = 0
    errors: int = 0  # frames on which detect raised (scored as finding nothing)
    sq_errors: list[float] = field(default_factory=list)  # squared point errors (px^2)
    clean_sq_errors: list[float] = field(default_factory=list)  # discs >= 8 px only
    ms: list[float] = field(default_factory=list)
    stages: dict[str, list[float]] = field(default_factory=dict)  # ms by stage, for detectors that report them
    # (viewing-cosine bin, disc-size bin) -> [counted targets, correct]: `BINS_COS`, `BINS_DISC_PX`
    binned: dict[tuple[int, int], list[int]] = field(default_factory=dict)

    @property
    def rate(self) -> float:
        return self.correct / self.targets if self.targets else float("nan")

    @property
    def false_per_1000(self) -> float:
        return 1000.0 * self.false / self.frames if self.frames else float("nan")

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.sq_errors))) if self.sq_errors else float("nan")

    @property
    def clean_rms(self) -> float:
        return float(np.sqrt(np.mean(self.clean_sq_errors))) if self.clean_sq_errors else float("nan")

    @property
    def median_ms(self) -> float:
        return float(np.median(self.ms)) if self.ms else float("nan")


def timed_detect(det: PeerDetector, image: np.ndarray, stats: Stats) -> list[Detection]:
    start = time.perf_counter()
    try:
        found = det.detect(image)
    except Exception as exc:  # work in progress elsewhere must not end the run
        stats.errors += 1
        if stats.errors == 1:
            print(f"\n{det.name}: {exc!r} (further errors counted only)", file=sys.stderr)
        found = []
    stats.ms.append((time.perf_counter() - start) * 1e3 if det.last_ms is None else det.last_ms)
    for stage, ms in det.last_stages.items():
        stats.stages.setdefault(stage, []).append(ms)
    return found


@functools.cache
def _classifier() -> cand.DiscClassifier:
    return cand.load_default_classifier()


#: The floor's buffers, kept from frame to frame as the detector keeps its own (fresh
#: image-sized buffers would add their page faults to the floor).
_FLOOR_BUFFERS = cand._Workspace()


def floor_ms(gray: np.ndarray) -> dict[str, float]:
    """What the candidate stage's design costs on this frame before any of its glue: the
    pixel passes of stage 1a over the pyramid (`candidates.scan_levels`: pyramid,
    morphology, scores, maxima) and the matrix products of the screen (every stage-1a
    window) and of stage 2 (the accepted candidates' windows only), timed alone; the
    windows are gathered and normalised untimed."""
    classifier = _classifier()
    start = time.perf_counter()
    cand.scan_levels(gray, classifier.blob_thresholds, _FLOOR_BUFFERS)
    passes = time.perf_counter() - start
    s1 = cand.stage1_windows(gray, classifier, apply_screen=False)
    _, kept, index = cand.detect_windows(gray, classifier)
    windows = cand.normalise_windows(s1.windows)
    accepted = cand.normalise_windows(kept.windows[index])
    start = time.perf_counter()
    cand.screen_scores(windows, classifier)
    cand.nn_scores(accepted, classifier)
    products = time.perf_counter() - start
    return {"floor.stage1a": passes * 1e3, "floor.products": products * 1e3,
            "floor.candidates": (passes + products) * 1e3}


def add_floor(stats: Stats, gray: np.ndarray) -> None:
    """The frame's `floor_ms` into the live detector's stage timings."""
    for stage, ms in floor_ms(gray).items():
        stats.stages.setdefault(stage, []).append(ms)


def view_bin(cosine: float, disc_px: float) -> tuple[int, int]:
    """The (viewing-cosine, disc-size) bin of a card (`BINS_COS`, `BINS_DISC_PX`)."""
    return (int(np.clip(np.searchsorted(BINS_COS, cosine, side="right") - 1, 0, len(BINS_COS) - 2)),
            int(np.clip(np.searchsorted(BINS_DISC_PX, disc_px, side="right") - 1, 0, len(BINS_DISC_PX) - 2)))


def score_frame(stats: Stats, found: list[Detection], cards: list[TruthCard], clean: bool,
                cosines: list[float] | None = None) -> None:
    """Score one frame's detections; `cosines` (one per card) also counts each counted
    card in its viewing-angle and disc-size bin."""
    stats.frames += 1
    stats.targets += sum(c.counted for c in cards)
    by_id = {c.id: c for c in cards}
    matched: set[int] = set()
    for marker_id, points in found:
        card = by_id.get(marker_id)
        if card is not None:
            if not card.counted:
                continue  # a real target, partly out of view or covered: neither way
            err2 = np.sum((np.asarray(points, np.float64) - card.points) ** 2, axis=1)
            if np.sqrt(err2.max()) <= MATCH_PX:
                if marker_id in matched:
                    stats.duplicates += 1
                    continue
                matched.add(marker_id)
                stats.correct += 1
                stats.sq_errors.extend(err2.tolist())
                if clean and card.disc_px >= CLEAN_MIN_DISC_PX:
                    stats.clean_sq_errors.extend(err2.tolist())
            else:
                stats.off += 1
            continue
        centre = np.asarray(points, np.float64).mean(axis=0)
        if any(np.linalg.norm(centre - c.centre) <= 0.5 * c.side_px for c in cards if np.isfinite(c.centre).all()):
            stats.wrong_ids += 1
        else:
            stats.false += 1
    if cosines is not None:
        for card, cosine in zip(cards, cosines, strict=True):
            if card.counted:
                counts = stats.binned.setdefault(view_bin(cosine, card.disc_px), [0, 0])
                counts[0] += 1
                counts[1] += card.id in matched


def frame_rng(seed: int, condition: str, index: int, attempt: int = 0) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(condition.encode()), index, attempt])


REDRAWN: dict[str, set[int]] = {}


def draw_frame(seed: int, condition: str, index: int, artwork: Callable | None
               ) -> tuple[np.ndarray, scenes.FrameTruth]:
    """The frame of (seed, condition, index) with this artwork. A draw on which the
    simulator fails (e.g. a NaN blur kernel: numpy warnings are errors here) is
    replaced by the next attempt's seed - the same for every artwork - and counted."""
    for attempt in range(10):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error", RuntimeWarning)
                return scenes.scenario_frame(condition, frame_rng(seed, condition, index, attempt), artwork=artwork)
        except (ValueError, RuntimeWarning, FloatingPointError):
            REDRAWN.setdefault(condition, set()).add(index)
    raise RuntimeError(f"the simulator failed 10 times on {condition} frame {index}")


def run(detectors: list[PeerDetector], conditions: list[str], n_frames: int, n_empty: int, seed: int
        ) -> dict[str, dict[str, Stats]]:
    cv2.setNumThreads(1)
    groups: dict[int, tuple[Callable | None, list[PeerDetector]]] = {}
    for det in detectors:
        groups.setdefault(id(det.artwork), (det.artwork, []))[1].append(det)
    results = {det.name: {} for det in detectors}
    total = len(conditions) * n_frames * len(groups) + n_empty
    with tqdm(total=total, desc="frames", unit="fr", file=sys.stderr, dynamic_ncols=True) as bar:
        for condition in conditions:
            for det in detectors:
                results[det.name][condition] = Stats()
            bar.set_postfix_str(condition)
            for i in range(n_frames):
                for artwork, dets in groups.values():
                    image, truth = draw_frame(seed, condition, i, artwork)
                    cards = truth_cards(truth, artwork)
                    for det in dets:
                        stats = results[det.name][condition]
                        found = timed_detect(det, image, stats)
                        if det.name == LIVE:
                            add_floor(stats, image)
                        score_frame(stats, found, cards, clean=condition == CLEAN,
                                    cosines=[t.facing_cos for t in truth.targets])
                        stats.occluded += sum(1 for c, t in zip(cards, truth.targets, strict=True)
                                              if t.visible and not c.counted)
                    bar.update()
        if n_empty:
            for det in detectors:
                results[det.name][EMPTY] = Stats()
            bar.set_postfix_str(EMPTY)
            for i in range(n_empty):
                image, truth = draw_frame(seed, EMPTY, i, None)
                assert not truth.targets
                for det in detectors:
                    stats = results[det.name][EMPTY]
                    found = timed_detect(det, image, stats)
                    if det.name == LIVE:
                        add_floor(stats, image)
                    score_frame(stats, found, [], clean=False)
                bar.update()
    return results


# --- tables ---------------------------------------------------------------------------


def _pct(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{100 * x:.1f}%"


def _num(x: float, fmt: str = ".2f") -> str:
    return "-" if not np.isfinite(x) else format(x, fmt)


def _is_peer(name: str) -> bool:
    return name.startswith(("AprilTag", "ArUco"))


def _apriltag_ms(results: dict[str, dict[str, Stats]], condition: str) -> float:
    for name, by_condition in results.items():
        if name.startswith("AprilTag") and "decimate 1" in name and condition in by_condition:
            return by_condition[condition].median_ms
    return float("nan")


def _apriltag_d2(results: dict[str, dict[str, Stats]]) -> str | None:
    """The row name of AprilTag at decimate 2, the speed target's peer (None if not run)."""
    return next((n for n in results if n.startswith("AprilTag") and "decimate 2" in n), None)


def best_peer(results: dict[str, dict[str, Stats]], condition: str) -> tuple[str, float]:
    peers = [(s[condition].rate, n) for n, s in results.items() if _is_peer(n) and condition in s]
    peers = [(r, n) for r, n in peers if np.isfinite(r)]
    if not peers:
        return "-", float("nan")
    rate, name = max(peers)
    return name, rate


def condition_table(results: dict[str, dict[str, Stats]], unavailable: dict[str, str], conditions: list[str]) -> str:
    lines = [
        "| condition | detector | targets | detected | rate | rate vs best peer | false /1000 fr | wrong ids "
        "| off >2px | RMS px | median ms | speed vs AprilTag |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for condition in conditions:
        _, best = best_peer(results, condition)
        april = _apriltag_ms(results, condition)
        for name, by_condition in results.items():
            s = by_condition[condition]
            versus = "-" if _is_peer(name) or not np.isfinite(best) else f"{100 * (s.rate - best):+.1f} pp"
            speed = april / s.median_ms if s.median_ms > 0 else float("nan")
            lines.append(
                f"| {condition} | {name} | {s.targets} | {s.correct} | {_pct(s.rate)} | {versus} "
                f"| {_num(s.false_per_1000, '.1f')} | {s.wrong_ids} | {s.off} | {_num(s.rms, '.3f')} "
                f"| {_num(s.median_ms)} | {_num(speed, '.1f')}x |"
            )
        for name, reason in unavailable.items():
            lines.append(f"| {condition} | {name} | {reason} | | | | | | | | | |")
    return "\n".join(lines)


def empty_table(results: dict[str, dict[str, Stats]], unavailable: dict[str, str]) -> str:
    lines = ["| marker-free frames | frames | detections | false /1000 fr | median ms |", "|---|---:|---:|---:|---:|"]
    for name, by_condition in results.items():
        s = by_condition[EMPTY]
        lines.append(f"| {name} | {s.frames} | {s.false + s.wrong_ids} | {_num(s.false_per_1000, '.1f')} "
                     f"| {_num(s.median_ms)} |")
    for name, reason in unavailable.items():
        lines.append(f"| {name} | {reason} | | | |")
    return "\n".join(lines)


def clean_table(results: dict[str, dict[str, Stats]]) -> str:
    lines = [f"| clean, fronto-parallel, discs >= {CLEAN_MIN_DISC_PX:.0f} px | targets | rate | point RMS px "
             "| points |", "|---|---:|---:|---:|---:|"]
    for name, by_condition in results.items():
        s = by_condition[CLEAN]
        lines.append(f"| {name} | {s.targets} | {_pct(s.rate)} | {_num(s.clean_rms, '.3f')} "
                     f"| {len(s.clean_sq_errors)} |")
    return "\n".join(lines)


def _binned(by_condition: dict[str, Stats], conditions: list[str]) -> dict[tuple[int, int], list[int]]:
    """[targets, correct] per view bin, over `conditions`."""
    out: dict[tuple[int, int], list[int]] = {}
    for condition in conditions:
        for key, (n, k) in by_condition[condition].binned.items():
            counts = out.setdefault(key, [0, 0])
            counts[0] += n
            counts[1] += k
    return out


def _bin_label(key: tuple[int, int]) -> str:
    c, d = key
    disc = (f"{BINS_DISC_PX[d]:g}-{BINS_DISC_PX[d + 1]:g} px" if np.isfinite(BINS_DISC_PX[d + 1])
            else f">= {BINS_DISC_PX[d]:g} px")
    return f"{BINS_COS[c]:g}-{min(BINS_COS[c + 1], 1.0):g} | {disc}"


def bin_table(results: dict[str, dict[str, Stats]], conditions: list[str]) -> str:
    """The rate of every detector per viewing-cosine and disc-size bin, over `conditions`."""
    names = list(results)
    binned = {name: _binned(results[name], conditions) for name in names}
    keys = sorted({k for b in binned.values() for k in b if b[k][0] >= MIN_BIN_TARGETS})
    lines = ["| viewing cosine | disc diameter | targets | " + " | ".join(names) + " |",
             "|---|---|---:|" + "---:|" * len(names)]
    for key in keys:
        n = max(binned[name].get(key, [0, 0])[0] for name in names)
        cells = [_pct(binned[name][key][1] / binned[name][key][0]) if binned[name].get(key, [0])[0] else "-"
                 for name in names]
        lines.append(f"| {_bin_label(key)} | {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


#: The live detector's stages as `Detector.detect` times them, in the order they run.
STAGES = ("candidates", "targets.group", "targets.verify", "targets.refine", "targets.identify",
          "targets.complete", "targets", "detect", "floor.stage1a", "floor.products", "floor.candidates")


def speed_table(results: dict[str, dict[str, Stats]], ours: str, baseline: str, conditions: list[str]) -> str:
    """Our live detector's median ms per condition against the baseline checkout's and
    AprilTag (decimate 2), same frames, same run."""
    april = _apriltag_d2(results)
    lines = [f"| condition | this tree ms | baseline ms | this / baseline | AprilTag decimate 2 ms "
             f"| this / AprilTag d2 |", "|---|---:|---:|---:|---:|---:|"]
    for condition in [*conditions, EMPTY]:
        if condition not in results[ours]:
            continue
        a, b = results[ours][condition].median_ms, results[baseline][condition].median_ms
        t = results[april][condition].median_ms if april and condition in results[april] else float("nan")
        lines.append(f"| {condition} | {_num(a)} | {_num(b)} | {_num(a / b)} | {_num(t)} | {_num(a / t)} |")
    a, b = (float(np.median(np.concatenate([v.ms for v in results[n].values()]))) for n in (ours, baseline))
    lines.append(f"| all frames | {_num(a)} | {_num(b)} | {_num(a / b)} | | |")
    return "\n".join(lines)


def stage_table(results: dict[str, dict[str, Stats]], names: list[str]) -> str:
    """Median ms of each stage of the live detector over all frames, per detector that
    reports its stages (this tree, the baseline)."""
    names = [n for n in names if any(st.stages for st in results[n].values())]
    lines = ["| stage | " + " | ".join(names) + (" | ratio |" if len(names) == 2 else " |"),
             "|---|" + "---:|" * (len(names) + (len(names) == 2))]
    for stage in STAGES:
        meds = []
        for n in names:
            values = [v for st in results[n].values() for v in st.stages.get(stage, [])]
            meds.append(float(np.median(values)) if values else float("nan"))
        ratio = f" {_num(meds[0] / meds[1])} |" if len(names) == 2 and meds[1] > 0 else (" - |" if len(names) == 2 else "")
        lines.append(f"| {stage} | " + " | ".join(_num(m) for m in meds) + " |" + ratio)
    return "\n".join(lines)


def target_check(results: dict[str, dict[str, Stats]], ours: str, conditions: list[str], speed: bool = True,
                 baseline: str | None = None) -> str:
    """The detector's targets (rate against the peers, blur and low light, false and wrong
    ids, disc RMS, and with `speed` its time a frame), each PASS or FAIL."""
    s = results[ours]
    rows = []
    for condition in conditions:
        name, best = best_peer(results, condition)
        rate = s[condition].rate
        rows.append((f"rate >= best peer in {condition} ({_pct(rate)} vs {_pct(best)}, {name})",
                     np.isfinite(best) and rate >= best))
    for condition in ("blur", "dark"):
        if condition in s:
            rows.append((f"rate >= 97% in {condition} ({_pct(s[condition].rate)})", s[condition].rate >= 0.97))
    if EMPTY in s:
        rows.append((f"<= 1 false target /1000 marker-free frames ({_num(s[EMPTY].false_per_1000, '.1f')})",
                     s[EMPTY].false_per_1000 <= 1.0))
    wrong = sum(v.wrong_ids for v in s.values())
    rows.append((f"no wrong ids ({wrong})", wrong == 0))
    if CLEAN in s:
        rows.append((f"disc RMS <= 0.1 px on clean frames, discs >= 8 px ({_num(s[CLEAN].clean_rms, '.3f')})",
                     s[CLEAN].clean_rms <= 0.1))
    binned = _binned(s, conditions)
    good = [v for (c, d), v in binned.items() if BINS_COS[c] >= GOOD_VIEW[0] and BINS_DISC_PX[d] >= GOOD_VIEW[1]]
    n_good, k_good = sum(v[0] for v in good), sum(v[1] for v in good)
    if n_good:
        rows.append((f"rate >= 99% for cards at a viewing cosine >= {GOOD_VIEW[0]:g} with discs >= "
                     f"{GOOD_VIEW[1]:g} px ({_pct(k_good / n_good)} of {n_good})", k_good >= 0.99 * n_good))
    peers = {n: _binned(v, conditions) for n, v in results.items() if _is_peer(n)}
    behind = [key for key, (n, k) in binned.items() if n >= MIN_BIN_TARGETS
              and any(p.get(key, [0, 0])[0] and p[key][1] / p[key][0] > k / n for p in peers.values())]
    if peers:
        rows.append((f"rate >= best peer in every view bin ({len(behind)} bins behind"
                     + (f": {', '.join(_bin_label(b).replace(' | ', ', ') for b in sorted(behind))}" if behind else "")
                     + ")", not behind))
    ms = np.concatenate([np.asarray(v.ms) for v in s.values()]) if s else np.zeros(0)
    median = float(np.median(ms)) if ms.size else float("nan")
    if speed:
        rows.append((f"median <= 4 ms/frame, one thread ({_num(median)} ms over all frames)", median <= 4.0))
        april = _apriltag_d2(results)
        if april:
            slower = [c for c in conditions if c in results[april] and not s[c].median_ms < results[april][c].median_ms]
            rows.append((f"median below AprilTag decimate 2 in every condition ({len(slower)} not"
                         + (f": {', '.join(slower)}" if slower else "") + ")", not slower))
        if baseline and baseline in results:
            before = np.concatenate([np.asarray(v.ms) for v in results[baseline].values()])
            b_med = float(np.median(before))
            rows.append((f"median <= half the baseline's, same frames, same run ({_num(median)} vs {_num(b_med)} ms: "
                         f"{_num(median / b_med)}x)", median <= 0.5 * b_med))
    lines = ["| target | |", "|---|---|"]
    lines += [f"| {text} | {'PASS' if ok else 'FAIL'} |" for text, ok in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=200, help="frames per condition (default 200)")
    parser.add_argument("--empty-frames", type=int, default=1000, help="marker-free frames (default 1000)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--conditions", default=",".join((*CONDITIONS, CLEAN)),
                        help=f"comma-separated scenario names (default {','.join((*CONDITIONS, CLEAN))})")
    parser.add_argument("--baseline", default="", metavar="DIR",
                        help="a checkout of another version of fidotrack: its live detector runs on the same frames "
                        "(in a worker process) as the row 'fidotrack (learned), baseline'")
    parser.add_argument("--only", default="", help="run only detectors whose name contains one of these "
                        "comma-separated words (case-insensitive)")
    args = parser.parse_args(argv)

    conditions = [c for c in args.conditions.split(",") if c]
    for c in conditions:
        if c not in scenes.SCENARIOS or c == EMPTY:
            parser.error(f"unknown condition {c!r}")
    detectors = all_detectors()
    if args.baseline:
        detectors.insert(1, CheckoutDetector(BASELINE, None, checkout=args.baseline))
    if args.only:
        words = [w.lower() for w in args.only.split(",") if w]
        detectors = [d for d in detectors if any(w in d.name.lower() for w in words)]
    unavailable = {d.name: d.reason for d in detectors if not d.available}
    detectors = [d for d in detectors if d.available]
    for name, reason in unavailable.items():
        print(f"{name}: {reason}", file=sys.stderr)

    start = time.perf_counter()
    try:
        results = run(detectors, conditions, args.frames, args.empty_frames, args.seed)
    finally:
        for det in detectors:
            if isinstance(det, CheckoutDetector):
                det.close()
    elapsed = time.perf_counter() - start

    table_conditions = [c for c in conditions if c != CLEAN]
    print(f"## Detection, 640x480, {args.frames} frames per condition, seed {args.seed}\n")
    print("Same geometry, background and degradations for every detector; cards of the same printed size "
          "(tags' black square = our discs' outer extent). Points: our disc centres, the tags' outer corners. "
          "'rate vs best peer' is against the best AprilTag/ArUco row of the condition; "
          "'speed vs AprilTag' = AprilTag (decimate 1) median ms / this row's.\n")
    if table_conditions:
        print(condition_table(results, unavailable, table_conditions))
        occluded = {c: next(iter(results.values()))[c].occluded for c in table_conditions} if results else {}
        if any(occluded.values()):
            print("\n(Targets the simulator calls visible but covered by a nearer card, or with the tag "
                  "square not wholly in the image, left out of every row: "
                  f"{', '.join(f'{c} {n}' for c, n in occluded.items() if n)}.)")
    if table_conditions and results:
        print(f"\nThe rate per viewing angle and disc size, over {', '.join(table_conditions)} (bins of "
              f"{MIN_BIN_TARGETS} targets or more; cosine 1: face-on):\n")
        print(bin_table(results, table_conditions))
    if CLEAN in conditions and results:
        print("\n" + clean_table(results))
    if args.empty_frames and results:
        print("\n" + empty_table(results, unavailable))
    ours = [d.name for d in detectors if d.name.startswith("fidotrack") and d.name in results and d.name != BASELINE]
    baseline = BASELINE if BASELINE in results else None
    if ours and ours[0] == LIVE:
        if baseline:
            print(f"\nThe live detector's median ms, this tree against the baseline ({args.baseline}) and AprilTag "
                  "decimate 2, same frames, same run:\n")
            print(speed_table(results, LIVE, baseline, table_conditions))
        print("\nThe live detector stage by stage (median ms over all frames; the targets' sub-stages are "
              "medians of their own, so they need not add up):\n")
        print(stage_table(results, [LIVE, *([baseline] if baseline else [])]))
    for k, name in enumerate(ours):
        # the speed target is live tracking's: the survey's detector trades time for cards
        print(f"\nTargets, {name}:\n\n" + target_check(results, name, table_conditions, speed=k == 0,
                                                           baseline=baseline))
    if not ours:
        print("\nOur detector: " + next((r for n, r in unavailable.items() if n.startswith("fidotrack")),
                                        "not selected"))
    errors = [f"{name} {c}: {st.errors}" for name, by in results.items() for c, st in by.items() if st.errors]
    if errors:
        print("\nFrames on which a detector raised (scored as finding nothing): " + "; ".join(errors) + ".")
    if REDRAWN:
        print("\nFrames redrawn from the next seed because the simulator failed on the first: "
              + ", ".join(f"{c} {sorted(v)}" for c, v in REDRAWN.items()) + ".")
    print(f"\n{elapsed:.0f} s in all (rendering included).")


if __name__ == "__main__":
    main()
