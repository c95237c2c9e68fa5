"""Where the job engine listens, and who may use it: every socket of `fidotrack serve`'s
process tree (its local cluster's scheduler, nannies, workers and their HTTP servers) with
a survey running, and of `fidotrack scheduler` and `fidotrack worker` with their default
arguments, is on the loopback; the scheduler and the workers refuse an address off the
loopback without TLS; with the certificates `fidotrack engine-certs` makes, a scheduler,
a worker and the web's client work over ``tls://``, and a peer without a certificate of
the engine's authority can neither connect nor run code.

Traffic goes only to the loopback (or inside a network namespace a test makes itself)."""

from __future__ import annotations

import asyncio
import ipaddress
import json
import operator
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx
import psutil
import pytest

from app.settings import Settings
from tests.conftest import free_port, running_server, wait_for_job
from tests.routers.test_survey_api import MARKER_M, room  # noqa: F401  (the fixture: a rendered room's MP4)

FIDOTRACK = str(Path(sys.executable).parent / "fidotrack")
#: How long a scheduler or a worker gets to start (2 shared cores, a cold import of distributed).
START_S = 90.0


@dataclass(frozen=True)
class Listening:
    """A listening TCP socket (or a bound, unconnected UDP one) of a process."""

    pid: int
    name: str
    ip: str
    port: int

    @property
    def on_loopback(self) -> bool:
        return ipaddress.ip_address(self.ip.split("%")[0]).is_loopback

    def __str__(self) -> str:
        return f"{self.ip}:{self.port} (pid {self.pid}, {self.name})"


def listening(pid: int) -> list[Listening]:
    """The sockets that the process `pid` and all its descendants listen on."""
    root = psutil.Process(pid)
    found = []
    for process in [root, *root.children(recursive=True)]:
        try:
            name = " ".join(process.cmdline()[:4])
            connections = process.net_connections(kind="inet")
        except psutil.NoSuchProcess:
            continue
        for c in connections:
            if c.status == psutil.CONN_LISTEN or (c.status == psutil.CONN_NONE and not c.raddr):
                found.append(Listening(process.pid, name, c.laddr.ip, c.laddr.port))
    return found


def _off_loopback(pid: int) -> list[str]:
    return [str(s) for s in listening(pid) if not s.on_loopback]


def _wait_listening(process: subprocess.Popen[bytes], port: int, log: Path) -> None:
    """Wait until `process` (or a child) listens on `port`."""
    deadline = time.monotonic() + START_S
    while not any(s.port == port for s in listening(process.pid)):
        if process.poll() is not None or time.monotonic() > deadline:
            pytest.fail(f"nothing listens on port {port}:\n{log.read_text()}")
        time.sleep(0.2)


def _stop(process: subprocess.Popen[bytes]) -> None:
    process.terminate()
    try:
        process.wait(30)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(30)


def _env(tmp_path: Path, **variables: str) -> dict[str, str]:
    """This process's environment for a fidotrack command, with no engine of the caller's."""
    env = {name: value for name, value in os.environ.items()
           if not name.startswith(("FIDOTRACK_JOB_", "DASK_"))}
    return {**env, "FIDOTRACK_DATA_DIR": str(tmp_path / "data"), **variables}


