"""Where the disc centres' bias comes from, one effect at a time.

The survey's floor on a hand-held centre loop is set by the detected disc centres
(`bench_survey_floor`: 2-3 mm with the discs as detected, 0.2-0.6 mm with exact ones).
Each card of such a walk is seen from one side only, so a bias its views share does not
average out. The one that matters most is a bias of the card's size: if the four discs
come out nearer the card's middle than they are, the card's image is too small and the
survey puts the card further away by the same fraction of its distance.

The bench renders one walk (`--walk`, the bench room's hand-held centre loop by default:
the same room, poses and exposures every time) once per effect, with every other effect
off, and detects every frame with the survey's detector (`Detector.for_survey`: fitted
disc centres) and the live detector (`Detector`: centroids). Per effect and detector,
over every card detected whole and identified:

* *disc error*: median distance of the disc centres from the true projections (px);
* *radial*: the mean component of the four discs' errors along the direction from the
  card's middle (mpx, mean and standard error over the card views): negative, the card's
  image shrinks;
* *scale*: the radial error over the discs' distance from the card's middle (1e-4);
* *depth*: the scale times the card's distance (mm, mean): how much further (positive)
  a map of one-sided views would put the card;
* *near side*: the card's mean error toward its near side, where perspective makes its
  discs larger (mpx): a tilt error of the card.

Effects: `none` (sharp and noise-free: the renderer's own sampling), `noise` (sensor read
and shot noise), `straight smear` (the walk's motion blur over the exposure, a straight
smear), `path smear` (the same exposure rendered along the camera's path), `defocus`
(isotropic, 0-1 px), `depth of field` (the cine lens, f/2.8 focused at 2.5 m), `clipping`
(1.5-2.5 times the exposure: the white clips), `jpeg` (quality 80-95), `phone video`
(H.264 at a phone's bit rate, sharp frames), and `default`: the survey benchmarks' own
frames (the `default` preset and the straight smear).

Run: ``.venv/bin/python bench/bench_disc_bias.py [--frames 150] [--seeds 0 1]
[--effects none "straight smear"]`` (markdown tables; progress on stderr).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from app.core.detection import Detector, load_default_classifier, warm_up  # noqa: E402
from app.sim import CINE_LENS, WALKS  # noqa: E402
from app.sim.degrade import DEFAULT, DegradationRanges, ThinLens  # noqa: E402
from app.sim.video import PHONE, PhoneVideo  # noqa: E402
from bench.bench_disc_fit import toward_near_side  # noqa: E402


@dataclass(frozen=True)
class Effect:
    """One way of rendering the walk: the degradation ranges drawn per frame, whether the
    walk's exposure smears it (straight, or along the camera's path), the lens's depth of
    field and the phone's video."""

    name: str
    ranges: DegradationRanges = field(default_factory=DegradationRanges)
    smear: bool = False
    follow_path: bool = False
    lens: ThinLens | None = None
    video: PhoneVideo | None = None


EFFECTS = (
    Effect("none"),
    Effect("noise", DegradationRanges(read_sigma=DEFAULT.read_sigma, shot_scale=DEFAULT.shot_scale)),
    Effect("straight smear", smear=True),
    Effect("path smear", smear=True, follow_path=True),
    Effect("defocus", DegradationRanges(p_defocus=1.0, defocus_radius=DEFAULT.defocus_radius)),
    Effect("depth of field", lens=CINE_LENS),
    Effect("clipping", DegradationRanges(gain=(1.5, 2.5))),
    Effect("jpeg", DegradationRanges(p_jpeg=1.0, jpeg_quality=DEFAULT.jpeg_quality)),
    Effect("phone video", video=PHONE),
    Effect("default", DEFAULT, smear=True),
)


@dataclass
class Views:
    """Per card view: the radial error (px), its scale (fraction), its depth (mm), the
    error toward the near side (px); and every disc's 2-D error (px)."""

    radial: list[float] = field(default_factory=list)
    scale: list[float] = field(default_factory=list)
    depth_mm: list[float] = field(default_factory=list)
    near: list[float] = field(default_factory=list)
    disc_error: list[float] = field(default_factory=list)

    def add(self, found: np.ndarray, true: np.ndarray, distance_m: float) -> None:
        """One card view: detected and true disc centres (4, 2)."""
        err = found - true
        out = true - true.mean(axis=0)
        reach = np.linalg.norm(out, axis=1)
        radial = float(((err * out).sum(axis=1) / reach).mean())
        self.radial.append(radial)
        self.scale.append(radial / float(reach.mean()))
        self.depth_mm.append(-1000.0 * distance_m * radial / float(reach.mean()))
        self.near.append(float(err.mean(axis=0) @ toward_near_side(true[None])[0]))
        self.disc_error.extend(np.hypot(err[:, 0], err[:, 1]).tolist())


