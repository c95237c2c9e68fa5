"""The /track WebSocket on HD frames: 640x480, 1280x720 and 1920x1080 side by side, with a
real client (the `websockets` package) against a running ``fidotrack serve``.

The bench room (`app.sim.examples.BENCH_ROOM`: 8 x 6 x 3 m, 30 cards of 0.2 m) is rendered
along the same tracking walk at every size, through the bench camera's lens at that size
(`bench_browser.camera_for`: the focal length scales with the width, the principal point
at the centre, the same distortion: the same horizontal field of view, a 16:9 frame
showing the middle band of the 4:3 one). Each size gets an environment of its own with
the room's true map and that size's camera.

Lock-step clients, one per size and mode (``regions``: the default region scans;
``full``: every frame scanned whole), all open at once and interleaved: frame k goes to
each connection in turn (the order rotating from frame to frame), each connection
waiting for its reply before the next, so every size and mode sees the same machine
load. A connection's frames per second are its frames over the time it spent waiting
for its replies.

Columns: frames per second, client latency p50/p99, the server's time per frame
(``timing_ms.total``) p50/p99, its JPEG decoding (``decode``), detection and pose
(p50), frames with a pose, the camera position error against the renderer's truth
(median, p90, mm), the share of frames scanned whole, and how many frames the server
decoded at 1/2 or 1/4 of their size (``timing_ms.reduction``). Then the ratios of each
size to 640x480 in the same run, where the server's time goes per size, and what
decoding alone costs (the bench process decoding the same frames, whole and reduced:
the floor under the server's time).

With ``--baseline-env KEY=VALUE`` (``PYTHONPATH=`` a checkout of another version of the
code) a second server, "baseline", runs beside this tree's, its connections interleaved
with the others, and a table gives this tree's figures over the baseline's. The server
started first measured a few per cent slower at 640x480 in this layout: swap the two to
check a small difference.

Run: ``.venv/bin/python bench/bench_hd.py [--frames 300] [--sizes 640x480,1280x720,1920x1080]
[--cache DIR] [--baseline-env PYTHONPATH=...]`` (``--cache`` keeps the rendered JPEGs
between runs; the servers start with ``FIDOTRACK_MAX_TRACK_FPS=1000``, which lifts the
rate limit off lock-step clients, and ``OPENBLAS_NUM_THREADS=1``; ``--server-env
KEY=VALUE`` adds to them).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import pickle
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path

import cv2
import numpy as np
import simplejpeg
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core.geometry import Pose  # noqa: E402
from app.local_server import running_server  # noqa: E402
from app.sim import BENCH_ROOM, render_walk  # noqa: E402
from bench.bench_browser import camera_for  # noqa: E402
from bench.track_clients import (  # noqa: E402
    MODES,
    QUIET_SERVER,
    SPLIT,
    RunStats,
    account,
    http_json,
    open_track,
)

#: The server's environment unless --server-env says otherwise.
SERVER_ENV = {"FIDOTRACK_MAX_TRACK_FPS": "1000", "OPENBLAS_NUM_THREADS": "1"}
#: Frames each connection gets before the measured run (the first full scans, caches).
WARM_UP = 20


def _size(text: str) -> tuple[int, int]:
    width, height = text.lower().split("x")
    return int(width), int(height)


def _render(width: int, height: int, frames: int, seed: int, quality: int, cache: Path | None
            ) -> tuple[list[bytes], list[Pose], dict]:
    """The walk at `width` x `height` as JPEGs, its true poses and the room's map with
    this size's camera (from `cache` when it holds them)."""
    camera = camera_for(width, height)
    room = BENCH_ROOM.walk(seed, frames, kind="tracking")
    document = room.scene.map_document(camera)
    path = cache / f"walk-{seed}-{frames}-q{quality}-{width}x{height}.pkl" if cache else None
    if path is not None and path.exists():
        with path.open("rb") as f:
            return pickle.load(f), room.poses, document
    jpegs = []
    for image, _ in tqdm(render_walk(room.scene, camera, room.poses, room.rng, degradation="default"),
                         total=frames, desc=f"rendering {width}x{height}", unit="frame"):
        jpegs.append(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])[1].tobytes())
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("wb") as f:
            pickle.dump(jpegs, f)
    return jpegs, room.poses, document


Key = tuple[str, str, str]  # (server, size, mode)


