"""Pages of other origins in a real browser (Debian's Chromium, driven by Playwright),
against a real server: a page served from another port can neither stream frames to
/track nor change the map, while the web app, served by the service itself, works under
its Content-Security-Policy and keeps the API key for its tab only unless told."""

from __future__ import annotations

import functools
import threading
import time
from collections.abc import Iterator
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.conftest import NEEDS_CHROMIUM, example_map, free_port, running_server

pytestmark = NEEDS_CHROMIUM

#: Frames the other origin's page tries to stream.
FRAMES = 20

#: A page of another origin: it streams frames to /track, then tries to restore the map
#: with what a page may send without asking the service (no-cors: no body, a text body),
#: and with JSON (which needs a CORS preflight).
ATTACK_PAGE = """<!doctype html><meta charset="utf-8"><title>another site</title>
<script>
async function attack(service, environment, count) {
  const canvas = document.createElement("canvas");
  canvas.width = 320; canvas.height = 240;
  const g = canvas.getContext("2d"); g.fillStyle = "#888"; g.fillRect(0, 0, 320, 240);
  const frame = await (await new Promise((done) => canvas.toBlob(done, "image/jpeg", 0.8))).arrayBuffer();
  const track = await new Promise((done) => {
    const seen = { hello: false, frames: 0, closeCode: null, closeReason: "" };
    const ws = new WebSocket(service.replace(/^http/, "ws") + "/track?environment_id=" + environment);
    ws.onmessage = (event) => {
      const message = JSON.parse(event.data);
      if (message.type === "hello") { seen.hello = true; ws.send(frame); }
      if (message.type === "frame") { seen.frames += 1; if (seen.frames < count) ws.send(frame); else ws.close(); }
    };
    ws.onclose = (event) => { seen.closeCode = event.code; seen.closeReason = event.reason; done(seen); };
    setTimeout(() => done(seen), 60000);
  });
  const url = service + "/environments/" + environment + "/map/restore";
  const restores = [];
  for (const init of [{}, { body: "{}", headers: { "Content-Type": "text/plain" } }]) {
    try { await fetch(url, { method: "POST", mode: "no-cors", ...init }); restores.push("sent"); }
    catch (error) { restores.push("failed: " + error); }
  }
  let json;
  try { json = (await fetch(url, { method: "POST", headers: { "Content-Type": "application/json" }, body: "{}" })).status; }
  catch (error) { json = "failed: " + error; }
  restores.push(json);
  return { track, restores };
}
</script>"""


@pytest.fixture
def other_origin(tmp_path: Path) -> Iterator[str]:
    """The attack page, served on 127.0.0.1 at another port than the service's."""
    site = tmp_path / "site"
    site.mkdir()
    (site / "index.html").write_text(ATTACK_PAGE)

    class Quiet(SimpleHTTPRequestHandler):
        def log_message(self, format: str, *args: Any) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", free_port()), functools.partial(Quiet, directory=str(site)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


def _environment_with_two_maps(url: str) -> int:
    env = httpx.post(f"{url}/environments", json={"name": "studio", "marker_size_m": 0.15}).json()["id"]
    for n in (2, 3):
        assert httpx.put(f"{url}/environments/{env}/map", json=example_map(n)).status_code == 200
    return int(env)


def _csp_violations(page: Any) -> list[str]:
    found: list[str] = []
    page.on("console", lambda message: found.append(message.text)
            if "Content Security Policy" in message.text else None)
    return found


def test_a_page_of_another_origin_can_neither_stream_nor_restore_the_map(
        tmp_path: Path, browser: Any, other_origin: str) -> None:
    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        env = _environment_with_two_maps(server.url)
        before = httpx.get(f"{server.url}/environments/{env}/map").json()
        versions = httpx.get(f"{server.url}/environments/{env}/map/versions").json()
        page = browser.new_page()
        page.goto(other_origin + "/index.html")
        result = page.evaluate("([service, env, count]) => attack(service, env, count)", [server.url, env, FRAMES])
        page.close()
        print("the other origin's page:", result)
        assert result["track"]["frames"] == 0 and not result["track"]["hello"], result
        assert result["track"]["closeCode"] == 1008 and "is not allowed" in result["track"]["closeReason"], result
        # The JSON request needs a preflight the service never grants: the browser does not send it.
        assert result["restores"][2].startswith("failed"), result
        assert httpx.get(f"{server.url}/environments/{env}/map").json() == before
        assert httpx.get(f"{server.url}/environments/{env}/map/versions").json() == versions


