"""Pure ASGI middleware (no task groups around ``receive``, so an error raised while a
body is read reaches the exception handlers as itself).

`ApiKeyGate`: with API keys on, every request's key and scope are checked before any of
its body is read (a dependency would run only after FastAPI has read and parsed it).

`BodyLimit`: request body limits, enforced before and while the body is read. A declared
Content-Length over the limit is refused with 413 before a byte of the body is read; a
body without one (chunked) is counted as it streams in and refused as soon as it passes
the limit, so nothing ever holds more than the limit in memory or on disk.

`ClientLimits`: each client address's and API key's request rate and /track
connection-open rate (token buckets), refused with 429 and ``Retry-After`` before the
key is looked up or the body read.
"""

from __future__ import annotations

import base64
import hashlib
import json
import logging
import re
import time
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any, Literal

import anyio
from fastapi import HTTPException
from starlette.requests import HTTPConnection

from app import logs
from app.schemas import TrackRefusal
from app.services import keys
from app.services.metrics import Metrics
from app.services.rate_limits import ClientRates, RateRefusal, client_address
from app.settings import normalize_origin

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

#: Routes that take large uploads (survey videos, training image sets).
UPLOAD_ROUTES = (re.compile(r"^/environments/\d+/survey$"), re.compile(r"^/classifiers/?$"))
#: Routes that take one image.
IMAGE_ROUTES = (re.compile(r"^/detect/?$"), re.compile(r"^/environments/\d+/locate/?$"))
#: What multipart framing may add to an image.
MULTIPART_FRAMING_BYTES = 64 * 1024


def too_large(limit: int) -> HTTPException:
    return HTTPException(413, f"request body exceeds the limit of {limit} bytes")


class BodyLimit:
    """Uploads may be up to `upload_limit`, images up to `image_limit` (and their
    multipart framing), every other body (JSON) up to `json_limit`."""

    def __init__(self, app: ASGIApp, upload_limit: int, image_limit: int, json_limit: int) -> None:
        self.app = app
        self.upload_limit = upload_limit
        self.image_limit = image_limit
        self.json_limit = json_limit

    def limit_for(self, scope: Scope) -> int:
        path = scope.get("path", "")
        if any(r.match(path) for r in UPLOAD_ROUTES):
            return self.upload_limit
        if any(r.match(path) for r in IMAGE_ROUTES):
            return self.image_limit + MULTIPART_FRAMING_BYTES
        return self.json_limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.limit_for(scope)
        headers = dict(scope.get("headers") or [])
        declared = headers.get(b"content-length")
        if declared is not None:
            try:
                size = int(declared)
            except ValueError:
                await _reply(send, 400, "Content-Length is not a number")
                return
            if size > limit:
                await _reply(send, 413, f"request body of {size} bytes exceeds the limit of {limit} bytes")
                return
        received = 0

        async def counted() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    raise too_large(limit)
            return message

        await self.app(scope, counted, send)


async def _refuse_websocket(receive: Receive, send: Send, code: int, reason: str, first: str | None = None) -> None:
    # Accepted, then closed: refused before accepting, a server can only answer the
    # handshake with a bare HTTP 403, which no WebSocket client can read a reason from.
    await receive()  # the client's connect
    await send({"type": "websocket.accept"})
    if first is not None:
        await send({"type": "websocket.send", "text": first})
    await send({"type": "websocket.close", "code": code, "reason": reason})


async def _reply(send: Send, status: int, detail: str, headers: list[tuple[bytes, bytes]] | None = None) -> None:
    # The connection is closed after the reply: the client may still be sending a body
    # that nobody will read.
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close"), *(headers or [])]})
    await send({"type": "http.response.body", "body": body})


# --- API keys -------------------------------------------------------------------------

#: Where the scripts and styles of /docs and /redoc are served.
DOCS_ASSETS_URL = "/docs-assets"
#: Where the web app's files are served (`app/web`): pages and scripts, no data; the page
#: sends the user's key with each API call it makes.
WEB_APP_URL = "/app"
#: Paths anyone may call even with keys on: orchestrators' probes carry no keys, and the
#: API's description (and its pages' assets, under `DOCS_ASSETS_URL`) holds no data.
OPEN_PATHS = frozenset({"/", "/livez", "/readyz", "/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json",
                        WEB_APP_URL})