async def _lock_step_all(urls: dict[tuple[str, str], str], frames: dict[str, list[bytes]], truth: list[Pose],
                         start: int, stop: int) -> tuple[dict[Key, RunStats], dict[Key, list[float]]]:
    """Lock-step on one connection per server, size and mode (`urls`: (server, size) ->
    its /track URL): frames 0 to `start` as warm-up, then frames `start` to `stop`
    (exclusive) measured, frame by frame in rotating order: the stats and each frame's
    decode reduction."""
    keys = [(server, size, mode) for server, size in urls for mode in MODES]
    stats = {key: RunStats(f"{key[0]} {key[1]}", key[2]) for key in keys}
    reductions: dict[Key, list[float]] = {key: [] for key in keys}
    sockets = {key: await open_track(urls[key[:2]], key[2]) for key in keys}
    try:
        for warm in range(start):  # the first frames' full scans, left out
            for key in keys:
                await sockets[key].send(frames[key[1]][warm])
                await sockets[key].recv()
        for seq in range(start, stop):
            turn = seq % len(keys)
            for key in keys[turn:] + keys[:turn]:
                sent = time.perf_counter()
                await sockets[key].send(frames[key[1]][seq])
                stats[key].sent += 1
                reply = json.loads(await sockets[key].recv())
                took = time.perf_counter() - sent
                if reply["type"] != "frame":
                    raise RuntimeError(f"unexpected reply {reply}")
                stats[key].latency_ms.append(took * 1e3)
                stats[key].seconds += took
                account(stats[key], reply, truth)
                reductions[key].append(float(reply["timing_ms"].get("reduction", 1.0)))
    finally:
        for ws in sockets.values():
            await ws.close()
    return stats, reductions


