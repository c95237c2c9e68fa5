"""An environment's ``updated_at`` follows its map too, and an environment without a map
is answered alike on every route that needs one."""

from __future__ import annotations

from datetime import datetime

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.conftest import example_map, wait_for_job
from tests.services.job_handlers import StoreMapParams

NO_MAP = "environment {id} has no map yet: run a survey or PUT one"


def _create(client: TestClient) -> int:
    reply = client.post("/environments", json={"name": "studio", "marker_size_m": 0.2})
    assert reply.status_code == 201, reply.text
    return int(reply.json()["id"])


def _updated_at(client: TestClient, environment_id: int) -> datetime:
    return datetime.fromisoformat(client.get(f"/environments/{environment_id}").json()["updated_at"])


def test_updated_at_moves_with_every_change_of_the_environment_or_its_map(client: TestClient) -> None:
    env = _create(client)
    times = [_updated_at(client, env)]

    assert client.put(f"/environments/{env}/map", json=example_map(3)).status_code == 200
    times.append(_updated_at(client, env))
    assert client.put(f"/environments/{env}/map", json=example_map(2)).status_code == 200  # replaced
    times.append(_updated_at(client, env))
    aligned = client.post(f"/environments/{env}/alignment", json={"origin_target_id": 0})
    assert aligned.status_code == 200, aligned.text
    times.append(_updated_at(client, env))
    assert client.patch(f"/environments/{env}", json={"name": "studio B"}).status_code == 200
    times.append(_updated_at(client, env))
    assert all(a < b for a, b in zip(times, times[1:])), times
    # The list shows the same time as the environment itself.
    assert datetime.fromisoformat(client.get("/environments").json()[0]["updated_at"]) == times[-1]


def test_updated_at_stays_when_a_change_is_refused(client: TestClient) -> None:
    env = _create(client)
    assert client.put(f"/environments/{env}/map", json=example_map(2)).status_code == 200
    before = _updated_at(client, env)
    outside = example_map(1)
    outside["targets"][0]["id"] = 10**6  # outside the marker family: refused whole
    assert client.put(f"/environments/{env}/map", json=outside).status_code == 422
    assert client.post(f"/environments/{env}/alignment", json={"origin_target_id": 9}).status_code == 422
    assert client.patch(f"/environments/{env}", json={"classifier_id": 42}).status_code == 422
    assert _updated_at(client, env) == before


def test_updated_at_moves_when_a_job_stores_the_map(client: TestClient) -> None:
    # A survey stores its map in its worker process, in the transaction that marks the
    # job succeeded (`environments.stage_map`); this job does only that last step.
    env = _create(client)
    before = _updated_at(client, env)
    with client.app.state.sessionmaker() as session:
        job = client.app.state.jobs.submit(session, "store_map", StoreMapParams(document=example_map(2)),
                                           environment_id=env)
    assert wait_for_job(client, job.id, timeout=60, poll=0.1)["status"] == "succeeded"
    assert client.get(f"/environments/{env}/map").json()["targets"] == example_map(2)["targets"]
    assert _updated_at(client, env) > before


def _png() -> bytes:
    return cv2.imencode(".png", np.full((48, 64), 200, np.uint8))[1].tobytes()


@pytest.mark.parametrize("method,path,body", [
    ("GET", "/environments/{id}/map", None),
    ("POST", "/environments/{id}/alignment", {"origin_target_id": 0}),
    ("POST", "/environments/{id}/locate", "image"),
])
def test_no_map_is_409_with_the_same_message_on_every_route(client: TestClient, method: str, path: str,
                                                            body: object) -> None:
    env = _create(client)
    if body == "image":
        reply = client.request(method, path.format(id=env), content=_png(), headers={"content-type": "image/png"})
    else:
        reply = client.request(method, path.format(id=env), json=body)
    assert reply.status_code == 409, reply.text
    assert reply.json() == {"detail": NO_MAP.format(id=env)}
    # An unknown environment stays a 404: the id itself is wrong.
    if body == "image":
        unknown = client.request(method, path.format(id=999), content=_png(), headers={"content-type": "image/png"})
    else:
        unknown = client.request(method, path.format(id=999), json=body)
    assert unknown.status_code == 404 and unknown.json() == {"detail": "environment 999 not found"}


def test_track_refuses_an_environment_without_a_map_with_the_same_message(client: TestClient) -> None:
    env = _create(client)
    with client.websocket_connect(f"/track?environment_id={env}") as ws:
        message = ws.receive_json()
    assert message["code"] == "no_map" and message["message"] == NO_MAP.format(id=env)
