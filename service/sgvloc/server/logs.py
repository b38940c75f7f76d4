"""Logging of ``sgvloc serve``: text or JSON lines, with the request id of every record
made while a request is handled.

The request id comes from the request's ``X-Request-ID`` header when it is sane (1 to 128
characters of letters, digits and ``._:+/=-``), else a new random one; it is sent back in
the response's ``X-Request-ID``. It lives in a context variable: each request runs in its
own asyncio task and the worker threads run in a copy of its context, so every record
logged for the request (on the event loop or in a worker) carries it.

JSON lines (``--log-format json``) hold ``time`` (UTC, ISO 8601), ``level``, ``logger``,
``message``, ``request_id`` (null outside requests), ``exc`` (a traceback, when there is
one) and, on the one access line per request (logger ``sgvloc.access``), ``method``,
``route``, ``status``, ``duration_ms`` and ``key_name``. Only the standard library is
imported here: the CLI configures logging before the numeric libraries load.
"""

from __future__ import annotations

import contextvars
import json
import logging
import re
import uuid
from datetime import datetime, timezone
from typing import Literal

LogFormat = Literal["text", "json"]

REQUEST_ID_HEADER = "X-Request-ID"
_SANE_ID = re.compile(r"[A-Za-z0-9._:+/=-]{1,128}")
#: the access line fields (``extra=`` of the access log call)
ACCESS_FIELDS = ("method", "route", "status", "duration_ms", "key_name", "code", "client")
#: routes whose 503 is an answer, not a failure (a probe saying "not ready")
PROBE_ROUTES = frozenset({"/healthz", "/readyz", "/metrics"})

request_id: contextvars.ContextVar[str | None] = contextvars.ContextVar(
    "sgvloc_request_id", default=None
)
access_log = logging.getLogger("sgvloc.access")
_access_level = logging.DEBUG  # INFO with JSON lines (configure_logging)


def request_id_from(header: str | None) -> str:
    """The id to use for a request: its sane ``X-Request-ID`` header, or a new one."""
    if header is not None and _SANE_ID.fullmatch(header):
        return header
    return uuid.uuid4().hex


def current_request_id() -> str | None:
    """The id of the request being handled, or None outside a request."""
    return request_id.get()


class RequestIdFilter(logging.Filter):
    """Sets ``record.request_id`` from the context (None outside a request)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if not hasattr(record, "request_id"):
            record.request_id = request_id.get()
        return True


class TextFormatter(logging.Formatter):
    """``time LEVEL logger: message``, then ``[request <id>]`` inside a request."""

    def __init__(self) -> None:
        super().__init__("%(asctime)s %(levelname)s %(name)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        line = super().format(record)
        rid = getattr(record, "request_id", None)
        if rid is None:
            return line
        first, sep, rest = line.partition("\n")  # after the message, before a traceback
        return f"{first} [request {rid}]{sep}{rest}"


class JsonFormatter(logging.Formatter):
    """One JSON object per record (see the module docstring)."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, object] = {
            "time": datetime.fromtimestamp(record.created, timezone.utc).isoformat(
                timespec="milliseconds"
            ),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
            "request_id": getattr(record, "request_id", None),
        }
        for name in ACCESS_FIELDS:
            if hasattr(record, name):
                out[name] = getattr(record, name)
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        elif record.exc_text:
            out["exc"] = record.exc_text
        return json.dumps(out, default=str)


def configure_logging(level: str, fmt: LogFormat = "text") -> None:
    """One handler on the root logger (stderr), in ``fmt``, with request ids; like
    :func:`logging.basicConfig`, nothing changes when the root logger has handlers already.

    Access lines (``sgvloc.access``) are INFO in JSON (for log pipelines) and DEBUG in text
    (a console shows them with ``--log-level debug``)."""
    root = logging.getLogger()
    if not root.handlers:
        handler = logging.StreamHandler()
        handler.setFormatter(JsonFormatter() if fmt == "json" else TextFormatter())
        handler.addFilter(RequestIdFilter())
        root.addHandler(handler)
        root.setLevel(level.upper())
    # faiss logs which CPU build it loaded (and every build it could not) at INFO
    logging.getLogger("faiss.loader").setLevel(logging.WARNING)
    # the pool warns at every failed connection try during a store outage; the service
    # says once that the store does not answer, and again when it does (sgvloc_store_up)
    logging.getLogger("psycopg.pool").setLevel(logging.ERROR)
    global _access_level
    _access_level = logging.INFO if fmt == "json" else logging.DEBUG


def log_access(
    method: str,
    route: str,
    status: int,
    duration_ms: float,
    key_name: str | None,
    code: str | None = None,
    client: str | None = None,
) -> None:
    """The access line of one answered request (in the request's context): at the access
    level, or WARNING for a 5xx answer (not a probe's), so that a service logging at INFO
    in text shows its failures with their error code and caller."""
    level = _access_level
    if status >= 500 and route not in PROBE_ROUTES:
        level = max(level, logging.WARNING)
    if not access_log.isEnabledFor(level):
        return
    access_log.log(
        level,
        "%s %s %d %.1f ms key=%s code=%s client=%s",
        method,
        route,
        status,
        duration_ms,
        key_name or "-",
        code or "-",
        client or "-",
        extra={
            "method": method,
            "route": route,
            "status": status,
            "duration_ms": round(duration_ms, 3),
            "key_name": key_name,
            "code": code,
            "client": client,
        },
    )
