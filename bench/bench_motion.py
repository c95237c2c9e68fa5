"""Poses as a studio or an AR app uses them, through a real `fidotrack serve` and a real
WebSocket client: jitter and lag of raw, smoothed and predicted poses, a lone card's
tilt flips with and without the track's choice, and FreeD output (packets per second,
frame-to-packet time) caught by a real UDP receiver.

Sequences (rendered by the simulator, 640x480 JPEG, the walks' 30 frames a second):

* ``static``: a camera on a tripod in the bench room (8 x 6 x 3 m, 30 cards): one pose,
  every frame rendered afresh (noise, JPEG);
* ``moving``: the bench room's hand-held centre loop (exposure blur of the camera's
  motion);
* ``sparse``: the centre loop in the sparse room, one or two cards in most frames;
* ``lone card``: one 12 cm card on the wall of a room of the bench room's size, filmed from 4
  to 5 m and up to 20 degrees either side of its normal, swaying: the card's two tilts fit
  almost alike.

The paced runs send the frames at 30 a second, as a camera delivers them (the
filter's clock is the frames' arrival at the server). Each run's replies give the raw
pose (``pose``) and, per its config, the smoothed or predicted one (``filtered``):

* jitter: the spread (standard deviation, all axes together) of the camera position and
  of its orientation over the static sequence;
* lag: the time shift that best fits the moving sequence's poses to the truth's path
  (positive: behind it), and their RMS error against the truth at the frame's own time
  and ``--predict-ms`` later (a pose used that long after its frame, as a renderer does);
* flips: single-card frames (the pose rests on one card) whose orientation is more than
  10 degrees off the truth, per 1000 such frames, with config ``tilt`` residual and track
  (the sparse room and the lone card);
* FreeD: the environment's FreeD output points at a UDP socket of the bench; a lock-step
  run as fast as the server goes counts the packets received a second, the server's
  frame-arrival-to-packet time (``timing_ms.freed``) and the client's frame-sent-to-packet
  time, next to a lock-step run on a connection that opts out of FreeD (interleaved).

Run: ``.venv/bin/python bench/bench_motion.py [--frames 300] [--predict-ms 50]``
(prints markdown tables).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import websockets
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core import freed  # noqa: E402
from app.core.geometry import Pose  # noqa: E402
from app.local_server import start_server  # noqa: E402
from app.sim import BENCH_ROOM, render_walk  # noqa: E402
from app.sim.examples import CENTRE_LOOP_WALK, SPARSE_WALK  # noqa: E402
from app.sim.scenes import room_scene  # noqa: E402
from app.sim.walks import FPS  # noqa: E402
from bench.track_clients import QUIET_SERVER, http_json  # noqa: E402

#: Side of the lone card, m: small, as a card on a far wall looks.
LONE_CARD_M = 0.12
#: A pose whose orientation is further than this from the truth is a flip (the other tilt
#: of a lone card is tens of degrees off).
FLIP_DEG = 10.0


@dataclass
class Sequence:
    name: str
    frames: list[bytes]
    truth: list[Pose]


@dataclass
class Reply:
    seq: int
    sent: float  # perf_counter when the frame was sent
    message: dict


@dataclass
class Receiver:
    """A UDP socket on 127.0.0.1 that keeps every FreeD packet with its arrival time."""

    sock: socket.socket = field(default_factory=lambda: socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
    packets: list[tuple[float, freed.FreeDPacket]] = field(default_factory=list)
    bad: int = 0

    def __post_init__(self) -> None:
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    @property
    def port(self) -> int:
        return int(self.sock.getsockname()[1])

    def _run(self) -> None:
        while not self.stop.is_set():
            try:
                data = self.sock.recv(64)
            except TimeoutError:
                continue
            now = time.perf_counter()
            try:
                self.packets.append((now, freed.decode(data)))
            except ValueError:
                self.bad += 1

    def close(self) -> None:
        self.stop.set()
        self.thread.join()
        self.sock.close()


def lone_card(seed: int, n_frames: int) -> tuple[object, list[Pose], np.random.Generator]:
    """One `LONE_CARD_M` card on a wall of an 8 x 6 x 3 m room and a walk 4-5 m from it, up
    to 20 degrees either side of its normal, looking at it (30 frames a second)."""
    rng = np.random.default_rng(seed)
    size = (8.0, 6.0, 3.0)
    scene = room_scene(rng, size, n_targets=1, marker_size_m=LONE_CARD_M)
    card = scene.targets[0]
    centre = card.origin + card.size_m / 2 * (card.x_axis + card.y_axis)
    normal = np.cross(card.x_axis, card.y_axis)
    if normal @ (np.array(size) / 2 - centre) < 0:
        normal = -normal  # into the room
    side = np.cross([0.0, 0.0, 1.0], normal)
    side /= np.linalg.norm(side)
    poses = []
    for k in range(n_frames):
        t = k / FPS
        # Up to 20 degrees either side of the card's normal, 4 to 5 m away: seen nearly
        # square-on from afar, a card's two tilts (mirror images about the line of sight,
        # twice the viewing angle apart) fit its discs almost alike.
        angle = np.radians(20 * np.sin(2 * np.pi * t / 9))
        distance = 4.5 + 0.5 * np.sin(2 * np.pi * t / 7)
        eye = (centre + distance * (np.cos(angle) * normal + np.sin(angle) * side)
               + np.array([0.0, 0.0, 0.25 * np.sin(2 * np.pi * t / 5)]))
        eye = np.clip(eye, 0.3, np.array(size) - 0.3)
        gaze = centre + 0.05 * np.array([np.sin(1.3 * t), np.cos(1.7 * t), np.sin(2.1 * t)])
        poses.append(Pose.look_at(eye, gaze, up=(0.0, 0.0, 1.0)))
    return scene, poses, rng


def _render(name: str, scene, camera, poses: list[Pose], rng, blur=None) -> Sequence:
    frames = []
    for image, _ in tqdm(render_walk(scene, camera, poses, rng, degradation="default", blur=blur), total=len(poses),
                         desc=f"rendering {name}", unit="frame"):
        frames.append(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes())
    return Sequence(name, frames, list(poses))


async def _paced(url: str, sequence: Sequence, config: dict) -> list[Reply]:
    """Send at the walk's frame rate without waiting; every reply kept."""
    replies: list[Reply] = []
    sent_at: dict[int, float] = {}
    async with websockets.connect(url, max_size=None) as ws:
        await ws.recv()  # hello
        await ws.send(json.dumps({"type": "config", **config}))
        assert json.loads(await ws.recv())["type"] == "config"
        start = time.perf_counter()

        async def send() -> None:
            for seq, data in enumerate(sequence.frames):
                await asyncio.sleep(max(0.0, start + seq / FPS - time.perf_counter()))
                sent_at[seq] = time.perf_counter()
                await ws.send(data)

        sender = asyncio.create_task(send())
        last = len(sequence.frames) - 1
        while True:
            message = json.loads(await ws.recv())
            if message["type"] != "frame":
                continue
            replies.append(Reply(message["seq"], sent_at[message["seq"]], message))
            if message["seq"] == last:
                break
        await sender
    return replies


