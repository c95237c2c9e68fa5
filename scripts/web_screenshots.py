"""Screenshots of each page of the web app for the docs (``docs/images/web-*.png``).

Starts a server on a fresh data directory, surveys a rendered room through the survey
page, then visits the environments, map, live tracking (Chromium's fake camera playing a
rendered walk of the surveyed room) and detection pages. Needs Chromium
(``apt-get install chromium``) and the test extras (Playwright).

Run: ``.venv/bin/python scripts/web_screenshots.py [--out docs/images]``
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import cv2
import httpx
import numpy as np
from playwright.sync_api import sync_playwright

from app.local_server import running_server
from app.sim import SMALL_ROOM, render_walk
from app.sim.camera_feed import write_y4m
from app.sim.scenes import scenario_frame

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "images")
    args = parser.parse_args()
    chromium = shutil.which("chromium")
    if chromium is None:
        print("web_screenshots: needs Chromium (apt-get install chromium)", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        room = SMALL_ROOM.walk(5, 90, kind="calibration")
        size = (SMALL_ROOM.camera.width, SMALL_ROOM.camera.height)
        writer = cv2.VideoWriter(str(tmp / "room.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, size)
        for image, _ in render_walk(room.scene, SMALL_ROOM.camera, room.poses, room.rng, degradation="none"):
            writer.write(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
        writer.release()
        walk = SMALL_ROOM.walk(5, 90, kind="tracking")
        write_y4m(tmp / "walk.y4m", (image for image, _ in render_walk(
            walk.scene, SMALL_ROOM.camera, walk.poses, walk.rng, degradation="default")))
        picture, _ = scenario_frame("default", np.random.default_rng(2))
        cv2.imwrite(str(tmp / "cards.png"), picture)

        with running_server(tmp / "data", log=tmp / "server.log") as server, sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=chromium, args=[
                "--no-sandbox", "--use-fake-device-for-media-stream", "--use-fake-ui-for-media-stream",
                f"--use-file-for-fake-video-capture={tmp / 'walk.y4m'}"])
            page = browser.new_context(viewport={"width": 1300, "height": 820}, permissions=["camera"]).new_page()
            httpx.post(f"{server.url}/environments", json={"name": "studio A", "marker_size_m": 0.2})
            page.goto(f"{server.url}/app/")
            page.fill("input[name=name]", "small room")
            page.fill("input[name=marker_size_mm]", str(1000 * SMALL_ROOM.marker_size_m))
            page.click("button:text-is('Create')")
            page.wait_for_function("location.hash.endsWith('/survey')")
            page.set_input_files("input[name=video]", str(tmp / "room.avi"))
            page.click("button:text-is('Upload and survey')")
            page.wait_for_function("window.fidotrack.survey.job && window.fidotrack.survey.job.progress > 0.3",
                                   timeout=120_000)
            page.screenshot(path=str(args.out / "web-survey-running.png"))
            page.wait_for_function("window.fidotrack.survey.job.status === 'succeeded'", timeout=300_000)
            page.screenshot(path=str(args.out / "web-survey.png"))
            environment_id = page.evaluate("window.fidotrack.survey.environmentId")
            page.goto(f"{server.url}/app/#/environments")
            page.wait_for_selector("#environments")
            page.screenshot(path=str(args.out / "web-environments.png"))
            page.goto(f"{server.url}/app/#/environments/{environment_id}/map")
            page.wait_for_function("window.fidotrack.map && window.fidotrack.map.cards > 0")
            page.wait_for_timeout(500)
            page.screenshot(path=str(args.out / "web-map.png"))
            page.goto(f"{server.url}/app/#/environments/{environment_id}/track")
            page.click("#start")
            page.wait_for_function("window.fidotrack.track.replies.filter(r => r.pose).length >= 40", timeout=60_000)
            page.wait_for_function("window.fidotrack.track.replies.at(-1).pose !== null", timeout=30_000)
            page.screenshot(path=str(args.out / "web-track.png"))
            page.click("#start")
            page.goto(f"{server.url}/app/#/detect")
            page.set_input_files("#detect-file", str(tmp / "cards.png"))
            page.wait_for_function("window.fidotrack.detect.result !== null")
            page.screenshot(path=str(args.out / "web-detect.png"), full_page=True)
            browser.close()
    for path in sorted(args.out.glob("web-*.png")):
        print(f"wrote {path.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