def _decode_floor(frames: dict[str, list[bytes]], count: int = 60) -> dict[tuple[str, int], float]:
    """Milliseconds (median) to decode a frame's luma whole, at 1/2 and at 1/4 in this
    process, the sizes and factors interleaved."""
    times: dict[tuple[str, int], list[float]] = {}
    for k in range(count):
        for size, jpegs in frames.items():
            data = jpegs[k % len(jpegs)]
            height, width = simplejpeg.decode_jpeg_header(data)[:2]
            for factor in (1, 2, 4):
                scale = {"min_height": -(-height // factor), "min_width": -(-width // factor),
                         "min_factor": float(factor)} if factor > 1 else {}
                started = time.perf_counter()
                simplejpeg.decode_jpeg(data, colorspace="GRAY", **scale)
                times.setdefault((size, factor), []).append((time.perf_counter() - started) * 1e3)
    return {key: float(np.median(values)) for key, values in times.items()}


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--quality", type=int, default=90, help="JPEG quality")
    parser.add_argument("--sizes", default="640x480,1280x720,1920x1080", help="comma-separated, the first the reference")
    parser.add_argument("--cache", type=Path, default=None, help="directory keeping the rendered frames between runs")
    parser.add_argument("--server-env", action="append", default=[], metavar="KEY=VALUE",
                        help="extra environment for the server; repeatable")
    parser.add_argument("--baseline-env", action="append", default=[], metavar="KEY=VALUE",
                        help="start a second server, 'baseline', with this environment added too (PYTHONPATH=a "
                             "checkout of another version of the code), streamed in the same run; repeatable")
    args = parser.parse_args()

    sizes = [_size(s) for s in args.sizes.split(",")]
    names = [f"{w}x{h}" for w, h in sizes]
    frames: dict[str, list[bytes]] = {}
    documents: dict[str, dict] = {}
    truth: list[Pose] = []
    for name, (width, height) in zip(names, sizes, strict=True):
        frames[name], truth, documents[name] = _render(width, height, args.frames, args.seed, args.quality,
                                                       args.cache)

    server_env = {**SERVER_ENV, **dict(item.split("=", 1) for item in args.server_env)}
    servers = {"this tree": server_env}
    if args.baseline_env:
        servers["baseline"] = {**server_env, **dict(item.split("=", 1) for item in args.baseline_env)}
    load = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as running:
        urls = {}
        for label, env_vars in servers.items():
            server = running.enter_context(running_server(Path(tmp) / label.replace(" ", "-"),
                                                          settings={**QUIET_SERVER, **env_vars}))
            for name in names:
                env = http_json("POST", f"{server.url}/environments", {"name": f"bench room {name}",
                                                                       "marker_size_m": 0.2})
                http_json("PUT", f"{server.url}/environments/{env['id']}/map", documents[name])
                urls[(label, name)] = f"{server.ws_url}/track?environment_id={env['id']}"
        stats, reductions = asyncio.run(_lock_step_all(urls, frames, truth, WARM_UP, args.frames))
        load.append(os.getloadavg()[0])
    floor = _decode_floor(frames)

    ref = names[0]
    print(f"\n/track lock-step, {args.frames - WARM_UP} frames a connection (after {WARM_UP} of warm-up) of the bench "
          f"walk as JPEG q{args.quality} at {', '.join(names)}, one connection per server, size and mode, interleaved; "
          f"uvicorn on 127.0.0.1, {os.cpu_count()} cores, server env "
          f"{' '.join(f'{k}={v}' for k, v in server_env.items())}"
          f"{' (baseline: ' + ' '.join(args.baseline_env) + ')' if args.baseline_env else ''}; load average (1 min) "
          f"{' -> '.join(f'{x:.2f}' for x in load)}\n")
    print("| server | size | mode | fps | latency p50 ms | latency p99 ms | server p50 ms | server p99 ms | "
          "decode p50 ms | detect p50 ms | pose p50 ms | with pose | err p50 mm | err p90 mm | full scans | "
          "decoded at 1/1, 1/2, 1/4 |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for label in servers:
        for name in names:
            for mode in MODES:
                s, red = stats[(label, name, mode)], reductions[(label, name, mode)]
                shares = "/".join(f"{red.count(float(f)) / max(len(red), 1):.0%}" for f in (1, 2, 4))
                print(f"| {label} | {name} | {mode} | {s.fps:.0f} | {_pct(s.latency_ms, 50):.1f} | "
                      f"{_pct(s.latency_ms, 99):.1f} | {_pct(s.server_ms, 50):.2f} | {_pct(s.server_ms, 99):.1f} | "
                      f"{_pct(s.split['decode'], 50):.2f} | {_pct(s.detect_ms, 50):.2f} | {_pct(s.split['pose'], 50):.2f} | "
                      f"{s.posed / max(s.replies, 1):.0%} | {_pct(s.errors_mm, 50):.2f} | {_pct(s.errors_mm, 90):.2f} | "
                      f"{s.full_scans / max(s.replies, 1):.0%} | {shares} |")

    print(f"\nRatios to {ref} on the same server (same run, same mode): frames per second, and server time p50 "
          f"and p99:\n")
    print("| server | size | mode | fps ratio | server p50 ratio | server p99 ratio |")
    print("|---|---|---|---|---|---|")
    for label in servers:
        for name in names[1:]:
            for mode in MODES:
                s, r = stats[(label, name, mode)], stats[(label, ref, mode)]
                print(f"| {label} | {name} | {mode} | {s.fps / r.fps:.2f} | "
                      f"{_pct(s.server_ms, 50) / _pct(r.server_ms, 50):.2f} | "
                      f"{_pct(s.server_ms, 99) / _pct(r.server_ms, 99):.2f} |")
    if "baseline" in servers:
        print("\nThis tree / baseline (same run, same size and mode):\n")
        print("| size | mode | fps | server p50 | server p99 | err p50 | err p90 |")
        print("|---|---|---|---|---|---|---|")
        for name in names:
            for mode in MODES:
                a, b = stats[("this tree", name, mode)], stats[("baseline", name, mode)]
                cells = [a.fps / b.fps] + [_pct(getattr(a, attr), q) / _pct(getattr(b, attr), q) for attr, q in
                                           (("server_ms", 50), ("server_ms", 99), ("errors_mm", 50),
                                            ("errors_mm", 90))]
                print(f"| {name} | {mode} | " + " | ".join(f"{c:.2f}" for c in cells) + " |")

    print("\nWhere the server's time goes (timing_ms, p50 ms; the total is not the sum of the medians):\n")
    print("| server | size | mode | " + " | ".join(SPLIT) + " |")
    print("|---|---|---|" + "---|" * len(SPLIT))
    for label in servers:
        for name in names:
            for mode in MODES:
                s = stats[(label, name, mode)]
                print(f"| {label} | {name} | {mode} | " + " | ".join(f"{_pct(s.split[k], 50):.2f}" for k in SPLIT)
                      + " |")

    print("\nDecoding alone (this process, the same frames, luma only; p50 ms) and the frame's size:\n")
    print("| size | JPEG kB (mean) | whole | at 1/2 | at 1/4 |")
    print("|---|---|---|---|---|")
    for name in names:
        kb = np.mean([len(f) for f in frames[name]]) / 1e3
        print(f"| {name} | {kb:.0f} | {floor[(name, 1)]:.2f} | {floor[(name, 2)]:.2f} | {floor[(name, 4)]:.2f} |")


if __name__ == "__main__":
    main()