async def _lock_step_pair(url: str, sequence: Sequence, configs: dict[str, dict]) -> dict[str, tuple[list[Reply], float]]:
    """Lock-step on one connection per config, frames interleaved: replies and seconds spent."""
    out: dict[str, tuple[list[Reply], float]] = {name: ([], 0.0) for name in configs}
    sockets = {}
    for name, config in configs.items():
        ws = await websockets.connect(url, max_size=None)
        await ws.recv()
        await ws.send(json.dumps({"type": "config", **config}))
        await ws.recv()
        sockets[name] = ws
    try:
        names = list(configs)
        for seq, data in enumerate(sequence.frames):
            for name in (names if seq % 2 == 0 else names[::-1]):
                sent = time.perf_counter()
                await sockets[name].send(data)
                message = json.loads(await sockets[name].recv())
                replies, seconds = out[name]
                replies.append(Reply(seq, sent, message))
                out[name] = (replies, seconds + time.perf_counter() - sent)
    finally:
        for ws in sockets.values():
            await ws.close()
    return out


def _pose(message: dict, which: str) -> Pose | None:
    source = message.get(which)
    return None if source is None else Pose(np.array(source["R"]), np.array(source["t"]))


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(cv2.Rodrigues(a @ b.T)[0])))


def jitter(replies: list[Reply], truth: Pose, which: str) -> tuple[float, float, int]:
    """(position std mm, orientation std deg, poses) of one output over a still camera."""
    poses = [p for r in replies if (p := _pose(r.message, which)) is not None]
    positions = np.array([p.position for p in poses])
    turns = np.array([cv2.Rodrigues(p.R.T @ truth.R)[0].ravel() for p in poses])  # camera-frame deviation
    position_std = float(np.sqrt(positions.var(axis=0).sum())) * 1e3
    angle_std = float(np.degrees(np.sqrt(turns.var(axis=0).sum())))
    return position_std, angle_std, len(poses)


