"""``fidotrack demo``: the whole system at work on a simulated room, in one command.

The simulator renders a room with cards on its walls (`app.sim.examples.SMALL_ROOM`),
films it along a survey walk and a tracking walk, and knows where every disc and every
camera truly is. The demo then uses the service as a client would, through
`app.client.Client`: it creates an environment, surveys it from the video, aligns the
surveyed map to the room with four known disc positions (rigid: the survey is already
metric), streams the tracking walk to ``/track``, and prints how close the map and the
poses are to the truth. Without ``--url`` it starts its own ``fidotrack serve`` on a free
port with a temporary data directory, and stops it at the end.

Needs the simulator: ``pip install -e '.[sim]'``.
"""

from __future__ import annotations

import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from tqdm import tqdm

from app.client import ApiError, Client, JobFailed
from app.core.geometry import Pose
from app.local_server import ServerNotReady, free_port, running_server
from app.schemas import AlignmentRequest, JobOut, SurveyResult

__all__ = ["DEMO_FRAMES", "run_demo"]

#: Frames of the survey walk and of the tracking walk: the full demo, and ``--small``.
DEMO_FRAMES = {False: (120, 150), True: (60, 60)}
#: The demo's random seed: the same room, walks and frames every time.
SEED = 5
#: The settings of the service the demo starts, over the caller's environment: no API
#: keys (the demo is its only client), and warnings only in its log.
DEMO_SERVER_SETTINGS = {"FIDOTRACK_API_KEYS": "false", "FIDOTRACK_LOG_LEVEL": "WARNING"}
#: Seconds the demo waits for the service it starts: a machine's first start compiles the
#: detector's kernels.
DEMO_READY_TIMEOUT_S = 300.0


@contextmanager
def _service(url: str | None, api_key: str | None, data_dir: Path, quiet: bool) -> Iterator[Client]:
    """A client of the service at `url`, or of a ``fidotrack serve`` started for the demo."""
    if url is not None:
        with Client(url, api_key=api_key) as client:
            if not client.ready():
                raise ApiError(0, f"no ready service at {url}")
            print(f"service: {url}")
            yield client
        return
    port = free_port()
    print(f"service: starting on http://127.0.0.1:{port} (the first start on a machine compiles the detector's "
          "kernels: 10-30 s)")
    began = time.monotonic()
    try:
        with running_server(data_dir, port=port, settings=DEMO_SERVER_SETTINGS, log=data_dir.parent / "server.log",
                            timeout=DEMO_READY_TIMEOUT_S) as server, Client(server.url) as client:
            print(f"service: ready after {time.monotonic() - began:.1f} s")
            yield client
    except ServerNotReady as error:
        raise ApiError(0, f"the service did not start: {error}") from None


