"""The job engine as a deployment runs it: a `fidotrack scheduler`, `fidotrack worker`s and
`fidotrack serve` as separate processes (on one machine here; they speak TCP, as across
machines). A survey posted to the web process runs on the workers, outlives a restart of
the web process, and runs again when the worker running it is killed."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from app.settings import Settings
from tests.conftest import free_port, running_server, wait_for_job
from tests.routers.test_survey_api import MARKER_M, room  # noqa: F401  (the fixture: a rendered room's MP4)

FIDOTRACK = str(Path(sys.executable).parent / "fidotrack")


class Engine:
    """A scheduler and a worker command (with its worker processes), each in its own
    process group so that a test can kill one worker process alone."""

    def __init__(self, data_dir: Path, log: Path, n_workers: int) -> None:
        self.address = f"tcp://127.0.0.1:{free_port()}"
        port = self.address.rsplit(":", 1)[1]
        self.env = {**os.environ, "FIDOTRACK_DATA_DIR": str(data_dir), "FIDOTRACK_JOB_SCHEDULER": self.address}
        self.log = log
        with log.open("ab") as out:
            self.scheduler = subprocess.Popen([FIDOTRACK, "scheduler", "--host", "127.0.0.1", "--port", port],
                                              env=self.env, stdout=out, stderr=subprocess.STDOUT)
            self.workers = subprocess.Popen([FIDOTRACK, "worker", "--nworkers", str(n_workers)], env=self.env,
                                            stdout=out, stderr=subprocess.STDOUT)

    def restart_scheduler(self) -> None:
        """Kill the scheduler and start another at the same address (its workers wait)."""
        self.scheduler.kill()
        self.scheduler.wait(30)
        port = self.address.rsplit(":", 1)[1]
        with self.log.open("ab") as out:
            self.scheduler = subprocess.Popen([FIDOTRACK, "scheduler", "--host", "127.0.0.1", "--port", port],
                                              env=self.env, stdout=out, stderr=subprocess.STDOUT)

    def stop(self) -> None:
        for process in (self.workers, self.scheduler):
            process.terminate()
        for process in (self.workers, self.scheduler):
            try:
                process.wait(30)
            except subprocess.TimeoutExpired:
                process.kill()


@pytest.fixture
def engine(settings: Settings, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Engine]:
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    engine = Engine(settings.data_dir, tmp_path / "engine.log", n_workers=2)
    monkeypatch.setenv("FIDOTRACK_JOB_SCHEDULER", engine.address)
    try:
        yield engine
    finally:
        engine.stop()


#: The surveys here are about the job engine, not the map: the cards alone, the quicker survey.
CARDS_ONLY = {"feature_tracks": "false"}


def _survey(http: httpx.Client, video: bytes) -> str:
    env = http.post("/environments", json={"name": "room", "marker_size_m": MARKER_M}).json()["id"]
    reply = http.post(f"/environments/{env}/survey", files={"video": ("room.mp4", video, "video/mp4")},
                      data=CARDS_ONLY)
    assert reply.status_code == 202, reply.text
    return reply.json()["id"]


def _worker_pid(engine: Engine, worker: str) -> int:
    """The process of the worker at `worker` (tcp://host:port), as it says itself."""
    from distributed import Client

    with Client(engine.address, timeout=30) as client:
        return int(client.run(os.getpid, workers=[worker])[worker])


def test_a_survey_runs_on_the_workers_and_outlives_a_restart_of_the_web_process(
        settings: Settings, engine: Engine, room, tmp_path: Path) -> None:  # noqa: F811
    with running_server(settings.data_dir, tmp_path / "web.log") as server, \
            httpx.Client(base_url=server.url, timeout=30) as http:
        job_id = _survey(http, room[2])
        running = wait_for_job(http, job_id, {"running"}, timeout=120, poll=0.1)
        assert running["worker"] and running["attempt"] == 1
    # No web process for a while: the job goes on, on its worker.
    time.sleep(2.0)
    with running_server(settings.data_dir, tmp_path / "web.log") as server, \
            httpx.Client(base_url=server.url, timeout=30) as http:
        body = wait_for_job(http, job_id, timeout=300)
        assert body["status"] == "succeeded", body
        assert body["attempt"] == 1 and body["result"]["n_targets"] >= 12
        assert body["result"]["stage_s"]["detecting"] > 0


def test_a_survey_whose_worker_is_killed_runs_again_on_another(
        settings: Settings, engine: Engine, room, tmp_path: Path) -> None:  # noqa: F811
    with running_server(settings.data_dir, tmp_path / "web.log") as server, \
            httpx.Client(base_url=server.url, timeout=30) as http:
        job_id = _survey(http, room[2])
        running = wait_for_job(http, job_id, lambda j: j["status"] == "running" and j["progress"] > 0,
                               timeout=120, poll=0.05)
        os.kill(_worker_pid(engine, running["worker"]), signal.SIGKILL)
        body = wait_for_job(http, job_id, timeout=300)
        assert body["status"] == "succeeded", body
        assert body["attempt"] == 2 and body["worker"] != running["worker"]
        document = http.get(f"/environments/{body['environment_id']}/map").json()
        assert document["survey_job_id"] == job_id and len(document["targets"]) >= 12


def test_jobs_of_a_scheduler_that_dies_are_failed_not_left_running(
        settings: Settings, engine: Engine, room, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: F811
    monkeypatch.setenv("FIDOTRACK_JOB_LEASE_S", "6")
    with running_server(settings.data_dir, tmp_path / "web.log") as server, \
            httpx.Client(base_url=server.url, timeout=30) as http:
        job_id = _survey(http, room[2])
        wait_for_job(http, job_id, {"running"}, timeout=120, poll=0.05)
        engine.scheduler.kill()
        engine.workers.kill()  # (its worker processes exit with their nanny)
        body = wait_for_job(http, job_id, timeout=90)
        assert body["status"] == "failed" and body["stage"] in ("interrupted", "worker lost"), body
        assert http.get("/readyz").status_code == 200


def test_several_server_processes_share_one_local_cluster_and_its_limits(
        settings: Settings, room, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: F811
    # The embedded default with 2 web processes: one job slot and one queue limit for both.
    monkeypatch.setenv("FIDOTRACK_MAX_CONCURRENT_JOBS", "1")
    monkeypatch.setenv("FIDOTRACK_MAX_QUEUED_JOBS", "2")
    two_processes = [FIDOTRACK, "serve", "--workers", "2"]
    with running_server(settings.data_dir, tmp_path / "web.log", command=two_processes) as server, \
            httpx.Client(base_url=server.url, timeout=60) as http:
        env = http.post("/environments", json={"name": "room", "marker_size_m": MARKER_M}).json()["id"]

        def post(_: int) -> httpx.Response:
            with httpx.Client(base_url=server.url, timeout=60) as own:  # a connection of its own
                return own.post(f"/environments/{env}/survey",
                                files={"video": ("room.mp4", room[2], "video/mp4")}, data=CARDS_ONLY)

        with ThreadPoolExecutor(6) as pool:
            replies = list(pool.map(post, range(6)))
        accepted = [r.json()["id"] for r in replies if r.status_code == 202]
        assert len(accepted) == 2 and all(r.status_code == 429 for r in replies if r.status_code != 202)
        jobs = [wait_for_job(http, job_id, timeout=300) for job_id in accepted]
        assert all(job["status"] == "succeeded" for job in jobs), jobs
        first, second = sorted(jobs, key=lambda job: job["started_at"])
        # One slot, on one worker, whichever web process took each survey.
        assert second["started_at"] >= first["finished_at"] and first["worker"] == second["worker"]


def test_the_web_process_takes_jobs_again_once_its_scheduler_is_back(
        settings: Settings, engine: Engine, room, tmp_path: Path) -> None:  # noqa: F811
    with running_server(settings.data_dir, tmp_path / "web.log") as server, \
            httpx.Client(base_url=server.url, timeout=30) as http:
        assert wait_for_job(http, _survey(http, room[2]), timeout=300)["status"] == "succeeded"
        engine.restart_scheduler()
        time.sleep(15.0)  # past the client's wait for the old scheduler: it has given up on it
        deadline = time.monotonic() + 90
        while True:  # 503 until the scheduler answers and a worker is back with it
            env = http.post("/environments", json={"name": "again", "marker_size_m": MARKER_M}).json()["id"]
            reply = http.post(f"/environments/{env}/survey", files={"video": ("room.mp4", room[2], "video/mp4")},
                              data=CARDS_ONLY)
            if reply.status_code == 202 or time.monotonic() > deadline:
                break
            assert reply.status_code == 503, reply.text
            time.sleep(1.0)
        assert reply.status_code == 202, reply.text
        assert wait_for_job(http, reply.json()["id"], timeout=300)["status"] == "succeeded"