def lag(replies: list[Reply], truth: list[Pose], which: str, use_ms: float) -> tuple[float, float, float, float, int]:
    """(lag ms, median and p90 error mm at the frame's time, median error mm `use_ms`
    after it, poses more than 10 cm off at the frame's time)."""
    times = np.arange(len(truth)) / FPS
    path = np.array([p.position for p in truth])
    got = [(r.seq / FPS, p.position) for r in replies if (p := _pose(r.message, which)) is not None]
    t = np.array([g[0] for g in got])
    positions = np.array([g[1] for g in got])
    keep = (t > 0.5) & (t < times[-1] - 0.5)  # room for the shifts, and past the filter's start

    def errors(shift_s: float) -> np.ndarray:
        at = np.stack([np.interp(t[keep] - shift_s, times, path[:, k]) for k in range(3)], axis=1)
        return np.linalg.norm(positions[keep] - at, axis=1) * 1e3

    # Medians, not means: a few frames posed metres off (a wrong tilt, a misread card)
    # would otherwise decide the fit.
    shifts = np.arange(-0.3, 0.3001, 0.001)
    best = shifts[int(np.argmin([np.median(errors(s)) for s in shifts]))]
    at_frame = errors(0.0)
    return (float(best * 1e3), float(np.median(at_frame)), float(np.percentile(at_frame, 90)),
            float(np.median(errors(-use_ms / 1e3))), int((at_frame > 100).sum()))


def flips(replies: list[Reply], truth: list[Pose]) -> tuple[int, int]:
    """(flipped single-card frames, single-card frames)."""
    single = flipped = 0
    for r in replies:
        pose = r.message.get("pose")
        if pose is None or pose["n_targets"] != 1:
            continue
        single += 1
        flipped += _angle_deg(np.array(pose["R"]), truth[r.seq].R) > FLIP_DEG
    return flipped, single


