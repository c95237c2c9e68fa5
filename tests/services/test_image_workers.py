"""/detect and /locate run in worker processes: apart from the web process, replaced
when one dies, and bounded in how many requests they take in at once."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.services.errors import Busy
from app.settings import Settings
from app.sim import scenes


@pytest.fixture(scope="module")
def jpeg() -> bytes:
    image, _ = scenes.scenario_frame("clean", np.random.default_rng(11))
    return cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()


def _worker_pids(client: TestClient) -> set[int]:
    return set(client.app.state.image_workers._executor._processes)  # noqa: SLF001 - the pool's own record


def test_images_are_processed_in_another_process_which_is_replaced_when_it_dies(tmp_path: Path, jpeg: bytes
                                                                                ) -> None:
    with TestClient(create_app(Settings(data_dir=tmp_path / "data"))) as client:
        first = client.post("/detect", content=jpeg, headers={"content-type": "image/jpeg"})
        assert first.status_code == 200 and first.json()["targets"]
        workers = _worker_pids(client)
        assert workers and os.getpid() not in workers
        for pid in workers:
            os.kill(pid, signal.SIGKILL)  # out of memory, say
        statuses = [client.post("/detect", content=jpeg, headers={"content-type": "image/jpeg"}).status_code
                    for _ in range(3)]
        # The request that meets the dead worker may get 503 (retry); then new workers answer.
        assert set(statuses[:1]) <= {200, 503} and statuses[1:] == [200, 200], statuses
        assert _worker_pids(client).isdisjoint(workers)
        assert client.get("/livez").status_code == 200


def test_image_requests_beyond_the_bound_are_refused_not_queued(tmp_path: Path) -> None:
    with TestClient(create_app(Settings(data_dir=tmp_path / "data", max_image_requests=2))) as client:
        workers = client.app.state.image_workers
        with workers.admitted(), workers.admitted():
            with pytest.raises(Busy, match="2 images"), workers.admitted():
                pass
        with workers.admitted():  # the slots were given back
            assert workers.in_flight == 1
