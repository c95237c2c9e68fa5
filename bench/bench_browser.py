"""Live tracking from the web app's page against the same frames sent by a Python client:
frames per second, latency from the browser to the pose, and the page's own cost per
frame (its JPEG encoding), at 640x480 and 1280x720.

For each size the bench room (`app.sim.examples.BENCH_ROOM`: 8 x 6 x 3 m, 30 cards of
0.2 m, k1 = -0.12; f = 820 px at 640x480, and the same lens at 1280x720: f = 1640 px,
principal point at the centre, so the same horizontal field and a shorter vertical one)
is rendered along a tracking walk; each frame gets its index stamped in its top-left
corner (`app.sim.camera_feed`) and the walk is written as a YUV4MPEG2 file, which
Chromium's fake camera (``--use-file-for-fake-video-capture``) plays in a loop at 30 fps.
The room's true map, with that size's camera, is PUT into an environment of its own on a
real ``fidotrack serve``. Then, one after the other:

* browser: Debian's Chromium, headless, driven by Playwright, opens the tracking page
  ``/app/#/environments/{id}/track`` with "Frames sent" at the camera's size and the
  JPEG quality of ``--quality``, and presses Start. The page draws the camera's current
  picture to a canvas, encodes it (``canvas.toBlob``, JPEG), sends it on ``/track`` and
  sends the next one when the reply is in (lock-step); it draws the targets over the
  video and moves the camera in its 3D map view (drawn at most 10 times a second) with
  each reply. Its measurements are
  read from ``window.fidotrack.track``; every binary frame it sends is captured, and the
  stamp in it says which walk frame it shows, hence the true camera centre;
* python: a `websockets` client in lock-step, sending the same stamped frames in walk
  order (cycling), JPEG-encoded by cv2 (grey, quality ``--quality``) before the run.

Each run lasts ``--seconds`` after 5 warm-up replies; the server is warmed up with 20
frames per environment first. Neither client sends a config message: the server's
default (region scans) for both. The server is started with
``FIDOTRACK_MAX_TRACK_FPS=1000``: the python client goes past the default limit of 120
frames a second, and its row is meant to show the server's own pace.

Columns: frames per second (replies in the window over its length), latency p50/p99
(browser: from the start of the canvas draw and encode to the reply; python: send to
reply, its frames encoded beforehand), the server's time per frame (``timing_ms.total``)
p50, the page's draw + encode per frame p50/p99 (browser only), the mean JPEG size,
frames with a pose and the camera position error against the truth (median, p90, mm);
then the ratios browser / python; the position error on the same walk frames (each
browser pose paired with the python client's median error on the frame it showed); where
a frame's cycle goes (medians of per-frame values); the server's time by stage
(``timing_ms``) and its share of whole-frame scans; and the CPU each process used during
each run, in cores (from /proc).

Chromium, the server and the bench run on the same machine: the load average and the
number of cores are printed, and the CPU table's "others" column shows what processes
that are not the bench's took during each run. Before each run the bench waits (up to
``--settle`` seconds, 30) for the machine to be idle. Timings are wall-clock on a shared
machine; compare within a run, and rerun when "others" is not near zero.

Run: ``.venv/bin/python bench/bench_browser.py [--sizes 640x480,1280x720] [--seconds 20]
[--frames 150] [--quality 85] [--settle 30] [--server-env KEY=VALUE]
[--chromium-arg=--disable-gpu] [--stop-3d-view]`` (prints markdown tables; needs
Chromium on the PATH as ``chromium`` and the ``playwright`` package, and exits with a
message without them; about two and a half minutes with the defaults, at most two more
waiting for an idle machine). ``--stop-3d-view`` is a diagnostic: it ends the page's 3D
view's drawing before Start, to show what the view costs the tracking.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import websockets
from tqdm import tqdm

from app.core.geometry import Camera, Pose
from app.local_server import start_server
from app.sim import BENCH_ROOM, render_walk
from app.sim.camera_feed import read_frame_index, stamp_frame_index, write_y4m

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.track_clients import QUIET_SERVER, SPLIT, http_json  # noqa: E402

#: Replies left out at the start of each run (the page's first frames, the connection's
#: first full scans).
WARM_UP = 5
CLIENTS = ("browser", "python")


def camera_for(width: int, height: int) -> Camera:
    """The bench camera's lens at `width` x `height`: 640x480 is BENCH_CAMERA itself; other
    sizes scale its focal length with the width, the principal point at the centre."""
    base = BENCH_ROOM.camera
    if (width, height) == base.size:
        return base
    f = base.fx * width / base.width
    return Camera.pinhole(f, width, height, dist=base.dist)


@dataclass
class Run:
    size: str
    client: str
    seconds: float = 0.0
    latency_ms: list[float] = field(default_factory=list)
    server_ms: list[float] = field(default_factory=list)
    encode_ms: list[float] = field(default_factory=list)
    #: per frame: the time from the previous reply to this one
    cycle_ms: list[float] = field(default_factory=list)
    #: per frame: latency minus encode minus server time
    rest_ms: list[float] = field(default_factory=list)
    #: per frame: from the previous reply to the start of this frame (the page's work on
    #: the reply before it captures the next frame)
    after_ms: list[float] = field(default_factory=list)
    jpeg_bytes: list[int] = field(default_factory=list)
    split: dict[str, list[float]] = field(default_factory=dict)  # timing_ms key -> values
    full_scans: int = 0
    replies: int = 0
    posed: int = 0
    dropped: int = 0
    errors: int = 0
    unstamped: int = 0
    errors_mm: list[float] = field(default_factory=list)
    by_index: dict[int, list[float]] = field(default_factory=dict)  # walk frame -> its position errors, mm
    cpu: dict[str, float] = field(default_factory=dict)  # process group -> cores
    load: tuple[float, float] = (0.0, 0.0)  # 1-min load average before, after

    @property
    def fps(self) -> float:
        return self.replies / self.seconds if self.seconds else 0.0


def _pct(values: list[float], q: float, digits: int = 1) -> str:
    return f"{np.percentile(values, q):.{digits}f}" if values else "-"


def _median(values: list[float]) -> float:
    return float(np.median(values)) if values else float("nan")


# --------------------------------------------------------------------------------------
# CPU per process group, from /proc
# --------------------------------------------------------------------------------------

_TICK = os.sysconf("SC_CLK_TCK")


def _proc_table() -> dict[int, tuple[int, str, int]]:
    """pid -> (parent pid, command name, CPU ticks user + system) of every process."""
    table = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue
        name = stat[stat.index("(") + 1:stat.rindex(")")]
        fields = stat[stat.rindex(")") + 2:].split()
        table[int(entry)] = (int(fields[1]), name, int(fields[11]) + int(fields[12]))
    return table


def _cpu_snapshot(server_pid: int) -> dict[int, tuple[str, int]]:
    """pid -> (group, CPU ticks) for the server's processes, the bench itself, the
    browser's processes and the Playwright driver (the bench's other descendants)."""
    table = _proc_table()

    def descends(pid: int, root: int) -> bool:
        while pid > 1:
            if pid == root:
                return True
            pid = table[pid][0] if pid in table else 0
        return False

    me, out = os.getpid(), {}
    for pid, (_, name, ticks) in table.items():
        if descends(pid, server_pid):
            out[pid] = ("server", ticks)
        elif pid == me:
            out[pid] = ("bench", ticks)
        elif descends(pid, me):
            out[pid] = (_chromium_group(pid) if "chrom" in name.lower() else "playwright driver", ticks)
    return out


def _chromium_group(pid: int) -> str:
    """A Chromium process's group by its --type: the page's renderer, the GPU process
    (software rendering and compositing, headless) or the rest (browser, network, ...)."""
    try:
        # (Chromium rewrites its command line: the arguments are separated by spaces.)
        args = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").split()
    except OSError:
        return "chromium, other"
    kind = next((a.split(b"=", 1)[1].decode() for a in args if a.startswith(b"--type=")), "")
    return {"renderer": "chromium renderer", "gpu-process": "chromium gpu"}.get(kind, "chromium, other")


def _machine_ticks() -> tuple[int, int]:
    """(busy, total) CPU ticks of the whole machine since boot."""
    values = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = values[3] + values[4]  # idle + iowait
    return sum(values) - idle, sum(values)


class CpuMeter:
    """CPU used by each process group (in cores) and by the machine between start and stop."""

    GROUPS = ("server", "chromium renderer", "chromium gpu", "chromium, other", "playwright driver", "bench")

    def __init__(self, server_pid: int) -> None:
        self.server_pid = server_pid

    def start(self) -> None:
        self.began, self.first, self.machine = time.perf_counter(), _cpu_snapshot(self.server_pid), _machine_ticks()

    def stop(self) -> dict[str, float]:
        wall = time.perf_counter() - self.began
        last, machine = _cpu_snapshot(self.server_pid), _machine_ticks()
        used = dict.fromkeys(self.GROUPS, 0.0)
        for pid, (group, ticks) in last.items():
            used[group] += (ticks - self.first.get(pid, (group, 0))[1]) / _TICK / wall
        busy, total = machine[0] - self.machine[0], machine[1] - self.machine[1]
        used["machine"] = (os.cpu_count() or 1) * busy / max(total, 1)
        used["others"] = max(0.0, used["machine"] - sum(used[g] for g in self.GROUPS))
        return used


def settle(limit_s: float, idle_cores: float = 0.3, window_s: float = 3.0) -> float:
    """Wait (up to `limit_s`) until the machine has been nearly idle for `window_s`: less
    than `idle_cores` busy. Returns the seconds waited (`limit_s` if it never settled)."""
    began = time.perf_counter()
    while (waited := time.perf_counter() - began) < limit_s:
        first = _machine_ticks()
        time.sleep(window_s)
        busy, total = (b - a for a, b in zip(first, _machine_ticks(), strict=True))
        if (os.cpu_count() or 1) * busy / max(total, 1) < idle_cores:
            return waited
    return limit_s


# --------------------------------------------------------------------------------------
# The two clients
# --------------------------------------------------------------------------------------


def _account_split(run: Run, reply: dict[str, Any]) -> None:
    for key in SPLIT:
        run.split.setdefault(key, []).append(float(reply["timing_ms"].get(key, 0.0)))
    run.full_scans += reply.get("scan", "full") == "full"


def _error_mm(position: Any, truth: Pose) -> float:
    return 1e3 * float(np.linalg.norm(np.asarray(position) - truth.position))


def browser_run(base: str, environment_id: int, y4m: Path, size: str, seconds: float, quality: int,
                truth: list[Pose], meter: CpuMeter, extra_args: tuple[str, ...] = (), stop_view: bool = False) -> Run:
    """The tracking page in headless Chromium, its camera the y4m file, for `seconds`;
    `stop_view`: with the page's 3D view stopped (its requestAnimationFrame loop ends)."""
    from playwright.sync_api import sync_playwright

    run = Run(size, "browser")
    payloads: list[bytes] = []
    messages: dict[int, dict[str, Any]] = {}  # seq -> the server's frame reply as sent

    def on_message(payload: str | bytes) -> None:
        message = json.loads(payload)
        if message.get("type") == "frame":
            messages[message["seq"]] = message

    def on_socket(ws: Any) -> None:
        if "/track" in ws.url:
            ws.on("framesent", lambda payload: payloads.append(payload) if isinstance(payload, bytes) else None)
            ws.on("framereceived", on_message)

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=shutil.which("chromium"),
            args=["--no-sandbox", "--use-fake-device-for-media-stream", "--use-fake-ui-for-media-stream",
                  f"--use-file-for-fake-video-capture={y4m}", *extra_args])
        try:
            context = browser.new_context(viewport={"width": 1300, "height": 900}, permissions=["camera"])
            page = context.new_page()
            page.on("websocket", on_socket)
            page.goto(f"{base}/app/#/environments/{environment_id}/track")
            page.wait_for_selector("#start", timeout=60_000)
            page.select_option("#frame-width", "native")
            page.fill("#jpeg-quality", f"{quality / 100:.2f}")
            if stop_view:  # the view redraws in a requestAnimationFrame loop: end it (a diagnostic)
                page.evaluate("() => { window.requestAnimationFrame = () => 0; }")
            page.click("#start")
            page.wait_for_function(f"() => (window.fidotrack?.track?.replies?.length ?? 0) >= {WARM_UP}",
                                   timeout=60_000)
            run.load = (os.getloadavg()[0], 0.0)
            meter.start()
            began = page.evaluate("() => performance.now()")
            page.wait_for_timeout(seconds * 1000)  # (not time.sleep: Playwright's events must keep flowing)
            ended = page.evaluate("() => performance.now()")
            run.cpu = meter.stop()
            run.load = (run.load[0], os.getloadavg()[0])
            state = page.evaluate("() => { const s = window.fidotrack.track; "
                                  "return {sent: s.sent, replies: s.replies, errors: s.errors}; }")
            page.click("#start")  # Stop
            page.wait_for_timeout(200)
        finally:
            browser.close()

    replies = sorted(state["replies"], key=lambda r: r["seq"])
    run.errors = len(state["errors"])
    run.seconds = (ended - began) / 1e3
    previous: dict[str, Any] | None = None
    for reply in replies:
        inside = began <= reply["receivedAt"] <= ended
        if inside:
            run.replies += 1
            run.latency_ms.append(reply["latencyMs"])
            run.encode_ms.append(reply["encodeMs"])
            run.server_ms.append(reply["serverMs"])
            run.rest_ms.append(reply["latencyMs"] - reply["encodeMs"] - reply["serverMs"])
            run.dropped += int(reply["dropped"])
            if reply["seq"] in messages:
                _account_split(run, messages[reply["seq"]])
            if previous is not None and previous["seq"] == reply["seq"] - 1:
                cycle = reply["receivedAt"] - previous["receivedAt"]
                run.cycle_ms.append(cycle)
                run.after_ms.append(cycle - reply["latencyMs"])
            if reply["seq"] < len(payloads):
                data = payloads[reply["seq"]]
                run.jpeg_bytes.append(len(data))
                image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
                index = read_frame_index(image) if image is not None else None
            else:
                index = None
            if index is None or index >= len(truth):
                run.unstamped += 1
            if reply["pose"] is not None:
                run.posed += 1
                if index is not None and index < len(truth):
                    run.errors_mm.append(_error_mm(reply["pose"]["position"], truth[index]))
                    run.by_index.setdefault(index, []).append(run.errors_mm[-1])
        previous = reply
    return run


