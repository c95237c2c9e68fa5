"""The service's own pages in a real browser (Debian's Chromium, driven by Playwright),
against a real server, with every request that would leave the service blocked: what a
user on a network without internet sees."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.conftest import running_server

CHROMIUM = shutil.which("chromium")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium: apt-get install chromium (.ci/run does)")


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        launched = playwright.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        yield launched
        launched.close()


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
        page.wait_for_selector("text=Find and identify the targets in a JPEG or PNG image.", timeout=30_000)
        # ReDoc's bundle asks its maker's site for its logo: decoration, nothing the page needs.
        assert all(url.endswith((".svg", ".png")) for url in offsite), offsite
