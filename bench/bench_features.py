"""Natural-feature tracks (`app.core.features`) through rendered walks, against the scene's truth.

Every example walk of `app.sim.examples.WALKS` (the bench room's survey loops, a loop near
the middle looking out at the walls, a pure pan, the sparse and the plain-walled room) is
rendered for each seed (its own room and walk) and tracked each way of `VARIANTS` on the
same frames: each method of `app.core.features.Method` (KLT alone, ORB or SIFT keypoints
matched frame to frame and at keyframes, KLT with ORB or SIFT keyframe matching), then
the chosen one on the frames as they are (no shading removed) and without the lens. The
cards are excluded as a caller excludes its detections (`exclusion_mask` of every card
with a disc in view, from the truth). The tracker gets the true lens for its geometric
checks, as the survey will give it the lens it fits from the cards.

Truth comes from the scene, never from the tracker: a feature seen at uv in frame a lies
where the ray through uv (lens-corrected) leaves the box room, or on a card if it meets
one first; that point projected into frame b is where the same feature must be seen
there. A link between two consecutive observations of a track is wrong when it lands
more than 2 px from there (or where frame b cannot see the point); a track's position
error is each observation's distance from where its first observation's point projects.

Run: ``.venv/bin/python bench/bench_features.py --quick`` (2 rooms x 150 frames per walk,
plus the centre loop and the pan at 330 frames, a full turn and then some, for their loop
closures; about 9 minutes); ``--seeds``, ``--frames``, ``--walks``, ``--variants``,
``--loop-walks`` and ``--loop-frames`` choose otherwise. Timings are one thread
(``cv2.setNumThreads(1)``), the tracker alone (not the render, not the masks).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import cv2
import numpy as np
from tqdm import tqdm

from app.core.features import (
    FeatureSettings,
    FeatureTracker,
    FeatureTracks,
    Method,
    exclusion_mask,
)
from app.core.geometry import Camera
from app.sim import WALKS, Scene

#: A link is wrong when it lands farther than this from the truth, px.
WRONG_PX = 2.0
#: A link across at least this many frames joins two visits of a wall (a loop closure);
#: the keyframe matches across shorter gaps bridge a track lost for a moment.
LOOP_GAP = 30
#: Tracks seen in fewer frames than this cannot be triangulated usefully: the per-frame
#: counts leave them out.
MIN_VIEWS = 3
#: Frames that see fewer tracks than this (of MIN_VIEWS frames or more) hardly register.
FEW_TRACKS = 30


@dataclass
class Video:
    """A rendered walk: its frames, the cards' exclusion masks and the truth to score against."""

    walk: str
    seed: int
    images: list[np.ndarray]
    masks: list[np.ndarray]
    R: np.ndarray  # (F, 3, 3) map to camera
    t: np.ndarray  # (F, 3)
    scene: Scene
    camera: Camera


def render_video(walk: str, seed: int, n_frames: int) -> Video:
    """Render one example walk and the exclusion masks of its cards."""
    example = WALKS[walk]
    room_walk = example.walk(seed, n_frames)
    camera = example.room.camera
    images, masks, R, t = [], [], [], []
    for image, truth in tqdm(room_walk.frames(camera), total=n_frames, desc=f"render {walk} {seed}", unit="frame",
                             leave=False):
        quads = [target.discs_px for target in truth.targets if target.disc_visible.any()]
        images.append(image)
        masks.append(exclusion_mask(image.shape, np.array(quads).reshape(-1, 4, 2)))
        R.append(truth.pose.R)
        t.append(truth.pose.t)
    return Video(walk, seed, images, masks, np.array(R), np.array(t), room_walk.scene, camera)


