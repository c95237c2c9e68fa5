"""Classifiers as data: the default installed at first start and loaded from the
database, a training job end to end, an environment choosing its classifier; and
DELETE /classifiers/{id}: a classifier nothing uses goes, with its arrays, while the
default one, one an environment detects with and one a waiting job will load stay, the
refusal saying why and naming the environments."""

from __future__ import annotations

import cv2
import numpy as np
from fastapi.testclient import TestClient
from pydantic import BaseModel
from sqlalchemy import func, select

from app.core.detection import load_default_classifier
from app.main import create_app
from app.models import ClassifierArray
from app.services import classifiers
from app.services.jobs import JobKind, store
from app.settings import Settings
from app.sim import scenes
from tests.conftest import wait_for_job


def _png(image: np.ndarray) -> bytes:
    return cv2.imencode(".png", image)[1].tobytes()


def test_default_classifier_is_installed_once_and_loads_from_the_database(settings: Settings) -> None:
    with TestClient(create_app(settings)) as client:
        listed = client.get("/classifiers").json()
        assert [c["is_default"] for c in listed] == [True]
        default = listed[0]
        assert default["source"] == "builtin" and default["training_stats"]
        assert client.get(f"/classifiers/{default['id']}").json() == default
        with client.app.state.sessionmaker() as session:
            stored = classifiers.load(session, default["id"])
        shipped = load_default_classifier()
        for name, array in shipped.to_arrays().items():
            np.testing.assert_array_equal(stored.to_arrays()[name], array)
    with TestClient(create_app(Settings(data_dir=settings.data_dir))) as again:
        assert [c["id"] for c in again.get("/classifiers").json()] == [default["id"]]
        assert again.get("/classifiers/999").status_code == 404


def test_training_job_end_to_end_and_environment_uses_it(client: TestClient) -> None:
    rng = np.random.default_rng(5)
    frames = [scenes.scenario_frame(name, rng) for name in ("default", "dark", "blur")]
    files = [("images", (f"f{i}.png", _png(image), "image/png")) for i, (image, _) in enumerate(frames)]
    reply = client.post("/classifiers", files=files, data={"name": "site A"})
    assert reply.status_code == 202, reply.text
    job = reply.json()
    assert reply.headers["location"] == f"/jobs/{job['id']}" and job["kind"] == "train_classifier"
    body = wait_for_job(client, job["id"], timeout=300)
    assert body["status"] == "succeeded", body
    new_id = body["result"]["classifier_id"]
    trained = client.get(f"/classifiers/{new_id}").json()
    assert trained["source"] == "trained" and trained["name"] == "site A"
    assert trained["training_job_id"] == job["id"]

    image, truth = frames[0]
    detected = client.post(f"/detect?classifier_id={new_id}", content=_png(image),
                           headers={"content-type": "image/png"}).json()
    assert {t["id"] for t in detected["targets"]} >= {t.id for t in truth.visible_targets()}

    env = client.post("/environments", json={"name": "site A", "marker_size_m": 0.2,
                                             "classifier_id": new_id}).json()
    assert env["classifier_id"] == new_id


def test_bad_training_upload_stores_nothing(client: TestClient, settings: Settings) -> None:
    image, _ = scenes.scenario_frame("clean", np.random.default_rng(1))
    files = [("images", ("a.png", _png(image), "image/png")), ("images", ("b.txt", b"hello", "text/plain"))]
    reply = client.post("/classifiers", files=files, data={"name": "broken"})
    assert reply.status_code == 415 and "images[1]" in reply.json()["detail"]
    reply = client.post("/classifiers", files=files[:1], data={"name": "x", "base_classifier_id": "999"})
    assert reply.status_code == 404
    assert client.post("/classifiers", data={"name": "none"}).status_code == 422
    uploads = settings.data_dir / "uploads"
    assert not uploads.exists() or not any(uploads.iterdir())
    assert len(client.get("/classifiers").json()) == 1


def test_training_on_images_without_targets_fails_with_a_clear_message(client: TestClient) -> None:
    image, _ = scenes.scenario_frame("empty", np.random.default_rng(3))
    reply = client.post("/classifiers", files=[("images", ("e.png", _png(image), "image/png"))],
                        data={"name": "nothing"})
    assert reply.status_code == 202
    job_id = reply.json()["id"]
    body = wait_for_job(client, job_id, timeout=120)
    assert body["status"] == "failed" and "no target" in body["error"]
    assert [c["source"] for c in client.get("/classifiers").json()] == ["builtin"]


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
