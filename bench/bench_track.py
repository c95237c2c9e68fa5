"""The /track WebSocket under load, with and without region-of-interest tracking: a real
client (the `websockets` package) against a running ``fidotrack serve``, streaming a
rendered 640x480 room sequence.

The bench room (`app.sim.examples.BENCH_ROOM`: 8 x 6 x 3 m, 30 cards of 0.2 m, f = 820 px,
k1 = -0.12) is rendered along a
tracking walk; its true map is PUT into a fresh environment. Every run is made twice on
the same server, once per mode, set by the client's config message:

* ``regions``: ``{"type": "config", "regions": true}`` (the default): the server searches
  only around the targets its previous poses predict, with a full scan every 30th frame
  and whenever the track is lost;
* ``full``: ``{"type": "config", "regions": false}``: every frame scanned whole.

Runs (in that order, each mode in turn, ``--repeat`` times):

* lock-step: send a frame, wait for its reply, send the next. Both modes run at once,
  interleaved: one connection per mode, each frame goes to one then the other (the
  order alternating), so that both see the same machine load; a mode's frames per
  second are its frames over the time it spent waiting for its replies;
* free-running: a client that sends at a camera's pace (``--free-fps``, 100) without
  waiting while replies stream back; the server drops the older frames it cannot keep
  up with (never the newest);
* two lock-step clients at once (aggregate frames per second).

Columns: frames per second (lock-step: frames per second of the exchange; free-running:
replies per second), client-side latency p50/p99 (send to reply), the server's own
processing time per frame (``timing_ms.total``: decode + detect + pose) p50/p99, its
detection time p50, dropped frames, frames with a pose, camera position error against
the renderer's truth (median and p90, mm) and the fraction of frames scanned whole
(``scan`` of the reply). Then the ratios regions / full, and how far apart the two
modes' lock-step positions are frame by frame.

Timings are wall-clock on a shared machine: run it two or three times and compare the
medians (the load average is printed).

Run: ``.venv/bin/python bench/bench_track.py [--frames 300] [--repeat 1]`` (prints
markdown tables; ``--no-pair`` skips the two-client runs, ``--server-env
OPENBLAS_NUM_THREADS=1`` starts the server with that environment: numpy's OpenBLAS
otherwise runs a second thread that spins after every small matrix product, which on
two cores costs the other client, and the event loop, a core).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core.geometry import Pose  # noqa: E402
from app.local_server import running_server  # noqa: E402
from app.sim import BENCH_ROOM, render_walk  # noqa: E402
from bench.track_clients import (  # noqa: E402
    HEADER,
    MODES,
    QUIET_SERVER,
    SPLIT,
    RunStats,
    account,
    http_json,
    open_track,
    stream_lock_step,
)


async def _lock_step(url: str, mode: str, frames: list[bytes], truth: list[Pose], name: str) -> RunStats:
    return await stream_lock_step(await open_track(url, mode), frames, truth, RunStats(name, mode))


async def _lock_step_pair(url: str, frames: list[bytes], truth: list[Pose], name: str) -> list[RunStats]:
    """Lock-step in both modes at once, frame by frame in alternating order."""
    stats = {mode: RunStats(name, mode) for mode in MODES}
    sockets = {mode: await open_track(url, mode) for mode in MODES}
    try:
        for seq, data in enumerate(frames):
            for mode in (list(MODES) if seq % 2 == 0 else list(MODES)[::-1]):
                sent = time.perf_counter()
                await sockets[mode].send(data)
                stats[mode].sent += 1
                reply = json.loads(await sockets[mode].recv())
                if reply["type"] != "frame":
                    raise RuntimeError(f"unexpected reply {reply}")
                took = time.perf_counter() - sent
                stats[mode].latency_ms.append(took * 1e3)
                stats[mode].seconds += took
                account(stats[mode], reply, truth)
    finally:
        for ws in sockets.values():
            await ws.close()
    return list(stats.values())


async def _free_running(url: str, mode: str, frames: list[bytes], truth: list[Pose], fps: float) -> RunStats:
    stats = RunStats(f"free-running, sent at {fps:.0f} fps", mode)
    sent_at: dict[int, float] = {}
    ws = await open_track(url, mode)
    try:
        start = time.perf_counter()

        async def send() -> None:
            # A camera that delivers `fps` frames a second, whatever the server manages.
            for seq, data in enumerate(frames):
                await asyncio.sleep(max(0.0, start + seq / fps - time.perf_counter()))
                sent_at[seq] = time.perf_counter()
                await ws.send(data)
                stats.sent += 1

        sender = asyncio.create_task(send())
        last = len(frames) - 1
        while True:
            reply = json.loads(await asyncio.wait_for(ws.recv(), timeout=30))
            if reply["type"] != "frame":
                raise RuntimeError(f"unexpected reply {reply}")
            stats.latency_ms.append((time.perf_counter() - sent_at[reply["seq"]]) * 1e3)
            account(stats, reply, truth)
            if reply["seq"] == last:
                break
        await sender
        stats.seconds = time.perf_counter() - start
    finally:
        await ws.close()
    return stats


async def _two(url: str, mode: str, frames: list[bytes], truth: list[Pose]) -> list[RunStats]:
    return list(await asyncio.gather(_lock_step(url, mode, frames, truth, "2 clients, lock-step (a)"),
                                     _lock_step(url, mode, frames, truth, "2 clients, lock-step (b)")))


def _summary(runs: list[RunStats], name: str, mode: str) -> dict[str, float]:
    """Medians over the repeats of one run and mode."""
    mine = [r for r in runs if r.name == name and r.mode == mode]

    def pooled(attr: str, q: float) -> float:
        return float(np.median([np.percentile(getattr(r, attr), q) for r in mine if getattr(r, attr)]))

    return {"fps": float(np.median([r.fps for r in mine])), "latency_p50": pooled("latency_ms", 50),
            "latency_p99": pooled("latency_ms", 99), "server_p50": pooled("server_ms", 50),
            "server_p99": pooled("server_ms", 99), "err_p50": pooled("errors_mm", 50),
            "err_p90": pooled("errors_mm", 90)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--quality", type=int, default=90, help="JPEG quality")
    parser.add_argument("--free-fps", type=float, default=100.0, help="send rate of the free-running client")
    parser.add_argument("--repeat", type=int, default=1, help="rounds of all runs (both modes each round)")
    parser.add_argument("--no-pair", action="store_true", help="skip the two-client runs")
    parser.add_argument("--server-env", action="append", default=[], metavar="KEY=VALUE",
                        help="extra environment for the server (e.g. OPENBLAS_NUM_THREADS=1); repeatable")
    args = parser.parse_args()

    room = BENCH_ROOM.walk(args.seed, args.frames, kind="tracking")
    scene, poses, rng, camera = room.scene, room.poses, room.rng, BENCH_ROOM.camera
    frames: list[bytes] = []
    for image, _ in tqdm(render_walk(scene, camera, poses, rng, degradation="default"), total=len(poses),
                         desc="rendering", unit="frame"):
        frames.append(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, args.quality])[1].tobytes())

    runs: list[RunStats] = []
    pairs: list[tuple[str, float]] = []
    load = [os.getloadavg()[0]]
    server_env = {**QUIET_SERVER, **dict(item.split("=", 1) for item in args.server_env)}
    with tempfile.TemporaryDirectory() as tmp, running_server(Path(tmp), settings=server_env) as server:
        # The deployment as the README starts it: `fidotrack serve`.
        env = http_json("POST", f"{server.url}/environments", {"name": "bench room", "marker_size_m": 0.2})
        http_json("PUT", f"{server.url}/environments/{env['id']}/map", scene.map_document(camera))
        url = f"{server.ws_url}/track?environment_id={env['id']}"
        asyncio.run(_lock_step_pair(url, frames[:20], poses[:20], "warm-up"))
        for round_ in range(args.repeat):
            order = list(MODES) if round_ % 2 == 0 else list(MODES)[::-1]  # neither always first
            runs += asyncio.run(_lock_step_pair(url, frames, poses, "lock-step"))
            for mode in order:
                runs.append(asyncio.run(_free_running(url, mode, frames, poses, args.free_fps)))
            if not args.no_pair:
                for mode in order:
                    pair = asyncio.run(_two(url, mode, frames, poses))
                    runs += pair
                    pairs.append((mode, sum(r.replies for r in pair) / max(max(r.seconds for r in pair), 1e-9)))
            load.append(os.getloadavg()[0])

    print(f"\n/track, {args.frames} frames 640x480 JPEG q{args.quality}, room 8x6x3 m, 30 cards, "
          f"uvicorn on 127.0.0.1, {os.cpu_count()} cores, {args.repeat} round(s), "
          f"server env {' '.join(args.server_env) or '(as is)'}; "
          f"load average (1 min) {' -> '.join(f'{x:.2f}' for x in load)}\n")
    print(HEADER)
    for run in runs:
        print(run.row())
    if pairs:
        print()
        for mode in MODES:
            totals = [t for m, t in pairs if m == mode]
            print(f"Two clients together, {mode}: {np.median(totals):.0f} frames per second (median of "
                  f"{len(totals)}).")

    print("\nRatios regions / full (medians over the rounds):\n")
    print("| run | fps | latency p50 | latency p99 | server p50 | server p99 | position err p50 | position err p90 |")
    print("|---|---|---|---|---|---|---|---|")
    free_name = f"free-running, sent at {args.free_fps:.0f} fps"
    for name in ("lock-step", free_name):
        on, off = _summary(runs, name, "regions"), _summary(runs, name, "full")
        cells = " | ".join(f"{on[k] / off[k]:.2f}" if off[k] else "-" for k in
                           ("fps", "latency_p50", "latency_p99", "server_p50", "server_p99", "err_p50", "err_p90"))
        print(f"| {name} | {cells} |")
    print("\nAbsolute (medians over the rounds):\n")
    print("| run | mode | fps | latency p50 ms | latency p99 ms | server p50 ms | server p99 ms | err p50 mm | "
          "err p90 mm |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in ("lock-step", free_name):
        for mode in MODES:
            s = _summary(runs, name, mode)
            print(f"| {name} | {mode} | {s['fps']:.0f} | {s['latency_p50']:.1f} | {s['latency_p99']:.1f} | "
                  f"{s['server_p50']:.2f} | {s['server_p99']:.1f} | {s['err_p50']:.1f} | {s['err_p90']:.1f} |")

    print("\nWhere the server's time goes, lock-step (timing_ms, p50 ms over all rounds; total is not the "
          "sum of the medians):\n")
    print("| mode | " + " | ".join(SPLIT) + " |")
    print("|---|" + "---|" * len(SPLIT))
    for mode in MODES:
        mine = [r for r in runs if r.name == "lock-step" and r.mode == mode]
        cells = " | ".join(f"{np.median([v for r in mine for v in r.split[k]]):.2f}" for k in SPLIT)
        print(f"| {mode} | {cells} |")

    print("\nWhy frames were scanned as they were (scan_reason), regions mode, summed over the rounds:\n")
    for name in ("lock-step", free_name):
        total: dict[str, int] = {}
        for r in runs:
            if r.name == name and r.mode == "regions":
                for k, v in r.reasons.items():
                    total[k] = total.get(k, 0) + v
        print(f"- {name}: " + ", ".join(f"{k} {v}" for k, v in sorted(total.items(), key=lambda kv: -kv[1])))

    # The same frames in both modes (lock-step): how far apart are the two modes' poses?
    on = [r for r in runs if r.name == "lock-step" and r.mode == "regions"]
    off = [r for r in runs if r.name == "lock-step" and r.mode == "full"]
    gaps = [1e3 * float(np.linalg.norm(a.positions[s] - b.positions[s]))
            for a, b in zip(on, off, strict=True) for s in a.positions.keys() & b.positions.keys()]
    only = sum(len(a.positions.keys() ^ b.positions.keys()) for a, b in zip(on, off, strict=True))
    if gaps:
        print(f"\nLock-step, regions vs full on the same frames: position difference median "
              f"{np.median(gaps):.3f} mm, p99 {np.percentile(gaps, 99):.3f} mm, max {max(gaps):.2f} mm; "
              f"{only} frame(s) with a pose in one mode only.")


if __name__ == "__main__":
    main()
