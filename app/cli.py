"""The ``fidotrack`` command: run the service (``serve``, ``keys``), use a running one
through the Python client (``survey``, ``track``, ``map``), print cards (``markers``),
render simulated rooms (``synth``) and show the whole system at work (``demo``)."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from tqdm import tqdm

if TYPE_CHECKING:
    from app.client import Client
    from app.settings import Settings


#: How much larger than ``max_frame_bytes`` a WebSocket message may be and still be read
#: (and answered with ``frame_too_large``).
WS_MESSAGE_MARGIN = 1024 * 1024


def ws_message_limit(settings: Settings) -> int:
    """The largest WebSocket message the server reads: a frame's limit and a margin.
    Larger messages close the connection (1009) from their header, before a byte of them
    is read: the web server assembles and decodes every message it reads on the event
    loop, where 12 MB of text held every other client up for tens of milliseconds."""
    return settings.max_frame_bytes + WS_MESSAGE_MARGIN


#: Seconds `fidotrack serve` gives open connections to close when it is stopped.
SHUTDOWN_GRACE_S = 5


def _settings(command: str) -> Settings | None:
    """The settings from the environment, or None after saying why they cannot be used
    (a database URL without its driver, a value out of range)."""
    from pydantic import ValidationError

    from app.settings import Settings

    try:
        return Settings()
    except ValidationError as exc:
        print(f"fidotrack {command}: {exc}", file=sys.stderr)
        return None


def _serve(args: argparse.Namespace) -> int:
    from app import server

    settings = _settings("serve")
    if settings is None:
        return 2
    if (settings.tls_certfile is None) != (settings.tls_keyfile is None):
        print("fidotrack serve: TLS needs both FIDOTRACK_TLS_CERTFILE and FIDOTRACK_TLS_KEYFILE", file=sys.stderr)
        return 2
    with _shared_job_cluster(settings, args.workers):
        server.run(
            settings,
            host=args.host or settings.host,
            port=args.port or settings.port,
            workers=args.workers,
            # Frames are JPEGs: deflate cannot shrink them and costs ~10 ms per 200 KB frame.
            ws_per_message_deflate=False,
            # The transport's bound on one message; frames under it but over max_frame_bytes
            # get the frame_too_large error and the connection stays open.
            ws_max_size=ws_message_limit(settings),
            proxy_headers=True,
            ssl_certfile=settings.tls_certfile,
            ssl_keyfile=settings.tls_keyfile,
            # A stop waits this long for open connections, then closes them: a browser may
            # leave a TLS connection's closing unanswered, which asyncio waits out for 30 s.
            timeout_graceful_shutdown=SHUTDOWN_GRACE_S,
        )
    return 0


@contextlib.contextmanager
def _shared_job_cluster(settings: Settings, workers: int) -> Iterator[None]:
    """With several server processes and no job scheduler of the deployment's own, one
    local job cluster for them all, started here (each process would otherwise start its
    own, and the job slots would multiply with the processes)."""
    if workers <= 1 or settings.job_scheduler is not None:
        yield
        return
    import tempfile

    from app.db import make_engine, make_sessionmaker
    from app.services.jobs import JobRunner
    from app.services.jobs.cluster import write_tls_files

    engine = make_engine(settings.resolved_database_url, settings.sqlite_busy_timeout_ms)
    runner = JobRunner(settings, make_sessionmaker(engine))
    client = runner.client()
    # The server processes connect with the cluster's own key, in a folder of this user's only.
    with tempfile.TemporaryDirectory(prefix="fidotrack-engine-") as folder:
        tls = write_tls_files(client.security, Path(folder))
        variables = {"FIDOTRACK_JOB_SCHEDULER": client.scheduler.address,
                     "FIDOTRACK_JOB_TLS_CA_FILE": str(tls.ca_file), "FIDOTRACK_JOB_TLS_CERT_FILE": str(tls.cert_file),
                     "FIDOTRACK_JOB_TLS_KEY_FILE": str(tls.key_file)}
        os.environ.update(variables)
        try:
            yield
        finally:
            for name in variables:
                os.environ.pop(name, None)
            runner.shutdown()  # fails the jobs it still held: they die with its workers
            engine.dispose()


def _scheduler(args: argparse.Namespace) -> int:
    from app.services.jobs.cluster import EngineSetupError, engine_tls, insecure_reason, run_scheduler

    settings = _settings("scheduler")
    if settings is None:
        return 2
    try:
        tls = engine_tls(settings)
    except EngineSetupError as exc:
        print(f"fidotrack scheduler: {exc}", file=sys.stderr)
        return 2
    refusal = insecure_reason("scheduler", [args.host])
    if tls is None and refusal is not None and not args.insecure:
        print(refusal, file=sys.stderr)
        return 2
    run_scheduler(settings, args.host, args.port, tls)
    return 0


def _worker(args: argparse.Namespace) -> int:
    from urllib.parse import urlsplit

    from app.services.jobs.cluster import (EngineSetupError, engine_security, engine_tls, insecure_reason,
                                           is_loopback, run_workers)

    settings = _settings("worker")
    if settings is None:
        return 2
    scheduler = args.scheduler or settings.job_scheduler
    if scheduler is None:
        print("fidotrack worker: give the scheduler's address (--scheduler or FIDOTRACK_JOB_SCHEDULER)",
              file=sys.stderr)
        return 2
    try:
        engine_security(settings, scheduler)  # (refuses tls:// without certificates, and the reverse)
        tls = engine_tls(settings)
    except EngineSetupError as exc:
        print(f"fidotrack worker: {exc}", file=sys.stderr)
        return 2
    scheduler_host = urlsplit(scheduler).hostname or ""
    if is_loopback(args.host) and not is_loopback(scheduler_host):
        print(f"fidotrack worker: the scheduler at {scheduler} cannot reach workers on {args.host}: give --host, an "
              "address of this machine that it and the other workers reach", file=sys.stderr)
        return 2
    # Its own sockets, and the scheduler it takes code from.
    refusal = insecure_reason("worker", [args.host, scheduler_host])
    if tls is None and refusal is not None and not args.insecure:
        print(refusal, file=sys.stderr)
        return 2
    return run_workers(scheduler, args.nworkers, args.nthreads, args.host, tls)


def _engine_certs(args: argparse.Namespace) -> int:
    from app.services.jobs.certs import make_engine_certs

    try:
        issued = make_engine_certs(args.out, days=args.days, if_missing=args.if_missing)
    except FileExistsError as exc:
        print(f"fidotrack engine-certs: {exc}", file=sys.stderr)
        return 2
    print(f"authority: {issued.ca_file} (its key, {issued.ca_key_file}, only signs: keep it off the engine's machines)")
    for role, (cert, key) in issued.certs.items():
        print(f"{role}: FIDOTRACK_JOB_TLS_CA_FILE={issued.ca_file} FIDOTRACK_JOB_TLS_CERT_FILE={cert} "
              f"FIDOTRACK_JOB_TLS_KEY_FILE={key}")
    return 0


def _markers(args: argparse.Namespace) -> int:
    from app.services import markers
    from app.services.errors import ServiceError

    with tqdm(desc="cards", unit="card", disable=args.quiet) as bar:

        def progress(done: int, total: int) -> None:
            bar.total = total
            bar.n = done
            bar.refresh()

        try:
            pdf = markers.sheet(args.family, args.ids, args.size_mm, progress)
        except ServiceError as exc:
            print(f"fidotrack markers: {exc.detail}", file=sys.stderr)
            return 2
    args.output.write_bytes(pdf)
    print(f"wrote {args.output} ({len(pdf)} bytes)", file=sys.stderr)
    return 0


# -- commands on a running service (the Python client) ---------------------------------


def _client(args: argparse.Namespace) -> Client:
    from app.client import Client

    return Client(args.url, api_key=args.api_key)


def _fail(command: str, error: Exception) -> int:
    print(f"fidotrack {command}: {error}", file=sys.stderr)
    return 1


def _survey(args: argparse.Namespace) -> int:
    from app.client import ApiError, JobFailed
    from app.schemas import JobOut, SurveyResult

    with _client(args) as client, tqdm(total=1.0, unit="", bar_format="{l_bar}{bar}| {elapsed}<{remaining}",
                                       disable=args.quiet) as bar:
        def progress(job: JobOut) -> None:
            bar.set_description(job.stage[:40])
            bar.n = job.progress
            bar.refresh()

        try:
            job = client.survey(args.environment, args.video, progress, max_frames=args.max_frames,
                                marker_size_m=args.marker_size, feature_tracks=args.feature_tracks,
                                readout_ms=args.readout_ms)
        except (ApiError, JobFailed) as error:
            bar.close()
            return _fail("survey", error)
    result = job.result
    assert isinstance(result, SurveyResult)
    print(f"survey {job.id}: {result.n_targets} cards mapped from {result.n_registered} of {result.n_frames} "
          f"frames, reprojection RMS {result.rms_px:.2f} px, focal length {result.focal_px:.1f} px")
    for warning in result.warnings:
        print(f"warning: {warning}")
    return 0


def _frames_of(source: str) -> Iterator[tuple[str, bytes]]:
    """Frames of a video file, a folder of images (in name order) or a camera index, as
    (name, JPEG or PNG bytes)."""
    import cv2

    path = Path(source)
    if path.is_dir():
        for image in sorted(p for p in path.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png")):
            yield image.name, image.read_bytes()
        return
    capture = cv2.VideoCapture(int(source) if source.isdigit() else str(path))
    if not capture.isOpened():
        raise FileNotFoundError(f"cannot open {source!r} as a video, a folder of images or a camera index")
    try:
        index = 0
        while True:
            ok, frame = capture.read()
            if not ok:
                return
            yield str(index), cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
            index += 1
    finally:
        capture.release()


def _video_frame_rate(source: str) -> float | None:
    """The frame rate a video file states, or None (a folder, a camera, no rate)."""
    import cv2

    if Path(source).is_dir() or source.isdigit():
        return None
    capture = cv2.VideoCapture(source)
    try:
        fps = float(capture.get(cv2.CAP_PROP_FPS) or 0.0) if capture.isOpened() else 0.0
    finally:
        capture.release()
    return fps if fps > 0 else None


def _track(args: argparse.Namespace) -> int:
    import csv
    import json

    from app.client import ApiError, TrackRefused
    from app.schemas import FreeDConnection, Smoothing, TrackConfig

    names: list[str] = []

    def frames() -> Iterator[bytes]:
        for name, data in _frames_of(args.source):
            names.append(name)
            yield data

    out = sys.stdout if args.output is None else open(args.output, "w", newline="")
    fields: dict[str, object] = {}
    if args.method:
        fields["method"] = args.method
    if args.smooth:
        fields["smoothing"] = Smoothing()
    if args.predict_ms:
        fields["predict_ms"] = args.predict_ms
    if args.no_freed:
        fields["freed"] = FreeDConnection(enabled=False)
    elif args.freed or args.camera_id is not None:
        host, _, port = (args.freed or "").rpartition(":")
        if args.freed and not (host and port.isdigit()):
            return _fail("track", ValueError(f"--freed wants HOST:PORT, got {args.freed!r}"))
        fields["freed"] = FreeDConnection(host=host or None, port=int(port) if port else None,
                                          camera_id=1 if args.camera_id is None else args.camera_id)
    if args.readout_ms is not None:
        frame_rate = args.frame_rate or _video_frame_rate(args.source)
        if frame_rate is None:
            return _fail("track", ValueError("--readout-ms needs --frame-rate: the source states no frame rate"))
        fields["rolling_shutter"] = {"readout_ms": args.readout_ms, "frame_rate": frame_rate}
    try:
        config = TrackConfig(**fields) if fields else None  # type: ignore[arg-type]
    except ValueError as error:
        return _fail("track", error)
    try:
        with _client(args) as client:
            writer = csv.writer(out) if args.format == "csv" else None
            if writer is not None:
                writer.writerow(["frame", "seq", "x", "y", "z", "targets", "reprojection_rms_px", "pose_error"])
            for reply in tqdm(client.track(args.environment, frames(), config), unit="frame", disable=args.quiet,
                              file=sys.stderr):
                name = names[reply.seq]
                if writer is not None:
                    used = reply.filtered or reply.pose  # smoothed or predicted when asked for
                    position = used.position if used else ["", "", ""]
                    writer.writerow([name, reply.seq, *position, len(reply.targets),
                                     reply.pose.reprojection_rms_px if reply.pose else "", reply.pose_error or ""])
                else:
                    out.write(json.dumps({"frame": name, **reply.model_dump(mode="json")}) + "\n")
    except (ApiError, TrackRefused, FileNotFoundError, OSError) as error:
        return _fail("track", error)
    finally:
        if out is not sys.stdout:
            out.close()
    return 0


def _map(args: argparse.Namespace) -> int:
    import json

    from app.client import ApiError, MapChanged

    def revision(client: Client) -> str:
        return (client.map_etag(args.environment) or "unknown").strip('"')

    # The revision as the commands print and take it (7); its ETag is quoted ("7").
    if_match = args.if_match and (args.if_match if args.if_match.strip().startswith(('"', "W/", "*"))
                                  else f'"{args.if_match.strip()}"')
    try:
        with _client(args) as client:
            if args.action == "restore":
                document = client.restore_map(args.environment, args.version, if_match=if_match)
                print(f"environment {args.environment}: restored a map of {len(document.targets)} cards "
                      f"({document.frame} frame), now revision {revision(client)}", file=sys.stderr)
                return 0
            if args.action == "versions":
                for version in client.map_versions(args.environment):
                    print(f"{version.version:6d}  {version.frame:6s} {version.n_targets:4d} cards  replaced by "
                          f"{version.replaced_by.value} at {version.replaced_at:%Y-%m-%d %H:%M:%S}"
                          + (f"  (was revision {version.revision})" if version.revision is not None else ""))
                return 0
            if args.action == "put":
                document = client.put_map(args.environment, json.loads(Path(args.file).read_text()), if_match=if_match)
                print(f"stored a map of {len(document.targets)} cards in environment {args.environment}, now revision "
                      f"{revision(client)}", file=sys.stderr)
                return 0
            document = client.get_map(args.environment)
            current = revision(client)
    except MapChanged:
        return _fail(f"map {args.action}", ValueError(
            f"the map of environment {args.environment} is no longer at revision {args.if_match}: nothing was "
            "changed. `fidotrack map get` it again, redo the change on it and give its revision, or leave "
            "--if-match out to replace the map whatever it is now"))
    except (ApiError, OSError, ValueError) as error:
        return _fail(f"map {args.action}", error)
    if args.action == "get":
        text = document.model_dump_json(indent=1)
        if args.file:
            Path(args.file).write_text(text)
        else:
            print(text)
        print(f"environment {args.environment}: map at revision {current} (put it back with --if-match {current})",
              file=sys.stderr)
        return 0
    camera = document.camera
    print(f"environment {args.environment}: {len(document.targets)} cards, frame {document.frame}, "
          f"camera {camera.width}x{camera.height} f={camera.K[0][0]:.1f} px"
          + (f", survey RMS {document.rms_px:.2f} px" if document.rms_px is not None else "")
          + f", revision {current}")
    print(f"{'card':>5} {'x':>8} {'y':>8} {'z':>8} {'std mm':>7} {'views':>5}")
    for target in sorted(document.targets, key=lambda t: t.id):
        centre = [sum(disc[k] for disc in target.discs) / len(target.discs) for k in range(3)]
        std = f"{1000 * max(target.std_m):7.2f}" if target.std_m else f"{'-':>7}"
        views = f"{target.n_views:5d}" if target.n_views is not None else f"{'-':>5}"
        print(f"{target.id:5d} {centre[0]:8.3f} {centre[1]:8.3f} {centre[2]:8.3f} {std} {views}")
    return 0


def _demo(args: argparse.Namespace) -> int:
    from app.demo import run_demo

    return run_demo(url=args.url, api_key=args.api_key, small=args.small, quiet=args.quiet, keep=args.keep)


def _synth_frames(args: argparse.Namespace) -> int:
    import dataclasses
    import json

    import cv2
    import numpy as np

    from app.sim import scenes

    args.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    scenario = scenes.SCENARIOS[args.scenario]
    if args.degradation:
        scenario = dataclasses.replace(scenario, degradation=args.degradation)
    truths = []
    for index in tqdm(range(args.count), desc=f"{args.scenario} frames", unit="frame", disable=args.quiet):
        image, truth = scenes.scenario_frame(scenario, rng, args.width, args.height, args.family)
        name = f"{args.scenario}_{index:04d}.png"
        cv2.imwrite(str(args.out / name), image)
        truths.append({"file": name, "camera": truth.camera.to_dict(), **truth.to_dict()})
    (args.out / "truth.json").write_text(json.dumps({"scenario": args.scenario, "frames": truths}, indent=1))
    print(f"wrote {args.count} frames and truth.json to {args.out}", file=sys.stderr)
    return 0


def _synth_room(args: argparse.Namespace) -> int:
    import json

    import cv2
    import numpy as np

    from app.core.geometry import Camera
    from app.sim import scenes

    size = tuple(float(v) for v in args.room.split("x"))
    if len(size) != 3:
        print("fidotrack synth room: --room must be WxDxH, e.g. 8x6x3", file=sys.stderr)
        return 2
    rng = np.random.default_rng(args.seed)
    camera = Camera.pinhole(args.focal, args.width, args.height, dist=[args.k1, args.k2, 0.0, 0.0, 0.0])
    scene = scenes.room_scene(rng, size, args.markers, args.marker_size, args.family)  # type: ignore[arg-type]
    args.out.mkdir(parents=True, exist_ok=True)
    document: dict[str, object] = {"camera": camera.to_dict(), "map": scene.map_document(camera),
                                   "room_size": list(size), "marker_size_m": args.marker_size}
    for walk in ("calibration", "tracking"):
        poses = scenes.camera_walk(rng, size, args.frames, walk)  # type: ignore[arg-type]
        frames = []
        writer = None
        if args.format == "mp4":
            writer = cv2.VideoWriter(str(args.out / f"{walk}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), args.fps,
                                     (args.width, args.height), isColor=False)
        else:
            (args.out / walk).mkdir(exist_ok=True)
        frames_iter = scenes.render_walk(scene, camera, poses, rng, args.degradation)
        for index, (image, truth) in enumerate(tqdm(frames_iter, total=len(poses), desc=walk, unit="frame",
                                                     disable=args.quiet)):
            if writer is not None:
                writer.write(image)
            else:
                cv2.imwrite(str(args.out / walk / f"{index:05d}.jpg"), image, [cv2.IMWRITE_JPEG_QUALITY, 92])
            frames.append(truth.to_dict())
        if writer is not None:
            writer.release()
        document[walk] = frames
    (args.out / "truth.json").write_text(json.dumps(document))
    print(f"wrote the {args.format} walks and truth.json to {args.out}", file=sys.stderr)
    return 0


def _keys(args: argparse.Namespace) -> int:
    from app.db import make_engine, make_sessionmaker, upgrade_to_head
    from app.services import keys
    from app.services.errors import ServiceError

    settings = _settings("keys")
    if settings is None:
        return 2
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    engine = make_engine(settings.resolved_database_url, settings.sqlite_busy_timeout_ms)
    try:
        upgrade_to_head(engine, settings.data_dir)
        with make_sessionmaker(engine)() as session:
            if args.action == "create":
                created = keys.create(session, args.name, [s.strip() for s in args.scopes.split(",") if s.strip()])
                print(f"id {created.id}  name {created.name!r}  scopes {','.join(created.scopes)}", file=sys.stderr)
                print("the key (shown only now; only its hash is stored):", file=sys.stderr)
                print(created.key)
            elif args.action == "list":
                for row in keys.list_all(session):
                    state = f"revoked {row.revoked_at:%Y-%m-%d}" if row.revoked_at else "active"
                    print(f"{row.id}\t{row.name}\t{','.join(row.scopes)}\tft_{row.prefix}_...\t{state}")
            else:
                keys.revoke(session, args.id)
                print(f"revoked key {args.id}", file=sys.stderr)
    except ServiceError as exc:
        print(f"fidotrack keys: {exc.detail}", file=sys.stderr)
        return 2
    finally:
        engine.dispose()
    return 0


class _ScenarioNames(Sequence[str]):
    """The simulator's scenario names, sorted, loaded when argparse first looks at them
    (parsing or help): building the parser, as every command does, loads no simulator.
    The option names its metavar, else argparse would list the names at once."""

    def _names(self) -> list[str]:
        from app.sim.scenes import SCENARIOS

        return sorted(SCENARIOS)

    def __getitem__(self, index: int) -> str:  # type: ignore[override]
        return self._names()[index]

    def __len__(self) -> int:
        return len(self._names())


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fidotrack", description="fidotrack: marker-based camera tracking. Run the service, use it, print "
        "cards, render simulated rooms, or see it all at work with `fidotrack demo`.")
    commands = parser.add_subparsers(dest="command", required=True)

    serve = commands.add_parser("serve", help="run the HTTP/WebSocket service")
    serve.add_argument("--host", help="default: FIDOTRACK_HOST or 127.0.0.1")
    serve.add_argument("--port", type=int, help="default: FIDOTRACK_PORT or 8000")
    serve.add_argument("--workers", type=int, default=1, help="server processes (default: %(default)s)")
    serve.set_defaults(run=_serve)

    insecure_help = ("listen or connect off the loopback without TLS: whoever reaches the engine's ports can run "
                     "code; only on a network that only the engine's machines reach")
    scheduler = commands.add_parser("scheduler", help="run the job engine's scheduler (for workers on other machines)")
    scheduler.add_argument("--host", default="127.0.0.1",
                           help="address to listen on; off the loopback it needs the engine's TLS "
                                "(FIDOTRACK_JOB_TLS_*) or --insecure (default: %(default)s)")
    scheduler.add_argument("--port", type=int, default=8786, help="port to listen on (default: %(default)s)")
    scheduler.add_argument("--insecure", action="store_true", help=insecure_help)
    scheduler.set_defaults(run=_scheduler)

    worker = commands.add_parser("worker", help="run job workers (surveys, training) for a job scheduler")
    worker.add_argument("--scheduler", help="the scheduler, tcp://host:port, or tls://host:port with the engine's "
                                            "TLS (default: FIDOTRACK_JOB_SCHEDULER)")
    worker.add_argument("--host", default="127.0.0.1",
                        help="address the workers listen on, which the scheduler and the other workers must reach; "
                             "off the loopback it needs the engine's TLS or --insecure (default: %(default)s)")
    worker.add_argument("--nworkers", type=int, default=1,
                        help="worker processes; each runs one job at a time and pieces of others' "
                             "(default: %(default)s)")
    worker.add_argument("--nthreads", type=int, default=1, help="threads per worker process (default: %(default)s)")
    worker.add_argument("--insecure", action="store_true", help=insecure_help)
    worker.set_defaults(run=_worker)

    certs = commands.add_parser("engine-certs", help="make TLS certificates for the job engine: an authority and a "
                                                     "certificate per role (scheduler, worker, web)")
    certs.add_argument("--out", type=Path, required=True, help="the folder to write (made if missing; must not "
                                                               "hold certificates already)")
    certs.add_argument("--days", type=int, default=825, help="how long they are valid (default: %(default)s)")
    certs.add_argument("--if-missing", action="store_true",
                       help="leave a folder that already holds a full set as it is (for a start-up step)")
    certs.set_defaults(run=_engine_certs)

    cards = commands.add_parser("markers", help="write printable marker cards as an A4 PDF")
    cards.add_argument("--ids", default="0-11", help='ids, e.g. "0-11" or "0,3,5-7"')
    cards.add_argument("--size-mm", type=float, default=150.0, help="side of each card in mm")
    cards.add_argument("--family", default="fido3x3", help="code family of the cards (default: %(default)s)")
    cards.add_argument("-o", "--output", type=Path, default=Path("markers.pdf"),
                       help="the PDF to write (default: %(default)s)")
    cards.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    cards.set_defaults(run=_markers)

    api_keys = commands.add_parser("keys", help="manage API keys (used when FIDOTRACK_API_KEYS=true)")
    key_actions = api_keys.add_subparsers(dest="action", required=True)
    create = key_actions.add_parser("create", help="create a key and print it (once)")
    create.add_argument("--name", required=True, help="what the key is for (shown in lists and logs)")
    create.add_argument("--scopes", default="read,track", help="comma list of read, track, admin")
    key_actions.add_parser("list", help="list keys (never the secrets)")
    revoke = key_actions.add_parser("revoke", help="revoke a key by id")
    revoke.add_argument("id", type=int, help="the key's id (from `fidotrack keys list`)")
    api_keys.set_defaults(run=_keys)

    def on_service(parser: argparse.ArgumentParser, url_help: str | None = None) -> None:
        if url_help is None:
            parser.add_argument("--url", default=os.environ.get("FIDOTRACK_URL", "http://127.0.0.1:8000"),
                                help="the service (default: FIDOTRACK_URL or %(default)s)")
        else:
            parser.add_argument("--url", default=os.environ.get("FIDOTRACK_URL"), help=url_help)
        parser.add_argument("--api-key", default=os.environ.get("FIDOTRACK_API_KEY"),
                            help="API key, when the service requires keys (default: FIDOTRACK_API_KEY)")
        parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")

    survey = commands.add_parser("survey", help="survey an environment from a video of its room, with progress")
    survey.add_argument("video", type=Path, help="the video of the room (MP4, MOV or AVI)")
    survey.add_argument("--environment", "-e", type=int, required=True, help="the environment's id")
    survey.add_argument("--max-frames", type=int, help="frames to use, evenly spaced (default: the service's)")
    survey.add_argument("--marker-size", type=float, help="printed card side in metres (default: the environment's)")
    survey.add_argument("--feature-tracks", action=argparse.BooleanOptionalAction, default=True,
                        help="track the walls' own texture beside the cards (default); --no-feature-tracks: "
                             "the cards alone")
    survey.add_argument("--readout-ms", type=float,
                        help="the camera's rolling shutter readout, first row to last, ms (a phone's: 10-30); the "
                             "survey then models it (default: a global shutter)")
    on_service(survey)
    survey.set_defaults(run=_survey)

    track = commands.add_parser("track", help="stream frames to /track and print the poses (CSV or JSON lines)")
    track.add_argument("source", help="a video file, a folder of JPEG/PNG images (name order) or a camera index")
    track.add_argument("--environment", "-e", type=int, required=True, help="the environment's id")
    track.add_argument("--format", choices=["csv", "jsonl"], default="csv",
                       help="csv: frame, position, targets; jsonl: each whole reply (default: %(default)s)")
    track.add_argument("--method", choices=["nonlinear", "posit", "mean", "single"],
                       help="pose method (default: the service's, nonlinear)")
    track.add_argument("--smooth", action="store_true",
                       help="smooth the poses (One Euro filter); CSV positions are then the smoothed ones")
    track.add_argument("--predict-ms", type=float, default=0.0,
                       help="predict each pose this many ms ahead (0-500); CSV positions are then the predicted ones")
    track.add_argument("--freed", metavar="HOST:PORT",
                       help="send the poses as FreeD packets over UDP to this receiver (default: the environment's "
                            "FreeD output, if it has one)")
    track.add_argument("--camera-id", type=int, help="the FreeD camera id (0-255, default 1)")
    track.add_argument("--no-freed", action="store_true", help="send no FreeD, even to the environment's output")
    track.add_argument("--readout-ms", type=float,
                       help="the camera's rolling shutter readout, first row to last, ms (a phone's: 10-30); each "
                            "pose is then fitted with the camera's motion through it (default: a global shutter)")
    track.add_argument("--frame-rate", type=float,
                       help="frames a second of the source, for --readout-ms (default: the video file's own)")
    track.add_argument("-o", "--output", type=Path, help="write the poses here (default: standard output)")
    on_service(track)
    track.set_defaults(run=_track)

    maps = commands.add_parser("map", help="show, export or import an environment's map")
    maps.add_argument("action", choices=["show", "get", "put", "versions", "restore"],
                      help="show: a table of the cards; get: the map as JSON; put: store a JSON map; versions: the "
                           "maps earlier changes replaced; restore: make one current again (the newest by default)")
    maps.add_argument("file", nargs="?", help="get: write here (default: standard output); put: read from here")
    maps.add_argument("--environment", "-e", type=int, required=True, help="the environment's id")
    maps.add_argument("--version", type=int, help="restore: the version to restore (from `map versions`)")
    maps.add_argument("--if-match", metavar="REVISION",
                      help="put, restore: only if the map is still at this revision (as `map get` and `map show` "
                           "print it); refused, changing nothing, if it has changed since")
    on_service(maps)
    maps.set_defaults(run=_map)

    demo = commands.add_parser("demo", help="render a room, survey it, track through it, print the accuracy")
    demo.add_argument("--small", action="store_true", help="a smaller room and shorter walks (about half the time)")
    demo.add_argument("--keep", type=Path, help="keep the rendered video, frames and truth in this folder")
    on_service(demo, url_help="a running service to use (default: FIDOTRACK_URL, else the demo starts its own "
                              "on a free port with a temporary data directory)")
    demo.set_defaults(run=_demo)

    synth = commands.add_parser("synth", help="render simulated frames with ground truth")
    kinds = synth.add_subparsers(dest="kind", required=True)
    frames = kinds.add_parser("frames", help="single frames of a named scenario")
    frames.add_argument("--scenario", default="default", choices=_ScenarioNames(), metavar="SCENARIO",
                        help="one of %(choices)s (default: %(default)s)")
    frames.add_argument("--count", type=int, default=10, help="frames to render (default: %(default)s)")
    frames.add_argument("--degradation", choices=["none", "default", "blur", "dark", "full"],
                        help="override the scenario's degradation preset")
    frames.set_defaults(run=_synth_frames)
    room = kinds.add_parser("room", help="a room with markers; calibration and tracking walks")
    room.add_argument("--room", default="8x6x3", help="W x D x H in metres")
    room.add_argument("--markers", type=int, default=30, help="cards on the walls (default: %(default)s)")
    room.add_argument("--marker-size", type=float, default=0.2, help="card side in metres")
    room.add_argument("--frames", type=int, default=300, help="frames per walk (default: %(default)s)")
    room.add_argument("--focal", type=float, default=820.0, help="focal length, px (default: %(default)s)")
    room.add_argument("--k1", type=float, default=-0.12, help="radial distortion k1 (default: %(default)s)")
    room.add_argument("--k2", type=float, default=0.0, help="radial distortion k2 (default: %(default)s)")
    room.add_argument("--fps", type=float, default=30.0, help="video frame rate (default: %(default)s)")
    room.add_argument("--degradation", default="default", choices=["none", "default", "blur", "dark", "full"],
                      help="camera degradation preset (default: %(default)s)")
    room.add_argument("--format", choices=["mp4", "jpeg"], default="mp4",
                      help="walks as MP4 videos or folders of JPEGs (default: %(default)s)")
    room.set_defaults(run=_synth_room)
    for sub in (frames, room):
        sub.add_argument("--out", type=Path, required=True, help="the folder to write")
        sub.add_argument("--seed", type=int, default=0, help="random seed: the same seed, the same room (default: 0)")
        sub.add_argument("--width", type=int, default=640, help="image width, px (default: %(default)s)")
        sub.add_argument("--height", type=int, default=480, help="image height, px (default: %(default)s)")
        sub.add_argument("--family", default="fido3x3", help="code family of the cards (default: %(default)s)")
        sub.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.run(args))


if __name__ == "__main__":
    raise SystemExit(main())
