"""The README's tour, run as written: every shell block of "A tour", in order, in a fresh
folder, against a real server (the tour's ``localhost:8000`` pointed at the test's own
port). A newcomer copies these lines; they must work and give what the text says."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import httpx

from tests.conftest import running_server

ROOT = Path(__file__).resolve().parents[1]


def tour_blocks() -> list[str]:
    """The ``bash`` blocks of the README's "A tour" section, in order."""
    text = (ROOT / "README.md").read_text()
    tour = text.split("\n## A tour\n", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```bash\n(.*?)```", tour, flags=re.S)


def _run(block: str, cwd: Path, port: int) -> str:
    # The tour's pip line installs what the test environment already has.
    lines = [line for line in block.splitlines() if not line.startswith(".venv/bin/pip install")]
    script = "set -euo pipefail\n" + "\n".join(lines).replace("localhost:8000", f"127.0.0.1:{port}")
    done = subprocess.run(["bash", "-c", script], cwd=cwd, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, f"{block}\n--- stdout\n{done.stdout[-3000:]}\n--- stderr\n{done.stderr[-3000:]}"
    return done.stdout


def _json_objects(output: str) -> list[dict]:
    """The JSON objects a block printed (curl prints no newline after a body: they may
    follow each other on one line)."""
    decoder = json.JSONDecoder()
    found, position = [], 0
    while (start := output.find("{", position)) != -1:
        try:
            value, position = decoder.raw_decode(output, start)
        except ValueError:
            position = start + 1
            continue
        if isinstance(value, dict):
            found.append(value)
    return found


def test_the_readme_tour_runs_as_written(tmp_path: Path) -> None:
    blocks = tour_blocks()
    assert len(blocks) >= 7
    work = tmp_path / "tour"
    work.mkdir()
    (work / ".venv").symlink_to(ROOT / ".venv")
    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        port = int(server.url.rsplit(":", 1)[1])
        api = httpx.Client(base_url=server.url, timeout=30)
        outputs = []
        for block in blocks:
            outputs.append(_run(block, work, port))
            if "/survey" in block:
                # The tour's survey is the sample room's: every card mapped, at the card size printed.
                surveyed = api.get("/environments/1/map").json()
                truth = json.loads((work / "map.json").read_text())
                assert surveyed["frame"] == "survey" and len(surveyed["targets"]) >= 0.9 * len(truth["targets"])
            if "/alignment" in block:
                # The alignment to the room's true disc positions fits: metric scale, small residuals.
                aligned = [r for r in _json_objects(outputs[-1]) if "residuals" in r]
                assert aligned, outputs[-1]
                points = aligned[0]
                assert abs(points["scale"] - 1.0) < 0.01 and points["rms_m"] < 0.01, points
    assert "Traceback" not in (tmp_path / "server.log").read_text()
