"""Jobs run on the job engine's workers, report progress, fail clearly, can be cancelled,
fan out over every worker, survive a worker's death or fail saying so, and never hang."""

from __future__ import annotations

import os
import signal
import time
from datetime import timedelta

import pytest
from fastapi.testclient import TestClient
from pydantic import BaseModel

from app.db import utcnow
from app.main import create_app
from app.models import Job
from app.schemas import JobStatus
from app.services import jobs
from app.services.jobs import JobKind
from app.settings import Settings
from tests.conftest import free_port, wait_for_job
from tests.services.job_handlers import CountParams, NoParams, SpreadParams


def _submit(client: TestClient, kind: str, params: BaseModel) -> str:
    with client.app.state.sessionmaker() as session:
        return client.app.state.jobs.submit(session, kind, params).id


def test_job_runs_reports_progress_and_succeeds(client: TestClient) -> None:
    job_id = _submit(client, "count", CountParams(steps=20, sleep=0.1))
    running = wait_for_job(client, job_id, {"running", "succeeded"}, timeout=60, poll=0.1)
    assert running["kind"] == "count"
    seen_progress = set()
    while (body := client.get(f"/jobs/{job_id}").json())["status"] == "running":
        seen_progress.add((body["stage"], body["progress"]))
        time.sleep(0.1)
    assert body["status"] == "succeeded" and body["progress"] == 1.0
    assert body["result"] == {"counted": 20}
    assert body["started_at"] and body["finished_at"]
    assert any(stage == "counting" and 0 < p < 1 for stage, p in seen_progress)


def test_failed_job_says_why(client: TestClient) -> None:
    body = wait_for_job(client, _submit(client, "fail", NoParams()), {"failed"}, timeout=60, poll=0.1)
    assert "no markers" in body["error"] and body["finished_at"]


def test_a_fault_of_the_service_is_reported_without_its_internals(client: TestClient) -> None:
    job_id = _submit(client, "crash", NoParams())
    body = wait_for_job(client, job_id, {"failed"}, timeout=60, poll=0.1)
    assert "out of bounds" not in body["error"] and "axis" not in body["error"]
    assert "internal error (IndexError)" in body["error"] and job_id in body["error"]


def test_cancel_stops_a_running_job(client: TestClient) -> None:
    job_id = _submit(client, "count", CountParams(steps=400, sleep=0.05))
    wait_for_job(client, job_id, {"running"}, timeout=60, poll=0.1)
    cancelled = client.delete(f"/jobs/{job_id}")
    assert cancelled.status_code == 200 and cancelled.json()["status"] == "cancelled"
    time.sleep(1.0)
    body = client.get(f"/jobs/{job_id}").json()
    assert body["status"] == "cancelled" and body["result"] is None


def test_a_result_json_cannot_carry_fails_the_job_on_every_engine(client: TestClient) -> None:
    body = wait_for_job(client, _submit(client, "nan_result", NoParams()), timeout=60, poll=0.1)
    assert body["status"] == "failed" and "NaN" in body["error"] and body["result"] is None


def test_unknown_job_is_404(client: TestClient) -> None:
    assert client.get("/jobs/nope").status_code == 404
    assert client.delete("/jobs/nope").status_code == 404


def _age(client: TestClient, job_id: str, seconds: float) -> None:
    """Make a job look submitted `seconds` ago (past the grace a fresh job gets)."""
    with client.app.state.sessionmaker() as session:
        job = session.get(Job, job_id)
        job.created_at = utcnow() - timedelta(seconds=seconds)
        session.commit()


def test_jobs_of_an_engine_that_is_gone_are_failed_not_left_queued(settings: Settings) -> None:
    # A job handed to a scheduler that stopped (its server was killed): nothing will run it.
    gone = f"tcp://127.0.0.1:{free_port()}"
    with TestClient(create_app(settings)) as first:
        with first.app.state.sessionmaker() as session:
            job = jobs.create(session, "count", CountParams(steps=1), engine=gone)
        _age(first, job.id, 60)
    with TestClient(create_app(Settings(data_dir=settings.data_dir))) as second:
        body = second.get(f"/jobs/{job.id}").json()
        assert body["status"] == "failed" and "job engine" in body["error"] and "gone" in body["error"]


def test_a_server_that_stops_fails_the_jobs_its_own_engine_held(settings: Settings) -> None:
    with TestClient(create_app(settings)) as first:
        job_id = _submit(first, "count", CountParams(steps=600, sleep=0.05))
        wait_for_job(first, job_id, {"running"}, timeout=60, poll=0.1)
    with TestClient(create_app(Settings(data_dir=settings.data_dir))) as second:
        body = second.get(f"/jobs/{job_id}").json()
        assert body["status"] == "failed" and "server shut down" in body["error"]


