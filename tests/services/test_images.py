"""The image memory budget: every route's images share it, each held from its header."""

from __future__ import annotations

import threading
import time

import cv2
import numpy as np
import pytest

from app.services import images
from app.services.errors import Busy, Invalid, TooLarge
from app.settings import Settings


def test_an_image_needing_more_than_the_budget_is_refused_before_decoding() -> None:
    memory = images.MemoryBudget(100)
    with pytest.raises(TooLarge, match="needs"), memory.hold(101, "an image"):
        pass
    assert memory.held == 0


def test_images_wait_for_room_and_the_budget_returns_whole() -> None:
    memory = images.MemoryBudget(100, wait_s=5.0)
    entered = threading.Event()
    order: list[str] = []

    def second() -> None:
        entered.set()
        with memory.hold(60, "second"):
            order.append("second")

    with memory.hold(60, "first"):
        waiting = threading.Thread(target=second)
        waiting.start()
        entered.wait()
        time.sleep(0.2)
        order.append("first")  # the second is still waiting: 60 + 60 > 100
    waiting.join(5.0)
    assert order == ["first", "second"] and memory.held == 0


def test_an_image_gets_busy_after_waiting_too_long_and_a_failure_frees_its_share() -> None:
    memory = images.MemoryBudget(100, wait_s=0.1)
    with memory.hold(90, "first"), pytest.raises(Busy), memory.hold(20, "second"):
        pass
    with pytest.raises(RuntimeError), memory.hold(90, "third"):
        raise RuntimeError("detection failed")
    assert memory.held == 0


def test_decoded_holds_the_header_cost_while_the_block_runs(tmp_path) -> None:  # type: ignore[no-untyped-def]
    settings = Settings(data_dir=tmp_path)
    memory = images.MemoryBudget(10**9)
    data = cv2.imencode(".jpg", np.full((48, 64), 90, np.uint8))[1].tobytes()
    with images.decoded(data, settings, memory) as gray:
        assert gray.shape == (48, 64)
        assert memory.held == 48 * 64 * (1 + images.DETECT_BYTES_PER_PIXEL)
    assert memory.held == 0
    with pytest.raises(Invalid), images.decoded(data[:200] + b"\xff\xd9", settings, memory):
        pass
    assert memory.held == 0


def _hold_and_die(memory: images.MemoryBudget, ready: object) -> None:
    import os

    with memory.hold(70, "a worker's image"):
        ready.set()  # type: ignore[attr-defined]
        time.sleep(0.5)
        os._exit(1)  # killed while holding its share


def test_the_shares_of_dead_workers_can_be_given_back() -> None:
    import multiprocessing

    spawn = multiprocessing.get_context("spawn")
    memory = images.MemoryBudget(100, wait_s=0.1)
    ready = spawn.Event()
    worker = spawn.Process(target=_hold_and_die, args=(memory, ready))
    worker.start()
    assert ready.wait(30)
    with memory.hold(20, "the web process's frame"):
        worker.join(30)
        assert memory.held == 90  # the dead worker's 70 are lost to the budget ...
        memory.release_others()
        assert memory.held == 20  # ... until they are given back; this process's own stay
    assert memory.held == 0