def render(effect: Effect, walk_name: str, seed: int, n_frames: int):  # noqa: ANN201 - an iterator of frames
    """The walk's frames (image, truth) under `effect`; the same room, poses and
    exposures for every effect."""
    walk = WALKS[walk_name]
    room = walk.walk(seed, n_frames)
    if not effect.smear:
        room = dataclasses.replace(room, blur=None)  # the ranges' own blur, off unless they draw one
    return room.frames(walk.room.camera, effect.ranges, video=effect.video, follow_path=effect.follow_path,
                       lens=effect.lens)


def measure(effects: list[Effect], walk_name: str, seeds: list[int], n_frames: int
            ) -> dict[tuple[str, str], Views]:
    """Every card view of every effect, per (effect, detector)."""
    classifier = load_default_classifier()
    detectors = {"survey (fitted centres)": Detector.for_survey(classifier), "live (centroids)": Detector(classifier)}
    out = {(e.name, d): Views() for e in effects for d in detectors}
    with tqdm(total=len(effects) * len(seeds) * n_frames, desc="frames", unit="fr", file=sys.stderr) as bar:
        for effect in effects:
            bar.set_postfix_str(effect.name)
            for seed in seeds:
                for image, truth in render(effect, walk_name, seed, n_frames):
                    by_id = {t.id: t for t in truth.targets}
                    for name, detector in detectors.items():
                        for target in detector.detect(image).targets:
                            card = by_id.get(target.id)
                            if card is None or not np.isfinite(card.discs_px).all():
                                continue
                            out[(effect.name, name)].add(np.asarray(target.discs, np.float64),
                                                         np.asarray(card.discs_px, np.float64), card.distance_m)
                    bar.update()
    return out


def _mean_se(values: list[float], scale: float = 1.0) -> str:
    x = scale * np.asarray(values)
    if x.size < 2:
        return "-"
    return f"{x.mean():+.2f} +- {x.std(ddof=1) / np.sqrt(x.size):.2f}"


def table(views: dict[tuple[str, str], Views], effects: list[Effect], detector: str) -> str:
    lines = ["| effect | card views | disc error, median (px) | radial (mpx) | scale (1e-4) | depth (mm) "
             "| near side (mpx) |", "|---|---:|---:|---:|---:|---:|---:|"]
    for effect in effects:
        v = views[(effect.name, detector)]
        median = f"{np.median(v.disc_error):.4f}" if v.disc_error else "-"
        lines.append(f"| {effect.name} | {len(v.radial)} | {median} | {_mean_se(v.radial, 1000)} "
                     f"| {_mean_se(v.scale, 1e4)} | {_mean_se(v.depth_mm)} | {_mean_se(v.near, 1000)} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--walk", default="centre_loop", choices=sorted(WALKS), help="example walk (default centre_loop)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="rooms (default 0 1)")
    parser.add_argument("--frames", type=int, default=150, help="frames of each walk (default 150)")
    parser.add_argument("--effects", nargs="+", default=[e.name for e in EFFECTS],
                        help=f"effects to render (default all: {', '.join(e.name for e in EFFECTS)})")
    args = parser.parse_args(argv)
    known = {e.name: e for e in EFFECTS}
    unknown = [n for n in args.effects if n not in known]
    if unknown:
        parser.error(f"unknown effect(s) {unknown}; known: {list(known)}")
    effects = [known[n] for n in args.effects]
    cv2.setNumThreads(1)
    warm_up()
    start = time.perf_counter()
    views = measure(effects, args.walk, args.seeds, args.frames)
    print(f"## Disc-centre bias by effect: walk {args.walk}, rooms {args.seeds}, {args.frames} frames each\n")
    for detector in ("survey (fitted centres)", "live (centroids)"):
        print(f"\n{detector}, mean +- standard error over the card views:\n")
        print(table(views, effects, detector))
    print(f"\n{time.perf_counter() - start:.0f} s in all (rendering included).")


if __name__ == "__main__":
    main()
