"""Shared fixtures: every test gets its own data directory and SQLite database."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    return Settings(data_dir=tmp_path / "data")


@pytest.fixture
def client(settings: Settings) -> Iterator[TestClient]:
    with TestClient(create_app(settings)) as test_client:
        yield test_client


def example_map(n_targets: int = 2) -> dict:
    """A small valid map document (DESIGN.md format)."""
    return {
        "frame": "survey",
        "units": "m",
        "camera": {
            "width": 640,
            "height": 480,
            "K": [[820.0, 0.0, 320.0], [0.0, 820.0, 240.0], [0.0, 0.0, 1.0]],
            "dist": [-0.12, 0.01, 0.0, 0.0, 0.0],
        },
        "targets": [
            {
                "id": i,
                "discs": [[i + 0.0, 0.0, 2.0], [i + 0.1, 0.0, 2.0], [i + 0.1, 0.1, 2.0], [i + 0.0, 0.1, 2.0]],
                "std_m": [0.001, 0.001, 0.001, 0.001],
                "n_views": 12,
            }
            for i in range(n_targets)
        ],
        "rms_px": 0.21,
        "survey_job_id": None,
    }