def test_the_web_app_works_under_its_policy_from_its_own_origin(tmp_path: Path, browser: Any) -> None:
    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        env = _environment_with_two_maps(server.url)
        page = browser.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        violations = _csp_violations(page)
        document = page.goto(f"{server.url}/app/#/environments/{env}/map")
        assert "frame-ancestors 'none'" in document.headers["content-security-policy"]
        assert document.headers["x-frame-options"] == "DENY"
        # The map page draws the map with three.js (loaded through the import map) ...
        page.wait_for_selector(".viewer canvas", timeout=30_000)
        # ... and its restore button reverts the map.
        page.click("#restore-map")
        deadline = time.monotonic() + 30
        while len(httpx.get(f"{server.url}/environments/{env}/map").json()["targets"]) != 2:
            assert time.monotonic() < deadline, page.inner_text("#notice")
            time.sleep(0.2)
        assert httpx.get(f"{server.url}/environments/{env}/map/versions").json()[0]["replaced_by"] == "restore"
        # /track from the app's own origin (ws: under connect-src 'self').
        track = page.evaluate("""async (env) => {
          const { trackUrl } = await import("./js/api.js");
          const canvas = document.createElement("canvas"); canvas.width = 320; canvas.height = 240;
          const g = canvas.getContext("2d"); g.fillStyle = "#888"; g.fillRect(0, 0, 320, 240);
          const frame = await (await new Promise((done) => canvas.toBlob(done, "image/jpeg", 0.8))).arrayBuffer();
          return await new Promise((done) => {
            let frames = 0;
            const ws = new WebSocket(trackUrl(env));
            ws.onmessage = (event) => {
              const message = JSON.parse(event.data);
              if (message.type === "hello" || (message.type === "frame" && ++frames < 3)) ws.send(frame);
              else if (message.type === "frame") { ws.close(); done({ frames }); }
            };
            ws.onclose = (event) => done({ frames, code: event.code, reason: event.reason });
          });
        }""", env)
        assert track["frames"] == 3, track
        page.goto(f"{server.url}/app/#/environments")
        page.wait_for_selector("text=studio", timeout=30_000)
        assert errors == [] and violations == []


def test_the_key_is_kept_for_the_tab_unless_remembered(tmp_path: Path, browser: Any) -> None:
    with running_server(tmp_path / "data", tmp_path / "server.log") as server:
        context = browser.new_context()
        page = context.new_page()
        page.goto(f"{server.url}/app/")
        stores = "() => [sessionStorage.getItem('fidotrack.apiKey'), localStorage.getItem('fidotrack.apiKey')]"
        page.fill("#api-key", "ft_abc_secret")
        page.press("#api-key", "Enter")
        assert page.evaluate(stores) == ["ft_abc_secret", None]
        other_tab = context.new_page()
        other_tab.goto(f"{server.url}/app/")
        assert other_tab.input_value("#api-key") == ""  # another tab does not see it
        other_tab.close()
        page.check("#remember-key")
        assert page.evaluate(stores) == [None, "ft_abc_secret"]
        other_tab = context.new_page()
        other_tab.goto(f"{server.url}/app/")
        assert other_tab.input_value("#api-key") == "ft_abc_secret" and other_tab.is_checked("#remember-key")
        other_tab.click("#forget-key")
        assert other_tab.evaluate(stores) == [None, None] and other_tab.input_value("#api-key") == ""
        page.reload()
        assert page.input_value("#api-key") == ""
        context.close()
