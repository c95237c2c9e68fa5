"""Liveness, readiness, metrics and the OpenAPI page."""

from __future__ import annotations

from fastapi.testclient import TestClient

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
