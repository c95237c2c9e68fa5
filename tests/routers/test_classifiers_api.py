"""Classifiers as data: the default installed at first start and loaded from the
database, a training job end to end, and an environment choosing its classifier."""

from __future__ import annotations

import cv2
import numpy as np
from fastapi.testclient import TestClient

from app.sim import scenes
from app.core.detection.candidates import load_default_classifier
from app.main import create_app
from app.services import classifiers
from app.settings import Settings
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
