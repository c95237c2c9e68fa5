"""/readyz while the detector's kernels load or compile in the background (a real cold
compile, 10-30 s, is in tests/test_serve.py)."""

from __future__ import annotations

import threading
import time

from fastapi.testclient import TestClient
from numba.core import event as numba_event

from app.services.tracking import DetectorKernels


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