async def _python_run(url: str, frames: list[bytes], truth: list[Pose], size: str, seconds: float,
                      meter: CpuMeter) -> Run:
    """Lock-step for `seconds` (after the warm-up), the walk's frames in order, cycling."""
    run = Run(size, "python")
    async with websockets.connect(url, max_size=None) as ws:
        hello = json.loads(await ws.recv())
        assert hello["type"] == "hello", hello
        k, previous, ended = 0, 0.0, 0.0
        while True:
            index = k % len(frames)
            if k == WARM_UP:
                run.load = (os.getloadavg()[0], 0.0)
                meter.start()
                began = time.perf_counter()
                ended = began + seconds
            sent = time.perf_counter()
            await ws.send(frames[index])
            reply = json.loads(await ws.recv())
            while reply["type"] == "error" and reply["code"] == "rate_limited":  # the frame's reply follows
                run.errors += 1
                reply = json.loads(await ws.recv())
            now = time.perf_counter()
            if reply["type"] != "frame":
                raise RuntimeError(f"unexpected reply {reply}")
            if k >= WARM_UP:
                run.replies += 1
                run.latency_ms.append((now - sent) * 1e3)
                run.server_ms.append(reply["timing_ms"]["total"])
                run.rest_ms.append(run.latency_ms[-1] - run.server_ms[-1])
                run.jpeg_bytes.append(len(frames[index]))
                run.dropped += int(reply["dropped"])
                _account_split(run, reply)
                if k > WARM_UP:
                    run.cycle_ms.append((now - previous) * 1e3)
                    run.after_ms.append((sent - previous) * 1e3)
                if reply["pose"] is not None:
                    run.posed += 1
                    run.errors_mm.append(_error_mm(reply["pose"]["position"], truth[index]))
                    run.by_index.setdefault(index, []).append(run.errors_mm[-1])
            previous = now
            k += 1
            if k > WARM_UP and now >= ended:
                break
        run.seconds = now - began
        run.cpu = meter.stop()
        run.load = (run.load[0], os.getloadavg()[0])
    return run


