"""No single call loses a map: every change keeps the map it replaces, any earlier map can
be restored, and an alignment that cannot be right is refused unless forced."""

from __future__ import annotations

import numpy as np
from fastapi.testclient import TestClient

from tests.conftest import example_map


def _environment(client: TestClient) -> int:
    return client.post("/environments", json={"name": "room", "marker_size_m": 0.1}).json()["id"]


def _versions(client: TestClient, env: int) -> list[dict]:
    reply = client.get(f"/environments/{env}/map/versions")
    assert reply.status_code == 200, reply.text
    return reply.json()


def test_every_change_keeps_the_map_it_replaces_and_any_can_be_restored(client: TestClient) -> None:
    env = _environment(client)
    assert _versions(client, env) == []
    nothing = client.post(f"/environments/{env}/map/restore", json={})
    assert nothing.status_code == 409 and "no earlier map" in nothing.json()["detail"]

    first, second = example_map(3), example_map(2)
    client.put(f"/environments/{env}/map", json=first).raise_for_status()
    assert _versions(client, env) == []  # nothing was replaced
    client.put(f"/environments/{env}/map", json=second).raise_for_status()
    [imported] = _versions(client, env)
    assert imported["replaced_by"] == "import" and imported["n_targets"] == 3 and imported["frame"] == "survey"

    aligned = client.post(f"/environments/{env}/alignment", json={"origin_target_id": 0})
    assert aligned.status_code == 200
    by_alignment = _versions(client, env)[0]
    assert by_alignment["replaced_by"] == "alignment" and by_alignment["n_targets"] == 2

    # The last change undone: the map the alignment replaced is back, and the aligned one kept.
    before = client.get(f"/environments/{env}").json()["updated_at"]
    restored = client.post(f"/environments/{env}/map/restore", json={})
    assert restored.status_code == 200 and restored.json() == client.get(f"/environments/{env}/map").json()
    assert restored.json()["frame"] == "survey" and len(restored.json()["targets"]) == 2
    assert _versions(client, env)[0]["replaced_by"] == "restore" and _versions(client, env)[0]["frame"] == "world"
    assert client.get(f"/environments/{env}").json()["updated_at"] > before

    # Any version by its number; an unknown one is a 404 and changes nothing.
    back = client.post(f"/environments/{env}/map/restore", json={"version": imported["version"]})
    assert back.status_code == 200 and len(back.json()["targets"]) == 3
    assert client.post(f"/environments/{env}/map/restore", json={"version": 99999}).status_code == 404
    assert len(client.get(f"/environments/{env}/map").json()["targets"]) == 3
    assert client.post(f"/environments/{env}/map/restore", json={"version": 0}).status_code == 422

    client.delete(f"/environments/{env}").raise_for_status()
    assert client.get(f"/environments/{env}/map/versions").status_code == 404


def test_an_environment_keeps_its_last_twenty_maps(client: TestClient) -> None:
    env = _environment(client)
    for n in range(1, 24):
        client.put(f"/environments/{env}/map", json=example_map(n)).raise_for_status()
    versions = _versions(client, env)
    assert [v["n_targets"] for v in versions] == list(range(22, 2, -1))  # the newest first


def _room_map() -> tuple[dict, dict[int, np.ndarray]]:
    """A surveyed-looking map (its own frame) and the true world positions of its discs."""
    document = example_map(4)
    rng = np.random.default_rng(0)
    angle = 0.7
    R = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    t = np.array([2.0, 1.0, 0.5])
    world = {}
    for target in document["targets"]:
        target["discs"] = (np.asarray(target["discs"]) + [0.0, target["id"] * 0.7, target["id"] * 0.3]).tolist()
        world[target["id"]] = np.asarray(target["discs"]) @ R.T + t + rng.normal(0, 0.001, (4, 3))
    return document, world


def _points(world: dict[int, np.ndarray], scale: float = 1.0) -> list[dict]:
    return [{"target_id": i, "disc": d, "world": (scale * world[i][d]).tolist()} for i, d in
            ((0, 0), (1, 1), (2, 2), (3, 3), (3, 0))]


def test_a_rigid_fit_to_good_points_is_stored_with_its_residuals(client: TestClient) -> None:
    env = _environment(client)
    document, world = _room_map()
    client.put(f"/environments/{env}/map", json=document).raise_for_status()
    reply = client.post(f"/environments/{env}/alignment", json={"points": _points(world)})
    assert reply.status_code == 200, reply.text
    result = reply.json()
    assert result["scale"] == 1.0 and result["rms_m"] < 0.003 and len(result["residuals"]) == 5


def test_an_alignment_that_cannot_be_right_is_refused_and_changes_nothing(client: TestClient) -> None:
    env = _environment(client)
    document, world = _room_map()
    stored = client.put(f"/environments/{env}/map", json=document).json()

    wrong = _points(world)
    wrong[2]["world"][0] += 0.25  # a typo in one coordinate
    refused = client.post(f"/environments/{env}/alignment", json={"points": wrong})
    assert refused.status_code == 422
    # The worst point first: the one with the typo.
    assert "beyond their tolerance: card 2 disc 2 off by 0.1" in refused.json()["detail"]
    assert "force=true" in refused.json()["detail"]
    # A map a quarter of its size: the scale is refused even when asked for.
    shrunk = client.post(f"/environments/{env}/alignment", json={"points": _points(world, 0.28), "allow_scale": True})
    assert shrunk.status_code == 422 and "scale 0.280" in shrunk.json()["detail"]
    assert client.get(f"/environments/{env}/map").json() == stored and _versions(client, env) == []

    # Forced, it is stored, and the map it replaced can be restored.
    forced = client.post(f"/environments/{env}/alignment", json={"points": wrong, "force": True})
    assert forced.status_code == 200 and forced.json()["map"]["frame"] == "world"
    assert max(r["residual_m"] for r in forced.json()["residuals"]) > 0.1
    assert client.post(f"/environments/{env}/map/restore", json={}).json() == stored