#: What a ``track`` key may do: stream frames, detect and locate.
TRACK_ROUTES = (("POST", re.compile(r"^/detect/?$")), ("POST", re.compile(r"^/environments/[^/]+/locate/?$")),
                ("WEBSOCKET", re.compile(r"^/track/?$")))
WS_POLICY_VIOLATION = 1008


def required_scope(method: str, path: str) -> str | None:
    """The scope a request needs: None (open), ``track``, ``read`` (GET) or ``admin``."""
    if path in OPEN_PATHS or path.startswith((DOCS_ASSETS_URL + "/", WEB_APP_URL + "/")):
        return None
    if any(method == m and pattern.match(path) for m, pattern in TRACK_ROUTES):
        return "track"
    if path == "/keys" or path.startswith("/keys/"):
        return "admin"  # even listing keys
    if method in ("GET", "HEAD"):
        return "read"
    return "admin"


def presented_key(connection: HTTPConnection) -> str | None:
    """``X-API-Key``, or ``Authorization: Bearer``; WebSocket clients (browsers cannot
    set headers there) may also pass ``?api_key=``."""
    key = connection.headers.get("x-api-key")
    if key is None:
        auth = connection.headers.get("authorization", "")
        if auth[:7].lower() == "bearer ":
            key = auth[7:].strip()
    if key is None and connection.scope["type"] == "websocket":
        key = connection.query_params.get("api_key")
    return key


