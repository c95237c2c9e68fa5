"""The /track WebSocket under load: a real client (the `websockets` package) against a
running uvicorn server, streaming a rendered 640x480 room sequence.

The room (8 x 6 x 3 m, 30 cards of 0.2 m, f = 820 px, k1 = -0.12) is rendered along a
tracking walk; its true map is PUT into a fresh environment. Runs:

* lock-step: send a frame, wait for its reply, send the next;
* free-running: a client that sends at a camera's pace (``--free-fps``, 100) without
  waiting while replies stream back; the server drops the older frames it cannot keep
  up with (never the newest);
* two lock-step clients at once (aggregate frames per second).

Columns: frames per second, client-side latency p50/p99 (send to reply), the server's
own processing time per frame (``timing_ms.total``: decode + detect + pose) median,
dropped frames, frames with a pose, and camera position error against the renderer's
truth (median and RMS, mm).

Run: ``.venv/bin/python bench/bench_track.py [--frames 300]`` (prints markdown tables).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import websockets
from tqdm import tqdm

from app.core.camera import Camera, Pose
from app.core.scenes import camera_walk, render_walk, room_scene


@dataclass
class RunStats:
    name: str
    sent: int = 0
    replies: int = 0
    seconds: float = 0.0
    latency_ms: list[float] = field(default_factory=list)
    server_ms: list[float] = field(default_factory=list)
    detect_ms: list[float] = field(default_factory=list)
    dropped: int = 0
    posed: int = 0
    errors_mm: list[float] = field(default_factory=list)

    def row(self) -> str:
        lat = np.asarray(self.latency_ms)
        err = np.asarray(self.errors_mm)
        fps = self.replies / self.seconds if self.seconds else 0.0

        def pct(a: np.ndarray, q: float) -> str:
            return f"{np.percentile(a, q):.1f}" if a.size else "-"

        rms = f"{np.sqrt(np.mean(err ** 2)):.1f}" if err.size else "-"
        return (f"| {self.name} | {self.sent} | {self.replies} | {fps:.0f} | {pct(lat, 50)} | {pct(lat, 99)} | "
                f"{pct(np.asarray(self.server_ms), 50)} | {pct(np.asarray(self.detect_ms), 50)} | {self.dropped} | "
                f"{self.posed / max(self.replies, 1):.0%} | {pct(err, 50)} | {rms} |")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _http(method: str, url: str, body: dict | None = None) -> dict:
    data = json.dumps(body).encode() if body is not None else None
    request = urllib.request.Request(url, data=data, method=method, headers={"content-type": "application/json"})
    with urllib.request.urlopen(request, timeout=30) as reply:
        return json.loads(reply.read() or b"null")


def _start_server(data_dir: Path, port: int) -> subprocess.Popen:
    # The deployment as the README starts it: `fidotrack serve` (logs to a file).
    env = {**os.environ, "FIDOTRACK_DATA_DIR": str(data_dir), "FIDOTRACK_PORT": str(port),
           "FIDOTRACK_LOG_LEVEL": "WARNING"}
    proc = subprocess.Popen([str(Path(sys.executable).parent / "fidotrack"), "serve"], env=env,
                            stdout=subprocess.DEVNULL, stderr=(data_dir / "server.log").open("wb"))
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if _http("GET", f"http://127.0.0.1:{port}/readyz").get("status") == "ready":
                return proc
        except OSError:
            pass
        time.sleep(0.2)
    proc.kill()
    raise RuntimeError("the server did not become ready")


def _account(stats: RunStats, reply: dict, truth: list[Pose]) -> None:
    stats.replies += 1
    stats.server_ms.append(reply["timing_ms"]["total"])
    stats.detect_ms.append(reply["timing_ms"].get("detect", np.nan))
    stats.dropped += int(reply["dropped"])
    if reply["pose"] is not None:
        stats.posed += 1
        position = np.asarray(reply["pose"]["position"])
        stats.errors_mm.append(1e3 * float(np.linalg.norm(position - truth[reply["seq"]].position)))


async def _lock_step(url: str, frames: list[bytes], truth: list[Pose], name: str) -> RunStats:
    stats = RunStats(name)
    async with websockets.connect(url, max_size=None) as ws:
        hello = json.loads(await ws.recv())
        assert hello["type"] == "hello", hello
        start = time.perf_counter()
        for data in frames:
            sent = time.perf_counter()
            await ws.send(data)
            stats.sent += 1
            reply = json.loads(await ws.recv())
            if reply["type"] != "frame":
                raise RuntimeError(f"unexpected reply {reply}")
            stats.latency_ms.append((time.perf_counter() - sent) * 1e3)
            _account(stats, reply, truth)
        stats.seconds = time.perf_counter() - start
    return stats


async def _free_running(url: str, frames: list[bytes], truth: list[Pose], fps: float) -> RunStats:
    stats = RunStats(f"free-running, sent at {fps:.0f} fps")
    sent_at: dict[int, float] = {}
    async with websockets.connect(url, max_size=None) as ws:
        json.loads(await ws.recv())
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
            _account(stats, reply, truth)
            if reply["seq"] == last:
                break
        await sender
        stats.seconds = time.perf_counter() - start
    return stats


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--quality", type=int, default=90, help="JPEG quality")
    parser.add_argument("--free-fps", type=float, default=100.0, help="send rate of the free-running client")
    args = parser.parse_args()

    rng = np.random.default_rng(args.seed)
    scene = room_scene(rng, (8.0, 6.0, 3.0), n_targets=30, marker_size_m=0.2)
    camera = Camera(np.array([[820.0, 0, 319.5], [0, 820.0, 239.5], [0, 0, 1]]), np.array([-0.12, 0.0, 0, 0, 0]),
                    640, 480)
    poses = camera_walk(rng, scene.room_size, args.frames, kind="tracking")
    frames: list[bytes] = []
    for image, _ in tqdm(render_walk(scene, camera, poses, rng, degradation="default"), total=len(poses),
                         desc="rendering", unit="frame"):
        frames.append(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, args.quality])[1].tobytes())

    with tempfile.TemporaryDirectory() as tmp:
        port = _free_port()
        server = _start_server(Path(tmp), port)
        try:
            base = f"http://127.0.0.1:{port}"
            env = _http("POST", f"{base}/environments", {"name": "bench room", "marker_size_m": 0.2})
            _http("PUT", f"{base}/environments/{env['id']}/map", scene.map_document(camera))
            url = f"ws://127.0.0.1:{port}/track?environment_id={env['id']}"
            asyncio.run(_lock_step(url, frames[:20], poses[:20], "warm-up"))
            runs = [asyncio.run(_lock_step(url, frames, poses, "lock-step"))]
            runs.append(asyncio.run(_free_running(url, frames, poses, args.free_fps)))

            async def two() -> list[RunStats]:
                return list(await asyncio.gather(_lock_step(url, frames, poses, "2 clients, lock-step (a)"),
                                                 _lock_step(url, frames, poses, "2 clients, lock-step (b)")))

            pair = asyncio.run(two())
            runs += pair
        finally:
            server.terminate()
            server.wait(timeout=30)

    print(f"\n/track, {args.frames} frames 640x480 JPEG q{args.quality}, room 8x6x3 m, 30 cards, "
          f"uvicorn on 127.0.0.1, {os.cpu_count()} cores\n")
    print("| run | sent | replies | fps | latency p50 ms | latency p99 ms | server ms p50 | detect ms p50 | "
          "dropped | with pose | position err p50 mm | position err RMS mm |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for run in runs:
        print(run.row())
    total = sum(r.replies for r in pair) / max(max(r.seconds for r in pair), 1e-9)
    print(f"\nTwo clients together: {total:.0f} frames per second.")


if __name__ == "__main__":
    main()
