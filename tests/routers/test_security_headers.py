"""The headers that tell a browser what the service's pages may do: a Content-Security-
Policy on the web app, no framing, no type sniffing and no Referer on every reply."""

from __future__ import annotations

import base64
import hashlib
import re

from fastapi.testclient import TestClient

from app.main import WEB_DIR


def test_the_web_app_carries_a_policy_that_allows_its_import_map_and_nothing_inline(client: TestClient) -> None:
    for path in ("/app/", "/app/js/app.js", "/app/style.css", "/app/vendor/three/three.module.min.js"):
        reply = client.get(path)
        assert reply.status_code == 200, path
        assert reply.headers["x-content-type-options"] == "nosniff"
        assert reply.headers["x-frame-options"] == "DENY"
        assert reply.headers["referrer-policy"] == "no-referrer"
        policy = dict(d.strip().split(" ", 1) for d in reply.headers["content-security-policy"].split(";"))
        assert policy["default-src"] == "'self'" and policy["connect-src"] == "'self'"
        assert policy["frame-ancestors"] == "'none'" and policy["object-src"] == "'none'"
        assert "unsafe-inline" not in reply.headers["content-security-policy"]
    # The only inline script of the page, its import map, is allowed by its hash.
    inline = re.findall(r"<script type=\"importmap\">(.*?)</script>", (WEB_DIR / "index.html").read_text(), re.S)
    digest = base64.b64encode(hashlib.sha256(inline[0].encode()).digest()).decode()
    assert policy["script-src"] == f"'self' 'sha256-{digest}'"


def test_every_reply_refuses_framing_and_sniffing_and_the_docs_keep_their_inline_scripts(client: TestClient) -> None:
    for method, path in (("GET", "/environments"), ("GET", "/docs"), ("GET", "/redoc"), ("GET", "/environments/99"),
                         ("POST", "/environments")):
        reply = client.request(method, path, headers={"origin": "http://127.0.0.1:9000"})
        assert reply.headers["x-content-type-options"] == "nosniff", path
        assert reply.headers["x-frame-options"] == "DENY", path
        assert reply.headers["referrer-policy"] == "no-referrer", path
        # The API's pages run inline scripts: a policy would break them.
        assert "content-security-policy" not in reply.headers, path
