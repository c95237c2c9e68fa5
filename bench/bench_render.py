"""Speed of the scene simulator: 640x480 room frames with photo-textured walls and
visible marker cards, as the survey and tracking benchmarks render them.

Run: ``.venv/bin/python bench/bench_render.py`` (prints markdown tables).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from app.core.geometry import Camera
from app.sim import degrade, render, scenes


def _percentiles(ms: list[float]) -> str:
    a = np.asarray(ms)
    return f"{np.median(a):.1f} | {np.percentile(a, 90):.1f} | {a.max():.1f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    rng = np.random.default_rng(args.seed)
    camera = Camera.pinhole(820.0, 640, 480, dist=[-0.12, 0.0, 0.0, 0.0, 0.0])
    # Dense enough that many frames see ten or more cards.
    scene = scenes.room_scene(rng, (8.0, 6.0, 3.0), n_targets=60, marker_size_m=0.2)
    poses = scenes.camera_walk(rng, scene.room_size or (8.0, 6.0, 3.0), args.frames, "calibration")
    ranges = degrade.PRESETS["default"]
    render(camera, poses[0], scene.quads())  # warm-up: distortion maps, mipmaps

    rows: dict[str, list[float]] = {"all frames": [], ">= 10 visible cards": []}
    full: list[float] = []
    for pose in poses:
        start = time.perf_counter()
        render(camera, pose, scene.quads(), supersample=2)
        elapsed = (time.perf_counter() - start) * 1000
        n_visible = len(scenes.frame_truth(camera, pose, scene).visible_targets())
        rows["all frames"].append(elapsed)
        if n_visible >= 10:
            rows[">= 10 visible cards"].append(elapsed)
        start = time.perf_counter()
        scenes.render_frame(scene, camera, pose, rng, ranges.sample(rng))
        full.append((time.perf_counter() - start) * 1000)

    print("| 640x480 room frame, supersample 2, k1 -0.12 | frames | median ms | p90 ms | max ms |")
    print("|---|---:|---:|---:|---:|")
    for name, ms in rows.items():
        if ms:
            print(f"| render, {name} | {len(ms)} | {_percentiles(ms)} |")
    print(f"| render + truth + default degradations + uint8 | {len(full)} | {_percentiles(full)} |")
    per_frame = float(np.median(full)) / 1000
    print(f"\n300-frame survey video: about {300 * per_frame:.0f} s of rendering "
          f"(median {per_frame * 1000:.0f} ms a frame).")


if __name__ == "__main__":
    main()
