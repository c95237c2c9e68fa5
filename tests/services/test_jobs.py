"""Jobs run in worker processes, report progress, fail clearly, can be cancelled, and
never hang across a restart."""

from __future__ import annotations

import time

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.services import jobs
from app.settings import Settings


@pytest.fixture(autouse=True)
def _test_handlers(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(jobs.HANDLERS, "count", "tests.job_handlers:count")
    monkeypatch.setitem(jobs.HANDLERS, "fail", "tests.job_handlers:fail")


def _submit(client: TestClient, kind: str, params: dict) -> str:
    with client.app.state.sessionmaker() as session:
        job = jobs.create(session, kind, params)
    client.app.state.jobs.submit(job.id, kind)
    return job.id


def _wait(client: TestClient, job_id: str, statuses: set[str], timeout: float = 60) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        body = client.get(f"/jobs/{job_id}").json()
        if body["status"] in statuses:
            return body
        assert time.monotonic() < deadline, body
        time.sleep(0.1)


def test_job_runs_reports_progress_and_succeeds(client: TestClient) -> None:
    job_id = _submit(client, "count", {"steps": 20, "sleep": 0.1})
    running = _wait(client, job_id, {"running", "succeeded"})
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
    body = _wait(client, _submit(client, "fail", {}), {"failed"})
    assert "no markers" in body["error"] and body["finished_at"]


def test_cancel_stops_a_running_job(client: TestClient) -> None:
    job_id = _submit(client, "count", {"steps": 400, "sleep": 0.05})
    _wait(client, job_id, {"running"})
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
            job = jobs.create(session, "count", {"steps": 1})  # queued, never dispatched
    with TestClient(create_app(Settings(data_dir=settings.data_dir))) as second:
        body = second.get(f"/jobs/{job.id}").json()
        assert body["status"] == "failed" and "server stopped" in body["error"]
