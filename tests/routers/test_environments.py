"""Environments CRUD and map import/export through the HTTP API; an environment's
``updated_at`` follows its map too, and an environment without a map is answered alike
on every route that needs one."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from datetime import datetime

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import text

from app.main import create_app
from app.schemas import MAX_LISTED_ERRORS
from app.settings import Settings
from tests.conftest import example_map, wait_for_job
from tests.services.job_handlers import StoreMapParams


def _create(client: TestClient, name: str = "studio", size: float = 0.15) -> dict:
    reply = client.post("/environments", json={"name": name, "marker_size_m": size})
    assert reply.status_code == 201, reply.text
    assert reply.headers["location"] == f"/environments/{reply.json()['id']}"
    return reply.json()


def test_crud_round_trip(client: TestClient) -> None:
    env = _create(client)
    assert env["marker_family"] == "fido3x3" and env["has_map"] is False
    assert client.get("/environments").json() == [env]
    patched = client.patch(f"/environments/{env['id']}", json={"name": "stage B", "marker_size_m": 0.2})
    assert patched.status_code == 200
    assert patched.json()["name"] == "stage B" and patched.json()["marker_size_m"] == 0.2
    assert client.get(f"/environments/{env['id']}").json()["name"] == "stage B"
    assert client.delete(f"/environments/{env['id']}").status_code == 204
    assert client.get(f"/environments/{env['id']}").status_code == 404
    assert client.get("/environments").json() == []


@pytest.mark.parametrize(
    "method,path",
    [("get", "/environments/999"), ("patch", "/environments/999"), ("delete", "/environments/999"),
     ("get", "/environments/999/map"), ("put", "/environments/999/map")],
)
def test_unknown_environment_is_404_with_message(client: TestClient, method: str, path: str) -> None:
    kwargs = {"json": {"name": "x"}} if method == "patch" else {}
    if method == "put":
        kwargs = {"json": example_map()}
    reply = getattr(client, method)(path, **kwargs)
    assert reply.status_code == 404
    assert "environment 999 not found" in reply.json()["detail"]


@pytest.mark.parametrize(
    "body,field",
    [
        ({"marker_size_m": 0.15}, "name"),
        ({"name": "a", "marker_size_m": -1}, "marker_size_m"),
        ({"name": "a", "marker_size_m": "big"}, "marker_size_m"),
        ({"name": "a", "marker_size_m": 0.1, "marker_family": "qr"}, "marker_family"),
        ({"name": "", "marker_size_m": 0.1}, "name"),
        ({"name": "a", "marker_size_m": 0.1, "colour": "red"}, "colour"),
    ],
)
def test_malformed_environment_is_422_naming_the_field(client: TestClient, body: dict, field: str) -> None:
    reply = client.post("/environments", json=body)
    assert reply.status_code == 422
    body = reply.json()
    errors = body["errors"]
    assert any(field in error["loc"] for error in errors), errors
    assert all(error["msg"] for error in errors)
    assert field in body["detail"]  # one readable string, like every other error
    assert client.get("/environments").json() == []


def test_patch_refuses_null_and_unknown_classifier(client: TestClient) -> None:
    env = _create(client)
    assert client.patch(f"/environments/{env['id']}", json={"name": None}).status_code == 422
    reply = client.patch(f"/environments/{env['id']}", json={"classifier_id": 42})
    assert reply.status_code == 422 and "classifier" in reply.json()["detail"]
    assert client.get(f"/environments/{env['id']}").json() == env


def test_map_import_and_export(client: TestClient) -> None:
    env = _create(client)
    assert client.get(f"/environments/{env['id']}/map").status_code == 409  # no map yet
    document = example_map(3)
    reply = client.put(f"/environments/{env['id']}/map", json=document)
    assert reply.status_code == 200, reply.text
    assert client.get(f"/environments/{env['id']}/map").json() == document
    assert client.get(f"/environments/{env['id']}").json()["has_map"] is True


def _broken_maps() -> list[tuple[str, dict]]:
    cases: list[tuple[str, dict]] = []

    def case(name: str, mutate: Callable[[dict], object]) -> None:
        document = example_map(2)
        mutate(document)
        cases.append((name, document))

    case("nan disc", lambda d: d["targets"][0]["discs"][1].__setitem__(2, float("nan")))
    case("inf focal", lambda d: d["camera"]["K"][0].__setitem__(0, float("inf")))
    case("three discs", lambda d: d["targets"][0]["discs"].pop())
    case("2d disc", lambda d: d["targets"][1]["discs"].__setitem__(0, [1.0, 2.0]))
    case("dist of 4", lambda d: d["camera"]["dist"].pop())
    case("K not 3x3", lambda d: d["camera"].__setitem__("K", [[1, 0], [0, 1]]))
    case("K bottom row", lambda d: d["camera"]["K"].__setitem__(2, [0, 0, 2]))
    case("negative std", lambda d: d["targets"][0]["std_m"].__setitem__(0, -0.1))
    case("duplicate ids", lambda d: d["targets"][1].__setitem__("id", 0))
    case("bad frame", lambda d: d.__setitem__("frame", "camera"))
    case("id outside family", lambda d: d["targets"][1].__setitem__("id", 60))
    case("zero width", lambda d: d["camera"].__setitem__("width", 0))
    case("huge focal", lambda d: d["camera"]["K"][0].__setitem__(0, 1e300))
    case("tiny focal", lambda d: d["camera"]["K"][1].__setitem__(1, 1e-300))
    case("huge distortion", lambda d: d["camera"]["dist"].__setitem__(0, 1e300))
    case("far principal point", lambda d: d["camera"]["K"][0].__setitem__(2, 1e12))
    case("far disc", lambda d: d["targets"][0]["discs"][2].__setitem__(0, 1e307))
    return cases


@pytest.mark.parametrize("name,document", _broken_maps(), ids=[n for n, _ in _broken_maps()])
def test_bad_map_is_refused_whole_and_old_map_stays(client: TestClient, name: str, document: dict) -> None:
    env = _create(client)
    good = example_map(1)
    assert client.put(f"/environments/{env['id']}/map", json=good).status_code == 200
    # json.dumps writes NaN/Infinity tokens, as a careless client would.
    reply = client.put(
        f"/environments/{env['id']}/map",
        content=json.dumps(document),
        headers={"content-type": "application/json"},
    )
    assert reply.status_code == 422, (name, reply.text)
    assert reply.json()["detail"]
    assert client.get(f"/environments/{env['id']}/map").json() == good


def test_malformed_json_body_is_422(client: TestClient) -> None:
    env = _create(client)
    reply = client.put(
        f"/environments/{env['id']}/map", content=b"{not json", headers={"content-type": "application/json"}
    )
    assert reply.status_code == 422


def test_a_json_body_over_its_limit_is_413_before_it_is_read(client: TestClient) -> None:
    # A map of every card of the largest family is about 0.1 MiB; 20 MiB of one once held
    # every other client for seconds while it was parsed.
    env = _create(client)
    good = example_map()
    body = json.dumps({**good, "targets": good["targets"] * 20_000}).encode()
    assert len(body) > 2 * 1024 * 1024
    reply = client.put(f"/environments/{env['id']}/map", content=body, headers={"content-type": "application/json"})
    assert reply.status_code == 413 and "limit" in reply.json()["detail"]


def test_an_object_of_too_many_keys_is_refused_with_a_short_reply(client: TestClient) -> None:
    env = _create(client)
    body = {**example_map(), **{f"e{i}": 0 for i in range(50_000)}}
    reply = client.put(f"/environments/{env['id']}/map", json=body)
    assert reply.status_code == 422
    assert "keys" in reply.json()["detail"] and len(reply.content) < 2000


def test_many_errors_are_counted_not_each_listed(client: TestClient) -> None:
    env = _create(client)
    good = example_map()
    wrong = {**good, "targets": [{"id": "x", "discs": "y", "std_m": "z"}] * 300}
    reply = client.put(f"/environments/{env['id']}/map", json=wrong)
    assert reply.status_code == 422
    detail, errors = reply.json()["detail"], reply.json()["errors"]
    assert len(errors) == MAX_LISTED_ERRORS and len(reply.content) < 5000
    counted = int(re.search(r"and (\d+) more errors", detail).group(1))  # type: ignore[union-attr]
    assert counted > 300 - MAX_LISTED_ERRORS  # each of the 300 targets is wrong at least once


def test_environments_and_maps_survive_restart(settings: Settings) -> None:
    document = example_map(4)
    with TestClient(create_app(settings)) as first:
        env = _create(first, name="warehouse", size=0.3)
        assert first.put(f"/environments/{env['id']}/map", json=document).status_code == 200
    with TestClient(create_app(Settings(data_dir=settings.data_dir))) as second:
        again = second.get(f"/environments/{env['id']}").json()
        assert again["name"] == "warehouse" and again["marker_size_m"] == 0.3 and again["has_map"]
        assert second.get(f"/environments/{env['id']}/map").json() == document


def test_deleting_environment_deletes_its_map_and_ids_are_not_reused(client: TestClient) -> None:
    env = _create(client)
    client.put(f"/environments/{env['id']}/map", json=example_map())
    assert client.delete(f"/environments/{env['id']}").status_code == 204
    with client.app.state.engine.connect() as connection:
        assert connection.execute(text("SELECT count(*) FROM maps")).scalar_one() == 0
    # A client holding the old id must not silently reach a new environment.
    assert _create(client, name="other")["id"] != env["id"]


@pytest.mark.parametrize("path_id", ["1%20", "%201", "+1", "01", "1.0", "0", "-1", "1e0", "%D9%A1"])
def test_an_id_in_a_path_is_plain_digits_or_nothing_is_touched(client: TestClient, path_id: str) -> None:
    # int("1 ") is 1: without a strict id, DELETE /environments/1%20 deleted environment 1.
    env = client.post("/environments", json={"name": "kept", "marker_size_m": 0.2}).json()
    assert env["id"] == 1
    for method in ("GET", "DELETE"):
        reply = client.request(method, f"/environments/{path_id}")
        assert reply.status_code == 422, (method, path_id, reply.status_code)
        assert "environment_id" in reply.text
    assert client.get("/environments/1").json()["name"] == "kept"


@pytest.mark.parametrize("name", ["a\x00b", "line\nbreak", "esc\x1b[31mred", "tab\there", "del\x7f"])
def test_names_with_control_characters_are_refused(client: TestClient, name: str) -> None:
    reply = client.post("/environments", json={"name": name, "marker_size_m": 0.2})
    assert reply.status_code == 422 and "control characters" in reply.text
    assert client.get("/environments").json() == []
    ok = client.post("/environments", json={"name": "Studio B — grün, 東京", "marker_size_m": 0.2})
    assert ok.status_code == 201
    assert client.patch(f"/environments/{ok.json()['id']}", json={"name": name}).status_code == 422
    assert client.get(f"/environments/{ok.json()['id']}").json()["name"] == "Studio B — grün, 東京"


NO_MAP = "environment {id} has no map yet: run a survey or PUT one"


def _create_id(client: TestClient) -> int:
    reply = client.post("/environments", json={"name": "studio", "marker_size_m": 0.2})
    assert reply.status_code == 201, reply.text
    return int(reply.json()["id"])


def _updated_at(client: TestClient, environment_id: int) -> datetime:
    return datetime.fromisoformat(client.get(f"/environments/{environment_id}").json()["updated_at"])


def test_updated_at_moves_with_every_change_of_the_environment_or_its_map(client: TestClient) -> None:
    env = _create_id(client)
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
    env = _create_id(client)
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
    env = _create_id(client)
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
    env = _create_id(client)
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
    env = _create_id(client)
    with client.websocket_connect(f"/track?environment_id={env}") as ws:
        message = ws.receive_json()
    assert message["code"] == "no_map" and message["message"] == NO_MAP.format(id=env)
