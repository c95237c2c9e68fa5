"""What the /track benchmarks share: a JSON request to a running server, a /track
connection opened in a mode, the statistics of a run and how a reply counts in them,
lock-step streaming on an open connection.

The servers themselves start through `app.local_server` (``start_server``, with
`QUIET_SERVER` among their settings). Used by bench_track.py (where these were first
written), bench_hd.py, bench_workers.py, bench_browser.py and bench_motion.py.
"""

from __future__ import annotations

import json
import time
import urllib.request
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import websockets

from app.core.geometry import Pose

__all__ = ["HEADER", "MODES", "QUIET_SERVER", "SPLIT", "RunStats", "account", "http_json", "open_track",
           "stream_lock_step"]

#: The two scan modes and the ``regions`` of their config message.
MODES = {"regions": True, "full": False}
#: timing_ms keys shown in the split of the server's time.
SPLIT = ("decode", "plan", "candidates", "targets", "pose", "total")
#: The benchmarks' servers log warnings and errors only (settings of ``start_server``).
QUIET_SERVER = {"FIDOTRACK_LOG_LEVEL": "WARNING"}


@dataclass
class RunStats:
    """One run of one mode: what was sent, what came back, and what the replies say."""

    name: str
    mode: str
    sent: int = 0
    replies: int = 0
    seconds: float = 0.0
    latency_ms: list[float] = field(default_factory=list)
    server_ms: list[float] = field(default_factory=list)
    detect_ms: list[float] = field(default_factory=list)
    dropped: int = 0
    posed: int = 0
    full_scans: int = 0
    reasons: dict[str, int] = field(default_factory=dict)  # scan_reason -> frames
    split: dict[str, list[float]] = field(default_factory=dict)  # timing_ms key -> values
    errors_mm: list[float] = field(default_factory=list)
    positions: dict[int, np.ndarray] = field(default_factory=dict)  # seq -> position

    @property
    def fps(self) -> float:
        return self.replies / self.seconds if self.seconds else 0.0

    def row(self) -> str:
        """The run as a row of the `HEADER` table."""
        def pct(values: list[float], q: float) -> str:
            return f"{np.percentile(values, q):.1f}" if values else "-"

        return (f"| {self.name} | {self.mode} | {self.sent} | {self.replies} | {self.fps:.0f} | "
                f"{pct(self.latency_ms, 50)} | {pct(self.latency_ms, 99)} | {pct(self.server_ms, 50)} | "
                f"{pct(self.server_ms, 99)} | {pct(self.detect_ms, 50)} | {self.dropped} | "
                f"{self.posed / max(self.replies, 1):.0%} | {pct(self.errors_mm, 50)} | {pct(self.errors_mm, 90)} | "
                f"{self.full_scans / max(self.replies, 1):.0%} |")


#: The head of the table of `RunStats.row`.
HEADER = ("| run | mode | sent | replies | fps | latency p50 ms | latency p99 ms | server ms p50 | server ms p99 | "
          "detect ms p50 | dropped | with pose | position err p50 mm | position err p90 mm | full scans |\n"
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")


def http_json(method: str, url: str, body: Any = None) -> Any:
    """A JSON request (`body` as JSON when given) and its JSON reply (None when empty)."""
    data = json.dumps(body).encode() if body is not None else None
    request = urllib.request.Request(url, data=data, method=method, headers={"content-type": "application/json"})
    with urllib.request.urlopen(request, timeout=30) as reply:
        return json.loads(reply.read() or b"null")


async def open_track(url: str, mode: str) -> websockets.ClientConnection:
    """A /track connection at `url` past its hello, configured for `mode` (`MODES`)."""
    ws = await websockets.connect(url, max_size=None)
    hello = json.loads(await ws.recv())
    assert hello["type"] == "hello", hello
    await ws.send(json.dumps({"type": "config", "regions": MODES[mode]}))
    echo = json.loads(await ws.recv())
    assert echo["type"] == "config" and echo["regions"] is MODES[mode], echo
    return ws


def account(stats: RunStats, reply: dict[str, Any], truth: list[Pose]) -> None:
    """Count a frame's reply in `stats`; `truth`: the walk's true poses by seq."""
    stats.replies += 1
    stats.server_ms.append(reply["timing_ms"]["total"])
    stats.detect_ms.append(reply["timing_ms"].get("detect", np.nan))
    stats.dropped += int(reply["dropped"])
    stats.full_scans += reply.get("scan", "full") == "full"
    for key in SPLIT:
        stats.split.setdefault(key, []).append(float(reply["timing_ms"].get(key, 0.0)))
    reason = reply.get("scan_reason", "?")
    stats.reasons[reason] = stats.reasons.get(reason, 0) + 1
    if reply["pose"] is not None:
        stats.posed += 1
        position = np.asarray(reply["pose"]["position"])
        stats.positions[reply["seq"]] = position
        stats.errors_mm.append(1e3 * float(np.linalg.norm(position - truth[reply["seq"]].position)))


async def stream_lock_step(ws: websockets.ClientConnection, frames: list[bytes], truth: list[Pose],
                           stats: RunStats) -> RunStats:
    """Send `frames` on an open connection, each when the reply to the last is in, into
    `stats`; the connection is closed after."""
    try:
        start = time.perf_counter()
        for data in frames:
            sent = time.perf_counter()
            await ws.send(data)
            stats.sent += 1
            reply = json.loads(await ws.recv())
            if reply["type"] != "frame":
                raise RuntimeError(f"unexpected reply {reply}")
            stats.latency_ms.append((time.perf_counter() - sent) * 1e3)
            account(stats, reply, truth)
        stats.seconds = time.perf_counter() - start
    finally:
        await ws.close()
    return stats
