"""DELETE /classifiers/{id}: a classifier nothing uses goes, with its arrays; the default
one, one an environment detects with and one a waiting job will load stay, and the
refusal says why and names the environments."""

from __future__ import annotations

import cv2
import numpy as np
from fastapi.testclient import TestClient
from pydantic import BaseModel
from sqlalchemy import func, select

from app.core.detection import load_default_classifier
from app.models import ClassifierArray
from app.services import classifiers
from app.services.jobs import JobKind, store
from app.sim import scenes


def _add_classifier(client: TestClient, name: str) -> int:
    """A stored classifier of source "trained" (the shipped arrays: no training job needed)."""
    with client.app.state.sessionmaker() as session:
        row = classifiers.add(session, load_default_classifier(), name, "trained")
        session.commit()
        return row.id


def _arrays(client: TestClient, classifier_id: int) -> int:
    with client.app.state.sessionmaker() as session:
        query = select(func.count()).select_from(ClassifierArray).where(ClassifierArray.classifier_id == classifier_id)
        return int(session.scalar(query) or 0)


def test_an_unused_classifier_is_deleted_with_its_arrays(client: TestClient) -> None:
    site = _add_classifier(client, "site A")
    assert _arrays(client, site) > 0
    reply = client.delete(f"/classifiers/{site}")
    assert reply.status_code == 204 and reply.content == b""
    assert client.get(f"/classifiers/{site}").status_code == 404
    assert [c["name"] for c in client.get("/classifiers").json()] == ["default"]
    assert _arrays(client, site) == 0
    assert client.delete(f"/classifiers/{site}").status_code == 404
    assert client.delete("/classifiers/999").status_code == 404


def test_a_deleted_classifier_is_not_used_again_to_detect(client: TestClient) -> None:
    site = _add_classifier(client, "site A")
    image, _ = scenes.scenario_frame("clean", np.random.default_rng(11))
    png = cv2.imencode(".png", image)[1].tobytes()
    detect = f"/detect?classifier_id={site}"
    assert client.post(detect, content=png, headers={"content-type": "image/png"}).status_code == 200
    assert client.delete(f"/classifiers/{site}").status_code == 204
    # The image worker holds the detector it built: the classifier is looked up all the same.
    reply = client.post(detect, content=png, headers={"content-type": "image/png"})
    assert reply.status_code == 404 and f"classifier {site}" in reply.json()["detail"]


def test_the_default_classifier_is_not_deleted(client: TestClient) -> None:
    default = client.get("/classifiers").json()[0]
    assert default["is_default"]
    reply = client.delete(f"/classifiers/{default['id']}")
    assert reply.status_code == 409 and "default" in reply.json()["detail"]
    assert client.get(f"/classifiers/{default['id']}").status_code == 200


def test_a_classifier_an_environment_uses_is_not_deleted_and_the_refusal_names_them(client: TestClient) -> None:
    site = _add_classifier(client, "site A")
    studio = client.post("/environments", json={"name": "studio", "marker_size_m": 0.2,
                                                "classifier_id": site}).json()
    lab = client.post("/environments", json={"name": "lab", "marker_size_m": 0.2, "classifier_id": site}).json()
    client.post("/environments", json={"name": "hall", "marker_size_m": 0.2})  # the default classifier's
    reply = client.delete(f"/classifiers/{site}")
    assert reply.status_code == 409
    detail = reply.json()["detail"]
    assert f"{studio['id']} ('studio')" in detail and f"{lab['id']} ('lab')" in detail and "hall" not in detail
    assert client.get(f"/classifiers/{site}").status_code == 200

    # Once no environment uses it, it goes.
    for environment in (studio, lab):
        changed = client.patch(f"/environments/{environment['id']}", json={"classifier_id": None})
        assert changed.status_code == 200 and changed.json()["classifier_id"] is None
    assert client.delete(f"/classifiers/{site}").status_code == 204


def test_a_classifier_a_waiting_job_will_load_is_not_deleted(client: TestClient) -> None:
    class TrainingLike(BaseModel):
        base_classifier_id: int

    site = _add_classifier(client, "site A")
    with client.app.state.sessionmaker() as session:
        job = store.create(session, JobKind.TRAIN_CLASSIFIER.value, TrainingLike(base_classifier_id=site))
    reply = client.delete(f"/classifiers/{site}")
    assert reply.status_code == 409 and job.id in reply.json()["detail"]
    with client.app.state.sessionmaker() as session:
        store.cancel(session, job.id)
    assert client.delete(f"/classifiers/{site}").status_code == 204
