"""The /track WebSocket under /detect load and under attack: does a tracking client keep
its frame rate and latency while other clients load the server and a hostile client
sends it what it should refuse?

A real ``fidotrack serve`` runs on 127.0.0.1 (a free port, a fresh data directory) with
API keys required (``FIDOTRACK_API_KEYS=true``); an admin key is made beforehand with
``fidotrack keys create``. The bench room (`app.sim.examples.BENCH_ROOM`: 8 x 6 x 3 m,
30 cards of 0.2 m) is rendered along a tracking walk (640x480 JPEG, quality 90) and its
true map is PUT into an environment; a second, "sacrificial" environment with the same
map is touched by the hostile client only.

Phases, each ``--seconds`` long, one after the other on the same server:

* ``track only``: ``--track-streams`` (4) /track streams;
* ``load``: the same plus ``--detect-clients`` (20) /detect clients;
* ``load + hostile``: the same plus one hostile client (left out with ``--no-hostile``);
  this phase goes on past ``--seconds`` until the hostile client has been through every
  case once, so that a short run still sees them all.

The legit clients share one asyncio process (an httpx client for /detect, the
`websockets` client for /track), all with the key (``X-API-Key``). A /detect client
POSTs the walk's frames (raw JPEG body) back to back, each client from a loopback address
of its own (127.0.0.10, 127.0.0.11, ...: twenty clients are twenty machines to the
server's limits per client address); the /track streams come from 127.0.0.1. A /track stream is a 30 fps camera
(``--track-fps``) in lock-step: it sends a frame at its slot, waits for the reply, then
waits for the next slot (a slot missed while waiting is skipped, as a camera's frame is
gone; never more than one frame in flight); it plays the walk forwards and back. The
streams' slots are staggered over one frame period.

The hostile client is a process of its own, so that its blocking cannot slow the legit
clients, at a lower CPU priority (``--hostile-nice``, 10): on a deployment it would run on
another machine, not on the server's two cores; its CPU use is reported. It connects from
127.0.0.2 with an admin key of its own. Throughout the phase it floods the server at its
full rate: four loops of ``GET /environments`` and two loops opening /track connections
(reading the first message, then closing), each sending again as soon as the reply
comes. Meanwhile it cycles through these cases as fast as their replies come, each
bounded by timeouts (30 s a request), its replies' statuses and close codes recorded per
case:

* PUT a 20 MiB map (~130k targets) on the sacrificial environment, with the key, and
  without it;
* /track: one 12 MB config text message (``{"type":"config","e0":0,...}``; the size of
  the reply is recorded); one 17 MiB binary message; ten connections opened and left
  idle for the rest of the phase (opened again when the server closes them: how many it
  closed, after how long); connections closed right after the handshake;
* /detect: eight at once of a 32x32 JPEG (some 340 bytes) whose frame header claims
  6324x6324 pixels, just under the default pixel limit;
  a 16-bit RGBA 6000x6000 PNG of zeros (a few hundred KB); a real frame cut at 20 KB
  with an end-of-image marker appended;
* a 200 MiB multipart survey upload without a key, streamed (the time to the reply);
* a map whose camera has K and distortion of 1e300, then ``locate`` with
  ``method=posit`` and ``method=mean``.

Its refusals by the per-client limits (HTTP 429, /track ``too_many_requests`` and
``client_connections``) are counted per second, and the server CPU the hostile client
costs is the server's CPU in its phase less that in the ``load`` phase.

The server's resident memory (VmRSS of its web process and that process's children, the
image workers) is sampled every 0.2 s: per phase before, peak, and 3 s after its clients
stopped. The CPU time each side used (the server, the legit clients, the hostile client)
is given in cores. Server errors are counted over all clients: HTTP statuses >= 500,
/track ``internal_error`` messages and close code 1011. The /track latencies are also
split by how the server scanned the frame (its predicted regions, or the whole frame).

Targets (with the hostile client running): every /track stream's latency p99 under
50 ms and its frames per second at least 0.8 of its own in the ``load`` phase; in every
phase the server's peak memory under 2 GB and no server error. Each gets PASS or FAIL.

Timings are wall-clock on a shared machine (the load average is printed); on two cores
the load generator itself takes a share of the CPU, so compare runs on the same machine.

Slowloris (``--slowloris``, on its own): a process opens as many connections as it can
from 127.0.0.2 (up to 2000 a second), sends each a request line and then one more
header line every 5 s, never ending the header, and replaces the ones the server closes;
meanwhile /livez is asked from 127.0.0.1 every 0.1 s on a fresh connection (5 s
allowed). Reported: the connections the slowloris held (peak, and median over the second
half; as it sees them, so connections the kernel completed that the server has not yet
accepted count too), the open files of the server's web process (sampled every second:
its connections are most of them), /livez p50/p99/max (a failed try counts with its
wait) and its failures; target: /livez p99 under 1 s.

Run: ``.venv/bin/python bench/bench_load.py [--seconds 60] [--no-hostile]`` (markdown
tables on stdout, progress on stderr; a default run takes about four minutes;
``--hostile-nice 0`` runs the hostile client at the server's priority;
``--server-env KEY=VALUE`` starts the server with that environment, repeatable).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import datetime
import errno
import json
import math
import multiprocessing
import os
import resource
import selectors
import shlex
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import websockets
from tqdm import tqdm
from websockets.exceptions import ConnectionClosed

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from app.core.imagecodec import read_header
from app.local_server import example_map, fidotrack_command, running_server
from app.sim import BENCH_ROOM, render_walk

#: Bound on one request, one WebSocket open or one awaited message, s.
TIMEOUT_S = 30.0
#: Bound on one hostile case as a whole (the extreme-map case makes three requests), s.
CASE_BUDGET_S = 3 * TIMEOUT_S + 10.0
#: The hostile phase goes on past --seconds until the hostile client has been through
#: every case once, this much longer at most, s.
FIRST_CYCLE_CAP_S = 20 * 60.0
#: Memory is sampled this often, s.
RSS_PERIOD_S = 0.2
#: "After" memory is read this long after a phase's clients stopped, s.
SETTLE_S = 3.0
TRACK_ONLY, LOAD, HOSTILE = "track only", "load", "load + hostile"
#: The targets, checked in the hostile phase (latency, fps ratio) and in every phase (memory, errors).
TARGET_P99_MS = 50.0
TARGET_FPS_RATIO = 0.8
TARGET_PEAK_MB = 2048.0
#: Hostile payloads.
BIG_MAP_BYTES = 20 * 1024 * 1024
BIG_CONFIG_BYTES = 12_000_000
BIG_FRAME_BYTES = 17 * 1024 * 1024
SURVEY_BYTES = 200 * 1024 * 1024
SOF_SIDE = 6324  # 6324^2 = 39,992,976 pixels: just under the default max_image_pixels
SOF_AT_ONCE = 8
CUT_AT = 20 * 1024
IDLE_CONNECTIONS = 10
HANDSHAKE_CLOSES = 5  # per cycle
#: The hostile client's loopback address; the /detect clients' are 127.0.0.<DETECT_SOURCE_BASE + i>.
HOSTILE_SOURCE = "127.0.0.2"
DETECT_SOURCE_BASE = 10
#: The hostile client's flood: loops of GET /environments, loops opening /track, at once.
FLOOD_REQUESTS = 4
FLOOD_TRACK_OPENS = 2


def _pct(values: Sequence[float], q: float) -> float:
    return float(np.percentile(values, q)) if len(values) else math.nan


def _fmt(value: float, digits: int = 1) -> str:
    return "-" if math.isnan(value) else f"{value:.{digits}f}"


def _histogram(counts: Counter[str]) -> str:
    return ", ".join(f"{k} x{v}" for k, v in counts.most_common()) or "-"


# ---------------------------------------------------------------------------- results


@dataclass
class StreamStats:
    """One /track stream over one phase."""

    index: int
    seconds: float = 0.0
    sent: int = 0
    replies: int = 0  # frame replies
    posed: int = 0
    latency_ms: list[float] = field(default_factory=list)
    server_ms: list[float] = field(default_factory=list)  # the reply's timing_ms.total: decode, detect, pose
    full_scan: list[bool] = field(default_factory=list)  # per reply: the whole frame was scanned
    errors: Counter[str] = field(default_factory=Counter)  # error codes, close codes, exceptions
    connections: int = 0
    server_errors: int = 0

    @property
    def fps(self) -> float:
        return self.replies / self.seconds if self.seconds else 0.0


@dataclass
class DetectStats:
    """All /detect clients of one phase together."""

    clients: int
    seconds: float = 0.0
    latency_ms: list[float] = field(default_factory=list)
    statuses: Counter[str] = field(default_factory=Counter)  # HTTP status or exception name
    server_errors: int = 0

    @property
    def rate(self) -> float:
        return len(self.latency_ms) / self.seconds if self.seconds else 0.0


@dataclass
class MemoryStats:
    before_mb: float
    peak_mb: float
    after_mb: float


@dataclass
class CaseStats:
    """One hostile case: every reply's status, close code or exception."""

    name: str
    attempts: int = 0
    outcomes: Counter[str] = field(default_factory=Counter)
    reply_s: list[float] = field(default_factory=list)
    exceptions: int = 0
    server_errors: int = 0
    reply_bytes: list[int] = field(default_factory=list)
    closed_after_s: list[float] = field(default_factory=list)  # idle connections the server closed
    body_sent: list[int] = field(default_factory=list)  # uploads: bytes sent before the reply came
    body_bytes: int = 0  # uploads: the whole body

    def reply(self, outcome: str, since: float | None) -> None:
        """A reply came (a status, a message, a close); `since`: when the request went out,
        None for an event that is no reply (the server closing an idle connection)."""
        self.outcomes[outcome] += 1
        if since is not None:
            self.reply_s.append(time.monotonic() - since)
        code = outcome.rsplit(" ", 1)[-1]
        if (code.isdigit() and (500 <= int(code) < 600 or int(code) == 1011)) or "internal_error" in outcome:
            self.server_errors += 1

    def failed(self, exc: BaseException, since: float | None = None) -> None:
        self.exceptions += 1
        self.outcomes[f"!{type(exc).__name__}"] += 1
        if since is not None:
            self.reply_s.append(time.monotonic() - since)

    def notes(self) -> str:
        parts = []
        if self.reply_bytes:
            parts.append(f"reply {max(self.reply_bytes):,} bytes at most")
        if self.body_sent:
            parts.append(f"body sent before the reply: {statistics.median(self.body_sent) / 2**20:.1f} MiB of "
                         f"{self.body_bytes / 2**20:.1f} (median)")
        if self.closed_after_s:
            parts.append(f"server closed {len(self.closed_after_s)}, after "
                         f"{statistics.median(self.closed_after_s):.1f} s (median)")
        return "; ".join(parts) or "-"


