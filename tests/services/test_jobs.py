"""Jobs run in worker processes, report progress, fail clearly, can be cancelled, and
never hang across a restart."""

from __future__ import annotations

import time

import pytest
from fastapi.testclient import TestClient
from pydantic import BaseModel

from app.main import create_app
from app.schemas import JobStatus
from app.services import jobs
from app.services.jobs import JobKind
from app.settings import Settings
from tests.conftest import wait_for_job
from tests.services.job_handlers import CountParams, NoParams


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


def test_unknown_job_is_404(client: TestClient) -> None:
    assert client.get("/jobs/nope").status_code == 404
    assert client.delete("/jobs/nope").status_code == 404


def test_jobs_interrupted_by_a_restart_are_failed_not_left_running(settings: Settings) -> None:
    with TestClient(create_app(settings)) as first:
        with first.app.state.sessionmaker() as session:
            job = jobs.create(session, "count", CountParams(steps=1))  # queued, never dispatched
    with TestClient(create_app(Settings(data_dir=settings.data_dir))) as second:
        body = second.get(f"/jobs/{job.id}").json()
        assert body["status"] == "failed" and "server stopped" in body["error"]


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
