"""A survey of 1000 frames on the job engine: the embedded default (`fidotrack serve`
alone, its local cluster), and a scheduler with 1 and with 2 worker processes of its own
(`fidotrack scheduler`, `fidotrack worker --nworkers N`), on this machine.

The video: the bench room (`app.sim.BENCH_ROOM`, 30 cards) on a 1000-frame calibration
walk at 640x480, encoded as a phone does (H.264, a keyframe a second, B-frames). Each run
gets a fresh database and data directory and the same upload, through the REST API as a
client sends it; the job's own `stage_s` says how long detection (fanned out over the
workers) and the reconstruction (one worker) took.

With ``--feature-tracks`` the job also tracks the scene's own points (after detection,
in the job's process: the job's ``stage_s`` has ``tracking`` too) and the survey adjusts
them with the cards. ``--only-embedded`` runs the embedded default alone, and
``--compare-with DIR`` runs it a second time, in turn, on the checkout in DIR (another
version of fidotrack, imported first through PYTHONPATH): today's code against that one,
side by side, on the same machine in the same minutes.

Run: ``.venv/bin/python bench/bench_jobs.py [--frames 1000] [--cache DIR] [--feature-tracks]
[--only-embedded] [--compare-with DIR]`` (markdown tables).
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.local_server import fidotrack_command, free_port, running_server  # noqa: E402
from app.sim import BENCH_CAMERA, BENCH_ROOM  # noqa: E402

FIDOTRACK = fidotrack_command()


def render_video(path: Path, n_frames: int) -> None:
    """The bench room's calibration walk as an H.264 MP4 (a phone's keyframe interval)."""
    import av
    import cv2

    frames = BENCH_ROOM.walk(0, n_frames, "calibration").frames(BENCH_CAMERA)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=30)
        stream.width, stream.height, stream.pix_fmt = BENCH_CAMERA.width, BENCH_CAMERA.height, "yuv420p"
        stream.options = {"g": "30", "bf": "2", "crf": "18"}
        for image, _ in tqdm(frames, total=n_frames, desc="rendering", unit="frame"):
            bgr = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image
            container.mux(stream.encode(av.VideoFrame.from_ndarray(bgr, format="bgr24")))
        container.mux(stream.encode())


@dataclass
class Run:
    name: str
    job_s: float
    detecting_s: float
    tracking_s: float
    reconstructing_s: float
    frames: int
    n_targets: int
    rms_px: float
    attempt: int


@contextmanager
def _processes(commands: list[list[str]], env: dict[str, str], log: Path) -> Iterator[None]:
    """The job engine's processes (`commands`), stopped when the block ends; their output appended to `log`."""
    out = log.open("ab")
    started = [subprocess.Popen(command, env=env, stdout=out, stderr=subprocess.STDOUT) for command in commands]
    try:
        yield
    finally:
        for process in reversed(started):
            process.terminate()
        for process in reversed(started):
            try:
                process.wait(30)
            except subprocess.TimeoutExpired:
                process.kill()
        out.close()


def survey_once(name: str, video: Path, n_workers: int | None, frames: int, feature_tracks: bool = False,
                code: Path | None = None) -> Run:
    """One survey of `video` on a fresh service: with `n_workers`, on a scheduler of its
    own with that many worker processes; None: the embedded default. `code`: run that
    checkout of fidotrack instead of this one."""
    with tempfile.TemporaryDirectory(prefix="fidotrack-bench-jobs-") as folder:
        data = Path(folder)
        # Each run its own SQLite file in its data directory (an empty FIDOTRACK_DATABASE_URL).
        settings = {"FIDOTRACK_LOG_LEVEL": "WARNING", "FIDOTRACK_DATABASE_URL": ""}
        if code is not None:
            settings["PYTHONPATH"] = str(code.resolve())
        engine = []
        if n_workers is not None:
            scheduler_port = str(free_port())
            settings["FIDOTRACK_JOB_SCHEDULER"] = f"tcp://127.0.0.1:{scheduler_port}"
            engine += [[*FIDOTRACK, "scheduler", "--host", "127.0.0.1", "--port", scheduler_port],
                       [*FIDOTRACK, "worker", "--nworkers", str(n_workers)]]
        env = {**os.environ, **settings, "FIDOTRACK_DATA_DIR": str(data)}
        log = data / "service.log"
        with _processes(engine, env, log), running_server(data, settings=settings, log=log) as server:
            with httpx.Client(base_url=server.url, timeout=120) as http:
                env_id = http.post("/environments", json={"name": "bench", "marker_size_m": BENCH_ROOM.marker_size_m}
                                   ).json()["id"]
                with video.open("rb") as upload:
                    started = time.perf_counter()
                    form = {"max_frames": str(frames), "feature_tracks": "true" if feature_tracks else "false"}
                    reply = http.post(f"/environments/{env_id}/survey", data=form,
                                      files={"video": ("walk.mp4", upload, "video/mp4")})
                reply.raise_for_status()
                job_id = reply.json()["id"]
                with tqdm(total=100, desc=name, unit="%") as bar:
                    while (job := http.get(f"/jobs/{job_id}").json())["status"] in ("queued", "running"):
                        bar.n = round(100 * job["progress"])
                        bar.set_postfix_str(job["stage"][:30])
                        bar.refresh()
                        time.sleep(0.25)
                job_s = time.perf_counter() - started
        if job["status"] != "succeeded":
            raise RuntimeError(f"{name}: the survey {job['status']}: {job.get('error')}")
        result = job["result"]
        stage_s = result["stage_s"]
        return Run(name, job_s, stage_s["detecting"], stage_s.get("tracking", 0.0), stage_s["reconstructing"],
                   result["frames_used"], result["n_targets"], result["rms_px"], job["attempt"])