class ApiKeyGate:
    """With ``api_keys`` on, every request passes here first (the policy is
    `required_scope`). HTTP: 401 without a valid key, 403 without the scope, before any
    of the body is read. WebSocket: accepted, then closed with code 1008 and the reason
    (refused before accepting, a server can only answer the handshake with a bare HTTP
    403, which no WebSocket client can read a reason from)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        state = scope["app"].state if "app" in scope else None
        if scope["type"] not in ("http", "websocket") or state is None or not state.settings.api_keys:
            await self.app(scope, receive, send)
            return
        method = "WEBSOCKET" if scope["type"] == "websocket" else scope["method"]
        needed = required_scope(method, scope["path"])
        if needed is None:
            await self.app(scope, receive, send)
            return
        key = presented_key(HTTPConnection(scope))
        principal = state.verified_keys.get(key)
        if principal is None:
            principal = await anyio.to_thread.run_sync(keys.verify_in, state.sessionmaker, key)
            if principal is not None and key is not None:
                state.verified_keys.remember(key, principal)
        if principal is not None and principal.allows(needed):
            if key is not None:  # (always: a principal comes from a key) for the limits per key, and /track
                scope.setdefault("state", {})[keys.CREDENTIAL_STATE] = keys.Credential(key, principal)
            await self.app(scope, receive, send)
            return
        reason = ("a valid API key is required (header X-API-Key)" if principal is None
                  else f"this API key lacks the {needed!r} scope")
        if scope["type"] == "websocket":
            await _refuse_websocket(receive, send, WS_POLICY_VIOLATION, reason)
        elif principal is None:
            await _reply(send, 401, reason, [(b"www-authenticate", b"ApiKey")])
        else:
            await _reply(send, 403, reason)


class RequestObserver:
    """Per HTTP request: a request id (the caller's ``X-Request-ID`` when sane, echoed in
    the reply) for every log line inside it, one access log line (the only one:
    `logs.DropDuplicates` drops the server's own; the route template, never the query,
    which may hold a key), Prometheus metrics by route template."""

    def __init__(self, app: ASGIApp, metrics: Any) -> None:
        self.app = app
        self.metrics = metrics
        self.log = logging.getLogger("app.access")

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        headers = dict(scope.get("headers") or [])
        raw = headers.get(b"x-request-id")
        rid = logs.client_request_id(raw.decode("latin-1") if raw is not None else None)
        token = logs.request_id.set(rid)
        status = 500

        async def send_with_id(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
                message["headers"] = [*message.get("headers", []), (b"x-request-id", rid.encode())]
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        finally:
            route = scope.get("route")
            template = getattr(route, "path", "unmatched")
            elapsed = time.perf_counter() - started
            self.metrics.observe_request(scope["method"], template, status, elapsed)
            client = scope.get("client")
            self.log.info("request", extra={"fields": {"method": scope["method"], "route": template,
                                                       "status": status, "ms": round(elapsed * 1e3, 2),
                                                       "client": client[0] if client else None}})
            logs.request_id.reset(token)


# --- Origins --------------------------------------------------------------------------

#: Methods that change state, which pages of other origins may not send.
STATE_CHANGING_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
#: ``Sec-Fetch-Site`` of a browser's request from a page of another origin.
OTHER_ORIGIN_FETCHES = frozenset({b"cross-site", b"same-site"})
#: What `OriginGate` takes from any origin.
ANY_ORIGIN = "*"


def own_origin(scope: Scope) -> str | None:
    """The origin a browser gives the service's own pages: the request's scheme (https
    behind a proxy that says so in ``X-Forwarded-Proto``) and its ``Host`` header."""
    host = dict(scope.get("headers") or []).get(b"host")
    if not host:
        return None
    scheme = "https" if scope.get("scheme") in ("https", "wss") else "http"
    try:
        return normalize_origin(f"{scheme}://{host.decode('latin-1')}")
    except ValueError:
        return None


class OriginGate:
    """Pages of other origins may neither open WebSockets (``/track``) nor send POST,
    PUT, PATCH or DELETE requests. A browser names a page's origin in ``Origin``: it must
    be the service's own (`own_origin`) or one of `allowed` (``*``: any). A request
    without ``Origin`` (curl, the Python client) passes, unless the browser's
    ``Sec-Fetch-Site`` says it comes from another site. HTTP: 403 before any of the body
    is read. WebSocket: accepted, then closed with code 1008 and the reason, as
    `ApiKeyGate` does."""

    def __init__(self, app: ASGIApp, allowed: tuple[str, ...]) -> None:
        self.app = app
        self.any = ANY_ORIGIN in allowed
        self.allowed = frozenset(allowed) - {ANY_ORIGIN}
        self.log = logging.getLogger("app.origins")

    def refusal(self, scope: Scope) -> str | None:
        """Why the request may not pass, or None."""
        headers = dict(scope.get("headers") or [])
        raw = headers.get(b"origin")
        if raw is None:
            if headers.get(b"sec-fetch-site", b"").lower() in OTHER_ORIGIN_FETCHES:
                return "a page of another site sent this without an Origin: refused"
            return None
        origin = raw.decode("latin-1").strip()
        try:
            origin = normalize_origin(origin)
        except ValueError:
            pass  # "null" (sandboxed frames, local files) or garbage: matches nothing
        if origin in self.allowed or origin == own_origin(scope):
            return None
        # Short enough for a WebSocket close reason (at most 123 bytes).
        shown = origin[:60].encode("ascii", "replace").decode()
        return f"origin {shown!r} is not allowed: see the allowed_origins setting"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (self.any or scope["type"] not in ("http", "websocket")
                or (scope["type"] == "http" and scope["method"] not in STATE_CHANGING_METHODS)):
            await self.app(scope, receive, send)
            return
        reason = self.refusal(scope)
        if reason is None:
            await self.app(scope, receive, send)
            return
        self.log.info("origin refused", extra={"fields": {"path": scope.get("path"), "reason": reason}})
        if scope["type"] == "websocket":
            await _refuse_websocket(receive, send, WS_POLICY_VIOLATION, reason)
        else:
            await _reply(send, 403, reason)


# --- Security headers -----------------------------------------------------------------

#: On every reply: no type sniffing, no framing (clickjacking), no Referer to other sites.
COMMON_SECURITY_HEADERS = ((b"x-content-type-options", b"nosniff"), (b"x-frame-options", b"DENY"),
                           (b"referrer-policy", b"no-referrer"))
#: Inline ``<script>`` elements of a page (the import map of the web app's page).
INLINE_SCRIPT = re.compile(r"<script\b(?![^>]*\bsrc=)[^>]*>(.*?)</script>", re.DOTALL | re.IGNORECASE)


def web_app_csp(index_html: str) -> str:
    """The web app's Content-Security-Policy: scripts, styles, fonts and connections
    (``/track``'s ws and wss included) from the service only, inline scripts only as
    hashed from its page (its import map), images also from ``data:`` and ``blob:``, no
    plugins, no framing."""
    hashes = " ".join("'sha256-" + base64.b64encode(hashlib.sha256(script.encode()).digest()).decode() + "'"
                      for script in INLINE_SCRIPT.findall(index_html))
    return ("default-src 'self'; " + f"script-src 'self' {hashes}".rstrip() + "; style-src 'self'; "
            "img-src 'self' data: blob:; media-src 'self' blob: mediastream:; connect-src 'self'; "
            "object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'")


class SecurityHeaders:
    """`COMMON_SECURITY_HEADERS` on every HTTP reply, and `csp` on the web app's (under
    `WEB_APP_URL`). ``/docs`` and ``/redoc`` get no policy: their pages run inline scripts."""

    def __init__(self, app: ASGIApp, csp: str) -> None:
        self.app = app
        self.web_app_headers = (*COMMON_SECURITY_HEADERS, (b"content-security-policy", csp.encode()))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path = scope.get("path", "")
        added = (self.web_app_headers if path == WEB_APP_URL or path.startswith(WEB_APP_URL + "/")
                 else COMMON_SECURITY_HEADERS)

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                names = {name.lower() for name, _ in message.get("headers", [])}
                message["headers"] = [*message.get("headers", []), *(h for h in added if h[0] not in names)]
            await send(message)

        await self.app(scope, receive, send_with_headers)


# --- Request rates per client ---------------------------------------------------------

#: Paths no client limit applies to: orchestrators' probes come often, from one address.
UNLIMITED_PATHS = frozenset({"/livez", "/readyz"})
#: At most one log line about refused requests per this many seconds (per middleware).
RATE_REFUSAL_LOG_S = 10.0


class ClientLimits:
    """The HTTP request rate and the /track connection-open rate of each client
    (`ClientRates`): with ``by="address"``, per client address, outside everything that
    costs (the key's lookup in the database, the body, the access log); with ``by="key"``,
    per API key, inside `ApiKeyGate`, which verified the key. Over a rate: HTTP 429 with
    ``Retry-After`` (seconds) and the reason, before any of the body is read; WebSocket:
    accepted, then a `TrackRefusal` ``too_many_requests`` with ``retry_after_s``, and close
    code 1013. /livez and /readyz are never limited."""

    def __init__(self, app: ASGIApp, rates: ClientRates, by: Literal["address", "key"],
                 metrics: Metrics | None = None) -> None:
        self.app = app
        self.rates = rates
        self.by = by
        self.metrics = metrics
        self.log = logging.getLogger("app.limits")
        self.refused_since_log = 0
        self.logged_at = -1e9

    def refusal(self, scope: Scope) -> RateRefusal | None:
        kind = scope["type"]
        if self.by == "address":
            client = scope.get("client")
            address = client_address(client[0] if client else None)
            return None if address is None else self.rates.admit_address(kind, address)
        credential = scope.get("state", {}).get(keys.CREDENTIAL_STATE)
        return None if credential is None else self.rates.admit_key(kind, credential.principal.key_id)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket") or scope["path"] in UNLIMITED_PATHS:
            await self.app(scope, receive, send)
            return
        refused = self.refusal(scope)
        if refused is None:
            await self.app(scope, receive, send)
            return
        self._count(refused, scope)
        if scope["type"] == "websocket":
            refusal = TrackRefusal(code="too_many_requests", message=refused.message,
                                   retry_after_s=round(refused.retry_after_s, 3))
            await _refuse_websocket(receive, send, refusal.close_code, refusal.message[:120],
                                    first=refusal.model_dump_json())
        else:
            await _reply(send, 429, refused.message, [(b"retry-after", refused.retry_after_header)])

    def _count(self, refused: RateRefusal, scope: Scope) -> None:
        """Metrics for every refusal, a log line now and then: a flood must not write a
        line per request."""
        if self.metrics is not None:
            self.metrics.refused(refused.limit)
        self.refused_since_log += 1
        now = time.monotonic()
        if now - self.logged_at >= RATE_REFUSAL_LOG_S:
            client = scope.get("client")
            self.log.warning("requests refused over a client's rate", extra={"fields": {
                "limit": str(refused.limit), "refused": self.refused_since_log,
                "client": client[0] if client else None}})
            self.logged_at, self.refused_since_log = now, 0

