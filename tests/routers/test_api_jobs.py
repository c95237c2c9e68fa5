"""GET /jobs: the newest jobs first, filtered by kind, status and environment, at most
`limit` of them, each with its typed result."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from fastapi.testclient import TestClient
from pydantic import BaseModel

from app.models import Job
from app.schemas import JobStatus
from app.services.jobs import JobKind, store


class _Params(BaseModel):
    upload_dir: str = "none"


def _store_job(client: TestClient, kind: JobKind, status: JobStatus, environment_id: int | None,
               minutes: int, result: dict | None = None) -> str:
    """A job row as a finished (or waiting) job leaves it, created `minutes` after a fixed
    instant; never dispatched to a worker."""
    with client.app.state.sessionmaker() as session:
        job = store.create(session, kind.value, _Params(), environment_id=environment_id)
        row = session.get(Job, job.id)
        assert row is not None
        row.status = status.value
        row.created_at = datetime(2026, 11, 20, 9, 0, tzinfo=UTC) + timedelta(minutes=minutes)
        row.result = result
        session.commit()
        return job.id


def test_jobs_are_listed_newest_first_and_filtered(client: TestClient) -> None:
    first = client.post("/environments", json={"name": "studio", "marker_size_m": 0.2}).json()["id"]
    second = client.post("/environments", json={"name": "lab", "marker_size_m": 0.15}).json()["id"]
    training = {"images": 3, "stats": {"site_images": 3}, "classifier_id": 7}
    ids = {
        "survey_failed": _store_job(client, JobKind.SURVEY, JobStatus.FAILED, first, 0),
        "training_done": _store_job(client, JobKind.TRAIN_CLASSIFIER, JobStatus.SUCCEEDED, None, 1, training),
        "survey_queued": _store_job(client, JobKind.SURVEY, JobStatus.QUEUED, second, 2),
        "survey_cancelled": _store_job(client, JobKind.SURVEY, JobStatus.CANCELLED, first, 3),
    }

    def listed(query: str = "") -> list[str]:
        reply = client.get(f"/jobs{query}")
        assert reply.status_code == 200, reply.text
        return [job["id"] for job in reply.json()]

    assert listed() == [ids["survey_cancelled"], ids["survey_queued"], ids["training_done"], ids["survey_failed"]]
    assert listed("?kind=survey") == [ids["survey_cancelled"], ids["survey_queued"], ids["survey_failed"]]
    assert listed("?kind=train_classifier") == [ids["training_done"]]
    assert listed("?status=queued") == [ids["survey_queued"]]
    assert listed(f"?environment_id={first}") == [ids["survey_cancelled"], ids["survey_failed"]]
    assert listed(f"?kind=survey&status=failed&environment_id={first}") == [ids["survey_failed"]]
    assert listed(f"?kind=survey&environment_id={first}&limit=1") == [ids["survey_cancelled"]]
    assert listed("?limit=2") == [ids["survey_cancelled"], ids["survey_queued"]]
    assert listed("?status=running") == []
    assert listed(f"?environment_id={second + 100}") == []

    done = client.get("/jobs?kind=train_classifier").json()[0]
    assert done["result"] == training and done["kind"] == "train_classifier"


def test_listing_refuses_what_it_cannot_filter_by(client: TestClient) -> None:
    for query in ("kind=nope", "status=done", "limit=0", "limit=501", "environment_id=0", "environment_id=x"):
        reply = client.get(f"/jobs?{query}")
        assert reply.status_code == 422, (query, reply.text)
        body = reply.json()
        assert body["detail"] and body["errors"][0]["loc"][0] == "query", body
    assert client.get("/jobs?limit=500").status_code == 200


def test_the_default_limit_is_50(client: TestClient) -> None:
    for minute in range(53):
        _store_job(client, JobKind.SURVEY, JobStatus.FAILED, None, minute)
    assert len(client.get("/jobs").json()) == 50
    assert len(client.get("/jobs?limit=500").json()) == 53
