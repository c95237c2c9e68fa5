"""Structured logs: one JSON object per line, carrying the request, WebSocket connection
or job it belongs to (context variables, so every log call inside a request or job gets
them without passing them around)."""

from __future__ import annotations

import contextvars
import json
import logging
import re
import sys
import time
import uuid

request_id: contextvars.ContextVar[str | None] = contextvars.ContextVar("request_id", default=None)
connection_id: contextvars.ContextVar[str | None] = contextvars.ContextVar("connection_id", default=None)
job_id: contextvars.ContextVar[str | None] = contextvars.ContextVar("job_id", default=None)

_CLIENT_ID = re.compile(r"^[A-Za-z0-9._-]{1,64}$")


def new_id() -> str:
    return uuid.uuid4().hex[:16]


def client_request_id(header: str | None) -> str:
    """The caller's X-Request-ID when it is a sane token, else a new one (a log line must
    not carry arbitrary client text)."""
    return header if header is not None and _CLIENT_ID.match(header) else new_id()


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, object] = {
            "ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": record.getMessage(),
        }
        for key, var in (("request_id", request_id), ("connection_id", connection_id), ("job_id", job_id)):
            value = var.get()
            if value is not None:
                entry[key] = value
        for key, value in getattr(record, "fields", {}).items():
            entry[key] = value
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


class TextFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        ids = " ".join(f"{k}={v.get()}" for k, v in (("req", request_id), ("conn", connection_id), ("job", job_id))
                       if v.get() is not None)
        fields = " ".join(f"{k}={v}" for k, v in getattr(record, "fields", {}).items())
        line = f"{self.formatTime(record)} {record.levelname} {record.name} {ids} {record.getMessage()} {fields}"
        if record.exc_info:
            line += "\n" + self.formatException(record.exc_info)
        return line.rstrip()


#: A secret in a URL's query (the documented ``?api_key=`` of ``/track``, for clients that
#: cannot set headers): the server's own access lines print the whole URL.
_SECRET_IN_QUERY = re.compile(r"(?i)\b(api_key=)[^&\s\"']*")
#: The loggers whose lines carry request URLs: uvicorn's access log, and its error log,
#: where WebSocket handshakes are reported.
SERVER_LOGGERS = ("uvicorn.access", "uvicorn.error")


def redact(text: str) -> str:
    """`text` with the value of every ``api_key=`` query parameter replaced by ``***``."""
    return _SECRET_IN_QUERY.sub(r"\1***", text)


class RedactSecrets(logging.Filter):
    """Rewrites a record's message and arguments so that no API key reaches a log line."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redact(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(redact(a) if isinstance(a, str) else a for a in record.args)
        elif isinstance(record.args, dict):
            record.args = {k: redact(v) if isinstance(v, str) else v for k, v in record.args.items()}
        return True


#: The server's access log: `app.middleware.RequestObserver` logs each request once,
#: with its request id, so uvicorn's own line would log it twice.
SERVER_ACCESS_LOGGER = "uvicorn.access"
#: What the WebSocket library logs of each connection, with neither path nor id: uvicorn's
#: handshake line and the service's own connection lines already say it.
_WEBSOCKET_CHATTER = frozenset({"connection open", "connection closed"})


class DropDuplicates(logging.Filter):
    """Drops the server's lines that repeat the service's own: its access log, and the
    WebSocket library's bare connection lines."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.name == SERVER_ACCESS_LOGGER:
            return False
        return not (isinstance(record.msg, str) and record.msg in _WEBSOCKET_CHATTER and not record.args)


_MARK = "_fidotrack_handler"


def configure(fmt: str = "json", level: str = "INFO") -> None:
    """Send the ``app`` loggers to stderr in `fmt` ("json" or "text"), keep API keys out
    of them and out of the server's own lines (`RedactSecrets`), and drop the server's
    lines that repeat the service's own (`DropDuplicates`); idempotent."""
    logger = logging.getLogger("app")
    logger.setLevel(level.upper())
    for handler in list(logger.handlers):
        if getattr(handler, _MARK, False):
            logger.removeHandler(handler)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter() if fmt == "json" else TextFormatter())
    setattr(handler, _MARK, True)
    handler.addFilter(RedactSecrets())
    logger.addHandler(handler)
    logger.propagate = False
    for name in SERVER_LOGGERS:
        server = logging.getLogger(name)
        if not any(isinstance(f, DropDuplicates) for f in server.filters):
            server.addFilter(DropDuplicates())
        if not any(isinstance(f, RedactSecrets) for f in server.filters):
            server.addFilter(RedactSecrets())
