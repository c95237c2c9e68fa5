"""The Python client and the commands built on it, against a real server: what a user
scripting fidotrack relies on (typed replies, the service's errors, a survey with
progress, lock-step tracking), and ``fidotrack demo`` end to end."""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from app.cli import build_parser, main
from app.client import ApiError, Client, JobFailed, TrackRefused
from app.core.geometry import Pose
from app.schemas import FreeDOutput, JobOut, JobStatus, TrackConfig
from tests.conftest import Server, example_map, running_server, start_server


@dataclass
class Room:
    """The small example room: a survey video, a tracking walk and the truth."""

    video: Path
    frames: list[bytes]
    poses: list[Pose]
    frames_dir: Path
    truth_map: dict
    marker_size_m: float


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> Room:
    from app.sim import SMALL_ROOM, render_walk
    from app.sim.walks import camera_walk

    folder = tmp_path_factory.mktemp("room")
    walk = SMALL_ROOM.walk(5, 60, kind="calibration")
    camera = SMALL_ROOM.camera
    video = folder / "room.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (camera.width, camera.height))
    for image, _ in render_walk(walk.scene, camera, walk.poses, walk.rng, degradation="none"):
        writer.write(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
    writer.release()
    poses = camera_walk(walk.rng, SMALL_ROOM.size, 30, kind="tracking")
    frames_dir = folder / "frames"
    frames_dir.mkdir()
    frames = []
    for k, (image, _) in enumerate(render_walk(walk.scene, camera, poses, walk.rng, degradation="default")):
        frames.append(cv2.imencode(".jpg", image)[1].tobytes())
        (frames_dir / f"{k:04d}.jpg").write_bytes(frames[-1])
    return Room(video, frames, list(poses), frames_dir, walk.scene.map_document(camera), SMALL_ROOM.marker_size_m)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    folder = tmp_path_factory.mktemp("server")
    # FreeD to the tests' receivers on 127.0.0.1, as with a renderer on the server's machine.
    with pytest.MonkeyPatch.context() as env:
        env.setenv("FIDOTRACK_FREED_CONNECTION_RECEIVERS", "true")
        env.setenv("FIDOTRACK_FREED_ALLOWED_NETWORKS", '["127.0.0.1/32"]')
        running = start_server(folder / "data", folder / "server.log")
    try:
        yield running
    finally:
        running.stop()


def _errors_mm(replies: list, poses: list[Pose]) -> np.ndarray:
    return np.array([1000 * np.linalg.norm(np.asarray(r.pose.position) - poses[r.seq].position)
                     for r in replies if r.pose is not None])


def test_the_client_manages_environments_and_maps_with_the_services_errors(server: Server) -> None:
    with Client(server.url) as client:
        environment = client.create_environment("lab", marker_size_m=0.2)
        assert environment.marker_size_m == 0.2 and not environment.has_map
        assert environment.id in [e.id for e in client.environments()]
        stored = client.put_map(environment.id, example_map())
        assert client.get_map(environment.id) == stored and client.environment(environment.id).has_map
        with pytest.raises(ApiError) as missing:
            client.environment(9999)
        assert missing.value.status == 404 and "9999" in missing.value.detail
        with pytest.raises(ApiError) as invalid:
            client.create_environment("bad", marker_size_m=-1.0)
        assert invalid.value.status == 422 and "marker_size_m" in invalid.value.detail
        assert client.sheet("0-3", 150.0).startswith(b"%PDF")
        client.delete_environment(environment.id)
        with pytest.raises(ApiError):
            client.get_map(environment.id)
    with pytest.raises(ApiError) as unreachable, Client("http://127.0.0.1:9") as nobody:
        nobody.environments()
    assert unreachable.value.status == 0 and "cannot reach" in unreachable.value.detail


def test_the_client_surveys_with_progress_and_tracks_in_lock_step(server: Server, room: Room) -> None:
    with Client(server.url) as client:
        environment = client.create_environment("small room", room.marker_size_m)
        seen: list[JobOut] = []
        job = client.survey(environment.id, room.video, progress=seen.append)
        assert job.status == JobStatus.SUCCEEDED and job.result is not None and job.result.n_targets >= 20
        fractions = [j.progress for j in seen]
        assert fractions == sorted(fractions) and len(set(fractions)) >= 3 and seen[-1].status == "succeeded"

        # Tracking against the true map: poses arrive for the frames, in order, one each.
        truth = client.create_environment("true map", room.marker_size_m)
        client.put_map(truth.id, room.truth_map)
        replies = list(client.track(truth.id, room.frames))
        assert [r.seq for r in replies] == list(range(len(room.frames)))
        assert sum(r.pose is not None for r in replies) >= 0.8 * len(replies)
        assert np.median(_errors_mm(replies, room.poses)) < 10.0
        # numpy images are encoded by the client; a config reaches the server.
        gray = [cv2.imdecode(np.frombuffer(f, np.uint8), cv2.IMREAD_GRAYSCALE) for f in room.frames[:5]]
        posit = list(client.track(truth.id, gray, TrackConfig(method="posit")))
        assert len(posit) == 5 and all(r.pose is None or r.pose.method == "posit" for r in posit)

        located = client.locate(truth.id, room.frames[0])
        assert located.pose is not None and located.pose.position == pytest.approx(replies[0].pose.position, abs=1e-3)
        assert {t.id for t in client.detect(room.frames[0]).targets} == {t.id for t in located.targets}

        with pytest.raises(TrackRefused) as refused:
            list(client.track(99999, room.frames[:1]))
        assert refused.value.code == "unknown_environment"
        # A video without cards: the survey fails, with the service's reason.
        blank = room.video.with_name("blank.avi")
        writer = cv2.VideoWriter(str(blank), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (640, 480))
        for _ in range(10):
            writer.write(np.full((480, 640, 3), 128, np.uint8))
        writer.release()
        with pytest.raises(JobFailed) as failed:
            client.survey(environment.id, blank)
        assert failed.value.job.status == "failed" and "no target" in (failed.value.job.error or "")
        assert client.environment(environment.id).has_map  # the first survey's map is kept


def test_the_client_sends_its_key(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import os
    import subprocess
    import sys

    monkeypatch.setenv("FIDOTRACK_API_KEYS", "true")
    with running_server(tmp_path / "data", tmp_path / "server.log") as keyed:
        created = subprocess.run([str(Path(sys.executable).with_name("fidotrack")), "keys", "create", "--name", "script",
                                  "--scopes", "read,track,admin"], capture_output=True, text=True, check=True,
                                 env={**os.environ, "FIDOTRACK_DATA_DIR": str(tmp_path / "data")})
        key = created.stdout.split()[-1]
        with pytest.raises(ApiError) as refused, Client(keyed.url) as anonymous:
            anonymous.environments()
        assert refused.value.status == 401
        with Client(keyed.url, api_key=key) as client:
            environment = client.create_environment("lab", 0.2)
            client.put_map(environment.id, example_map())
            frame = cv2.imencode(".jpg", np.full((480, 640), 128, np.uint8))[1].tobytes()
            assert [r.seq for r in client.track(environment.id, [frame, frame])] == [0, 1]


# -- the commands ------------------------------------------------------------------------


def test_every_command_and_option_says_what_it_is(capsys: pytest.CaptureFixture[str]) -> None:
    import argparse

    parser = build_parser()
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name in ("serve", "keys", "markers", "survey", "track", "map", "demo", "synth"):
        assert name in commands.choices and name in text

    def check(sub: argparse.ArgumentParser, path: str) -> None:
        for action in sub._actions:
            if isinstance(action, argparse._SubParsersAction):
                for choice, child in action.choices.items():
                    check(child, f"{path} {choice}")
            elif not isinstance(action, argparse._HelpAction):
                assert action.help, f"{path} {'/'.join(action.option_strings) or action.dest} has no help"

    check(parser, "fidotrack")


def test_survey_track_and_map_commands_on_a_running_service(server: Server, room: Room,
                                                            capsys: pytest.CaptureFixture[str],
                                                            tmp_path: Path) -> None:
    with Client(server.url) as client:
        environment = client.create_environment("cli room", room.marker_size_m).id
        truth = client.create_environment("cli truth", room.marker_size_m).id
    service = ["--url", server.url, "-q"]
    assert main(["survey", str(room.video), "-e", str(environment), *service]) == 0
    out = capsys.readouterr().out
    assert "cards mapped from" in out and "reprojection RMS" in out

    (tmp_path / "truth.json").write_text(json.dumps(room.truth_map))
    assert main(["map", "put", str(tmp_path / "truth.json"), "-e", str(truth), *service]) == 0
    assert main(["map", "show", "-e", str(truth), *service]) == 0
    shown = capsys.readouterr().out
    assert f"{len(room.truth_map['targets'])} cards" in shown
    assert main(["map", "get", str(tmp_path / "back.json"), "-e", str(truth), *service]) == 0
    assert len(json.loads((tmp_path / "back.json").read_text())["targets"]) == len(room.truth_map["targets"])

    # Stored again: the first import is kept as a version, and can be restored.
    assert main(["map", "put", str(tmp_path / "truth.json"), "-e", str(truth), *service]) == 0
    assert main(["map", "versions", "-e", str(truth), *service]) == 0
    listed = capsys.readouterr().out.strip().splitlines()
    assert len(listed) == 1 and "replaced by import" in listed[0]
    assert main(["map", "restore", "-e", str(truth), "--version", listed[0].split()[0], *service]) == 0
    with Client(server.url) as client:
        assert [v.replaced_by for v in client.map_versions(truth)] == ["restore", "import"]
        assert len(client.restore_map(truth).targets) == len(room.truth_map["targets"])
    assert main(["track", str(room.frames_dir), "-e", str(truth), *service]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [r["frame"] for r in rows] == sorted(p.name for p in room.frames_dir.iterdir())
    posed = [r for r in rows if r["x"]]
    errors = [1000 * np.linalg.norm(np.array([float(r["x"]), float(r["y"]), float(r["z"])])
                                    - room.poses[int(r["seq"])].position) for r in posed]
    assert len(posed) >= 0.8 * len(rows) and np.median(errors) < 10.0

    assert main(["track", str(room.video), "-e", str(truth), "--format", "jsonl", "-o", str(tmp_path / "p.jsonl"),
                 *service]) == 0
    lines = [json.loads(line) for line in (tmp_path / "p.jsonl").read_text().splitlines()]
    assert len(lines) == 60 and lines[0]["type"] == "frame" and lines[0]["frame"] == "0"
    # A rolling shutter's readout: the frame rate from the video file, or given.
    assert main(["track", str(room.frames_dir), "-e", str(truth), "--readout-ms", "1", *service]) == 1
    assert "--frame-rate" in capsys.readouterr().err
    assert main(["track", str(room.video), "-e", str(truth), "--readout-ms", "1", "--format", "jsonl", "-o",
                 str(tmp_path / "r.jsonl"), *service]) == 0
    rolled = [json.loads(line) for line in (tmp_path / "r.jsonl").read_text().splitlines()]
    assert len(rolled) == 60 and sum(line["pose"] is not None for line in rolled) >= 0.8 * 60

    assert main(["track", str(tmp_path / "nothing.mp4"), "-e", str(truth), *service]) == 1
    assert main(["map", "show", "-e", "99999", *service]) == 1
    assert "404" in capsys.readouterr().err


def test_the_demo_surveys_and_tracks_a_room_and_prints_its_accuracy(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--small", "-q"]) == 0
    out = capsys.readouterr().out
    mapped = next(line for line in out.splitlines() if line.startswith("map:"))
    tracked = next(line for line in out.splitlines() if line.startswith("tracking:"))
    map_rms_mm = float(mapped.split("within ")[1].split(" mm")[0])
    median_mm = float(tracked.split("median ")[1].split(" mm")[0])
    assert map_rms_mm < 2.0 and median_mm < 5.0, out
    assert "first pose" in out


def test_track_command_sends_freed_and_smooths(server: Server, room: Room, capsys: pytest.CaptureFixture[str],
                                               tmp_path: Path) -> None:
    """``fidotrack track --freed HOST:PORT`` feeds a studio's receiver (here a UDP socket)
    one packet per posed frame; ``--smooth`` and ``--predict-ms`` give the filtered poses;
    a FreeD config the service cannot use stops the command with its message."""
    import socket

    from app.core.freed import decode

    with Client(server.url) as client:
        environment = client.create_environment("freed room", room.marker_size_m).id
        client.put_map(environment, room.truth_map)
    service = ["--url", server.url, "-q"]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as receiver:
        receiver.bind(("127.0.0.1", 0))
        receiver.settimeout(5.0)
        port = receiver.getsockname()[1]
        assert main(["track", str(room.frames_dir), "-e", str(environment), "--format", "jsonl", "--smooth",
                     "--predict-ms", "30", "--freed", f"127.0.0.1:{port}", "--camera-id", "5",
                     "-o", str(tmp_path / "p.jsonl"), *service]) == 0
        lines = [json.loads(line) for line in (tmp_path / "p.jsonl").read_text().splitlines()]
        posed = [line for line in lines if line["pose"] is not None]
        assert len(posed) >= 0.8 * len(lines)
        for line in posed:
            packet = decode(receiver.recv(64))
            assert packet.camera_id == 5
            filtered = line["filtered"]
            assert filtered["smoothed"] and filtered["predict_ms"] == 30
            np.testing.assert_allclose([packet.x_mm, packet.y_mm, packet.z_mm], np.array(filtered["position"]) * 1e3,
                                       atol=0.02)
    capsys.readouterr()
    assert main(["track", str(room.frames_dir), "-e", str(environment), "--camera-id", "2", *service]) == 1
    assert "host and port" in capsys.readouterr().err  # no FreeD output in the environment to send to
    assert main(["track", str(room.frames_dir), "-e", str(environment), "--freed", "nowhere", *service]) == 1
    assert "HOST:PORT" in capsys.readouterr().err
    with Client(server.url) as client:
        assert client.freed_output(environment) is None
        client.set_freed_output(environment, {"host": "127.0.0.1", "port": 9, "camera_id": 2})
        assert client.freed_output(environment) == FreeDOutput(host="127.0.0.1", port=9, camera_id=2, enabled=True)
        client.remove_freed_output(environment)
        assert client.freed_output(environment) is None
        with pytest.raises(ApiError) as missing:
            client.freed_output(99999)
        assert missing.value.status == 404