@dataclass
class HostileReport:
    cases: list[CaseStats]
    cycles: int = 0
    seconds: float = 0.0
    cpu_s: float = 0.0  # the hostile process's own CPU time
    problem: str | None = None  # why the report is missing or partial

    @property
    def server_errors(self) -> int:
        return sum(c.server_errors for c in self.cases)

    @property
    def attempts(self) -> int:
        return sum(c.attempts for c in self.cases)

    @property
    def refused(self) -> int:
        """Replies that are refusals by the per-client limits."""
        return sum(n for c in self.cases for outcome, n in c.outcomes.items() if _limit_refusal(outcome))


def _limit_refusal(outcome: str) -> bool:
    """Whether a hostile case's outcome is a refusal by a per-client limit: HTTP 429, or a
    /track too_many_requests or client_connections."""
    return outcome.endswith("429") or "too_many_requests" in outcome or "client_connections" in outcome


@dataclass
class PhaseResult:
    name: str
    seconds: float
    streams: list[StreamStats]
    detect: DetectStats | None
    memory: MemoryStats
    hostile: HostileReport | None = None
    server_cpu_s: float = 0.0  # the web process and its workers
    client_cpu_s: float = 0.0  # the legit clients' process

    @property
    def server_errors(self) -> int:
        return (sum(s.server_errors for s in self.streams) + (self.detect.server_errors if self.detect else 0)
                + (self.hostile.server_errors if self.hostile else 0))


# ------------------------------------------------------------------- server memory


def _listening_inode(port: int) -> str | None:
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with contextlib.suppress(OSError), open(table) as f:
            for line in f.readlines()[1:]:
                cols = line.split()
                if cols[3] == "0A" and int(cols[1].rsplit(":", 1)[1], 16) == port:  # 0A: LISTEN
                    return cols[9]
    return None


def _descendants(pid: int) -> list[int]:
    found = []
    with contextlib.suppress(OSError):
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as f:
                for child in map(int, f.read().split()):
                    found += [child, *_descendants(child)]
    return found


def web_process(pid: int, port: int) -> int:
    """The process that serves `port` among `pid` and its descendants: the deepest one
    holding the listening socket (a supervisor's workers inherit it); `pid` if none
    can be told."""
    inode = _listening_inode(port)
    holders = []
    for candidate in [pid, *_descendants(pid)]:
        with contextlib.suppress(OSError):
            fds = os.listdir(f"/proc/{candidate}/fd")
            if any(os.readlink(f"/proc/{candidate}/fd/{fd}") == f"socket:[{inode}]" for fd in fds):
                holders.append(candidate)
    return holders[-1] if holders and inode else pid


def _rss_mb(pid: int) -> float:
    with contextlib.suppress(OSError), open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return math.nan


def cpu_seconds(pids: Sequence[int]) -> float:
    """User and system CPU time the processes `pids` have used so far, s."""
    ticks = 0
    for pid in pids:
        with contextlib.suppress(OSError), open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
            ticks += int(fields[11]) + int(fields[12])  # utime, stime (fields 14 and 15 of stat)
    return ticks / os.sysconf("SC_CLK_TCK")


def own_cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