async def _warm_up(url: str, frames: list[bytes]) -> None:
    async with websockets.connect(url, max_size=None) as ws:
        await ws.recv()
        for data in frames[:20]:
            await ws.send(data)
            await ws.recv()


# --------------------------------------------------------------------------------------
# Main
# --------------------------------------------------------------------------------------


def _sizes(text: str) -> list[tuple[int, int]]:
    sizes = []
    for item in text.split(","):
        w, _, h = item.strip().partition("x")
        if not (w.isdigit() and h.isdigit()) or int(w) % 2 or int(h) % 2:
            raise argparse.ArgumentTypeError(f"sizes are even WIDTHxHEIGHT, got {item!r}")
        sizes.append((int(w), int(h)))
    return sizes


def _chromium_or_exit() -> None:
    if shutil.which("chromium") is None:
        sys.exit("bench_browser: Chromium is not installed (no `chromium` on the PATH); install it "
                 "(Debian: apt-get install chromium) and run again.")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        sys.exit("bench_browser: the playwright package is missing; install the test extra "
                 "(pip install -e '.[test]') and run again.")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=_sizes, default=_sizes("640x480,1280x720"),
                        help="frame sizes, comma-separated WIDTHxHEIGHT (default 640x480,1280x720)")
    parser.add_argument("--seconds", type=float, default=20.0, help="length of each run after its warm-up")
    parser.add_argument("--frames", type=int, default=150, help="frames of the walk (the camera loops over them)")
    parser.add_argument("--quality", type=int, default=85, help="JPEG quality of both clients, 1-100")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--settle", type=float, default=30.0,
                        help="before each run, wait up to this many seconds for the machine to be idle "
                             "(other work on a shared machine; 0: do not wait)")
    parser.add_argument("--stop-3d-view", action="store_true",
                        help="diagnostic: stop the page's 3D map view (it redraws on every animation frame) "
                             "before Start, to see what it costs")
    parser.add_argument("--chromium-arg", action="append", default=[], metavar="ARG",
                        help="extra command-line switch for Chromium (e.g. --disable-gpu); repeatable")
    parser.add_argument("--server-env", action="append", default=[], metavar="KEY=VALUE",
                        help="extra environment for the server (e.g. OPENBLAS_NUM_THREADS=1); repeatable")
    args = parser.parse_args()
    _chromium_or_exit()
    # The python client would go past the default max_track_fps (120): let the server take
    # what it can, so that its row shows the server's pace.
    server_env = {"FIDOTRACK_MAX_TRACK_FPS": "1000", **dict(item.split("=", 1) for item in args.server_env)}

    runs: list[Run] = []
    cv2_encode: dict[str, list[float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        # Every size's walk first (the browser's y4m, the python client's JPEGs), then the server.
        walks = {}
        for width, height in args.sizes:
            size = f"{width}x{height}"
            camera = camera_for(width, height)
            room = BENCH_ROOM.walk(args.seed, args.frames, kind="tracking")
            stamped = [stamp_frame_index(image, i) for i, (image, _) in enumerate(tqdm(
                render_walk(room.scene, camera, room.poses, room.rng, degradation="default"),
                total=len(room.poses), desc=f"rendering {size}", unit="frame"))]
            y4m = Path(tmp) / f"walk-{size}.y4m"
            write_y4m(y4m, stamped, fps=30)
            frames, took = [], []
            for image in stamped:
                began = time.perf_counter()
                frames.append(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, args.quality])[1].tobytes())
                took.append((time.perf_counter() - began) * 1e3)
            cv2_encode[size] = took
            walks[size] = (camera, room, y4m, frames)
            del stamped

        load = [os.getloadavg()]
        waits: list[float] = []
        server = start_server(Path(tmp), settings={**QUIET_SERVER, **server_env})
        try:
            base = server.url
            meter = CpuMeter(server.process.pid)
            for size, (camera, room, y4m, frames) in walks.items():
                env = http_json("POST", f"{base}/environments", {"name": f"bench room {size}", "marker_size_m": 0.2})
                http_json("PUT", f"{base}/environments/{env['id']}/map", room.scene.map_document(camera))
                url = f"{server.ws_url}/track?environment_id={env['id']}"
                asyncio.run(_warm_up(url, frames))
                waits.append(settle(args.settle))
                print(f"{size}: browser run ({args.seconds:.0f} s)...", file=sys.stderr, flush=True)
                runs.append(browser_run(base, env["id"], y4m, size, args.seconds, args.quality, room.poses, meter,
                                        tuple(args.chromium_arg), args.stop_3d_view))
                waits.append(settle(args.settle))
                print(f"{size}: python run ({args.seconds:.0f} s)...", file=sys.stderr, flush=True)
                runs.append(asyncio.run(_python_run(url, frames, room.poses, size, args.seconds, meter)))
                load.append(os.getloadavg())
        except Exception:
            if server.process.poll() is not None:  # say why, when the server is gone
                log = server.log.read_text(errors="replace")[-3000:]
                print(f"bench_browser: the server exited with code {server.process.returncode}; its log ends:\n{log}",
                      file=sys.stderr)
            raise
        finally:
            server.stop()

    print(f"\nLive tracking, browser page vs Python client: bench room 8x6x3 m, 30 cards, tracking walk of "
          f"{args.frames} frames (the browser's camera plays it in a loop at 30 fps), JPEG quality "
          f"{args.quality}, {args.seconds:.0f} s per run after {WARM_UP} warm-up replies, lock-step, default "
          f"(region) scans; {'the page 3D view stopped (diagnostic); ' if args.stop_3d_view else ''}"
          f"server `fidotrack serve` on 127.0.0.1, env "
          f"{' '.join(f'{k}={v}' for k, v in server_env.items())}; headless Chromium, the server and the bench on one "
          f"machine of {os.cpu_count()} cores; load average (1, 5, 15 min) "
          + " -> ".join(" ".join(f"{x:.2f}" for x in la) for la in load)
          + f"; waited for an idle machine before the runs: {', '.join(f'{w:.0f}' for w in waits)} s "
          f"(at most {args.settle:.0f})\n")

    print("| size | client | frames | fps | latency p50 ms | latency p99 ms | server ms p50 | encode ms p50 | "
          "encode ms p99 | JPEG kB | with pose | position err p50 mm | position err p90 mm |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in runs:
        encode = (_pct(r.encode_ms, 50), _pct(r.encode_ms, 99)) if r.client == "browser" else ("-", "-")
        print(f"| {r.size} | {r.client} | {r.replies} | {r.fps:.1f} | {_pct(r.latency_ms, 50)} | "
              f"{_pct(r.latency_ms, 99)} | {_pct(r.server_ms, 50)} | {encode[0]} | {encode[1]} | "
              f"{np.mean(r.jpeg_bytes) / 1e3:.0f} | {r.posed / max(r.replies, 1):.0%} | {_pct(r.errors_mm, 50, 2)} | "
              f"{_pct(r.errors_mm, 90, 2)} |")

    print("\nBrowser / python:\n")
    print("| size | fps | latency p50 | server ms p50 |")
    print("|---|---|---|---|")
    for width, height in args.sizes:
        size = f"{width}x{height}"
        b, p = (next(r for r in runs if r.size == size and r.client == c) for c in CLIENTS)
        print(f"| {size} | {b.fps / p.fps:.2f} | {_median(b.latency_ms) / _median(p.latency_ms):.2f} | "
              f"{_median(b.server_ms) / _median(p.server_ms):.2f} |")

    print("\nPosition error on the same walk frames: the browser's frames are those its camera showed when it "
          "was ready, the python client's every frame in turn; here each browser pose is paired with the python "
          "client's median error on the same walk frame:\n")
    print("| size | poses paired | browser err p50 mm | python err p50 mm | browser err p90 mm | python err p90 mm |")
    print("|---|---|---|---|---|---|")
    for width, height in args.sizes:
        size = f"{width}x{height}"
        b, p = (next(r for r in runs if r.size == size and r.client == c) for c in CLIENTS)
        pairs = [(e, _median(p.by_index[i])) for i, errs in b.by_index.items() if i in p.by_index for e in errs]
        if pairs:
            mine, theirs = np.array(pairs).T
            print(f"| {size} | {len(pairs)} | {np.median(mine):.2f} | {np.median(theirs):.2f} | "
                  f"{np.percentile(mine, 90):.2f} | {np.percentile(theirs, 90):.2f} |")

    print("\nWhere a frame's cycle goes (medians of per-frame values, ms; cycle: from one reply to the next; "
          "after the reply: from a reply to the start of the next frame's capture; the parts need not add up "
          "to the cycle):\n")
    print("| size | client | cycle | encode | server | latency - encode - server | after the reply |")
    print("|---|---|---|---|---|---|---|")
    for r in runs:
        encode = f"{_median(r.encode_ms):.1f}" if r.encode_ms else "0 (before the run)"
        print(f"| {r.size} | {r.client} | {_median(r.cycle_ms):.1f} | {encode} | {_median(r.server_ms):.1f} | "
              f"{_median(r.rest_ms):.1f} | {_median(r.after_ms):.1f} |")

    print("\nThe server's time per frame (timing_ms of the replies, p50 ms; the total is not the sum of the "
          "medians), and the share of frames it scanned whole:\n")
    print("| size | client | " + " | ".join(SPLIT) + " | full scans |")
    print("|---|---|" + "---|" * (len(SPLIT) + 1))
    for r in runs:
        cells = " | ".join(f"{_median(r.split.get(k, [])):.2f}" for k in SPLIT)
        print(f"| {r.size} | {r.client} | {cells} | {r.full_scans / max(len(r.split.get('total', [])), 1):.0%} |")

    print("\nCPU during each run, in cores (of " + str(os.cpu_count()) + "; Chromium's renderer runs the page, its "
          "GPU process draws and composites in software; others: processes that are not the bench's):\n")
    print("| size | client | server | chromium renderer | chromium gpu | chromium, other | playwright driver | bench | "
          "others | machine | load avg before -> after |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in runs:
        cells = " | ".join(f"{r.cpu.get(g, 0.0):.2f}" for g in (*CpuMeter.GROUPS, "others", "machine"))
        print(f"| {r.size} | {r.client} | {cells} | {r.load[0]:.2f} -> {r.load[1]:.2f} |")

    print()
    for size, took in cv2_encode.items():
        print(f"- {size}: the python client's frames were encoded by cv2 (grey) before the run: "
              f"p50 {np.median(took):.1f} ms a frame.")
    for r in runs:
        notes = []
        if r.unstamped:
            notes.append(f"{r.unstamped} frame(s) whose stamp could not be read (no truth)")
        if r.dropped:
            notes.append(f"{r.dropped} dropped")
        if r.errors:
            notes.append(f"{r.errors} error message(s)")
        if notes:
            print(f"- {r.size} {r.client}: " + "; ".join(notes) + ".")


if __name__ == "__main__":
    main()