@contextmanager
def _running(args: Sequence[str], env: dict[str, str], log: Path) -> Iterator[subprocess.Popen[bytes]]:
    with log.open("ab") as out:
        process = subprocess.Popen([FIDOTRACK, *args], env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        yield process
    finally:
        _stop(process)


def _tls_env(tmp_path: Path, certs: Path, role: str) -> dict[str, str]:
    return _env(tmp_path, FIDOTRACK_JOB_TLS_CA_FILE=str(certs / "ca.pem"),
                FIDOTRACK_JOB_TLS_CERT_FILE=str(certs / f"{role}.pem"),
                FIDOTRACK_JOB_TLS_KEY_FILE=str(certs / f"{role}-key.pem"))


def _engine_certs(tmp_path: Path, folder: str) -> Path:
    out = tmp_path / folder
    done = subprocess.run([FIDOTRACK, "engine-certs", "--out", str(out)], env=_env(tmp_path), capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return out


async def _ask(address: str, connection_args: dict[str, object]) -> object:
    """Send a pickled function (this process's id) to the scheduler, nanny or worker at
    `address`, as an attacker would (Dask's ``run_function`` or ``run`` operation, after
    asking what it is); what it answers."""
    from distributed.core import rpc
    from distributed.protocol.pickle import dumps

    async with rpc(address, connection_args=connection_args, timeout=10) as remote:
        who = await remote.identity()
        run = remote.run_function if who.get("type") == "Scheduler" else remote.run
        return await run(function=dumps(os.getpid))


def _refused(address: str, connection_args: dict[str, object]) -> bool:
    """Whether `address` refuses to run a function sent with `connection_args`."""
    try:
        answer = asyncio.run(asyncio.wait_for(_ask(address, connection_args), 20))
    except Exception:  # noqa: BLE001  (any failure to connect, shake hands or be answered)
        return True
    return not (isinstance(answer, dict) and answer.get("status") == "OK")


def test_serve_with_a_survey_running_listens_on_the_loopback_only_and_runs_no_strangers_code(
        tmp_path: Path, room, monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: F811
    """The local cluster of a plain `fidotrack serve`: its scheduler, nannies, workers and
    their HTTP servers, all on the loopback; and no port of it runs a function sent
    without the cluster's own key (another user of the machine reaches the loopback)."""
    for name in ("FIDOTRACK_JOB_SCHEDULER", "FIDOTRACK_JOB_TLS_CA_FILE"):
        monkeypatch.delenv(name, raising=False)
    with running_server(tmp_path / "data", tmp_path / "web.log") as server, \
            httpx.Client(base_url=server.url, timeout=30) as http:
        env = http.post("/environments", json={"name": "room", "marker_size_m": MARKER_M}).json()["id"]
        reply = http.post(f"/environments/{env}/survey", files={"video": ("room.mp4", room[2], "video/mp4")})
        assert reply.status_code == 202, server.log.read_text()
        job = wait_for_job(http, reply.json()["id"], lambda j: j["status"] != "queued", timeout=180, poll=0.1)
        sockets = listening(server.process.pid)
        assert job["status"] == "running", job  # (the sockets were listed with the survey running)
        # The server's port, the scheduler's two, and each worker's nanny, worker and HTTP server.
        workers = [s for s in sockets if s.pid != server.process.pid]
        assert len(workers) >= 2 and len(sockets) >= 6, [str(s) for s in sockets]
        off = [str(s) for s in sockets if not s.on_loopback]
        assert not off, f"listening off the loopback: {off}"
        port = int(server.url.rsplit(":", 1)[1])
        ran = [str(s) for s in sockets
               if s.port != port and not _refused(f"tcp://{s.ip}:{s.port}", {})]
        assert not ran, f"ran a function sent without a key: {ran}"


def test_scheduler_and_worker_listen_on_the_loopback_by_default(tmp_path: Path) -> None:
    from distributed import Client

    port = free_port()
    env = _env(tmp_path)
    log = tmp_path / "engine.log"
    with _running(["scheduler", "--port", str(port)], env, log) as scheduler:
        _wait_listening(scheduler, port, log)
        with _running(["worker", "--scheduler", f"tcp://127.0.0.1:{port}"], env, log) as worker:
            with Client(f"tcp://127.0.0.1:{port}", timeout=START_S, set_as_default=False) as client:
                client.wait_for_workers(1, timeout=START_S)
                assert client.submit(operator.add, 1, 2).result(timeout=60) == 3
            for process in (scheduler, worker):
                sockets = listening(process.pid)
                assert len(sockets) >= 2, [str(s) for s in sockets]
                off = [str(s) for s in sockets if not s.on_loopback]
                assert not off, f"listening off the loopback: {off}\n{log.read_text()}"


@pytest.mark.parametrize("args", [
    ["scheduler", "--host", "0.0.0.0"],
    ["scheduler", "--host", "192.0.2.1"],
    ["worker", "--scheduler", "tcp://127.0.0.1:{port}", "--host", "0.0.0.0"],
], ids=["scheduler-any", "scheduler-address", "worker-any"])
def test_an_address_off_the_loopback_without_tls_is_refused_saying_why(tmp_path: Path, args: list[str]) -> None:
    port = free_port()
    args = [a.format(port=port) for a in args]
    if args[0] == "scheduler":
        args += ["--port", str(port)]
    with (tmp_path / "out.log").open("wb") as out:
        process = subprocess.Popen([FIDOTRACK, *args], env=_env(tmp_path), stdout=out, stderr=subprocess.PIPE)
    try:
        _, stderr = process.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        _stop(process)
        pytest.fail(f"`fidotrack {' '.join(args)}` ran without TLS")
    lines = stderr.decode().strip().splitlines()
    assert process.returncode == 2, lines
    assert len(lines) == 1 and "without TLS" in lines[0] and "--insecure" in lines[0], lines


def test_the_insecure_flag_and_loopback_names_are_taken(tmp_path: Path) -> None:
    """(The decision alone: `--insecure` is the operator's word; ::1 and localhost are the loopback.)"""
    from app.cli import build_parser
    from app.services.jobs.cluster import insecure_reason

    assert build_parser().parse_args(["scheduler", "--host", "0.0.0.0", "--insecure"]).insecure
    assert build_parser().parse_args(["worker", "--insecure"]).host == "127.0.0.1"
    assert insecure_reason("worker", ["127.0.0.1", "::1", "[::1]", "localhost", "127.0.0.2"]) is None
    for host in ("0.0.0.0", "::", "10.231.0.1", "scheduler", ""):
        assert insecure_reason("worker", ["127.0.0.1", host]) is not None, host


def test_over_tls_the_engine_works_and_refuses_peers_without_its_certificates(tmp_path: Path) -> None:
    from distributed import Client

    from app.db import make_engine, make_sessionmaker
    from app.services.jobs import JobRunner
    from app.services.jobs.cluster import EngineTls

    certs = _engine_certs(tmp_path, "certs")
    other = _engine_certs(tmp_path, "other")  # an authority the engine does not know
    for name in ("ca-key.pem", "scheduler-key.pem", "worker-key.pem", "web-key.pem"):
        assert (certs / name).stat().st_mode & 0o077 == 0, name
    port = free_port()
    address = f"tls://127.0.0.1:{port}"
    log = tmp_path / "engine.log"
    with _running(["scheduler", "--port", str(port)], _tls_env(tmp_path, certs, "scheduler"), log) as scheduler:
        _wait_listening(scheduler, port, log)
        with _running(["worker", "--scheduler", address], _tls_env(tmp_path, certs, "worker"), log) as worker:
            # The web process's client, with the web's certificate.
            settings = Settings(data_dir=tmp_path / "data", job_scheduler=address,
                                job_tls_ca_file=certs / "ca.pem", job_tls_cert_file=certs / "web.pem",
                                job_tls_key_file=certs / "web-key.pem")
            database = make_engine(settings.resolved_database_url)
            runner = JobRunner(settings, make_sessionmaker(database))
            try:
                client = runner.client()
                client.wait_for_workers(1, timeout=START_S)
                assert client.submit(operator.add, 1, 2).result(timeout=60) == 3
                nannies = [w["nanny"] for w in client.scheduler_info()["workers"].values()]
                workers = list(client.scheduler_info()["workers"])
            finally:
                runner.shutdown()
                database.dispose()
            for process in (scheduler, worker):
                assert not _off_loopback(process.pid), log.read_text()
            ends = [address, *nannies, *workers]
            assert all(end.startswith("tls://127.0.0.1:") for end in ends), ends
            web = EngineTls(certs / "ca.pem", certs / "web.pem", certs / "web-key.pem").security()
            stranger = EngineTls(other / "ca.pem", other / "web.pem", other / "web-key.pem").security()
            # With the web's certificate a function runs on a worker; without, nowhere.
            assert not _refused(workers[0], web.get_connection_args("client"))
            for end in ends:
                assert _refused(end.replace("tls://", "tcp://"), {}), end
                assert _refused(end, stranger.get_connection_args("client")), end
            with pytest.raises((OSError, TimeoutError)):
                Client(address.replace("tls://", "tcp://"), timeout=5, set_as_default=False)
            with pytest.raises((OSError, TimeoutError)):
                Client(address, security=stranger, timeout=5, set_as_default=False)


def test_a_tls_scheduler_without_certificates_is_refused_before_connecting(tmp_path: Path) -> None:
    done = subprocess.run([FIDOTRACK, "worker", "--scheduler", f"tls://127.0.0.1:{free_port()}"],
                          env=_env(tmp_path), capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "FIDOTRACK_JOB_TLS_CA_FILE" in done.stderr, done.stderr


#: What the other end of the veth pair tries against the scheduler (run there as a script).
_PEER = """
import json, os, sys
from distributed import Client
from distributed.protocol.pickle import dumps
from app.services.jobs.cluster import EngineTls
from tests.test_engine_network import _refused

address, certs, other = sys.argv[1], sys.argv[2], sys.argv[3]

def tls(folder):
    return EngineTls(f"{folder}/ca.pem", f"{folder}/web.pem", f"{folder}/web-key.pem").security()

result = {"plain": _refused(address.replace("tls://", "tcp://"), {}),
          "stranger": _refused(address, tls(other).get_connection_args("client"))}
with Client(address, security=tls(certs), timeout=60, set_as_default=False) as client:
    result["with_certificate"] = client.run_on_scheduler(os.getpid) > 0
print(json.dumps(result))
"""


@contextmanager
def _namespaces(tag: str) -> Iterator[tuple[str, str]]:
    """Two network namespaces joined by a veth pair: 10.231.0.1 in the first, 10.231.0.2
    in the second; nothing else in either but their loopbacks."""
    a, b = f"fdt{tag}a", f"fdt{tag}b"
    steps = [["netns", "add", a], ["netns", "add", b],
             ["link", "add", f"v{tag}a", "type", "veth", "peer", "name", f"v{tag}b"],
             ["link", "set", f"v{tag}a", "netns", a], ["link", "set", f"v{tag}b", "netns", b],
             ["-n", a, "addr", "add", "10.231.0.1/24", "dev", f"v{tag}a"],
             ["-n", b, "addr", "add", "10.231.0.2/24", "dev", f"v{tag}b"],
             ["-n", a, "link", "set", f"v{tag}a", "up"], ["-n", b, "link", "set", f"v{tag}b", "up"],
             ["-n", a, "link", "set", "lo", "up"], ["-n", b, "link", "set", "lo", "up"]]
    try:
        for step in steps:
            done = subprocess.run(["ip", *step], capture_output=True, text=True)
            if done.returncode != 0:
                pytest.skip(f"cannot make network namespaces here (ip {' '.join(step)}: {done.stderr.strip()})")
        yield a, b
    finally:
        for name in (a, b):
            subprocess.run(["ip", "netns", "del", name], capture_output=True)


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="needs root for network namespaces")
@pytest.mark.skipif(shutil.which("ip") is None, reason="needs the ip command (iproute2)")
def test_across_an_interface_the_scheduler_runs_code_only_for_holders_of_a_certificate(tmp_path: Path) -> None:
    certs = _engine_certs(tmp_path, "certs")
    other = _engine_certs(tmp_path, "other")
    port = 8786
    address = f"tls://10.231.0.1:{port}"
    log = tmp_path / "scheduler.log"
    with _namespaces(str(os.getpid() % 10000)) as (a, b):
        # Without TLS, on the interface: refused.
        plain = subprocess.run(["ip", "netns", "exec", a, FIDOTRACK, "scheduler", "--host", "10.231.0.1"],
                               env=_env(tmp_path), capture_output=True, text=True, timeout=60)
        assert plain.returncode == 2 and "without TLS" in plain.stderr, plain.stderr
        env = _tls_env(tmp_path, certs, "scheduler")
        with log.open("ab") as out:
            scheduler = subprocess.Popen(["ip", "netns", "exec", a, FIDOTRACK, "scheduler", "--host", "10.231.0.1",
                                          "--port", str(port)], env=env, stdout=out, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + START_S
            while address not in log.read_text():
                assert scheduler.poll() is None and time.monotonic() < deadline, log.read_text()
                time.sleep(0.2)
            peer = tmp_path / "peer.py"
            peer.write_text(_PEER)
            root = Path(__file__).resolve().parents[1]
            done = subprocess.run(["ip", "netns", "exec", b, sys.executable, str(peer), address, str(certs),
                                   str(other)], env={**_env(tmp_path), "PYTHONPATH": os.pathsep.join(
                                       filter(None, [os.environ.get("PYTHONPATH"), str(root)]))},
                                  capture_output=True, text=True, timeout=180)
            assert done.returncode == 0, done.stderr[-3000:]
            assert json.loads(done.stdout.strip().splitlines()[-1]) == {
                "plain": True, "stranger": True, "with_certificate": True}
        finally:
            _stop(scheduler)