class RssSampler:
    """VmRSS of the server (its web process and that process's workers, together) every
    `RSS_PERIOD_S`, in a thread."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.samples: list[tuple[float, float]] = []  # (monotonic time, MB)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rss", daemon=True)

    def processes(self) -> list[int]:
        return [self.pid, *_descendants(self.pid)]

    def read(self) -> float:
        return sum(_rss_mb(pid) for pid in self.processes())

    def _run(self) -> None:
        while not self._stop.wait(RSS_PERIOD_S):
            self.samples.append((time.monotonic(), self.read()))

    def start(self) -> None:
        self.samples.append((time.monotonic(), self.read()))
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def peak(self, since: float) -> float:
        values = [mb for t, mb in self.samples if t >= since and not math.isnan(mb)]
        return max(values) if values else math.nan


# ------------------------------------------------------------------- legit clients


def _walk_index(slot: int, n: int) -> int:
    """The walk forwards, then back, and again: no jump between the last frame and the first."""
    if n < 2:
        return 0
    k = slot % (2 * n - 2)
    return k if k < n else 2 * n - 2 - k


@dataclass
class PhaseClock:
    """When a phase's clients run: from `start` at least until `deadline`, and past it
    while `hold()` says so (the hostile client's first whole cycle), `cap` at the latest."""

    start: float
    deadline: float
    hold: Callable[[], bool] | None = None
    cap: float = math.inf
    end: float | None = None

    def over(self) -> bool:
        if self.end is None:
            now = time.monotonic()
            if now >= self.deadline and (self.hold is None or now >= self.cap or not self.hold()):
                self.end = now
        return self.end is not None

    @property
    def seconds(self) -> float:
        return (self.end if self.end is not None else time.monotonic()) - self.start


async def _track_reply(ws: websockets.ClientConnection, seq: int, stats: StreamStats) -> dict[str, Any] | None:
    """The reply to frame `seq` (a frame, or an error about it); other messages are counted."""
    while True:
        message = json.loads(await asyncio.wait_for(ws.recv(), TIMEOUT_S))
        if message.get("type") == "frame":
            return message
        code = str(message.get("code"))
        stats.errors[code] += 1
        if code == "internal_error":
            stats.server_errors += 1
        if message.get("seq") == seq and code in ("bad_frame", "frame_too_large", "internal_error"):
            return None


async def track_stream(stats: StreamStats, url: str, key: str, frames: list[bytes], fps: float, clock: PhaseClock,
                       stagger: float) -> None:
    """A lock-step camera at `fps` while the phase runs, reconnecting if the server closes
    the connection; its slots are `stagger` of a period after the phase's start."""
    period = 1.0 / fps
    base = clock.start + stagger * period
    slot = 0
    while not clock.over():
        try:
            async with websockets.connect(url, additional_headers={"X-API-Key": key}, open_timeout=TIMEOUT_S,
                                          close_timeout=5, max_size=2**22) as ws:
                stats.connections += 1
                hello = json.loads(await asyncio.wait_for(ws.recv(), TIMEOUT_S))
                if hello.get("type") != "hello":
                    stats.errors[f"refused {hello.get('code')}"] += 1
                    await asyncio.sleep(0.5)
                    continue
                seq = 0
                while True:
                    now = time.monotonic()
                    slot = max(slot, math.ceil((now - base) * fps))
                    await asyncio.sleep(max(0.0, base + slot * period - now))
                    if clock.over():
                        return
                    sent = time.monotonic()
                    await ws.send(frames[_walk_index(slot, len(frames))])
                    stats.sent += 1
                    reply = await _track_reply(ws, seq, stats)
                    seq += 1
                    slot += 1
                    if reply is not None:
                        stats.latency_ms.append((time.monotonic() - sent) * 1e3)
                        stats.server_ms.append(float(reply.get("timing_ms", {}).get("total", math.nan)))
                        stats.full_scan.append(reply.get("scan") == "full")
                        stats.replies += 1
                        stats.posed += reply.get("pose") is not None
        except ConnectionClosed as exc:
            code = exc.rcvd.code if exc.rcvd is not None else None
            stats.errors[f"close {code}"] += 1
            stats.server_errors += code == 1011
        except (OSError, TimeoutError, websockets.InvalidHandshake, json.JSONDecodeError) as exc:
            stats.errors[type(exc).__name__] += 1
            await asyncio.sleep(0.2)


async def detect_client(stats: DetectStats, client: httpx.AsyncClient, frames: list[bytes], first: int,
                        clock: PhaseClock) -> None:
    """POST /detect back to back while the phase runs."""
    i = first
    while not clock.over():
        data = frames[i % len(frames)]
        i += 1
        sent = time.monotonic()
        try:
            reply = await client.post("/detect", content=data, headers={"content-type": "image/jpeg"})
        except httpx.HTTPError as exc:
            stats.statuses[type(exc).__name__] += 1
            await asyncio.sleep(0.1)
            continue
        stats.latency_ms.append((time.monotonic() - sent) * 1e3)
        stats.statuses[str(reply.status_code)] += 1
        stats.server_errors += reply.status_code >= 500


async def _progress(label: str, clock: PhaseClock, streams: list[StreamStats], detect: DetectStats | None) -> None:
    while True:
        now = time.monotonic()
        done = f"{max(0.0, now - clock.start):.0f}/{clock.deadline - clock.start:.0f} s"
        if now > clock.deadline:
            done += " (until the hostile client's first whole cycle)"
        counts = f"track replies {sum(s.replies for s in streams)}"
        if detect is not None:
            counts += f", detect {len(detect.latency_ms)}"
        print(f"\r{label}: {done}, {counts}   ", end="", file=sys.stderr, flush=True)
        await asyncio.sleep(1.0)


async def run_legit(label: str, base: str, ws_url: str, key: str, frames: list[bytes], n_streams: int,
                    n_detect: int, fps: float, clock: PhaseClock) -> tuple[list[StreamStats], DetectStats | None]:
    """The legit clients of one phase, while `clock` runs (monotonic clock)."""
    streams = [StreamStats(i) for i in range(n_streams)]
    detect = DetectStats(n_detect) if n_detect else None
    async with contextlib.AsyncExitStack() as stack:
        # Each /detect client from an address of its own, as separate machines would be.
        clients = [await stack.enter_async_context(httpx.AsyncClient(
            base_url=base, headers={"X-API-Key": key}, timeout=TIMEOUT_S,
            transport=httpx.AsyncHTTPTransport(local_address=f"127.0.0.{DETECT_SOURCE_BASE + i}")))
            for i in range(n_detect)]
        await asyncio.sleep(max(0.0, clock.start - time.monotonic()))
        progress = asyncio.create_task(_progress(label, clock, streams, detect))
        tasks = [asyncio.create_task(track_stream(s, ws_url, key, frames, fps, clock, s.index / n_streams))
                 for s in streams]
        if detect is not None:
            tasks += [asyncio.create_task(detect_client(detect, client, frames, 7 * i, clock))
                      for i, client in enumerate(clients)]
        await asyncio.sleep(max(0.0, clock.deadline - time.monotonic()))
        while not clock.over():
            await asyncio.sleep(0.05)
        # Requests in flight at the end may finish; the bound is the request timeout.
        await asyncio.wait(tasks, timeout=TIMEOUT_S + 5)
        for task in [*tasks, progress]:
            task.cancel()
        await asyncio.gather(*tasks, progress, return_exceptions=True)
    print(file=sys.stderr)
    for stream in streams:
        stream.seconds = clock.seconds
    if detect is not None:
        detect.seconds = clock.seconds
    return streams, detect


# ----------------------------------------------------------------- hostile client


def _big_map(target_bytes: int) -> bytes:
    """A valid-looking map document (`example_map`) of just under `target_bytes` of JSON."""
    n = target_bytes // 160
    for _ in range(3):
        data = json.dumps(example_map(n)).encode()
        if 0.98 * target_bytes <= len(data) <= target_bytes:
            break
        n = int(n * 0.995 * target_bytes / len(data))
    return data


def _big_config(size: int) -> str:
    parts, total, i = ['{"type":"config"'], 16, 0
    while total < size:
        part = f'"e{i}":0'
        parts.append(part)
        total += len(part) + 1
        i += 1
    return ",".join(parts) + "}"


def _sof_bomb(side: int) -> bytes:
    """A real 32x32 JPEG whose frame header (SOF0) claims `side` x `side` pixels."""
    data = bytearray(cv2.imencode(".jpg", np.zeros((32, 32), np.uint8))[1].tobytes())
    at = data.find(b"\xff\xc0")
    data[at + 5:at + 9] = side.to_bytes(2, "big") * 2  # height, then width
    header = read_header(bytes(data))
    if (header.width, header.height) != (side, side):
        raise RuntimeError("the patched JPEG does not read as intended")
    return bytes(data)


async def _chunks(data: bytes, size: int = 2**20) -> AsyncIterator[bytes]:
    for i in range(0, len(data), size):
        yield data[i:i + size]


async def raw_upload(url: str, method: str, path: str, headers: dict[str, str], body: AsyncIterator[bytes],
                     length: int, source: str | None = None) -> tuple[int, int]:
    """Send a request with a `length`-byte body over a connection of its own, reading the
    reply while the body goes out: a server that answers before it has read the body (a
    refusal) is heard at once and the rest is not sent (an HTTP client library would
    fail on the closed connection instead). Returns the status and the bytes of body
    sent."""
    target = httpx.URL(url)
    reader, writer = await asyncio.wait_for(asyncio.open_connection(
        target.host, target.port, local_addr=(source, 0) if source else None), TIMEOUT_S)
    status_line = asyncio.create_task(reader.readline())
    sent = 0
    try:
        head = [f"{method} {path} HTTP/1.1", f"Host: {target.host}:{target.port}", f"Content-Length: {length}",
                "Connection: close", *(f"{k}: {v}" for k, v in headers.items())]
        writer.write(("\r\n".join(head) + "\r\n\r\n").encode())
        with contextlib.suppress(OSError):  # the server closed the connection: its reply is read below
            async for chunk in body:
                if status_line.done():
                    break
                writer.write(chunk)
                await asyncio.wait_for(writer.drain(), TIMEOUT_S)
                sent += len(chunk)
        line = await asyncio.wait_for(status_line, TIMEOUT_S)
        if not line:
            raise ConnectionError("closed without a reply")
        return int(line.split()[1]), sent
    finally:
        status_line.cancel()
        writer.close()
        with contextlib.suppress(OSError):
            await writer.wait_closed()


@dataclass
class HostilePayloads:
    base: str
    ws_url: str  # /track on the sacrificial environment
    key: str
    environment_id: int
    frame: bytes  # one real frame of the walk
    true_map: dict[str, Any]
    source: str = HOSTILE_SOURCE  # the loopback address it connects from


class Hostile:
    """The hostile client's cases; `run` cycles through them until the deadline."""

    def __init__(self, p: HostilePayloads) -> None:
        self.p = p
        self.key = {"X-API-Key": p.key}
        self.big_map = _big_map(BIG_MAP_BYTES)
        self.big_config = _big_config(BIG_CONFIG_BYTES)
        self.big_frame = bytes(BIG_FRAME_BYTES)
        self.sof = _sof_bomb(SOF_SIDE)
        self.png16 = cv2.imencode(".png", np.zeros((6000, 6000, 4), np.uint16))[1].tobytes()
        self.cut = p.frame[:CUT_AT] + b"\xff\xd9"
        extreme = json.loads(json.dumps(p.true_map))
        extreme["camera"]["K"] = [[1e300, 0.0, 320.0], [0.0, 1e300, 240.0], [0.0, 0.0, 1.0]]
        extreme["camera"]["dist"] = [1e300] * 5
        self.extreme_map = json.dumps(extreme).encode()
        self.cases: list[tuple[CaseStats, Callable[[CaseStats], Awaitable[None]]]] = [
            (CaseStats(f"PUT map {len(self.big_map) / 2**20:.0f} MiB, key"), self.put_big_map),
            (CaseStats(f"PUT map {len(self.big_map) / 2**20:.0f} MiB, no key"), self.put_big_map_keyless),
            (CaseStats(f"/track config {len(self.big_config) / 1e6:.0f} MB text"), self.track_big_config),
            (CaseStats(f"/detect {len(self.sof)}-byte JPEG claiming {SOF_SIDE}x{SOF_SIDE}, {SOF_AT_ONCE} at once"),
             self.detect_sof),
            (CaseStats(f"/detect 16-bit RGBA 6000x6000 PNG ({len(self.png16) // 1024} KB)"), self.detect_png16),
            (CaseStats(f"survey {SURVEY_BYTES // 2**20} MiB multipart, no key"), self.survey_keyless),
            (CaseStats("PUT map K, dist 1e300; locate posit, mean"), self.locate_extreme),
            (CaseStats(f"/detect JPEG cut at {CUT_AT // 1024} KB + EOI"), self.detect_cut),
            (CaseStats(f"/track binary {BIG_FRAME_BYTES // 2**20} MiB"), self.track_big_frame),
            (CaseStats(f"/track {IDLE_CONNECTIONS} idle connections"), self.track_idle),
            (CaseStats(f"/track closed after the handshake, {HANDSHAKE_CLOSES} a cycle"), self.track_handshake_close),
        ]
        self.flood_requests = CaseStats(f"flood: GET /environments, {FLOOD_REQUESTS} loops")
        self.flood_opens = CaseStats(f"flood: /track opened and closed, {FLOOD_TRACK_OPENS} loops")
        self.http: httpx.AsyncClient | None = None
        self.idle: list[asyncio.Task[None]] = []
        self.stopping = False

    async def _request(self, stats: CaseStats, label: str, method: str, path: str, **kwargs: Any) -> None:
        assert self.http is not None
        stats.attempts += 1
        sent = time.monotonic()
        try:
            reply = await self.http.request(method, path, **kwargs)
        except httpx.HTTPError as exc:
            stats.failed(exc, sent)
            return
        stats.reply(f"{label}{reply.status_code}", sent)

    async def _upload(self, stats: CaseStats, method: str, path: str, headers: dict[str, str],
                      body: AsyncIterator[bytes], length: int) -> None:
        stats.attempts += 1
        stats.body_bytes = length
        sent = time.monotonic()
        try:
            status, sent_bytes = await raw_upload(self.p.base, method, path, headers, body, length, self.p.source)
        except (OSError, TimeoutError, ValueError, IndexError) as exc:
            stats.failed(exc, sent)
            return
        stats.body_sent.append(sent_bytes)
        stats.reply(str(status), sent)

    def _connect(self, **kwargs: Any) -> Any:
        return websockets.connect(self.p.ws_url, additional_headers=self.key, open_timeout=TIMEOUT_S,
                                  close_timeout=5, max_size=None, local_addr=(self.p.source, 0), **kwargs)

    @staticmethod
    def _closed(exc: ConnectionClosed) -> str:
        return f"close {exc.rcvd.code if exc.rcvd is not None else 'none'}"

    async def put_big_map(self, stats: CaseStats) -> None:
        await self._upload(stats, "PUT", f"/environments/{self.p.environment_id}/map",
                           {"Content-Type": "application/json", **self.key}, _chunks(self.big_map), len(self.big_map))

    async def put_big_map_keyless(self, stats: CaseStats) -> None:
        await self._upload(stats, "PUT", f"/environments/{self.p.environment_id}/map",
                           {"Content-Type": "application/json"}, _chunks(self.big_map), len(self.big_map))

    async def track_big_config(self, stats: CaseStats) -> None:
        await self._send_one(stats, self.big_config)

    async def _send_one(self, stats: CaseStats, message: str | bytes) -> None:
        """One /track connection that sends `message` once and records the reply (or the close)."""
        stats.attempts += 1
        sent = time.monotonic()
        try:
            async with self._connect() as ws:
                await asyncio.wait_for(ws.recv(), TIMEOUT_S)  # hello
                sent = time.monotonic()
                await asyncio.wait_for(ws.send(message), TIMEOUT_S)
                reply = await asyncio.wait_for(ws.recv(), TIMEOUT_S)
                stats.reply_bytes.append(len(reply))
                decoded = json.loads(reply)
                stats.reply(f"{decoded.get('type')}/{decoded.get('code', '-')}", sent)
        except ConnectionClosed as exc:
            stats.reply(self._closed(exc), sent)

    async def detect_sof(self, stats: CaseStats) -> None:
        await asyncio.gather(*(self._request(stats, "", "POST", "/detect", content=self.sof,
                                             headers={"content-type": "image/jpeg", **self.key})
                               for _ in range(SOF_AT_ONCE)))

    async def detect_png16(self, stats: CaseStats) -> None:
        await self._request(stats, "", "POST", "/detect", content=self.png16,
                            headers={"content-type": "image/png", **self.key})

    async def survey_keyless(self, stats: CaseStats) -> None:
        boundary = "benchload0boundary"
        head = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"video\"; filename=\"walk.mp4\"\r\n"
                "Content-Type: video/mp4\r\n\r\n").encode()
        tail = f"\r\n--{boundary}--\r\n".encode()

        async def body() -> AsyncIterator[bytes]:
            yield head + b"\x00\x00\x00\x18ftypmp42"
            chunk = bytes(2**20)
            for _ in range(SURVEY_BYTES // len(chunk)):
                yield chunk
            yield tail

        length = len(head) + 12 + SURVEY_BYTES + len(tail)
        await self._upload(stats, "POST", f"/environments/{self.p.environment_id}/survey",
                           {"Content-Type": f"multipart/form-data; boundary={boundary}"}, body(), length)

    async def locate_extreme(self, stats: CaseStats) -> None:
        path = f"/environments/{self.p.environment_id}"
        await self._request(stats, "put ", "PUT", f"{path}/map", content=self.extreme_map,
                            headers={"content-type": "application/json", **self.key})
        for method in ("posit", "mean"):
            await self._request(stats, f"{method} ", "POST", f"{path}/locate", params={"method": method},
                                content=self.p.frame, headers={"content-type": "image/jpeg", **self.key})

    async def detect_cut(self, stats: CaseStats) -> None:
        await self._request(stats, "", "POST", "/detect", content=self.cut,
                            headers={"content-type": "image/jpeg", **self.key})

    async def track_big_frame(self, stats: CaseStats) -> None:
        await self._send_one(stats, self.big_frame)

    async def _hold(self, stats: CaseStats) -> None:
        """One idle connection, opened again each time the server closes it."""
        while not self.stopping:
            stats.attempts += 1
            sent = time.monotonic()
            try:
                async with self._connect(ping_interval=None) as ws:
                    hello = json.loads(await asyncio.wait_for(ws.recv(), TIMEOUT_S))
                    kind = "hello" if hello.get("type") == "hello" else f"{hello.get('type')}/{hello.get('code')}"
                    stats.reply(f"opened, {kind}", sent)
                    opened = time.monotonic()
                    await ws.wait_closed()
                    if hello.get("type") == "hello":
                        stats.closed_after_s.append(time.monotonic() - opened)
                    stats.reply(f"server closed {ws.close_code}", None)
                    await asyncio.sleep(0.2 if hello.get("type") == "hello" else 1.0)  # (no tight loop)
            except asyncio.CancelledError:
                raise
            except ConnectionClosed as exc:
                stats.reply(self._closed(exc), sent)
                await asyncio.sleep(1.0)
            except Exception as exc:  # noqa: BLE001 - counted, and the connection opened again
                stats.failed(exc, sent)
                await asyncio.sleep(1.0)

    async def track_idle(self, stats: CaseStats) -> None:
        self.idle = [t for t in self.idle if not t.done()]
        self.idle += [asyncio.create_task(self._hold(stats)) for _ in range(IDLE_CONNECTIONS - len(self.idle))]

    async def flood_request(self) -> None:
        """GET /environments again as soon as each reply comes."""
        while not self.stopping:
            await self._request(self.flood_requests, "", "GET", "/environments", headers=self.key)

    async def flood_open(self) -> None:
        """Open /track, read the first message (a hello or a refusal), close; again."""
        stats = self.flood_opens
        while not self.stopping:
            stats.attempts += 1
            sent = time.monotonic()
            try:
                async with self._connect() as ws:
                    first = json.loads(await asyncio.wait_for(ws.recv(), TIMEOUT_S))
                    stats.reply(f"{first.get('type')}/{first.get('code', '-')}", sent)
            except ConnectionClosed as exc:
                stats.reply(self._closed(exc), sent)
            except Exception as exc:  # noqa: BLE001 - counted, and sent again
                stats.failed(exc, sent)
                await asyncio.sleep(0.05)

    async def track_handshake_close(self, stats: CaseStats) -> None:
        for _ in range(HANDSHAKE_CLOSES):
            stats.attempts += 1
            sent = time.monotonic()
            try:
                ws = await self._connect()
                await ws.close()
                stats.reply(f"close {ws.close_code}", sent)
            except ConnectionClosed as exc:
                stats.reply(self._closed(exc), sent)
            except Exception as exc:  # noqa: BLE001 - counted
                stats.failed(exc, sent)

    async def run(self, start: float, deadline: float, first_cycle: Any) -> HostileReport:
        """Cycle through the cases from `start` until `deadline`, and at least once whole
        (then `first_cycle` is set)."""
        report = HostileReport([*(stats for stats, _ in self.cases), self.flood_requests, self.flood_opens])
        transport = httpx.AsyncHTTPTransport(local_address=self.p.source)
        async with httpx.AsyncClient(base_url=self.p.base, timeout=TIMEOUT_S, transport=transport) as self.http:
            await asyncio.sleep(max(0.0, start - time.monotonic()))
            flood = [*(asyncio.create_task(self.flood_request()) for _ in range(FLOOD_REQUESTS)),
                     *(asyncio.create_task(self.flood_open()) for _ in range(FLOOD_TRACK_OPENS))]
            while time.monotonic() < deadline or not report.cycles:
                for stats, case in self.cases:
                    if time.monotonic() >= deadline and report.cycles:
                        break
                    try:
                        await asyncio.wait_for(case(stats), CASE_BUDGET_S)
                    except Exception as exc:  # noqa: BLE001 - a case's failure is its result
                        stats.failed(exc)
                else:
                    report.cycles += 1
                    first_cycle.set()
            report.seconds = time.monotonic() - start
            self.stopping = True
            for task in [*self.idle, *flood]:
                task.cancel()
            await asyncio.gather(*self.idle, *flood, return_exceptions=True)
        return report


def hostile_process(payloads: HostilePayloads, nice: int, commands: Any, results: Any, first_cycle: Any) -> None:
    """The hostile client's process: lower its priority by `nice`, build the payloads, say
    "ready", take (start, deadline), run, and put its `HostileReport`."""
    try:
        os.nice(nice)
        hostile = Hostile(payloads)
        results.put("ready")
        start, deadline = commands.get(timeout=600)
        cpu = own_cpu_seconds()
        report = asyncio.run(hostile.run(start, deadline, first_cycle))
        report.cpu_s = own_cpu_seconds() - cpu
        results.put(report)
    except BaseException as exc:
        results.put(HostileReport([], problem=f"the hostile client failed: {exc!r}"))
        raise


# ------------------------------------------------------------------------- phases


@dataclass
class Bench:
    base: str
    key: str
    ws_url: str
    frames: list[bytes]
    args: argparse.Namespace
    sampler: RssSampler
    hostile_payloads: HostilePayloads

    def phase(self, index: int, name: str, total: int) -> PhaseResult:
        label = f"phase {index}/{total} {name}"
        n_detect = 0 if name == TRACK_ONLY else self.args.detect_clients
        start = time.monotonic() + 0.5
        clock = PhaseClock(start, start + self.args.seconds)
        process, commands, results = None, None, None
        hostile: HostileReport | None = None
        if name == HOSTILE:
            ctx = multiprocessing.get_context("spawn")
            commands, results, first_cycle = ctx.Queue(), ctx.Queue(), ctx.Event()
            process = ctx.Process(target=hostile_process, name="hostile", daemon=True,
                                  args=(self.hostile_payloads, self.args.hostile_nice, commands, results,
                                        first_cycle))
            print(f"{label}: preparing the hostile client", file=sys.stderr)
            process.start()
            ready = _get(results, 300)
            start = time.monotonic() + 0.5
            alive = process.is_alive
            clock = PhaseClock(start, start + self.args.seconds, hold=lambda: alive() and not first_cycle.is_set(),
                               cap=start + self.args.seconds + FIRST_CYCLE_CAP_S)
            if ready == "ready":
                commands.put((clock.start, clock.deadline))
            else:  # the phase runs without it, and says so
                hostile = ready if isinstance(ready, HostileReport) else HostileReport(
                    [], problem=f"the hostile client did not start ({ready!r})")
                process.kill()
                process.join()
                process = None
        before = self.sampler.read()
        server_cpu, client_cpu = cpu_seconds(self.sampler.processes()), own_cpu_seconds()
        streams, detect = asyncio.run(run_legit(label, self.base, self.ws_url, self.key, self.frames,
                                                self.args.track_streams, n_detect, self.args.track_fps, clock))
        if process is not None and results is not None:
            print(f"{label}: waiting for the hostile client's last case", file=sys.stderr)
            report = _get(results, CASE_BUDGET_S + 60)
            hostile = report if isinstance(report, HostileReport) else HostileReport(
                [], problem=f"the hostile client did not report in time ({report!r})")
            process.join(10)
            if process.is_alive():
                process.kill()
                process.join()
        server_cpu = cpu_seconds(self.sampler.processes()) - server_cpu
        client_cpu = own_cpu_seconds() - client_cpu
        time.sleep(SETTLE_S)
        memory = MemoryStats(before, self.sampler.peak(clock.start), self.sampler.read())
        return PhaseResult(name, clock.seconds, streams, detect, memory, hostile, server_cpu, client_cpu)


def _get(queue: Any, timeout: float) -> Any:
    try:
        return queue.get(timeout=timeout)
    except Exception as exc:  # noqa: BLE001 - queue.Empty, or a report that would not unpickle
        return exc


# ------------------------------------------------------------------------- report


def _verdict(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def print_report(results: list[PhaseResult], header: list[str]) -> None:
    print("\n".join(header))
    load = next((r for r in results if r.name == LOAD), None)

    def ratio(phase: PhaseResult, stream: StreamStats) -> float:
        if load is None or stream.index >= len(load.streams) or not load.streams[stream.index].fps:
            return math.nan
        return stream.fps / load.streams[stream.index].fps

    print("\n/track streams (lock-step; fps: frame replies per second of the phase; ratio: fps over the same "
          "stream's in the load phase):\n")
    print("| phase | stream | sent | replies | fps | fps / load | latency p50 ms | latency p99 ms | server p50 ms | "
          "server p99 ms | with pose | connections | errors and closes |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        for s in r.streams:
            print(f"| {r.name} | {s.index} | {s.sent} | {s.replies} | {s.fps:.1f} | {_fmt(ratio(r, s), 2)} | "
                  f"{_fmt(_pct(s.latency_ms, 50))} | {_fmt(_pct(s.latency_ms, 99))} | "
                  f"{_fmt(_pct(s.server_ms, 50))} | {_fmt(_pct(s.server_ms, 99))} | "
                  f"{s.posed / max(s.replies, 1):.0%} | {s.connections} | {_histogram(s.errors)} |")
        pooled = [v for s in r.streams for v in s.latency_ms]
        pooled_server = [v for s in r.streams for v in s.server_ms]
        print(f"| {r.name} | **mean** | {np.mean([s.sent for s in r.streams]):.0f} | "
              f"{np.mean([s.replies for s in r.streams]):.0f} | {np.mean([s.fps for s in r.streams]):.1f} | "
              f"{_fmt(float(np.mean([ratio(r, s) for s in r.streams])), 2)} | {_fmt(_pct(pooled, 50))} (pooled) | "
              f"{_fmt(_pct(pooled, 99))} (pooled) | {_fmt(_pct(pooled_server, 50))} (pooled) | "
              f"{_fmt(_pct(pooled_server, 99))} (pooled) | "
              f"{sum(s.posed for s in r.streams) / max(sum(s.replies for s in r.streams), 1):.0%} | | |")

    print("\n/track latency by how the frame was scanned (pooled over the streams): the predicted regions, or the "
          "whole frame (the first frame, every full_scan_every-th, and when the track is lost):\n")
    print("| phase | region frames | p50 ms | p99 ms | whole-frame scans | p50 ms | p99 ms |")
    print("|---|---|---|---|---|---|---|")
    for r in results:
        split = {kind: [v for s in r.streams for v, full in zip(s.latency_ms, s.full_scan, strict=False)
                        if full == kind] for kind in (False, True)}
        print(f"| {r.name} | {len(split[False])} | {_fmt(_pct(split[False], 50))} | {_fmt(_pct(split[False], 99))} | "
              f"{len(split[True])} | {_fmt(_pct(split[True], 50))} | {_fmt(_pct(split[True], 99))} |")

    print("\n/detect (all clients together):\n")
    print("| phase | clients | requests | requests/s | latency p50 ms | latency p99 ms | statuses |")
    print("|---|---|---|---|---|---|---|")
    for r in results:
        if r.detect is None:
            print(f"| {r.name} | 0 | - | - | - | - | - |")
            continue
        d = r.detect
        print(f"| {r.name} | {d.clients} | {len(d.latency_ms)} | {d.rate:.1f} | {_fmt(_pct(d.latency_ms, 50))} | "
              f"{_fmt(_pct(d.latency_ms, 99))} | {_histogram(d.statuses)} |")

    print("\nServer (resident memory of the web process and its image workers, MB; after: 3 s after the phase's "
          "clients stopped; server errors: HTTP 5xx, /track internal_error and close 1011, over all clients) and "
          "the CPU each side used, in cores (CPU seconds over the phase's seconds):\n")
    print("| phase | seconds | RSS before | RSS peak | RSS after | server errors | server CPU | legit clients' CPU "
          "| hostile client's CPU |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in results:
        m = r.memory
        hostile_cpu = _fmt(r.hostile.cpu_s / r.seconds, 2) if r.hostile is not None and r.seconds else "-"
        print(f"| {r.name} | {r.seconds:.1f} | {_fmt(m.before_mb, 0)} | {_fmt(m.peak_mb, 0)} | {_fmt(m.after_mb, 0)} | "
              f"{r.server_errors} | {_fmt(r.server_cpu_s / r.seconds, 2)} | {_fmt(r.client_cpu_s / r.seconds, 2)} | "
              f"{hostile_cpu} |")

    hostile = next((r for r in results if r.name == HOSTILE), None)
    if hostile is not None and hostile.hostile is not None:
        h = hostile.hostile
        print(f"\nHostile client, {h.cycles} whole cycle(s) in {h.seconds:.0f} s"
              f"{'; ' + h.problem if h.problem else ''} (outcomes: HTTP status, WebSocket reply type/code or "
              f"close code, !exception):\n")
        if h.seconds:
            cost = (f"{_fmt(hostile.server_cpu_s / hostile.seconds - load.server_cpu_s / load.seconds, 2)} cores (the "
                    f"server's {_fmt(hostile.server_cpu_s / hostile.seconds, 2)} in this phase, "
                    f"{_fmt(load.server_cpu_s / load.seconds, 2)} in the load phase)") if load and load.seconds else "-"
            print(f"- requests and /track connections: {h.attempts} ({h.attempts / h.seconds:.0f} a second); refused "
                  f"by the per-client limits (429, too_many_requests, client_connections): {h.refused} "
                  f"({h.refused / h.seconds:.0f} a second)")
            print(f"- the server CPU the hostile client costs: {cost}; its own CPU: "
                  f"{_fmt(h.cpu_s / h.seconds, 2)} cores\n")
        print("| case | attempts | outcomes | median reply s | exceptions | server errors | notes |")
        print("|---|---|---|---|---|---|---|")
        for c in h.cases:
            median = statistics.median(c.reply_s) if c.reply_s else math.nan
            print(f"| {c.name} | {c.attempts} | {_histogram(c.outcomes)} | {_fmt(median, 2)} | {c.exceptions} | "
                  f"{c.server_errors} | {c.notes()} |")

    print("\nTargets:\n")
    if hostile is None or load is None:
        print("- /track latency and fps under the hostile client: n/a (no hostile phase)")
    else:
        p99 = [_pct(s.latency_ms, 99) for s in hostile.streams]
        ratios = [ratio(hostile, s) for s in hostile.streams]
        print(f"- /track latency p99 < {TARGET_P99_MS:.0f} ms with the hostile client, every stream: "
              f"{', '.join(_fmt(v) for v in p99)} ms: "
              f"{_verdict(all(v < TARGET_P99_MS for v in p99))}")
        print(f"- /track fps with the hostile client >= {TARGET_FPS_RATIO} x the load phase's, every stream: "
              f"{', '.join(_fmt(v, 2) for v in ratios)}: {_verdict(all(v >= TARGET_FPS_RATIO for v in ratios))}")
    for r in results:
        print(f"- {r.name}: peak RSS {_fmt(r.memory.peak_mb, 0)} MB < {TARGET_PEAK_MB:.0f} MB: "
              f"{_verdict(r.memory.peak_mb < TARGET_PEAK_MB)}; server errors {r.server_errors} = 0: "
              f"{_verdict(r.server_errors == 0)}")


# ---------------------------------------------------------------------- slowloris

#: The slowloris client connects from this loopback address (/livez is asked from 127.0.0.1).
SLOWLORIS_SOURCE = "127.0.0.2"
#: It opens at most this many connections a second, and this many at once in flight.
SLOWLORIS_OPEN_PER_S = 2000
SLOWLORIS_CONNECTING = 256
#: Each open connection gets one more header line this often, s (never the empty line).
SLOWLORIS_TRICKLE_S = 5.0
#: /livez is asked this often, on a fresh connection each time, each given this long, s.
LIVEZ_PERIOD_S = 0.1
LIVEZ_TIMEOUT_S = 5.0
#: The target: /livez p99 under this while the slowloris runs, s.
TARGET_LIVEZ_P99_S = 1.0
#: Its source ports, taken in turn: the kernel picking them searches the ports in use,
#: which slows to a crawl with thousands of them.
SLOWLORIS_PORTS = range(10_000, 65_536)


@dataclass
class SlowlorisReport:
    """What the slowloris client got: connections accepted, closed by the server, held."""

    accepted: int = 0
    closed_by_server: int = 0
    held_peak: int = 0
    held_samples: list[int] = field(default_factory=list)  # once a second
    problem: str = ""


def _slowloris(port: int, seconds: float) -> SlowlorisReport:
    """Open as many connections as the server (and this process's open-file limit) allow
    from SLOWLORIS_SOURCE, each sending a request header a line at a time and never ending
    it; connections the server closes are replaced."""
    report = SlowlorisReport()
    fd_limit = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    selector = selectors.DefaultSelector()
    connecting: set[socket.socket] = set()
    held: list[socket.socket] = []
    start = time.monotonic()
    deadline, next_trickle, next_sample = start + seconds, start + SLOWLORIS_TRICKLE_S, start + 1.0
    opened, paused_until, next_port = 0, 0.0, 0

    def drop(sock: socket.socket) -> None:
        with contextlib.suppress(KeyError, ValueError):
            selector.unregister(sock)
        connecting.discard(sock)
        sock.close()

    while (now := time.monotonic()) < deadline:
        budget = int((now - start) * SLOWLORIS_OPEN_PER_S) - opened
        while (now >= paused_until and budget > 0 and len(connecting) < SLOWLORIS_CONNECTING
               and len(held) + len(connecting) < fd_limit - 16):
            try:
                sock = socket.socket()
            except OSError as exc:  # out of open files: wait for the server to close some
                if exc.errno not in (errno.EMFILE, errno.ENFILE):
                    raise
                paused_until = now + 1.0
                break
            sock.setblocking(False)
            for _ in range(64):  # (a port still held, or lingering after a close of ours: the next)
                next_port += 1
                try:
                    sock.bind((SLOWLORIS_SOURCE, SLOWLORIS_PORTS[next_port % len(SLOWLORIS_PORTS)]))
                    break
                except OSError:
                    continue
            else:
                sock.close()
                paused_until = now + 1.0
                break
            sock.connect_ex(("127.0.0.1", port))
            selector.register(sock, selectors.EVENT_WRITE)
            connecting.add(sock)
            opened += 1
            budget -= 1
        for key, _ in selector.select(timeout=0.02):
            sock = key.fileobj
            assert isinstance(sock, socket.socket)
            if sock in connecting:
                if sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR) != 0:
                    drop(sock)
                    continue
                connecting.discard(sock)
                try:
                    sock.send(b"GET / HTTP/1.1\r\nHost: fidotrack\r\n")
                except OSError:
                    drop(sock)
                    report.closed_by_server += 1
                    continue
                report.accepted += 1
                selector.modify(sock, selectors.EVENT_READ)
                held.append(sock)
                continue
            try:  # readable: the server answered (408) or closed it
                data = sock.recv(4096)
            except OSError:
                data = b""
            if not data:
                report.closed_by_server += 1
                held.remove(sock)
                drop(sock)
        now = time.monotonic()
        if now >= next_trickle:
            next_trickle = now + SLOWLORIS_TRICKLE_S
            for sock in list(held):
                try:
                    sock.send(b"X-Slow: 1\r\n")
                except OSError:
                    report.closed_by_server += 1
                    held.remove(sock)
                    drop(sock)
        if now >= next_sample:
            next_sample += 1.0
            report.held_samples.append(len(held))
            report.held_peak = max(report.held_peak, len(held))
            if len(report.held_samples) % 5 == 0:
                print(f"slowloris: {now - start:.0f} s, {len(held)} held, {len(connecting)} connecting, "
                      f"{report.closed_by_server} closed by the server", file=sys.stderr)
    for sock in [*held, *connecting]:
        sock.close()
    return report


def slowloris_process(port: int, seconds: float, results: Any) -> None:
    """The slowloris client, in a process of its own, its open-file limit raised to the most it may have."""
    _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    with contextlib.suppress(ValueError, OSError):
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    try:
        results.put(_slowloris(port, seconds))
    except Exception as exc:  # noqa: BLE001 - reported, not lost with the process
        results.put(SlowlorisReport(problem=repr(exc)))


@dataclass
class LivezStats:
    """/livez as a health check saw it: every try's wait (s; a failed try waited too) and the failures."""

    waits_s: list[float] = field(default_factory=list)
    failures: Counter[str] = field(default_factory=Counter)


def poll_livez(base: str, seconds: float) -> LivezStats:
    """Ask /livez every LIVEZ_PERIOD_S for `seconds`, each on a fresh connection."""
    stats = LivezStats()
    deadline = time.monotonic() + seconds
    while (start := time.monotonic()) < deadline:
        try:
            reply = httpx.get(f"{base}/livez", timeout=LIVEZ_TIMEOUT_S)
            if reply.status_code != 200:
                stats.failures[f"HTTP {reply.status_code}"] += 1
        except httpx.TransportError as exc:
            stats.failures[type(exc).__name__] += 1
        stats.waits_s.append(time.monotonic() - start)
        time.sleep(max(0.0, start + LIVEZ_PERIOD_S - time.monotonic()))
    return stats


def _open_files(pid: int) -> int:
    try:
        return len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return 0


def sample_open_files(pid: int, stop: threading.Event, samples: list[int]) -> None:
    """The open files of process `pid` (the web process: its connections are most of them), once a second."""
    while not stop.wait(1.0):
        samples.append(_open_files(pid))


def run_slowloris(seconds: float, server_env: dict[str, str]) -> None:
    """The slowloris scenario on a fresh server: its report as markdown on stdout."""
    with tempfile.TemporaryDirectory() as tmp:
        settings = {"FIDOTRACK_LOG_LEVEL": "WARNING", **server_env}
        with running_server(Path(tmp) / "data", settings=settings, log=Path(tmp) / "server.log") as server:
            port = server.port
            ctx = multiprocessing.get_context("spawn")
            results = ctx.Queue()
            process = ctx.Process(target=slowloris_process, name="slowloris", daemon=True,
                                  args=(port, seconds, results))
            print(f"slowloris from {SLOWLORIS_SOURCE} for {seconds:.0f} s; /livez from 127.0.0.1", file=sys.stderr)
            web = web_process(server.process.pid, port)
            server_fds: list[int] = []
            stop = threading.Event()
            sampler = threading.Thread(target=sample_open_files, args=(web, stop, server_fds), daemon=True)
            process.start()
            sampler.start()
            livez = poll_livez(server.url, seconds)
            stop.set()
            sampler.join()
            report = _get(results, 60)
            process.join(10)
            if process.is_alive():
                process.kill()
            if not isinstance(report, SlowlorisReport):
                report = SlowlorisReport(problem=f"the slowloris client did not report ({report!r})")
            server_fd_limit = _fd_limit(web)
    p99 = _pct(livez.waits_s, 99)
    last = report.held_samples[len(report.held_samples) // 2:] or [0]
    last_fds = server_fds[len(server_fds) // 2:] or [0]
    commit = _git("rev-parse", "--short", "HEAD") or "?"
    pythonpath = server_env.get("PYTHONPATH", os.environ.get("PYTHONPATH"))
    code = f"the code on PYTHONPATH={pythonpath}" if pythonpath else f"commit {commit}"
    env = " ".join(f"{k}={v}" for k, v in server_env.items()) or "(as is)"
    print("\n".join([
        "# /livez while a slowloris holds connections",
        "",
        f"- command: `{shlex.join(['python', *sys.argv])}`; {code}",
        f"- server: `fidotrack serve` on 127.0.0.1, env {env}; its open-file limit {server_fd_limit}",
        f"- slowloris: from {SLOWLORIS_SOURCE}, up to {SLOWLORIS_OPEN_PER_S} new connections a second, one header "
        f"line per connection every {SLOWLORIS_TRICKLE_S:.0f} s, for {seconds:.0f} s",
        "",
        "| slowloris: connected | closed by the server | held, peak | held, median of the 2nd half "
        "| server's open files, peak | median of the 2nd half "
        "| /livez asked | p50 ms | p99 ms | max ms | failed | p99 < 1 s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
        f"| {report.accepted} | {report.closed_by_server} | {report.held_peak} | {statistics.median(last):.0f} "
        f"| {max(server_fds, default=0)} | {statistics.median(last_fds):.0f} "
        f"| {len(livez.waits_s)} | {_fmt(_pct(livez.waits_s, 50) * 1e3)} | {_fmt(p99 * 1e3)} "
        f"| {_fmt(max(livez.waits_s, default=math.nan) * 1e3)} | {_histogram(livez.failures)} "
        f"| {_verdict(p99 < TARGET_LIVEZ_P99_S)} |",
    ]))
    if report.problem:
        print(f"\nslowloris client problem: {report.problem}")


def _fd_limit(pid: int) -> str:
    try:
        for line in Path(f"/proc/{pid}/limits").read_text().splitlines():
            if line.startswith("Max open files"):
                return line.split()[3]
    except OSError:
        pass
    return "?"


def _git(*args: str) -> str:
    try:
        done = subprocess.run(["git", *args], check=False, cwd=ROOT, capture_output=True, text=True, timeout=10)
        return done.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def _create_key(data_dir: Path) -> str:
    """An admin key, made with ``fidotrack keys create`` on `data_dir`."""
    env = {**os.environ, "FIDOTRACK_API_KEYS": "true", "FIDOTRACK_DATA_DIR": str(data_dir)}
    done = subprocess.run([*fidotrack_command(), "keys", "create", "--name", "bench-load", "--scopes", "admin"],
                          env=env, capture_output=True, text=True, timeout=120, check=True)
    return done.stdout.strip().splitlines()[-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=60.0, help="length of each phase")
    parser.add_argument("--track-fps", type=float, default=30.0, help="frame slots per second of a /track stream")
    parser.add_argument("--track-streams", type=int, default=4)
    parser.add_argument("--detect-clients", type=int, default=20)
    parser.add_argument("--no-hostile", action="store_true", help="skip the phase with the hostile client")
    parser.add_argument("--hostile-nice", type=int, default=10, help=(
        "lower the hostile client's CPU priority by this much (on a deployment it runs on another machine; here "
        "it shares the server's cores); 0 to run it as the server"))
    parser.add_argument("--frames", type=int, default=200, help="frames of the rendered walk")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--slowloris", action="store_true", help=(
        "run only the slowloris scenario, --seconds long: /livez while one address holds what connections it can"))
    parser.add_argument("--server-env", action="append", default=[], metavar="KEY=VALUE",
                        help="extra environment for the server (e.g. OPENBLAS_NUM_THREADS=1); repeatable")
    args = parser.parse_args()
    server_env = {}
    for item in args.server_env:
        name, sep, value = item.partition("=")
        if not sep:
            parser.error(f"--server-env takes KEY=VALUE, got {item!r}")
        server_env[name] = value
    if args.slowloris:
        run_slowloris(args.seconds, server_env)
        return

    load_start = os.getloadavg()
    room = BENCH_ROOM.walk(args.seed, args.frames, kind="tracking")
    camera = BENCH_ROOM.camera
    frames = [cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
              for image, _ in tqdm(render_walk(room.scene, camera, room.poses, room.rng, degradation="default"),
                                   total=len(room.poses), desc="rendering", unit="frame")]
    true_map = room.scene.map_document(camera)

    phases = [TRACK_ONLY, LOAD] + ([] if args.no_hostile else [HOSTILE])
    results: list[PhaseResult] = []
    with tempfile.TemporaryDirectory() as tmp:
        data_dir = Path(tmp) / "data"
        key = _create_key(data_dir)
        # The server takes this process's environment, and these settings over it.
        settings = {"FIDOTRACK_API_KEYS": "true", "FIDOTRACK_LOG_LEVEL": "WARNING", **server_env}
        with running_server(data_dir, settings=settings, log=Path(tmp) / "server.log") as server:
            port = server.port
            with httpx.Client(base_url=server.url, headers={"X-API-Key": key}, timeout=60) as http:
                environments = []
                for name in ("bench room", "sacrificial"):
                    created = http.post("/environments", json={"name": name, "marker_size_m": 0.2})
                    created.raise_for_status()
                    http.put(f"/environments/{created.json()['id']}/map", json=true_map).raise_for_status()
                    environments.append(created.json()["id"])
                # The hostile client's own key: a party of its own, as the limits per key see it.
                hostile_key = http.post("/keys", json={"name": "hostile", "scopes": ["admin"]})
                hostile_key.raise_for_status()
            ws_base = server.url.replace("http://", "ws://")
            sampler = RssSampler(web_process(server.process.pid, port))
            sampler.start()
            bench = Bench(server.url, key, f"{ws_base}/track?environment_id={environments[0]}", frames, args,
                          sampler, HostilePayloads(server.url, f"{ws_base}/track?environment_id={environments[1]}",
                                                   hostile_key.json()["key"], environments[1],
                                                   frames[len(frames) // 2], true_map))
            # Warm-up (compiled kernels, thread pools): a few seconds of both kinds of client.
            start = time.monotonic()
            asyncio.run(run_legit("warm-up", server.url, bench.ws_url, key, frames, 1, 2, args.track_fps,
                                  PhaseClock(start, start + 3.0)))
            for index, name in enumerate(phases, 1):
                results.append(bench.phase(index, name, len(phases)))
            sampler.stop()
            exit_code = server.process.poll()

    commit = _git("rev-parse", "--short", "HEAD") or "?"
    if _git("status", "--porcelain"):
        commit += " (with local changes)"
    loads = [" ".join(f"{x:.2f}" for x in values) for values in (load_start, os.getloadavg())]
    server_state = "still running at the end" if exit_code is None else f"exited with {exit_code} before the end"
    header = [
        "# /track under /detect load and a hostile client",
        "",
        f"- command: `{shlex.join(['python', *sys.argv])}`",
        f"- date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}; commit {commit}",
        f"- host: {os.cpu_count()} cpus; load average (1, 5, 15 min) {loads[0]} at the start, {loads[1]} at the end",
        (f"- server: `fidotrack serve` on 127.0.0.1 with API keys, env {' '.join(args.server_env) or '(as is)'}; "
         f"{server_state}"),
        (f"- phases of {args.seconds:.0f} s: {', '.join(phases)}; {args.track_streams} /track streams at "
         f"{args.track_fps:.0f} fps lock-step; {args.detect_clients} /detect clients back to back; "
         f"{args.frames} frames 640x480 JPEG q90 of the bench room's tracking walk"),
    ]
    print_report(results, header)


if __name__ == "__main__":
    main()
