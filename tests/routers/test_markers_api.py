"""Marker cards over HTTP: catalogue, layout JSON, PNG, SVG, PDF sheets, and bad requests."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient


def test_catalogue_lists_both_families(client: TestClient) -> None:
    body = client.get("/markers").json()
    assert body["default_family"] == "fido3x3"
    counts = {f["name"]: f["count"] for f in body["families"]}
    assert counts == {"fido3x3": 60, "fido4x4": 282}


def test_layout_json(client: TestClient) -> None:
    body = client.get("/markers/7").json()
    assert body["id"] == 7 and body["family"] == "fido3x3"
    assert len(body["discs"]) == 4 and len(body["code"]) == 3
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = body["discs"]
    # 0 top-left, 1 top-right, 2 bottom-right, 3 bottom-left (y down).
    assert x0 < x1 and y1 < y2 and x2 > x3 and y3 > y0
    assert len(client.get("/markers/7?family=fido4x4").json()["code"]) == 4


def test_png_is_the_card_at_the_requested_size(client: TestClient) -> None:
    reply = client.get("/markers/3.png?px=400")
    assert reply.status_code == 200 and reply.headers["content-type"] == "image/png"
    image = cv2.imdecode(np.frombuffer(reply.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image.shape == (400, 400)
    assert image[0, 0] == 255  # white card corner
    layout = client.get("/markers/3").json()
    x, y = np.array(layout["discs"][2]) * 400 - 0.5
    assert image[int(round(y)), int(round(x))] == 0  # black disc centre


def test_svg_and_pdf(client: TestClient) -> None:
    svg = client.get("/markers/3.svg?size_mm=150")
    assert svg.status_code == 200 and svg.headers["content-type"].startswith("image/svg+xml")
    assert "150mm" in svg.text
    pdf = client.get("/markers/sheet.pdf?ids=0-5&size_mm=80")
    assert pdf.status_code == 200 and pdf.headers["content-type"] == "application/pdf"
    assert pdf.content.startswith(b"%PDF")


@pytest.mark.parametrize(
    "path",
    ["/markers/60", "/markers/-1", "/markers/282?family=fido4x4", "/markers/60.png", "/markers/99.svg",
     "/markers/sheet.pdf?ids=0-60&size_mm=50", "/markers/1?family=qr"],
)
def test_ids_outside_family_are_404(client: TestClient, path: str) -> None:
    reply = client.get(path)
    assert reply.status_code == 404, reply.text
    assert reply.json()["detail"]


@pytest.mark.parametrize(
    "path,field",
    [("/markers/1.png?px=100000", "px"), ("/markers/1.png?px=0", "px"),
     ("/markers/sheet.pdf?ids=0-3&size_mm=1e9", "size_mm"), ("/markers/sheet.pdf?ids=0-3&size_mm=1", "size_mm"),
     ("/markers/sheet.pdf?ids=0-3&size_mm=nan", "size_mm"), ("/markers/sheet.pdf?ids=3-0&size_mm=50", "ids"),
     ("/markers/sheet.pdf?ids=0-99999999&size_mm=50", "ids"), ("/markers/1.svg?size_mm=1e12", "size_mm")],
)
def test_absurd_sizes_are_422(client: TestClient, path: str, field: str) -> None:
    reply = client.get(path)
    assert reply.status_code == 422, reply.text
    assert field in str(reply.json()["detail"])