def run_demo(url: str | None = None, api_key: str | None = None, small: bool = False, quiet: bool = False,
             keep: Path | None = None) -> int:
    """Render, survey, align, track, and print the accuracy against the truth.

    Parameters
    ----------
    url : str, optional
        A running service to use; default: start one.
    api_key : str, optional
        The key for `url`, when it requires keys (an ``admin`` key: the demo creates an
        environment).
    small : bool
        Shorter walks (`DEMO_FRAMES`).
    quiet : bool
        No progress bars.
    keep : Path, optional
        Keep the rendered video and frames there.

    Returns
    -------
    int
        0 when every step worked; 1 otherwise (the step and the reason printed).
    """
    import cv2

    from app.sim import SMALL_ROOM, render_walk
    from app.sim.walks import camera_walk

    started = time.monotonic()
    room = SMALL_ROOM
    camera = room.camera
    n_survey, n_track = DEMO_FRAMES[small]
    size_m = " x ".join(f"{v:g}" for v in room.size)
    print(f"fidotrack demo: a simulated room of {size_m} m with {room.n_targets} cards of {room.marker_size_m} m, "
          f"filmed by a {camera.width}x{camera.height} camera (f = {camera.fx:.0f} px, k1 = {camera.dist[0]:g})")
    with tempfile.TemporaryDirectory(prefix="fidotrack-demo-") as scratch:
        folder = Path(keep) if keep is not None else Path(scratch)
        folder.mkdir(parents=True, exist_ok=True)
        survey_walk = room.walk(SEED, n_survey, kind="calibration")
        video = folder / "survey.avi"
        writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (camera.width, camera.height))
        for image, _ in tqdm(render_walk(survey_walk.scene, camera, survey_walk.poses, survey_walk.rng,
                                         degradation="default"), total=n_survey, desc="rendering the survey video",
                             unit="frame", disable=quiet):
            writer.write(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
        writer.release()
        poses = camera_walk(survey_walk.rng, room.size, n_track, kind="tracking")
        frames = [cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
                  for image, _ in tqdm(render_walk(survey_walk.scene, camera, poses, survey_walk.rng,
                                                   degradation="default"), total=n_track,
                                       desc="rendering the tracking walk", unit="frame", disable=quiet)]
        truth = {target.id: target.discs for target in survey_walk.scene.targets}
        try:
            with _service(url, api_key, Path(scratch) / "data", quiet) as client:
                code = _use_the_service(client, video, frames, poses, truth, room.marker_size_m, started, quiet)
                if url is not None:
                    print(f"The map stays on the service: open {url.rstrip('/')}/app/ to see it.")
                return code
        except (ApiError, JobFailed) as error:
            print(f"fidotrack demo: {error}", file=sys.stderr)
            return 1


def _use_the_service(client: Client, video: Path, frames: list[bytes], poses: list[Pose],
                     truth: dict[int, np.ndarray], marker_size_m: float, started: float, quiet: bool) -> int:
    """Survey, align, track and print; 0 when a pose came back."""
    environment = client.create_environment(f"demo room {time.strftime('%H:%M:%S')}", marker_size_m)
    print(f"environment {environment.id}: cards of {marker_size_m} m")

    with tqdm(total=1.0, bar_format="{l_bar}{bar}| {elapsed}", disable=quiet) as bar:
        def progress(job: JobOut) -> None:
            bar.set_description(f"survey: {job.stage}"[:48])
            bar.n = job.progress
            bar.refresh()

        began = time.monotonic()
        job = client.survey(environment.id, video, progress)
    result = job.result
    assert isinstance(result, SurveyResult)
    print(f"survey: {result.n_targets} of {len(truth)} cards mapped from {result.n_registered} of "
          f"{result.n_frames} frames in {time.monotonic() - began:.1f} s; reprojection RMS "
          f"{result.rms_px:.2f} px; focal length {result.focal_px:.1f} px")
    for warning in result.warnings:
        print(f"  warning: {warning}")

    # The survey's map has its own origin and axes; four discs whose room positions are
    # known put it in the room's frame, without changing its scale.
    surveyed = client.get_map(environment.id)
    ids = sorted(t.id for t in surveyed.targets)
    picks = [ids[round(k * (len(ids) - 1) / 3)] for k in range(4)]
    points = [{"target_id": i, "disc": k, "world": truth[i][k].tolist()} for k, i in enumerate(picks)]
    aligned = client.align(environment.id, AlignmentRequest.model_validate({"points": points, "allow_scale": False}))
    errors = np.concatenate([np.linalg.norm(np.asarray(t.discs) - truth[t.id], axis=1) for t in aligned.map.targets])
    print(f"map: {len(errors)} disc centres within {1000 * np.sqrt(np.mean(errors ** 2)):.2f} mm RMS "
          f"({1000 * errors.max():.2f} mm at most) of their true places, after a rigid alignment on 4 of them")

    began = time.monotonic()
    position_mm: list[float] = []
    first_pose = None
    for reply in tqdm(client.track(environment.id, frames), total=len(frames), desc="tracking", unit="frame",
                      disable=quiet):
        if reply.pose is not None:
            if first_pose is None:
                first_pose = time.monotonic() - started
            position_mm.append(1000 * float(np.linalg.norm(np.asarray(reply.pose.position)
                                                          - poses[reply.seq].position)))
    seconds = time.monotonic() - began
    if not position_mm:
        print("tracking: no frame gave a pose", file=sys.stderr)
        return 1
    print(f"tracking: {len(position_mm)} of {len(frames)} frames posed at {len(frames) / seconds:.0f} frames/s; "
          f"camera position error median {np.median(position_mm):.1f} mm, p90 {np.quantile(position_mm, 0.9):.1f} mm")
    print(f"first pose {first_pose:.0f} s after the demo started; done in {time.monotonic() - started:.0f} s")
    return 0
