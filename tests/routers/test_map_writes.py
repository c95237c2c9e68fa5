"""Map writes are serialised and conditional: of many writes at once none is lost (each
that got 2xx is the map or a stored version, kept once), a write naming a revision the
map has left (``If-Match``) is refused with 412 and changes nothing, and an alignment
never replaces a newer map with one computed on an older."""

from __future__ import annotations

import threading
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient

from tests.conftest import example_map, running_server

#: PUTs sent at once.
CONCURRENT_PUTS = 20


@dataclass(frozen=True)
class LostWrites:
    """What became of `CONCURRENT_PUTS` maps PUT at once (each with its own number of cards)."""

    accepted: int
    #: Accepted maps that are neither the current map nor a stored version.
    lost: list[int]
    #: Maps stored as a version more than once, and how many times.
    kept_twice: dict[int, int]


def put_at_once(url: str) -> LostWrites:
    """PUT `CONCURRENT_PUTS` different maps at once to a new environment that has a map
    of one card, and find each that got 2xx again."""
    with httpx.Client(base_url=url, timeout=120) as http:
        env = http.post("/environments", json={"name": "contested", "marker_size_m": 0.1}).json()["id"]
        http.put(f"/environments/{env}/map", json=example_map(1)).raise_for_status()
    start = threading.Barrier(CONCURRENT_PUTS)

    def put(n_targets: int) -> int:
        with httpx.Client(base_url=url, timeout=120) as http:
            http.get("/livez")  # connected before the barrier: the PUTs leave together
            start.wait(timeout=60)
            return http.put(f"/environments/{env}/map", json=example_map(n_targets)).status_code

    sizes = list(range(2, 2 + CONCURRENT_PUTS))
    with ThreadPoolExecutor(CONCURRENT_PUTS) as pool:
        statuses = dict(zip(sizes, pool.map(put, sizes), strict=True))
    with httpx.Client(base_url=url, timeout=120) as http:
        current = len(http.get(f"/environments/{env}/map").json()["targets"])
        kept = Counter(v["n_targets"] for v in http.get(f"/environments/{env}/map/versions").json())
    accepted = [n for n, status in statuses.items() if 200 <= status < 300]
    return LostWrites(accepted=len(accepted), lost=[n for n in accepted if n != current and n not in kept],
                      kept_twice={n: times for n, times in sorted(kept.items()) if times > 1})


def test_twenty_puts_at_once_lose_nothing(tmp_path: Path) -> None:
    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        outcome = put_at_once(server.url)
    print(f"{CONCURRENT_PUTS} concurrent PUTs: {outcome}")
    assert outcome.accepted == CONCURRENT_PUTS
    assert outcome.lost == [] and outcome.kept_twice == {}


def _environment(client: TestClient) -> int:
    return client.post("/environments", json={"name": "room", "marker_size_m": 0.1}).json()["id"]


def _revision(reply: httpx.Response) -> int:
    """The map revision a reply's ETag names (strong, quoted)."""
    tag = reply.headers.get("ETag", "")
    assert tag.startswith('"') and tag.endswith('"') and tag[1:-1].isdigit(), reply.headers
    return int(tag[1:-1])


def test_a_stale_if_match_is_refused_and_changes_nothing(client: TestClient) -> None:
    env = _environment(client)
    path = f"/environments/{env}/map"
    # No map yet: no If-Match matches it, not even *.
    assert client.put(path, json=example_map(1), headers={"If-Match": "*"}).status_code == 412
    first = client.put(path, json=example_map(1))
    assert first.status_code == 200 and _revision(client.get(path)) == _revision(first)

    second = client.put(path, json=example_map(2), headers={"If-Match": first.headers["ETag"]})
    assert second.status_code == 200 and _revision(second) > _revision(first)
    assert _revision(client.get(path)) == _revision(second)
    versions = client.get(f"{path}/versions").json()

    # A write made from the first map: refused, with why, and nothing changes.
    for stale in (first.headers["ETag"], f'W/{second.headers["ETag"]}', "7x", '"999999"'):
        refused = client.put(path, json=example_map(3), headers={"If-Match": stale})
        assert refused.status_code == 412, (stale, refused.text)
        assert "changed" in refused.json()["detail"] and second.headers["ETag"] in refused.json()["detail"]
    for stale_write in (client.post(f"/environments/{env}/alignment", json={"origin_target_id": 0},
                                    headers={"If-Match": first.headers["ETag"]}),
                        client.post(f"{path}/restore", json={}, headers={"If-Match": first.headers["ETag"]})):
        assert stale_write.status_code == 412 and "changed" in stale_write.json()["detail"]
    now = client.get(path)
    assert len(now.json()["targets"]) == 2 and now.json()["frame"] == "survey"
    assert _revision(now) == _revision(second) and client.get(f"{path}/versions").json() == versions

    # Current tags (also * and a list naming it) are met, and each write moves the ETag on.
    aligned = client.post(f"/environments/{env}/alignment", json={"origin_target_id": 0},
                          headers={"If-Match": second.headers["ETag"]})
    assert aligned.status_code == 200 and _revision(aligned) > _revision(second)
    assert aligned.json()["map"] == client.get(path).json()
    restored = client.post(f"{path}/restore", json={}, headers={"If-Match": f'"1", {aligned.headers["ETag"]}'})
    assert restored.status_code == 200 and _revision(restored) > _revision(aligned)
    assert restored.json()["frame"] == "survey"
    anything = client.put(path, json=example_map(4), headers={"If-Match": "*"})
    assert anything.status_code == 200 and _revision(anything) > _revision(restored)
    assert client.put(path, json=example_map(5)).status_code == 200  # no If-Match: written all the same
    # Each version says the revision it had, once.
    kept = [v["revision"] for v in client.get(f"{path}/versions").json()]
    assert kept == sorted(set(kept), reverse=True) and kept[0] == _revision(anything)


