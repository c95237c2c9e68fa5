"""/track with one server process against two: four lock-step clients at once against
``fidotrack serve --workers 1`` and ``fidotrack serve --workers 2``, side by side in one
run.

Both servers run from the start, each on its own data directory (SQLite), with the bench
room's true map (`app.sim.examples.BENCH_ROOM`, the walk of bench/bench_track.py,
640x480 JPEG). Each round streams the walk to each configuration in turn (the order
rotating between rounds): ``--clients`` connections at once, each in lock-step (a frame
leaves when the reply to the previous one is in), regions on (the default config). A
round's aggregate frames per second are all replies over the time the slowest client
took; latency is the client's, from a frame's send to its reply, pooled over the
clients and rounds.

Where the connections land is the kernel's choice: the workers share one listening
socket, and the worker that wakes first accepts every connection waiting, so clients
that connect together often all land on one worker. Each round reads the database's
open connections (each row names the process holding it) and the tables give the
split (``4``: all on one worker, ``3+1``, ``2+2``). The configurations:

* ``--workers 1``;
* ``--workers 2``: the clients as they land;
* ``--workers 2, spread``: the clients reconnect together until they land evenly (what
  connections opened at different times, or through a balancing proxy, get), to show
  what the second process gives when it has its share.

Run: ``.venv/bin/python bench/bench_workers.py [--frames 300] [--rounds 6] [--clients 4]``
(prints markdown tables; the servers start with ``FIDOTRACK_MAX_TRACK_FPS=1000``, which
lifts the rate limit off lock-step clients, and ``OPENBLAS_NUM_THREADS=1``).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sqlite3
import sys
import tempfile
import time
from collections import Counter
from contextlib import ExitStack
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core.geometry import Pose  # noqa: E402
from app.local_server import running_server  # noqa: E402
from app.sim import BENCH_ROOM, render_walk  # noqa: E402
from bench.track_clients import (  # noqa: E402
    QUIET_SERVER,
    RunStats,
    http_json,
    open_track,
    stream_lock_step,
)

#: The servers' environment; an empty FIDOTRACK_DATABASE_URL: each server its own SQLite
#: file in its data directory, whatever the caller's environment names.
SERVER_ENV = {**QUIET_SERVER, "FIDOTRACK_MAX_TRACK_FPS": "1000", "OPENBLAS_NUM_THREADS": "1",
              "FIDOTRACK_DATABASE_URL": ""}
#: Frames each client streams before the measured rounds (first full scans, caches, both workers).
WARM_UP = 20
#: /readyz answers in a row before a server counts as ready (with two workers, each answers some).
READY_IN_A_ROW = 10


def _holders(data_dir: Path) -> Counter[str]:
    """Open /track connections by the server process holding them."""
    with sqlite3.connect(data_dir / "fidotrack.db", timeout=10) as db:
        return Counter(server for (server,) in db.execute("SELECT server FROM track_connections"))


async def _clients(url: str, frames: list[bytes], truth: list[Pose], clients: int, data_dir: Path,
                   name: str, spread_evenly: bool = False) -> tuple[list[RunStats], Counter[str]]:
    """`clients` lock-step clients at once; their stats and where they were held. With
    `spread_evenly`, they connect together again until every worker holds its share."""
    for _ in range(200):
        sockets = await asyncio.gather(*(open_track(url, "regions") for _ in range(clients)))
        spread = await asyncio.to_thread(_holders, data_dir)
        if not spread_evenly or (len(spread) > 1 and max(spread.values()) - min(spread.values()) <= 1):
            break
        for ws in sockets:
            await ws.close()
        while await asyncio.to_thread(_holders, data_dir):  # each server notices the closes
            await asyncio.sleep(0.02)
    else:
        raise RuntimeError("the clients never landed evenly on the workers")
    runs = [stream_lock_step(ws, frames, truth, RunStats(f"{name} ({i})", "regions")) for i, ws in enumerate(sockets)]
    return list(await asyncio.gather(*runs)), spread


def _row(name: str, rounds: list[tuple[list[RunStats], Counter[str]]]) -> dict[str, float | str]:
    fps = [sum(r.replies for r in runs) / max(r.seconds for r in runs) for runs, _ in rounds]
    latency = [v for runs, _ in rounds for r in runs for v in r.latency_ms]
    server = [v for runs, _ in rounds for r in runs for v in r.server_ms]
    splits = ", ".join("+".join(str(n) for n in sorted(spread.values(), reverse=True)) or "?" for _, spread in rounds)
    posed = sum(r.posed for runs, _ in rounds for r in runs) / max(sum(r.replies for runs, _ in rounds for r in runs), 1)
    return {"name": name, "fps": float(np.median(fps)), "fps_all": " / ".join(f"{x:.0f}" for x in fps),
            "p50": float(np.percentile(latency, 50)), "p99": float(np.percentile(latency, 99)),
            "server_p50": float(np.percentile(server, 50)), "posed": posed, "split": splits}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=300, help="frames of the walk each client streams")
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--quality", type=int, default=90, help="JPEG quality")
    args = parser.parse_args()

    room = BENCH_ROOM.walk(args.seed, args.frames, kind="tracking")
    scene, poses, camera = room.scene, room.poses, BENCH_ROOM.camera
    frames = [cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, args.quality])[1].tobytes()
              for image, _ in tqdm(render_walk(scene, camera, poses, room.rng, degradation="default"),
                                   total=len(poses), desc="rendering", unit="frame")]

    configs = {"`--workers 1`": (1, False), "`--workers 2`": (2, False), "`--workers 2`, spread": (2, True)}
    results: dict[str, list[tuple[list[RunStats], Counter[str]]]] = {name: [] for name in configs}
    load = [os.getloadavg()[0]]
    started = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as stack:
        servers: dict[int, tuple[str, Path]] = {}  # workers -> the /track URL, the data directory
        for workers in sorted({w for w, _ in configs.values()}):
            data_dir = Path(tmp) / f"workers-{workers}"
            # ``fidotrack serve --workers N``, as the README starts it; its log in data_dir.
            server = stack.enter_context(running_server(data_dir, settings=SERVER_ENV, workers=workers,
                                                        ready_in_a_row=READY_IN_A_ROW))
            env = http_json("POST", f"{server.url}/environments", {"name": "bench room", "marker_size_m": 0.2})
            http_json("PUT", f"{server.url}/environments/{env['id']}/map", scene.map_document(camera))
            servers[workers] = (f"{server.ws_url}/track?environment_id={env['id']}", data_dir)
        for workers, (url, data_dir) in servers.items():  # every worker warmed
            asyncio.run(_clients(url, frames[:WARM_UP], poses[:WARM_UP], args.clients, data_dir, "warm-up",
                                 spread_evenly=workers > 1))
        names = list(configs)
        for round_ in range(args.rounds):
            for name in names[round_ % len(names):] + names[:round_ % len(names)]:  # none always first
                workers, evenly = configs[name]
                url, data_dir = servers[workers]
                results[name].append(asyncio.run(
                    _clients(url, frames, poses, args.clients, data_dir, name, spread_evenly=evenly)))
            load.append(os.getloadavg()[0])

    rows = {name: _row(name, results[name]) for name in configs}
    one = rows["`--workers 1`"]
    print(f"\n/track, {args.clients} lock-step clients at once, {args.frames} frames each, 640x480 JPEG "
          f"q{args.quality}, bench room (30 cards), regions on; {os.cpu_count()} cores, {args.rounds} round(s) in "
          f"{time.monotonic() - started:.0f} s; load average (1 min) {' -> '.join(f'{x:.2f}' for x in load)}\n")
    print("| server | aggregate fps (median) | fps ratio to `--workers 1` | latency p50 ms | latency p99 ms | "
          "p50 ratio | p99 ratio | server ms p50 | with pose | fps per round | clients per worker, by round |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for row in rows.values():
        print(f"| {row['name']} | {row['fps']:.0f} | {row['fps'] / one['fps']:.2f} | {row['p50']:.1f} | "
              f"{row['p99']:.1f} | {row['p50'] / one['p50']:.2f} | {row['p99'] / one['p99']:.2f} | "
              f"{row['server_p50']:.1f} | {row['posed']:.0%} | {row['fps_all']} | {row['split']} |")

    # As they land, two workers help as far as the connections are spread: the rounds by split.
    by_split: dict[str, list[tuple[list[RunStats], Counter[str]]]] = {}
    for runs, spread in results["`--workers 2`"] + results["`--workers 2`, spread"]:
        by_split.setdefault("+".join(str(n) for n in sorted(spread.values(), reverse=True)) or "?", []).append(
            (runs, spread))
    print(f"\n`--workers 2`, every round by how the {args.clients} clients were spread over the workers:\n")
    print("| clients per worker | rounds | aggregate fps (median) | fps ratio to `--workers 1` | latency p50 ms | "
          "latency p99 ms |")
    print("|---|---|---|---|---|---|")
    for split, rounds in sorted(by_split.items()):
        row = _row(split, rounds)
        print(f"| {split} | {len(rounds)} | {row['fps']:.0f} | {row['fps'] / one['fps']:.2f} | {row['p50']:.1f} | "
              f"{row['p99']:.1f} |")


if __name__ == "__main__":
    main()