def print_comparison(runs: list[Run]) -> None:
    """Each run's stages and their shares of the job, and each run's time against the
    first's."""
    first = runs[0]
    print("| run | job s | detecting s | tracking s | reconstructing s | other s | shares (detect / track / "
          "reconstruct) | job against the first | cards | RMS px |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for run in runs:
        other = run.job_s - run.detecting_s - run.tracking_s - run.reconstructing_s
        shares = " / ".join(f"{100 * x / run.job_s:.0f} %" for x in (run.detecting_s, run.tracking_s,
                                                                     run.reconstructing_s))
        print(f"| {run.name} | {run.job_s:.1f} | {run.detecting_s:.1f} | {run.tracking_s:.1f} | "
              f"{run.reconstructing_s:.1f} | {other:.1f} | {shares} | {run.job_s / first.job_s:.2f} | "
              f"{run.n_targets} | {run.rms_px:.3f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--cache", type=Path, help="keep the rendered video here between runs")
    parser.add_argument("--feature-tracks", action="store_true", help="track the scene's points too")
    parser.add_argument("--only-embedded", action="store_true", help="the embedded default alone")
    parser.add_argument("--compare-with", type=Path, metavar="DIR",
                        help="also run the embedded default on the fidotrack checkout in DIR")
    args = parser.parse_args()
    cache = args.cache or Path(tempfile.mkdtemp(prefix="fidotrack-bench-video-"))
    cache.mkdir(parents=True, exist_ok=True)
    video = cache / f"bench_room_calibration_{args.frames}.mp4"
    if not video.exists():
        render_video(video, args.frames)
    features = args.feature_tracks
    heading = (f"\n{args.frames}-frame survey of the bench room (H.264 640x480, {video.stat().st_size / 1e6:.1f} MB"
               f"{', feature tracks' if features else ''}); {os.cpu_count()} cores, "
               f"{platform.processor() or platform.machine()}\n")
    if args.only_embedded or args.compare_with is not None:
        runs = [survey_once("embedded default", video, None, args.frames, features)]
        if args.compare_with is not None:
            runs.append(survey_once(f"embedded default, {args.compare_with.name}", video, None, args.frames, features,
                                    args.compare_with))
        print(heading)
        print_comparison(runs)
        return
    runs = [survey_once("embedded default", video, None, args.frames, features),
            survey_once("1 engine worker", video, 1, args.frames, features),
            survey_once("2 engine workers", video, 2, args.frames, features)]
    one = runs[1]
    print(heading)
    print("| run | job s | detecting s | detection fps | reconstructing s | detection speed-up | job speed-up | "
          "cards | RMS px | attempt |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for run in runs:
        print(f"| {run.name} | {run.job_s:.1f} | {run.detecting_s:.1f} | {run.frames / run.detecting_s:.1f} | "
              f"{run.reconstructing_s:.1f} | {one.detecting_s / run.detecting_s:.2f} | {one.job_s / run.job_s:.2f} | "
              f"{run.n_targets} | {run.rms_px:.3f} | {run.attempt} |")
    two = runs[2]
    print(f"\nOn paper, from this run: detection at {two.frames / two.detecting_s:.1f} frames a second on one "
          f"2-core machine ({two.detecting_s:.1f} s with 2 workers), spread over N such machines; "
          f"{two.reconstructing_s:.1f} s of reconstruction on one worker, whatever the cluster.\n")
    print("| machines (2 cores, 2 workers each) | detection s | job s (detection + reconstruction) | job speed-up |")
    print("|---|---|---|---|")
    for machines in (1, 2, 4, 8):
        detect = two.detecting_s / machines
        job = detect + two.reconstructing_s
        print(f"| {machines} | {detect:.1f} | {job:.1f} | {one.job_s / job:.2f} |")

if __name__ == "__main__":
    main()
