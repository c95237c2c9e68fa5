"""Liveness, readiness, metrics and the OpenAPI page."""

from __future__ import annotations

from fastapi.testclient import TestClient


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
