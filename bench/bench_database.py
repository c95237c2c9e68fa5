"""The same API test suite's time on SQLite and on PostgreSQL.

Every API test runs once per engine (tests/conftest.py parametrizes them over
``sqlite`` and ``postgresql``; PostgreSQL is a throwaway server the fixtures start). This
bench runs the API tests (``tests/routers tests/services`` unless told) twice, one half
after the other, each in a pytest subprocess of its own: ``-k sqlite`` selects the
``[sqlite]`` variants, ``-k postgresql`` the ``[postgresql]`` ones. Each half writes a JUnit
file, whose per-test times (setup, call and teardown) give the summed and median test
time; the wall time is the subprocess's, collection and the PostgreSQL server's start
included. The 1-minute load average is sampled every 5 s during each half, so that a run
that shared the machine with other work says so (the half's own pytest counts for 1-2).
Before the halves, one unmeasured test starts a service, so that compiling the detector's
kernels (once per checkout, about 20 s) falls on neither half.

Most of the time goes to a few tests that run surveys, whose time is computing, not
storing, and follows the machine's other load; so the times are also given apart for
those modules (``--apart``) and for the rest, where the database's share shows.

Run: ``.venv/bin/python bench/bench_database.py`` (7-12 minutes on 2 cores; prints
markdown tables); ``--keep DIR`` keeps the JUnit files and what the run measured, which
``--report DIR`` prints again. The page is docs/benchmarks/database.md.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import xml.etree.ElementTree as ET
from collections import defaultdict
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENGINES = ("sqlite", "postgresql")
DEFAULT_PATHS = ["tests/routers", "tests/services"]
#: The modules whose tests run surveys: minutes of computing beside which the database is noise.
DEFAULT_APART = ["tests/routers/test_survey_api.py", "tests/routers/test_resilience.py"]


@dataclass
class Half:
    """One engine's run: its tests' times by test id (the engine's name taken out)."""

    engine: str
    wall_s: float
    returncode: int
    times: dict[str, float] = field(default_factory=dict)
    outcomes: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    loads: list[float] = field(default_factory=list)
    #: Selected tests that are not this engine's variant (a test named after an engine).
    strays: list[str] = field(default_factory=list)

    @property
    def total_s(self) -> float:
        return sum(self.times.values())

    @property
    def median_s(self) -> float:
        return statistics.median(self.times.values()) if self.times else float("nan")


def _variant(name: str, engine: str) -> str | None:
    """The test's id with its engine taken out, or None when it is not that engine's variant:
    the database parameter comes first, so ids look like ``test_x[sqlite]`` or
    ``test_x[sqlite-other-params]``."""
    match = re.fullmatch(rf"(.*)\[{engine}(?:-(.*))?\]", name, re.DOTALL)
    if match is None:
        return None
    rest = match.group(2)
    return match.group(1) + (f"[{rest}]" if rest else "")


def _sample_load(loads: list[float], stop: threading.Event) -> None:
    while True:
        loads.append(os.getloadavg()[0])
        if stop.wait(5.0):
            return


def warm_up(log: Path) -> None:
    """Start one service on SQLite, unmeasured: the first start compiles and caches the kernels."""
    command = [sys.executable, "-m", "pytest", "tests/routers/test_health.py", "-q", "-p", "no:cacheprovider",
               "-k", "test_livez_and_readyz and sqlite"]
    with log.open("wb") as out:
        subprocess.run(command, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)


def run_half(engine: str, paths: list[str], junit: Path, log: Path) -> Half:
    command = [sys.executable, "-m", "pytest", *paths, "-q", "-p", "no:cacheprovider", "-k", engine,
               f"--junitxml={junit}"]
    loads: list[float] = []
    stop = threading.Event()
    sampler = threading.Thread(target=_sample_load, args=(loads, stop), daemon=True)
    sampler.start()
    start = time.perf_counter()
    with log.open("wb") as out:
        # A clean environment for the engine choice: conftest decides the database per test.
        env = {k: v for k, v in os.environ.items() if k != "FIDOTRACK_DATABASE_URL"}
        returncode = subprocess.run(command, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, env=env).returncode
    wall = time.perf_counter() - start
    stop.set()
    sampler.join()
    loads.append(os.getloadavg()[0])
    return read_half(engine, wall, returncode, loads, junit)


def read_half(engine: str, wall: float, returncode: int, loads: list[float], junit: Path) -> Half:
    half = Half(engine, wall, returncode, loads=loads)
    for case in ET.parse(junit).getroot().iter("testcase"):
        test_id = f"{case.get('classname')}::{case.get('name')}"
        key = _variant(case.get("name", ""), engine)
        if key is None:
            half.strays.append(test_id)
            continue
        outcome = next((child.tag for child in case if child.tag in ("failure", "error", "skipped")), "passed")
        half.outcomes[outcome] += 1
        half.times[f"{case.get('classname')}::{key}"] = float(case.get("time", "0"))
    return half


def _minutes(seconds: float) -> str:
    minutes, rest = divmod(round(seconds), 60)
    return f"{minutes} min {rest:02d} s" if minutes else f"{rest} s"


def _outcomes(half: Half) -> str:
    order = ("passed", "failure", "error", "skipped")
    names = {"failure": "failed", "error": "errors"}
    return ", ".join(f"{half.outcomes[o]} {names.get(o, o)}" for o in order if half.outcomes[o])


def _versions() -> str:
    """The engines' versions: the PostgreSQL server the fixtures start, psycopg, SQLite."""
    sys.path.insert(0, str(ROOT))
    from tests.conftest import postgres_bin_dir

    bin_dir = postgres_bin_dir()
    server = "no PostgreSQL server"
    if bin_dir is not None:
        server = subprocess.run([str(bin_dir / "postgres"), "--version"], capture_output=True, text=True).stdout.strip()
    try:
        psycopg = f"psycopg {metadata.version('psycopg')}"
    except metadata.PackageNotFoundError:
        psycopg = "no psycopg"
    return f"{server}, {psycopg}, SQLite {sqlite3.sqlite_version}"


def report(halves: dict[str, Half], apart: list[str]) -> None:
    print("| half | tests | outcome | wall time | sum of the tests' times | median test | load average (1 min) |")
    print("|---|---:|---|---:|---:|---:|---:|")
    for engine, half in halves.items():
        print(f"| `[{engine}]` | {len(half.times)} | {_outcomes(half)} | {_minutes(half.wall_s)} | "
              f"{half.total_s:.1f} s | {half.median_s:.2f} s | {min(half.loads):.1f}-{max(half.loads):.1f} |")
    sqlite, postgres = halves.get("sqlite"), halves.get("postgresql")
    if sqlite is None or postgres is None:
        return
    print(f"| PostgreSQL / SQLite | | | {postgres.wall_s / sqlite.wall_s:.2f} | "
          f"{postgres.total_s / sqlite.total_s:.2f} | {postgres.median_s / sqlite.median_s:.2f} | |")

    common = sorted(set(sqlite.times) & set(postgres.times))
    differences = [postgres.times[t] - sqlite.times[t] for t in common]
    only = len(set(sqlite.times) ^ set(postgres.times))
    print(f"\nTest by test ({len(common)} tests in both halves"
          + (f"; {only} in one half only" if only else "") + "): PostgreSQL's time minus SQLite's is "
          f"{statistics.median(differences):+.3f} s at the median, "
          f"{sum(differences):+.1f} s in all.")

    def module(test: str) -> str:
        return test.split("::")[0]

    apart_modules = {m.removesuffix(".py").replace("/", ".") for m in apart}
    groups = {"all": common,
              ", ".join(f"`{Path(m).name}`" for m in apart) + (" (they run surveys)" if apart == DEFAULT_APART else ""):
                  [t for t in common if module(t) in apart_modules],
              "the rest": [t for t in common if module(t) not in apart_modules]}
    print("\n| tests | n | SQLite, sum | PostgreSQL, sum | ratio | median difference |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, tests in groups.items():
        if not tests:
            continue
        s, p = sum(sqlite.times[t] for t in tests), sum(postgres.times[t] for t in tests)
        median = statistics.median(postgres.times[t] - sqlite.times[t] for t in tests)
        print(f"| {name} | {len(tests)} | {s:.1f} s | {p:.1f} s | {p / s:.2f} | {median:+.3f} s |")

    by_file: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0, 0.0])
    for test in common:
        row = by_file[module(test)]
        row[0] += 1
        row[1] += sqlite.times[test]
        row[2] += postgres.times[test]
    print("\n| test module | tests | SQLite | PostgreSQL | difference |")
    print("|---|---:|---:|---:|---:|")
    for name, (n, s, p) in sorted(by_file.items(), key=lambda item: item[1][2] - item[1][1], reverse=True):
        print(f"| `{name}` | {n:.0f} | {s:.1f} s | {p:.1f} s | {p - s:+.1f} s |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs="*", default=DEFAULT_PATHS,
                        help=f"test paths (default: {' '.join(DEFAULT_PATHS)})")
    parser.add_argument("--engines", nargs="+", choices=ENGINES, default=list(ENGINES),
                        help="the halves to run, in this order (default: both)")
    parser.add_argument("--keep", type=Path,
                        help="keep each half's JUnit file and pytest output in this folder")
    parser.add_argument("--apart", nargs="*", default=DEFAULT_APART,
                        help=f"test modules to sum apart (default: {' '.join(DEFAULT_APART)})")
    parser.add_argument("--report", type=Path, metavar="DIR",
                        help="print the tables of a run kept with --keep, without running anything")
    parser.add_argument("--no-warm-up", action="store_true",
                        help="skip the unmeasured service start that compiles the kernels first")
    args = parser.parse_args()

    if args.report is not None:
        runs = json.loads((args.report / "runs.json").read_text())
        halves = {engine: read_half(engine, run["wall_s"], run["returncode"], run["loads"],
                                    args.report / f"{engine}.xml") for engine, run in runs.items()}
        print(f"machine: {next(iter(runs.values())).get('machine', '')}\n")
        report(halves, args.apart)
        return 0

    folder = args.keep or Path(tempfile.mkdtemp(prefix="bench-database-"))
    folder.mkdir(parents=True, exist_ok=True)
    print(f"{os.cpu_count()} cores; {_versions()}; tests: {' '.join(args.paths)}", file=sys.stderr)
    if not args.no_warm_up:
        warm_up(folder / "warm-up.log")
    halves: dict[str, Half] = {}
    for engine in args.engines:
        print(f"running the [{engine}] half ...", file=sys.stderr)
        half = run_half(engine, args.paths, folder / f"{engine}.xml", folder / f"{engine}.log")
        print(f"  {_minutes(half.wall_s)}, {_outcomes(half)} (pytest exit code {half.returncode})", file=sys.stderr)
        if half.strays:
            print(f"  selected but not [{engine}] variants: {half.strays}", file=sys.stderr)
        halves[engine] = half
    machine = f"{os.cpu_count()} cores; {_versions()}"
    (folder / "runs.json").write_text(json.dumps(
        {h.engine: {"wall_s": h.wall_s, "returncode": h.returncode, "loads": h.loads, "machine": machine}
         for h in halves.values()}, indent=1))
    print(f"machine: {machine}\n")
    report(halves, args.apart)
    print(f"\nJUnit files and pytest output: {folder}", file=sys.stderr)
    failed = any(h.returncode != 0 for h in halves.values())
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