def transfer(video: Video, frame_a: np.ndarray, frame_b: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Where the scene point seen at uv in frame a appears in frame b: the truth.

    Parameters
    ----------
    video : Video
        The walk (poses, room, cards, camera).
    frame_a, frame_b : (M,) ndarray of int
        The frames of each point.
    uv : (M, 2) ndarray
        The points in frame a, px.

    Returns
    -------
    (M, 2) ndarray
        The points in frame b, px; nan where frame b cannot see the point.
    """
    camera, scene = video.camera, video.scene
    ideal = camera.undistort_pixels(uv)
    ray = np.c_[ideal, np.ones(len(uv))] @ np.linalg.inv(camera.K).T
    Ra, ta = video.R[frame_a], video.t[frame_a]
    d = np.einsum("mji,mj->mi", Ra, ray)
    eye = -np.einsum("mji,mj->mi", Ra, ta)
    size = np.array(scene.room_size)
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = np.where(d > 0, size, 0.0)
        exits = np.where(d != 0, (bound - eye) / d, np.inf)
    depth = exits.min(axis=1)
    for target in scene.targets:
        n = target.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            tc = ((target.origin - eye) @ n) / (d @ n)
        hit = eye + tc[:, None] * d
        cu = (hit - target.origin) @ target.x_axis / target.size_m
        cv = (hit - target.origin) @ target.y_axis / target.size_m
        on = (tc > 0) & (tc < depth) & (cu >= 0) & (cu <= 1) & (cv >= 0) & (cv <= 1)
        depth = np.where(on, tc, depth)
    X = eye + depth[:, None] * d
    Xb = np.einsum("mij,mj->mi", video.R[frame_b], X) + video.t[frame_b]
    out = camera.project(Xb)
    seen = (Xb[:, 2] > 0.05) & camera.in_field(Xb)
    seen &= (out[:, 0] >= -0.5) & (out[:, 0] < camera.width - 0.5)
    seen &= (out[:, 1] >= -0.5) & (out[:, 1] < camera.height - 0.5)
    out[~seen] = np.nan
    return out


@dataclass
class Scores:
    """One method on one video."""

    frames: int
    per_frame: float  # mean tracks (of MIN_VIEWS frames or more) per frame
    few: float  # fraction of frames with fewer than FEW_TRACKS such tracks
    length_median: float
    length_p90: float
    links: int
    wrong_links: int
    link_p50: float  # px, of the right links
    link_p90: float
    observations: int
    off: int  # observations more than WRONG_PX from where their track's first observation projects
    drift_p50: float
    drift_p90: float
    loops: int  # keyframe links across LOOP_GAP frames or more
    wrong_loops: int  # of them, those whose merges are mostly wrong (a repeated pattern taken for a wall seen again)
    loop_links: int  # track links across LOOP_GAP frames or more
    wrong_loop_links: int
    seconds: float


def score(video: Video, tracks: FeatureTracks, seconds: float) -> Scores:
    """Score feature tracks against the truth of their video."""
    useful = tracks.seen_in(MIN_VIEWS)
    per_frame = useful.per_frame()
    lengths = tracks.lengths()
    order = np.lexsort((tracks.frame, tracks.track))
    fr, tr, uv = tracks.frame[order], tracks.track[order], tracks.uv[order]
    same = tr[1:] == tr[:-1]
    a, b = np.flatnonzero(same), np.flatnonzero(same) + 1
    err = np.linalg.norm(transfer(video, fr[a], fr[b], uv[a]) - uv[b], axis=1)
    err = np.where(np.isfinite(err), err, np.inf)
    wrong = err > WRONG_PX
    gap = fr[b] - fr[a]
    loop = gap >= LOOP_GAP
    # Each observation against its track's first.
    start = np.r_[0, np.flatnonzero(~same) + 1]
    first = np.repeat(start, np.diff(np.r_[start, len(fr)]))
    later = np.flatnonzero(np.arange(len(fr)) != first)
    drift = np.linalg.norm(transfer(video, fr[first[later]], fr[later], uv[first[later]]) - uv[later], axis=1)
    drift = np.where(np.isfinite(drift), drift, np.inf)
    right = err[~wrong]
    # Each loop closure's merges: the join of each merged track just before the link's frame.
    wrong_loops = 0
    loops = [link for link in tracks.links if link.frame - link.earlier_frame >= LOOP_GAP]
    for link in loops:
        joins = []
        for t in link.tracks:
            pairs = np.flatnonzero((tr[a] == t) & (fr[b] <= link.frame))
            if len(pairs):
                joins.append(pairs[np.argmax(gap[pairs])])
        wrong_loops += int(np.mean(wrong[joins]) > 0.5) if joins else 0
    finite_drift = drift[np.isfinite(drift)]
    return Scores(
        frames=tracks.n_frames,
        per_frame=float(per_frame.mean()) if tracks.n_frames else 0.0,
        few=float(np.mean(per_frame < FEW_TRACKS)) if tracks.n_frames else 1.0,
        length_median=float(np.median(lengths)) if len(lengths) else 0.0,
        length_p90=float(np.percentile(lengths, 90)) if len(lengths) else 0.0,
        links=len(err),
        wrong_links=int(wrong.sum()),
        link_p50=float(np.median(right)) if len(right) else np.nan,
        link_p90=float(np.percentile(right, 90)) if len(right) else np.nan,
        observations=len(drift),
        off=int((drift > WRONG_PX).sum()),
        drift_p50=float(np.median(finite_drift)) if len(finite_drift) else np.nan,
        drift_p90=float(np.percentile(finite_drift, 90)) if len(finite_drift) else np.nan,
        loops=len(loops),
        wrong_loops=wrong_loops,
        loop_links=int(loop.sum()),
        wrong_loop_links=int((wrong & loop).sum()),
        seconds=seconds,
    )


@dataclass(frozen=True)
class Variant:
    """One way of tracking: a method and its settings, with or without the lens."""

    label: str
    settings: FeatureSettings
    lens: bool = True


#: The methods side by side, then the chosen one without two of its parts.
VARIANTS: dict[str, Variant] = {v.label: v for v in [
    *(Variant(m.value, FeatureSettings(method=m)) for m in Method),
    Variant("klt+orb, frames as they are", FeatureSettings(method=Method.KLT_ORB, shading_px=None)),
    Variant("klt+orb, no lens", FeatureSettings(method=Method.KLT_ORB), lens=False),
]}


def run(video: Video, variant: Variant) -> Scores:
    """Track a video one way (one thread) and score it."""
    tracker = FeatureTracker(variant.settings, video.camera if variant.lens else None)
    seconds = 0.0
    for image, mask in zip(video.images, video.masks, strict=True):
        start = time.perf_counter()
        tracker.add(image, mask)
        seconds += time.perf_counter() - start
    return score(video, tracker.tracks(), seconds)


def pooled(scores: list[Scores]) -> Scores:
    """Several videos' scores as one (counts summed, per-frame figures weighted by frames,
    percentiles as the frame-weighted mean of each video's)."""
    frames = sum(s.frames for s in scores)

    def mean(name: str, weight: str = "frames") -> float:
        ws = np.array([getattr(s, weight) for s in scores], float)
        vs = np.array([getattr(s, name) for s in scores], float)
        ok = np.isfinite(vs) & (ws > 0)
        return float(np.sum(vs[ok] * ws[ok]) / np.sum(ws[ok])) if ok.any() else np.nan

    return Scores(
        frames=frames, per_frame=mean("per_frame"), few=mean("few"), length_median=mean("length_median"),
        length_p90=mean("length_p90"), links=sum(s.links for s in scores),
        wrong_links=sum(s.wrong_links for s in scores), link_p50=mean("link_p50", "links"),
        link_p90=mean("link_p90", "links"), observations=sum(s.observations for s in scores),
        off=sum(s.off for s in scores), drift_p50=mean("drift_p50", "observations"),
        drift_p90=mean("drift_p90", "observations"), loops=sum(s.loops for s in scores),
        wrong_loops=sum(s.wrong_loops for s in scores),
        loop_links=sum(s.loop_links for s in scores), wrong_loop_links=sum(s.wrong_loop_links for s in scores),
        seconds=sum(s.seconds for s in scores),
    )


def _pct(k: int, n: int) -> str:
    return f"{100.0 * k / n:.2f}" if n else "-"


def table(rows: list[tuple[str, str, Scores]]) -> str:
    """The markdown table of scores, one row per walk and method."""
    header = (
        f"| walk | method | tracks per frame (seen in >= {MIN_VIEWS}) | frames with < {FEW_TRACKS} (%) "
        "| track length median / p90 | wrong links (%) | link error median / p90 (px) "
        f"| observations off their track's point by > {WRONG_PX:g} px (%) | position error median / p90 (px) "
        f"| loop closures (keyframe links >= {LOOP_GAP} frames): found / wrong | loop links (wrong %) | ms per frame |"
    )
    lines = [header, "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for walk, method, s in rows:
        lines.append(
            f"| {walk} | {method} | {s.per_frame:.0f} | {100 * s.few:.1f} "
            f"| {s.length_median:.0f} / {s.length_p90:.0f} | {_pct(s.wrong_links, s.links)} "
            f"| {s.link_p50:.3f} / {s.link_p90:.3f} | {_pct(s.off, s.observations)} "
            f"| {s.drift_p50:.2f} / {s.drift_p90:.2f} | {s.loops} / {s.wrong_loops} "
            f"| {s.loop_links} ({_pct(s.wrong_loop_links, s.loop_links)}) | {1e3 * s.seconds / max(s.frames, 1):.1f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--frames", type=int, default=300, help="frames of each walk")
    parser.add_argument("--loop-frames", type=int, default=330,
                        help="frames of the loop-closure runs of --loop-walks (0: none)")
    parser.add_argument("--loop-walks", nargs="+", default=["centre_loop", "pan"], choices=list(WALKS),
                        help="walks also run at --loop-frames, a full turn and then some")
    parser.add_argument("--walks", nargs="+", default=list(WALKS), choices=list(WALKS))
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--quick", action="store_true", help="2 rooms (seeds 0 1) x 150 frames per walk")
    args = parser.parse_args()
    if args.quick:
        args.seeds, args.frames = [0, 1], 150
    cv2.setNumThreads(1)
    variants = [VARIANTS[label] for label in args.variants]
    runs = [(walk, args.frames) for walk in args.walks]
    if args.loop_frames:
        runs += [(walk, args.loop_frames) for walk in args.loop_walks]
    started = time.perf_counter()
    rows: list[tuple[str, str, Scores]] = []
    overall: dict[str, list[Scores]] = {v.label: [] for v in variants}
    for walk, n_frames in runs:
        per_variant: dict[str, list[Scores]] = {v.label: [] for v in variants}
        for seed in args.seeds:
            video = render_video(walk, seed, n_frames)
            for variant in variants:
                s = run(video, variant)
                per_variant[variant.label].append(s)
                overall[variant.label].append(s)
        rows += [(f"{walk} ({n_frames} frames)", label, pooled(scores)) for label, scores in per_variant.items()]
    print(f"Feature tracks: seeds {args.seeds} (one room and walk each); the cards excluded; the true lens for "
          "the geometric checks unless said.\n")
    print(table(rows))
    print("\nAll walks pooled:\n")
    print(table([("all", label, pooled(scores)) for label, scores in overall.items()]))
    print(f"\nTotal {time.perf_counter() - started:.0f} s.")


if __name__ == "__main__":
    main()