def _pct(values: list[float], q: float) -> str:
    return f"{np.percentile(values, q):.2f}" if values else "-"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=300, help="frames per sequence")
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--predict-ms", type=float, default=50.0, help="prediction of the predicted runs")
    args = parser.parse_args()
    camera = BENCH_ROOM.camera

    room = BENCH_ROOM.walk(args.seed, args.frames, kind="centre_loop")
    still = [room.poses[0]] * args.frames
    static = _render("static", room.scene, camera, still, room.rng)
    loop = CENTRE_LOOP_WALK.walk(args.seed, args.frames)
    moving = _render("moving", loop.scene, camera, loop.poses, loop.rng, loop.blur)
    sparse_walk = SPARSE_WALK.walk(args.seed, args.frames)
    sparse = _render("sparse", sparse_walk.scene, SPARSE_WALK.room.camera, sparse_walk.poses, sparse_walk.rng,
                     sparse_walk.blur)
    lone_scene, lone_poses, lone_rng = lone_card(args.seed, args.frames)
    lone = _render("lone card", lone_scene, camera, lone_poses, lone_rng)

    receiver = Receiver()
    load = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory() as tmp:
        # The bench's FreeD receiver is on 127.0.0.1: the server sends there only when told.
        server = start_server(Path(tmp), settings={**QUIET_SERVER, "FIDOTRACK_MAX_TRACK_FPS": "1000",
                                                   "OPENBLAS_NUM_THREADS": "1",
                                                   "FIDOTRACK_FREED_ALLOWED_NETWORKS": '["127.0.0.1/32"]'})
        try:
            base = server.url
            urls = {}
            for name, scene, cam in (("bench", room.scene, camera), ("moving", loop.scene, camera),
                                     ("sparse", sparse_walk.scene, SPARSE_WALK.room.camera),
                                     ("lone", lone_scene, camera)):
                env = http_json("POST", f"{base}/environments", {"name": name, "marker_size_m": 0.2})
                http_json("PUT", f"{base}/environments/{env['id']}/map", scene.map_document(cam))
                http_json("PUT", f"{base}/environments/{env['id']}/freed",
                          {"host": "127.0.0.1", "port": receiver.port, "camera_id": 1})
                urls[name] = f"{server.ws_url}/track?environment_id={env['id']}"
            smooth = {"smoothing": {}}
            predicted = {"smoothing": {}, "predict_ms": args.predict_ms}
            asyncio.run(_lock_step_pair(urls["moving"], Sequence("warm-up", moving.frames[:20], moving.truth[:20]),
                                        {"warm": {}}))
            runs = {
                "static": asyncio.run(_paced(urls["bench"], static, smooth)),
                "static predicted": asyncio.run(_paced(urls["bench"], static, predicted)),
                "moving": asyncio.run(_paced(urls["moving"], moving, smooth)),
                "moving predicted": asyncio.run(_paced(urls["moving"], moving, predicted)),
                "sparse residual": asyncio.run(_paced(urls["sparse"], sparse, {"tilt": "residual"})),
                "sparse track": asyncio.run(_paced(urls["sparse"], sparse, {"tilt": "track"})),
                "lone residual": asyncio.run(_paced(urls["lone"], lone, {"tilt": "residual"})),
                "lone track": asyncio.run(_paced(urls["lone"], lone, {"tilt": "track"})),
            }
            load.append(os.getloadavg()[0])
            receiver.packets.clear()
            started = time.perf_counter()
            lock = asyncio.run(_lock_step_pair(urls["moving"], moving,
                                               {"FreeD on": {}, "FreeD off": {"freed": {"enabled": False}}}))
            lock_s = time.perf_counter() - started
            load.append(os.getloadavg()[0])
        finally:
            server.stop()
            receiver.close()

    print(f"\nPoses through /track: {args.frames} frames a sequence, 640x480 JPEG q90, sent at {FPS:.0f} fps; "
          f"uvicorn on 127.0.0.1, {os.cpu_count()} cores; load average (1 min) "
          f"{' -> '.join(f'{x:.2f}' for x in load)}\n")
    print("Jitter of a still camera (static), and lag under motion (moving):\n")
    print(f"| pose | position std mm | orientation std deg | lag ms | error at the frame's time mm p50 | p90 | "
          f"error {args.predict_ms:.0f} ms later mm p50 | poses > 10 cm off |")
    print("|---|---|---|---|---|---|---|---|")
    truth_still = static.truth[0]
    for label, still_run, moving_run, which in (
            ("raw", "static", "moving", "pose"),
            ("smoothed (One Euro)", "static", "moving", "filtered"),
            (f"smoothed + predicted {args.predict_ms:.0f} ms", "static predicted", "moving predicted", "filtered")):
        p_std, a_std, _ = jitter(runs[still_run], truth_still, which)
        lag_ms, p50, p90, at_use, gross = lag(runs[moving_run], moving.truth, which, args.predict_ms)
        print(f"| {label} | {p_std:.3f} | {a_std:.4f} | {lag_ms:+.0f} | {p50:.2f} | {p90:.2f} | {at_use:.2f} | "
              f"{gross} |")

    print("\nA lone card's tilt, per 1000 single-card frames:\n")
    print(f"| sequence | tilt | single-card frames | ambiguous | flipped (> {FLIP_DEG:.0f} deg off) | per 1000 | "
          "tilt_from_track |")
    print("|---|---|---|---|---|---|---|")
    for sequence, truth in (("sparse", sparse.truth), ("lone", lone.truth)):
        for label in ("residual", "track"):
            replies = runs[f"{sequence} {label}"]
            flipped, single = flips(replies, truth)
            ambiguous = sum(bool((r.message.get("pose") or {}).get("ambiguous")) for r in replies)
            chose = sum(bool((r.message.get("pose") or {}).get("tilt_from_track")) for r in replies)
            print(f"| {sequence} | {label} | {single} | {ambiguous} | {flipped} | {1000 * flipped / max(single, 1):.1f} "
                  f"| {chose} |")

    print("\nFreeD, lock-step as fast as the server goes (moving sequence), one connection sending FreeD "
          "and one opting out, interleaved:\n")
    on, on_s = lock["FreeD on"]
    off, off_s = lock["FreeD off"]
    packets = receiver.packets
    posed = [r for r in on if r.message.get("pose") is not None]
    server_ms = [r.message["timing_ms"]["freed"] for r in posed if "freed" in r.message["timing_ms"]]
    # Packets arrive in the order of the posed replies of the FreeD connection (one connection sends).
    client_ms = [(packets[k][0] - r.sent) * 1e3 for k, r in enumerate(posed[:len(packets)])]
    print("| connection | frames | fps | posed | packets received | packets a second | "
          "server arrival->packet ms p50 | p99 | client send->packet ms p50 | p99 |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    print(f"| FreeD on | {len(on)} | {len(on) / on_s:.0f} | {len(posed)} | {len(packets)} | "
          f"{len(packets) / on_s:.0f} | {_pct(server_ms, 50)} | {_pct(server_ms, 99)} | {_pct(client_ms, 50)} | "
          f"{_pct(client_ms, 99)} |")
    print(f"| FreeD off | {len(off)} | {len(off) / off_s:.0f} | "
          f"{sum(r.message.get('pose') is not None for r in off)} | - | - | - | - | - | - |")
    print(f"\nFreeD on / off frames a second: {(len(on) / on_s) / (len(off) / off_s):.2f}; packets that failed to "
          f"decode: {receiver.bad}; both connections took {lock_s:.1f} s.")


if __name__ == "__main__":
    main()
