"""The service's own pages in a real browser (Debian's Chromium, driven by Playwright),
against a real server, with every request that would leave the service blocked: what a
user on a network without internet sees."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest

from app.core.geometry import Pose

from tests.conftest import CHROMIUM, NEEDS_CHROMIUM, running_server

pytestmark = NEEDS_CHROMIUM


def _offline_page(browser: Any, origin: str, offsite: list[str]) -> Any:
    """A page that may load from `origin` only; every other request is aborted and noted."""
    page = browser.new_page()

    def only_the_service(route: Any) -> None:
        if route.request.url.startswith(origin):
            route.continue_()
        else:
            offsite.append(route.request.url)
            route.abort()

    page.route("**/*", only_the_service)
    return page


def test_docs_and_redoc_render_every_operation_without_internet(tmp_path: Path, browser: Any) -> None:
    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        spec = httpx.get(f"{server.url}/openapi.json").json()
        operations = {(method.upper(), path) for path, item in spec["paths"].items() for method in item}
        offsite: list[str] = []
        page = _offline_page(browser, server.url, offsite)
        page.goto(f"{server.url}/docs")
        page.wait_for_selector(".opblock", timeout=30_000)
        shown = {(method.strip().upper(), path.strip()) for method, path in zip(
            page.locator(".opblock-summary-method").all_inner_texts(),
            page.locator(".opblock-summary-path").all_inner_texts(), strict=True)}
        assert shown == operations
        assert offsite == []
        page.goto(f"{server.url}/redoc")
        page.wait_for_selector("text=Find and identify the targets in a JPEG or PNG image", timeout=30_000)
        # ReDoc's bundle asks its maker's site for its logo: decoration, nothing the page needs.
        assert all(url.endswith((".svg", ".png")) for url in offsite), offsite


# --------------------------------------------------------------------------------------
# The web app
# --------------------------------------------------------------------------------------

#: Where the tests keep their screenshots (CI keeps the directory as the run's artifacts).
ARTIFACTS = Path(os.environ.get("FIDOTRACK_TEST_ARTIFACTS", Path(__file__).resolve().parents[1] / "test-artifacts"))


def _watched_page(browser: Any, **context: Any) -> tuple[Any, list[str]]:
    """A page whose script errors are collected: a page that throws fails its test.
    (Its ``wait_for_function`` predicates are functions, ``"() => ..."``: the pages'
    Content-Security-Policy refuses the eval Playwright needs to poll a bare expression.)"""
    page = browser.new_context(viewport={"width": 1300, "height": 900}, **context).new_page()
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    return page, errors


def _screenshot(page: Any, name: str) -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / f"{name}.png"
    page.screenshot(path=str(path))
    return path


@dataclass
class StampedWalk:
    """A tracking walk of the bench room as the fake camera plays it, with its truth."""

    y4m: Path
    frames: list[np.ndarray]  # stamped grey frames, in walk order
    truth: list[Pose]
    map_document: dict


@pytest.fixture(scope="module")
def stamped_walk(tmp_path_factory: pytest.TempPathFactory) -> StampedWalk:
    from app.sim import BENCH_CAMERA, BENCH_ROOM, render_walk
    from app.sim.camera_feed import stamp_frame_index, write_y4m

    room = BENCH_ROOM.walk(3, 60, kind="tracking")
    frames = [stamp_frame_index(image, k) for k, (image, _) in
              enumerate(render_walk(room.scene, BENCH_CAMERA, room.poses, room.rng, degradation="default"))]
    path = tmp_path_factory.mktemp("camera") / "walk.y4m"
    write_y4m(path, frames, fps=30)
    return StampedWalk(path, frames, list(room.poses), room.scene.map_document(BENCH_CAMERA))


def _camera_browser(playwright: Any, y4m: Path) -> Any:
    """Chromium whose camera plays `y4m` (in a loop), granted to every page without asking."""
    return playwright.chromium.launch(executable_path=CHROMIUM, args=[
        "--no-sandbox", "--use-fake-device-for-media-stream", "--use-fake-ui-for-media-stream",
        f"--use-file-for-fake-video-capture={y4m}"])


def _errors_mm(replies: list[dict], indices: list[int | None], truth: list[Pose]) -> np.ndarray:
    """Position error of each posed reply against the truth of the walk frame it showed."""
    return np.array([1000 * np.linalg.norm(np.asarray(r["pose"]["position"]) - truth[indices[r["seq"]]].position)
                     for r in replies if r["pose"] is not None and indices[r["seq"]] is not None])


def _track_directly(url: str, frames: list[np.ndarray], quality: int = 85) -> list[dict]:
    """The same frames sent by a Python client in lock-step: the replies."""
    from websockets.sync.client import connect

    replies = []
    with connect(url, open_timeout=10, max_size=None) as ws:
        assert json.loads(ws.recv(timeout=10))["type"] == "hello"
        for frame in frames:
            ws.send(cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, quality])[1].tobytes())
            replies.append(json.loads(ws.recv(timeout=30)))
    return replies


def test_live_tracking_from_the_browser_camera_gives_the_poses_track_gives(tmp_path: Path, playwright: Any,
                                                                         stamped_walk: StampedWalk) -> None:
    # Chromium's fake camera plays the rendered walk; the page encodes what it shows and
    # streams it to /track. Each frame sent carries its walk index, read back from the
    # bytes on the wire, so every pose the page reports is checked against the truth.
    from app.sim.camera_feed import read_frame_index

    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        env = httpx.post(f"{server.url}/environments", json={"name": "bench room", "marker_size_m": 0.2}).json()
        httpx.put(f"{server.url}/environments/{env['id']}/map", json=stamped_walk.map_document).raise_for_status()
        browser = _camera_browser(playwright, stamped_walk.y4m)
        try:
            page, errors = _watched_page(browser, permissions=["camera"])
            sent: list[bytes] = []
            page.on("websocket", lambda ws: ws.on(
                "framesent", lambda payload: sent.append(payload) if isinstance(payload, bytes) else None))
            page.goto(f"{server.url}/app/#/environments/{env['id']}/track")
            page.click("#start")
            page.wait_for_function("() => window.fidotrack.track.replies.length >= 90", timeout=90_000)
            page.click("#start")  # stop
            state = page.evaluate("window.fidotrack.track")
            stats = page.locator("#track-stats").inner_text()
            _screenshot(page, "track")
        finally:
            browser.close()
        indices = [read_frame_index(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE))
                   for data in sent]
        assert all(i is not None for i in indices)
        # The same walk frames in the order the page sent them (it skips some, and the
        # camera loops), encoded here: what /track gives them tells the browser's part.
        url = server.url.replace("http://", "ws://") + f"/track?environment_id={env['id']}"
        direct = _track_directly(url, [stamped_walk.frames[i] for i in indices])

    assert errors == [] and state["errors"] == []
    replies = state["replies"]
    assert [r["seq"] for r in replies] == list(range(len(replies)))  # lock-step: every frame answered
    assert all(r["dropped"] == 0 for r in replies)
    assert len(set(indices)) >= 20  # the camera's picture moved on: the walk was played, not one frame
    with_targets = [r for r in replies if r["targets"]]
    assert len(with_targets) >= 0.5 * len(replies)
    assert sum(r["pose"] is not None for r in with_targets) >= 0.9 * len(with_targets)
    page_mm = _errors_mm(replies, indices, stamped_walk.truth)
    direct_mm = _errors_mm(direct, indices, stamped_walk.truth)
    # The browser's own JPEG of the same picture: poses as accurate as the frames sent directly.
    # (The tail rests on the few frames with one card in view, whose poses swing by
    # millimetres with a pixel's difference: it gets a wider margin than the median.)
    assert np.median(page_mm) <= 1.5 * np.median(direct_mm) + 0.5, (np.median(page_mm), np.median(direct_mm))
    assert np.quantile(page_mm, 0.9) <= 2 * np.quantile(direct_mm, 0.9) + 2.0
    assert "fps" in stats and "latency p50" in stats


@dataclass
class SurveyVideo:
    """A calibration walk of the small example room as a video file, with the room's truth."""

    path: Path
    scene: Any  # app.sim.scenes.Scene
    marker_size_m: float
    room_size: tuple[float, float, float]