def _worker_pid(client: TestClient, job: dict) -> int:
    engine = client.app.state.jobs.client()
    return int(engine.run(os.getpid, workers=[job["worker"]])[job["worker"]])


def test_a_job_whose_worker_is_killed_runs_again_and_succeeds(settings: Settings) -> None:
    settings = Settings(data_dir=settings.data_dir, job_attempts=2)
    with TestClient(create_app(settings)) as client:
        job_id = _submit(client, "count", CountParams(steps=40, sleep=0.1))
        running = wait_for_job(client, job_id, lambda j: j["status"] == "running" and j["progress"] > 0.1,
                               timeout=60, poll=0.1)
        assert running["attempt"] == 1 and running["worker"]
        os.kill(_worker_pid(client, running), signal.SIGKILL)
        body = wait_for_job(client, job_id, timeout=120, poll=0.2)
        assert body["status"] == "succeeded" and body["result"] == {"counted": 40}
        assert body["attempt"] == 2


def test_a_job_whose_workers_keep_dying_fails_saying_so(settings: Settings) -> None:
    settings = Settings(data_dir=settings.data_dir, job_attempts=1)
    with TestClient(create_app(settings)) as client:
        job_id = _submit(client, "count", CountParams(steps=400, sleep=0.05))
        running = wait_for_job(client, job_id, {"running"}, timeout=60, poll=0.1)
        os.kill(_worker_pid(client, running), signal.SIGKILL)
        body = wait_for_job(client, job_id, timeout=120, poll=0.2)
        assert body["status"] == "failed" and "worker" in body["error"] and "died" in body["error"]
        assert body["attempt"] == 1


def test_a_job_whose_worker_falls_silent_is_failed_and_its_worker_stops(settings: Settings) -> None:
    settings = Settings(data_dir=settings.data_dir, job_heartbeat_s=0.5, job_lease_s=3.0)
    with TestClient(create_app(settings)) as client:
        job_id = _submit(client, "count", CountParams(steps=400, sleep=0.05))
        running = wait_for_job(client, job_id, lambda j: j["status"] == "running" and j["progress"] > 0,
                               timeout=60, poll=0.1)
        pid = _worker_pid(client, running)
        os.kill(pid, signal.SIGSTOP)  # hung: alive to the operating system, silent to the job
        try:
            failed = wait_for_job(client, job_id, {"failed"}, timeout=30, poll=0.2)
            assert "went silent" in failed["error"] and failed["stage"] == "worker lost"
        finally:
            os.kill(pid, signal.SIGCONT)
        time.sleep(2.0)  # it wakes, finds its attempt over at its next report, and stops
        assert client.get(f"/jobs/{job_id}").json() == failed


def test_a_job_fans_its_pieces_out_over_every_worker(settings: Settings) -> None:
    # Two workers (each takes jobs): the pieces of one job run on both.
    settings = Settings(data_dir=settings.data_dir, max_concurrent_jobs=2)
    with TestClient(create_app(settings)) as client:
        job_id = _submit(client, "spread", SpreadParams(pieces=8, sleep=0.4))
        body = wait_for_job(client, job_id, timeout=120, poll=0.1)
        assert body["status"] == "succeeded", body
        assert body["result"]["pieces"] == list(range(8))
        assert len(body["result"]["pids"]) == 2 and os.getpid() not in body["result"]["pids"]


def test_jobs_beyond_the_job_slots_wait_even_while_a_job_fans_out(settings: Settings) -> None:
    # One job slot: the second job starts when the first has finished, though the first's
    # pieces leave its worker's thread free while they run.
    settings = Settings(data_dir=settings.data_dir, max_concurrent_jobs=1)
    with TestClient(create_app(settings)) as client:
        first = _submit(client, "spread", SpreadParams(pieces=6, sleep=0.5))
        wait_for_job(client, first, {"running"}, timeout=60, poll=0.05)
        second = _submit(client, "count", CountParams(steps=2, sleep=0.01))
        a = wait_for_job(client, first, timeout=120, poll=0.1)
        b = wait_for_job(client, second, timeout=120, poll=0.1)
        assert a["status"] == b["status"] == "succeeded"
        assert b["started_at"] >= a["finished_at"]


def test_only_registered_kinds_with_their_own_parameters_are_submitted(client: TestClient) -> None:
    runner = client.app.state.jobs
    with client.app.state.sessionmaker() as session:
        with pytest.raises(ValueError, match="unknown job kind"):
            runner.submit(session, "no such kind", NoParams())
        with pytest.raises(TypeError, match="CountParams"):
            runner.submit(session, "count", NoParams())
    assert jobs.handler_for(JobKind.SURVEY).kind == "survey"
    assert jobs.handler_for(JobKind.TRAIN_CLASSIFIER).kind == "train_classifier"
    assert [s.value for s in JobStatus] == ["queued", "running", "succeeded", "failed", "cancelled"]
