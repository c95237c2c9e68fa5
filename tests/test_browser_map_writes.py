"""The web app's map page changes only the map it shows: its alignments and restores carry
the map's ETag in If-Match, and when another change came first (412) the page says so and
reloads the map instead of overwriting it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import httpx

from tests.conftest import NEEDS_CHROMIUM, example_map, running_server

pytestmark = NEEDS_CHROMIUM


def test_the_map_page_reloads_a_map_changed_meanwhile_instead_of_overwriting_it(tmp_path: Path,
                                                                                browser: Any) -> None:
    with running_server(tmp_path / "data", tmp_path / "server.log") as server, \
            httpx.Client(base_url=server.url) as http:
        env = http.post("/environments", json={"name": "room", "marker_size_m": 0.1}).json()["id"]
        http.put(f"/environments/{env}/map", json=example_map(3)).raise_for_status()
        # (The page's Content-Security-Policy would refuse the test's own string predicates.)
        page = browser.new_context(viewport={"width": 1300, "height": 900}, bypass_csp=True).new_page()
        errors: list[str] = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto(f"{server.url}/app/#/environments/{env}/map")
        page.wait_for_function("window.fidotrack.map && window.fidotrack.map.cards === 3", timeout=30_000)
        assert page.evaluate("window.fidotrack.map.etag") == http.get(f"/environments/{env}/map").headers["ETag"]

        # Another client replaces the map while the page shows the old one.
        http.put(f"/environments/{env}/map", json=example_map(2)).raise_for_status()
        page.click("button:text-is('Set origin')")
        page.wait_for_function("window.fidotrack.map.reloads === 1 && window.fidotrack.map.cards === 2",
                               timeout=10_000)
        assert "changed meanwhile" in page.locator("#notice").inner_text()
        stored = http.get(f"/environments/{env}/map")
        assert stored.json()["frame"] == "survey" and len(stored.json()["targets"]) == 2  # not overwritten
        assert page.evaluate("window.fidotrack.map.etag") == stored.headers["ETag"]

        # Made again on the map now shown, the alignment is stored.
        page.click("button:text-is('Set origin')")
        page.wait_for_function("window.fidotrack.map.frame === 'world'", timeout=10_000)
        aligned = http.get(f"/environments/{env}/map")
        assert aligned.json()["frame"] == "world" and page.evaluate("window.fidotrack.map.etag") == aligned.headers["ETag"]

        # A restore is refused the same way when the map changed under the page.
        http.put(f"/environments/{env}/map", json=example_map(4)).raise_for_status()
        page.click("#restore-map")
        page.wait_for_function("window.fidotrack.map.reloads === 2 && window.fidotrack.map.cards === 4",
                               timeout=10_000)
        assert len(http.get(f"/environments/{env}/map").json()["targets"]) == 4
        page.click("#restore-map")
        page.wait_for_function("window.fidotrack.map.frame === 'world' && window.fidotrack.map.cards === 2",
                               timeout=10_000)
    assert errors == []