@pytest.fixture(scope="module")
def survey_video(tmp_path_factory: pytest.TempPathFactory) -> SurveyVideo:
    from app.sim import SMALL_ROOM, render_walk

    room = SMALL_ROOM.walk(5, 90, kind="calibration")
    path = tmp_path_factory.mktemp("survey") / "room.avi"
    size = (SMALL_ROOM.camera.width, SMALL_ROOM.camera.height)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, size)
    for image, _ in render_walk(room.scene, SMALL_ROOM.camera, room.poses, room.rng, degradation="none"):
        writer.write(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
    writer.release()
    return SurveyVideo(path, room.scene, SMALL_ROOM.marker_size_m, SMALL_ROOM.size)


def _survey_page(page: Any, server_url: str, video: SurveyVideo) -> None:
    """Create an environment through the page and choose the video on its survey page."""
    page.goto(f"{server_url}/app/")
    page.fill("input[name=name]", "small room")
    page.fill("input[name=marker_size_mm]", str(1000 * video.marker_size_m))
    page.click("button:text-is('Create')")
    page.wait_for_function("() => location.hash.endsWith('/survey')")
    page.set_input_files("input[name=video]", str(video.path))


def test_a_survey_uploaded_through_the_page_maps_and_shows_every_card(tmp_path: Path, browser: Any,
                                                                     survey_video: SurveyVideo) -> None:
    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        page, errors = _watched_page(browser)
        _survey_page(page, server.url, survey_video)
        # 30 of the 90 frames with the cards alone: a thin survey, so that it warns about some cards.
        page.fill("#survey-frames", "30")
        page.uncheck("#survey-features")
        # A rolling shutter's readout reaches the service: one longer than a frame is refused, said on the page.
        page.fill("#survey-readout", "40")
        page.click("button:text-is('Upload and survey')")
        page.locator("#notice").wait_for(state="visible")
        assert "readout_ms" in page.locator("#notice").inner_text()
        page.fill("#survey-readout", "")
        page.click("button:text-is('Upload and survey')")
        # The job's progress is shown live: record what the page shows while it runs.
        seen: list[float] = []
        for _ in range(600):
            job = page.evaluate("window.fidotrack.survey.job")
            if job is not None:
                seen.append(job["progress"])
                if job["status"] in ("succeeded", "failed", "cancelled"):
                    break
            page.wait_for_timeout(250)
        assert job is not None and job["status"] == "succeeded", job
        assert page.evaluate("window.fidotrack.survey.upload.done")
        assert len(set(seen)) >= 3 and seen == sorted(seen)  # several stages of progress, never backwards
        result_text = page.locator("#survey-result").inner_text()
        assert f"{job['result']['n_targets']} cards mapped" in result_text
        # Every warning is listed; those about cards carry a link to each card they name.
        assert page.locator("#survey-result ul.warnings li").count() == len(job["result"]["warnings"]) > 0
        chips = page.locator("#survey-result a.chip")
        named = [i for w in job["result"]["card_warnings"] for i in w["target_ids"]]
        assert chips.all_inner_texts() == [f"card {i}" for i in named] and named
        mapped = httpx.get(f"{server.url}/environments/{job['environment_id']}/map").json()
        in_map = [i for i in named if i in {t["id"] for t in mapped["targets"]}]
        if in_map:  # a card the survey mapped weakly: its link opens the map looking at it
            chips.nth(named.index(in_map[0])).click()
            page.wait_for_function(f"() => window.fidotrack.map && window.fidotrack.map.focused === {in_map[0]}",
                                   timeout=30_000)
            page.go_back()
        page.click("text=Open the map")
        page.wait_for_function("() => window.fidotrack.map && window.fidotrack.map.cards > 0 && "
                               "window.fidotrack.map.focused === null", timeout=30_000)
        state = page.evaluate("window.fidotrack.map")
        assert state["ids"] == sorted(t["id"] for t in mapped["targets"])
        # A still view is not redrawn (a phone without a GPU would draw it in software
        # 60 times a second); a change of view is.
        page.wait_for_timeout(500)  # (the first frames: the map, the layout's resize)
        drawn = page.evaluate("window.fidotrack.map.framesDrawn")
        page.wait_for_timeout(1000)
        assert page.evaluate("window.fidotrack.map.framesDrawn") == drawn > 0
        page.click("button:text-is('Top down')")
        page.wait_for_function(f"() => window.fidotrack.map.framesDrawn > {drawn}")
        assert state["trajectory"] == sum(p is not None for p in job["result"]["trajectory"])
        _screenshot(page, "map")
        # Align to the world with the first card as origin: the viewer redraws the aligned map.
        page.select_option("#origin-card", str(state["ids"][0]))
        page.click("button:text-is('Set origin')")
        page.wait_for_function("() => window.fidotrack.map.frame === 'world'", timeout=10_000)
        origin_map = httpx.get(f"{server.url}/environments/{state['environmentId']}/map").json()
        assert origin_map["frame"] == "world"
        assert page.evaluate("window.fidotrack.map.cards") == len(mapped["targets"])
        # Or known points: four discs at their true places in the room; the residuals are shown.
        truth = {t.id: t.discs for t in survey_video.scene.targets}
        lines = [f"{i} {d} " + " ".join(f"{x:.5f}" for x in truth[i][d]) for i, d in zip(state["ids"][:4], (0, 1, 2, 3))]
        page.fill("textarea", "\n".join(["# target disc x y z", *lines]))
        page.click("button:text-is('Fit')")
        page.wait_for_function("() => window.fidotrack.map.alignment && window.fidotrack.map.alignment.residuals.length === 4")
        alignment = page.evaluate("window.fidotrack.map.alignment")
        assert alignment["scale"] == 1.0 and alignment["rms_m"] < 0.005  # rigid: the survey's metric scale kept
        assert page.locator("#alignment-residuals tr").count() == 1 + 4
        # The survey's camera path moved with the map: now in the room, where the walk went.
        path = np.asarray(page.evaluate("window.fidotrack.map.cameraPath"))
        assert len(path) == state["trajectory"]
        assert np.all((path > -0.05) & (path < np.asarray(survey_video.room_size) + 0.05)), path
        # Undo the fit: the origin alignment's map is back, drawn whole.
        page.click("#restore-map")
        page.wait_for_function("() => window.fidotrack.map.alignment === null")
        assert httpx.get(f"{server.url}/environments/{state['environmentId']}/map").json() == origin_map
        assert page.evaluate("window.fidotrack.map.cards") == len(mapped["targets"])
    assert errors == []


def test_a_survey_cancelled_from_the_page_keeps_the_old_map(tmp_path: Path, browser: Any,
                                                            survey_video: SurveyVideo) -> None:
    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        page, errors = _watched_page(browser)
        _survey_page(page, server.url, survey_video)
        page.click("button:text-is('Upload and survey')")
        page.wait_for_function("() => window.fidotrack.survey.job && window.fidotrack.survey.job.status === 'running'",
                               timeout=60_000)
        page.click("button:text-is('Cancel')")
        page.wait_for_function("() => window.fidotrack.survey.job.status === 'cancelled'", timeout=60_000)
        assert "previous map" in page.locator("#survey-result").inner_text()
        environment_id = page.evaluate("window.fidotrack.survey.environmentId")
        assert httpx.get(f"{server.url}/environments/{environment_id}").json()["has_map"] is False
    assert errors == []


def test_the_detection_check_draws_the_targets_of_a_chosen_image(tmp_path: Path, browser: Any) -> None:
    from app.sim.scenes import scenario_frame

    image, truth = scenario_frame("default", np.random.default_rng(2))
    path = tmp_path / "cards.png"
    cv2.imwrite(str(path), image)
    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        page, errors = _watched_page(browser)
        page.goto(f"{server.url}/app/#/detect")
        page.set_input_files("#detect-file", str(path))
        page.wait_for_function("() => window.fidotrack.detect.result !== null", timeout=30_000)
        result = page.evaluate("window.fidotrack.detect.result")
        _screenshot(page, "detect")
        expected = httpx.post(f"{server.url}/detect", content=path.read_bytes(),
                              headers={"Content-Type": "image/png"}).json()
    assert sorted(t["id"] for t in result["targets"]) == sorted(t["id"] for t in expected["targets"])
    assert {t["id"] for t in result["targets"]} <= {t.id for t in truth.visible_targets()}
    assert len(result["targets"]) >= 1 and len(result["candidates"]) >= 4 * len(result["targets"])
    assert errors == []


def test_the_pages_show_the_services_errors_and_use_the_key_typed_in(tmp_path: Path, browser: Any,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FIDOTRACK_API_KEYS", "true")
    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        created = subprocess.run([str(Path(sys.executable).with_name("fidotrack")), "keys", "create", "--name", "web",
                                  "--scopes", "read,track,admin"], env={**os.environ, "FIDOTRACK_DATA_DIR": str(tmp_path / "data")},
                                 capture_output=True, text=True, check=True)
        key = created.stdout.split()[-1]
        page, errors = _watched_page(browser)
        page.goto(f"{server.url}/app/")  # the page itself needs no key
        notice = page.locator("#notice")
        notice.wait_for(state="visible")
        assert "401" in notice.inner_text()
        page.fill("#api-key", key)
        page.press("#api-key", "Enter")
        page.wait_for_selector("text=No environment yet")
        assert notice.is_hidden()
        page.fill("input[name=name]", "lab")
        page.fill("input[name=marker_size_mm]", "150")
        page.click("button:text-is('Create')")
        page.wait_for_function("() => location.hash.endsWith('/survey')")
        # The sheet of cards to print, at the environment's card side, fetched with the key.
        page.goto(f"{server.url}/app/#/environments")
        with page.expect_response(lambda r: "/markers/sheet.pdf" in r.url) as sheet, page.expect_popup():
            page.click("button:text-is('Print cards')")
        assert sheet.value.status == 200 and sheet.value.headers["content-type"] == "application/pdf"
        assert "size_mm=150" in sheet.value.url and "ids=0-11" in sheet.value.url
        page.goto(f"{server.url}/app/#/environments/1/map")  # no map yet: the service says so
        notice.wait_for(state="visible")
        assert "409" in notice.inner_text() and "no map" in notice.inner_text()
    assert errors == []


def _lan_address() -> str | None:
    """This machine's address on its network (what a phone would connect to), if it has one."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect(("192.0.2.123", 9))  # no packet is sent: this only picks the route
        except OSError:
            return None
        address = probe.getsockname()[0]
    return None if address.startswith("127.") else address


def test_a_phone_on_the_network_gets_the_camera_over_https(tmp_path: Path, playwright: Any,
                                                           stamped_walk: StampedWalk,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    # Browsers give a page the camera only in a secure context: https, or localhost. From
    # another machine, plain http must say so; `fidotrack serve` with a certificate works.
    address = _lan_address()
    if address is None or shutil.which("openssl") is None:
        pytest.skip("needs a network address and openssl")
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj",
                    f"/CN={address}", "-keyout", str(key), "-out", str(cert)], check=True, capture_output=True)
    monkeypatch.setenv("FIDOTRACK_HOST", "0.0.0.0")
    browser = _camera_browser(playwright, stamped_walk.y4m)
    try:
        with running_server(tmp_path / "data", tmp_path / "server.log") as server:
            env = httpx.post(f"{server.url}/environments", json={"name": "bench room", "marker_size_m": 0.2}).json()
            httpx.put(f"{server.url}/environments/{env['id']}/map", json=stamped_walk.map_document).raise_for_status()
            page, plain_errors = _watched_page(browser, permissions=["camera"])
            page.goto(server.url.replace("127.0.0.1", address) + f"/app/#/environments/{env['id']}/track")
            page.click("#start")
            page.locator("#notice").wait_for(state="visible")
            assert "https" in page.locator("#notice").inner_text()
            assert page.evaluate("window.fidotrack.track.sent") == 0
        monkeypatch.setenv("FIDOTRACK_TLS_CERTFILE", str(cert))
        monkeypatch.setenv("FIDOTRACK_TLS_KEYFILE", str(key))
        with running_server(tmp_path / "data", tmp_path / "server.log") as server:
            assert server.url.startswith("https://")
            page, errors = _watched_page(browser, permissions=["camera"], ignore_https_errors=True)
            page.goto(server.url.replace("127.0.0.1", address) + f"/app/#/environments/{env['id']}/track")
            page.click("#start")
            page.wait_for_function("() => window.fidotrack.track.replies.filter(r => r.pose).length >= 5", timeout=60_000)
            assert page.evaluate("window.fidotrack.track.errors") == []
    finally:
        browser.close()
    assert plain_errors == [] and errors == []


def test_the_3d_views_geometry_matches_numpy(tmp_path: Path, browser: Any) -> None:
    # The page's own numerics: the uncertainty ellipsoid's axes (eigen-decomposition of
    # the pose covariance) and a card's corners fitted to its four disc centres.
    rng = np.random.default_rng(1)
    a = rng.normal(size=(3, 3))
    covariance = (a @ a.T * 1e-6).tolist()
    origin, u_axis, v_axis = rng.normal(size=3), rng.normal(size=3), rng.normal(size=3)
    discs_uv = [[0.2, 0.2], [0.8, 0.2], [0.8, 0.8], [0.2, 0.8]]
    discs = [(origin + u * u_axis + v * v_axis).tolist() for u, v in discs_uv]
    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        page, errors = _watched_page(browser)
        page.goto(f"{server.url}/app/")
        values, vectors, corners = page.evaluate("""async ([covariance, discs, uv]) => {
            const scene = await import("./js/scene.js");
            const [values, vectors] = scene.symmetricEigen(covariance);
            const corners = scene.cardCorners(discs, uv).map((c) => [c.x, c.y, c.z]);
            return [values, vectors, corners];
        }""", [covariance, discs, discs_uv])
    expected = np.linalg.eigvalsh(np.asarray(covariance))
    np.testing.assert_allclose(sorted(values), expected, rtol=1e-9, atol=1e-15)
    v = np.asarray(vectors)
    np.testing.assert_allclose(v.T @ np.asarray(covariance) @ v, np.diag(values), atol=1e-15)
    truth = [origin + u * u_axis + w * v_axis for u, w in ((0, 0), (1, 0), (1, 1), (0, 1))]
    np.testing.assert_allclose(corners, truth, atol=1e-9)
    assert errors == []