def test_an_alignment_never_replaces_a_newer_map_with_one_fitted_to_an_older(
        client: TestClient, monkeypatch: pytest.MonkeyPatch) -> None:
    """A PUT lands while an alignment is fitting: the alignment holds the map's write lock,
    so the PUT waits for it and replaces the aligned map (the other way round, the
    alignment would store its fit of the older map over the newer one)."""
    from app.schemas import MapDocument
    from app.services import alignments, environments

    env = _environment(client)
    older, newer = example_map(3), example_map(2)
    client.put(f"/environments/{env}/map", json=older).raise_for_status()
    put_done = threading.Event()
    putting: list[threading.Thread] = []

    def put_newer() -> None:
        with client.app.state.sessionmaker() as session:
            environments.put_map(session, env, MapDocument.model_validate(newer))
        put_done.set()

    fit = alignments._transform

    def fit_while_a_put_lands(*args: object) -> object:
        putting.append(threading.Thread(target=put_newer))
        putting[-1].start()
        put_done.wait(timeout=2)  # it lands now unless the alignment holds the lock
        return fit(*args)

    monkeypatch.setattr(alignments, "_transform", fit_while_a_put_lands)
    aligned = client.post(f"/environments/{env}/alignment", json={"origin_target_id": 0})
    putting[0].join(timeout=60)
    assert aligned.status_code == 200 and put_done.is_set()

    current = client.get(f"/environments/{env}/map").json()
    versions = client.get(f"/environments/{env}/map/versions").json()
    # The map the alignment replaced is the map it fitted (3 cards), not the newer one...
    [by_alignment] = [v for v in versions if v["replaced_by"] == "alignment"]
    assert by_alignment["n_targets"] == len(aligned.json()["map"]["targets"]) == 3
    # ...and the newer map, stored after it, is the map.
    assert current["targets"] == newer["targets"] and current["frame"] == "survey"


def test_the_client_writes_only_over_the_map_it_read(client: TestClient) -> None:
    from app import client as client_module

    sent: list[httpx.Request] = []
    client.event_hooks["request"].append(sent.append)
    fidotrack = client_module.Client()
    fidotrack.http.close()
    fidotrack.http = client  # the service in this process

    env = fidotrack.create_environment("lab", marker_size_m=0.1).id
    fidotrack.put_map(env, example_map(1))
    read = fidotrack.get_map(env)
    etag = client.get(f"/environments/{env}/map").headers["ETag"]
    fidotrack.put_map(env, example_map(2))
    assert sent[-1].method == "PUT" and sent[-1].headers["If-Match"] == etag

    # Someone else changes the map: this client's next writes are refused, and change nothing.
    client.put(f"/environments/{env}/map", json=example_map(3)).raise_for_status()
    for write in (lambda: fidotrack.put_map(env, read),
                  lambda: fidotrack.align(env, {"origin_target_id": 0}),
                  lambda: fidotrack.restore_map(env)):
        with pytest.raises(client_module.ApiError) as refused:
            write()
        assert refused.value.status == 412 and "changed since this client read it" in str(refused.value)
        assert isinstance(refused.value, client_module.MapChanged)
    assert len(client.get(f"/environments/{env}/map").json()["targets"]) == 3

    # Read again, the change goes through; or forced over whatever the map is.
    assert len(fidotrack.get_map(env).targets) == 3
    assert fidotrack.align(env, {"origin_target_id": 0}).map.frame == "world"
    client.put(f"/environments/{env}/map", json=example_map(4)).raise_for_status()
    assert len(fidotrack.put_map(env, read, overwrite=True).targets) == 1
    assert "If-Match" not in sent[-1].headers


def test_the_map_commands_take_the_revision_they_printed(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from app.cli import main

    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        service = ["--url", server.url, "-q"]
        with httpx.Client(base_url=server.url) as http:
            env = str(http.post("/environments", json={"name": "cli", "marker_size_m": 0.1}).json()["id"])
            http.put(f"/environments/{env}/map", json=example_map(2)).raise_for_status()
        assert main(["map", "get", str(tmp_path / "map.json"), "-e", env, *service]) == 0
        printed = capsys.readouterr().err
        assert "map at revision 1 (put it back with --if-match 1)" in printed
        assert main(["map", "put", str(tmp_path / "map.json"), "-e", env, "--if-match", "1", *service]) == 0
        assert "now revision 2" in capsys.readouterr().err
        # The file was read at revision 1: the map has moved on, so it is refused.
        assert main(["map", "put", str(tmp_path / "map.json"), "-e", env, "--if-match", "1", *service]) == 1
        refused = capsys.readouterr().err
        assert "no longer at revision 1: nothing was changed" in refused
        assert main(["map", "restore", "-e", env, "--if-match", "1", *service]) == 1
        assert main(["map", "show", "-e", env, *service]) == 0
        assert ", revision 2" in capsys.readouterr().out
        assert main(["map", "restore", "-e", env, "--if-match", '"2"', *service]) == 0
        assert "now revision 3" in capsys.readouterr().err
        assert main(["map", "versions", "-e", env, *service]) == 0
        assert "(was revision 2)" in capsys.readouterr().out.splitlines()[0]
