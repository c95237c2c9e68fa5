"""Liveness, readiness, metrics and the OpenAPI page; /readyz while the detector's
kernels load or compile in the background (a real cold compile, 10-30 s, is in
tests/test_serve.py)."""

from __future__ import annotations

import re
import threading
import time

import pytest
from fastapi.testclient import TestClient
from numba.core import event as numba_event

from app.services.detection import DetectorKernels
from app.settings import Settings


def test_livez_and_readyz(client: TestClient) -> None:
    assert client.get("/livez").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200
    assert ready.json()["database"] == "ok" and ready.json()["status"] == "ready"


def test_metrics_count_requests_by_route_template(client: TestClient) -> None:
    client.get("/environments/5")
    client.get("/environments/6")
    text = client.get("/metrics").text
    assert 'fidotrack_http_requests_total{method="GET",route="/environments/{environment_id}",status="404"} 2.0' in text
    assert "fidotrack_http_request_seconds_bucket" in text


def test_docs_and_openapi(client: TestClient) -> None:
    assert client.get("/docs").status_code == 200
    paths = client.get("/openapi.json").json()["paths"]
    for path in ["/environments", "/environments/{environment_id}/map", "/markers/{marker_id}.png",
                 "/markers/sheet.pdf", "/readyz", "/metrics"]:
        assert path in paths


def test_server_limits_the_threads_of_one_frame(settings: Settings) -> None:
    """Frames of different clients run in parallel: inside one frame OpenCV and BLAS
    get `compute_threads`, so their idle pool threads do not spin on the other cores."""
    import cv2
    from threadpoolctl import threadpool_info

    from app.main import create_app

    with TestClient(create_app(settings.model_copy(update={"compute_threads": 1}))):
        assert cv2.getNumThreads() == 1
        assert all(pool["num_threads"] == 1 for pool in threadpool_info())


@pytest.mark.parametrize("api_keys", [False, True])
@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_pages_load_everything_from_the_service_itself(tmp_path, page: str, api_keys: bool) -> None:  # type: ignore[no-untyped-def]
    # Offline (a studio network, a laptop on a film set) the pages must still work: every
    # script, style and image they load comes from the service, keys or not.
    from app.main import create_app

    with TestClient(create_app(Settings(data_dir=tmp_path / "data", api_keys=api_keys))) as client:
        html = client.get(page)
        assert html.status_code == 200
        sources = re.findall(r'(?:src|href)="([^"]+)"', html.text) + re.findall(r"url: '([^']+)'", html.text)
        assert sources and all(s.startswith("/") for s in sources), sources
        assets = [s for s in sources if s.endswith((".js", ".css"))]
        assert assets
        for asset in assets:
            reply = client.get(asset)
            assert reply.status_code == 200 and len(reply.content) > 10_000, asset
        assert "https://" not in html.text and "http://" not in html.text


def _compiling_until(release: threading.Event) -> DetectorKernels:
    """Kernels that need compiling (numba reports a compilation) until `release` is set."""

    def compile_all() -> None:
        with numba_event.trigger_event("numba:compile", data={"dispatcher": None, "args": ()}):
            assert release.wait(30)

    return DetectorKernels(compile_all)


def test_readyz_says_503_and_why_until_the_kernels_are_compiled(client: TestClient) -> None:
    release = threading.Event()
    kernels = _compiling_until(release)
    client.app.state.kernels = kernels
    kernels.start()
    started = time.monotonic()
    assert kernels.wait_unless_compiling(10) is False  # start-up does not wait for a compilation
    assert time.monotonic() - started < 5
    assert client.get("/livez").status_code == 200
    reply = client.get("/readyz")
    assert reply.status_code == 503
    assert reply.json()["status"] == "not ready" and reply.json()["reason"] == "compiling the detector's kernels"
    assert reply.json()["database"] == "ok"
    release.set()
    assert kernels.wait(10)
    reply = client.get("/readyz")
    assert reply.status_code == 200 and reply.json()["status"] == "ready" and reply.json()["reason"] is None


def test_kernels_from_the_cache_are_waited_for() -> None:
    # No compilation: start-up waits the moment they take to load, so a restart comes up ready.
    kernels = DetectorKernels(lambda: time.sleep(0.3))
    kernels.start()
    assert kernels.not_ready == "loading the detector's kernels"
    assert kernels.wait_unless_compiling(10) is True
    assert kernels.not_ready is None and kernels.seconds is not None and kernels.seconds >= 0.3


def test_kernels_that_fail_keep_the_service_not_ready(client: TestClient) -> None:
    def broken() -> None:
        raise RuntimeError("no LLVM")

    kernels = DetectorKernels(broken)
    client.app.state.kernels = kernels
    kernels.start()
    assert kernels.wait(10)
    reply = client.get("/readyz")
    assert reply.status_code == 503
    assert reply.json()["reason"] == "the detector's kernels failed to compile: RuntimeError: no LLVM"
