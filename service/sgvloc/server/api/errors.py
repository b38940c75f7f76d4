"""Errors as HTTP answers: every 4xx/5xx has the body of docs/API.md.

``{"error": {"code": "<machine code>", "message": "<what is wrong>", "field": "<path>"}}``

Engine errors map to codes here (the core never imports FastAPI); request validation
errors (FastAPI's and pydantic's) become ``invalid_input``; anything unexpected becomes
``internal`` with its traceback logged, never a bare 500 page.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any, TypeVar

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response
from pydantic import BaseModel, ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from sgvloc.core.errors import (
    CallerGone,
    ConflictError,
    DeadlineExceeded,
    EmptyScanError,
    EncoderMismatchError,
    InputError,
    NotFoundError,
    SgvlocError,
    StorageFullError,
)
from sgvloc_client.wire import WireError

from ..logs import REQUEST_ID_HEADER, current_request_id
from ..maps import MapUnavailableError, StaleError
from ..store import StoreClosedError, StoreUnavailableError, storage_full

M = TypeVar("M", bound=BaseModel)

log = logging.getLogger(__name__)


class ApiError(Exception):
    """An error answered as-is: HTTP status, machine code, message and optional field."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        field: str | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(message)
        self.status, self.code, self.message, self.field = status, code, message, field
        self.headers = headers or {}


def error_response(
    request: Request,
    status: int,
    code: str,
    message: str,
    field: str | None = None,
    headers: dict[str, str] | None = None,
) -> Response:
    """The error body, encoded as the request's ``Accept`` asks (JSON by default)."""
    from .body import encode

    body = {"error": {"code": code, "message": message, "field": field}}
    request.state.error_code = code  # for the access line
    metrics = getattr(request.app.state, "metrics", None)
    if metrics is not None:  # codes are a fixed set, routes are templates: few series
        route = getattr(request.scope.get("route"), "path", None) or "unmatched"
        metrics.errors.labels(route, code).inc()
    response = encode(request, body, status)
    response.headers.update(headers or {})
    return response


def loc_to_field(loc: Sequence[Any]) -> str | None:
    """A pydantic error location as a field path: ``("keyframes", 3, "points")`` ->
    ``keyframes[3].points``. FastAPI's leading ``body``, ``query``, ``path`` or
    ``header`` is dropped: a field is named alike wherever it was checked."""
    parts = list(loc[1:] if loc and loc[0] in ("body", "query", "path", "header") else loc)
    out = ""
    for p in parts:
        if isinstance(p, int):
            out += f"[{p}]"
        else:
            out += f".{p}" if out else str(p)
    return out or None


def _clean(msg: str) -> str:
    for prefix in ("Value error, ", "Assertion failed, "):
        if msg.startswith(prefix):
            return msg[len(prefix) :]
    return msg


def validation_message(errors: Sequence[dict[str, Any]]) -> tuple[str, str | None]:
    """One message naming every problem (at most 5), and the first problem's field."""
    items = []
    for e in errors[:5]:
        where = loc_to_field(e.get("loc", ()))
        msg = _clean(str(e.get("msg", "invalid")))
        items.append(f"{where}: {msg}" if where else msg)
    more = f" (and {len(errors) - 5} more)" if len(errors) > 5 else ""
    first = loc_to_field(errors[0].get("loc", ())) if errors else None
    return "; ".join(items) + more, first


def validated(model: type[M], data: Any, context: dict[str, Any] | None = None) -> M:
    """``model.model_validate(data, context=context)``, its errors as the 422 answer: the
    message is made here, in the worker thread that validates, and not on the event loop
    (a body with many bad fields has as many errors)."""
    try:
        return model.model_validate(data, context=context)
    except ValidationError as exc:
        message, field = validation_message(
            exc.errors(include_url=False, include_context=False, include_input=False)
        )
        raise ApiError(422, "invalid_input", message, field) from None


#: engine error -> status, code, and whether the answer carries Retry-After
_ENGINE_CODES: list[tuple[type[SgvlocError], int, str, bool]] = [
    (CallerGone, 499, "caller_gone", False),  # nobody reads it: for the log and metrics
    (DeadlineExceeded, 503, "deadline_exceeded", True),
    (StoreUnavailableError, 503, "store_unavailable", True),
    (StaleError, 503, "stale", True),
    (StorageFullError, 507, "insufficient_storage", False),
    (MapUnavailableError, 503, "map_unavailable", False),
    (EncoderMismatchError, 409, "encoder_mismatch", False),
    (NotFoundError, 404, "not_found", False),
    (StoreClosedError, 404, "not_found", False),  # the map was deleted during the request
    (ConflictError, 409, "conflict", False),
    (EmptyScanError, 422, "empty_scan", False),
    (InputError, 422, "invalid_input", False),
]


async def _api_error(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, ApiError)
    return error_response(request, exc.status, exc.code, exc.message, exc.field, exc.headers)


async def _engine_error(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, SgvlocError)
    field = getattr(exc, "field", None)
    for cls, status, code, retry in _ENGINE_CODES:
        if isinstance(exc, cls):
            after = str(request.app.state.settings.retry_after_s)
            headers = {"Retry-After": after} if retry else None
            return error_response(request, status, code, str(exc), field, headers)
    log.error("unmapped engine error on %s %s: %r", request.method, request.url.path, exc)
    return error_response(request, 500, "internal", str(exc), field)


async def _wire_error(request: Request, exc: Exception) -> Response:
    return error_response(request, 400, "bad_body", str(exc), getattr(exc, "field", None))


async def _request_validation(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, RequestValidationError | ValidationError)
    message, field = validation_message(exc.errors())
    return error_response(request, 422, "invalid_input", message, field)


async def _http_error(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, StarletteHTTPException)
    codes = {
        401: "unauthorized",
        403: "forbidden",
        404: "not_found",
        405: "method_not_allowed",
        413: "payload_too_large",
        429: "overloaded",
    }
    code = codes.get(exc.status_code, "internal" if exc.status_code >= 500 else "bad_request")
    message = str(exc.detail)
    if exc.status_code == 404 and message == "Not Found":
        message = f"no route {request.method} {request.url.path}"
    headers = dict(exc.headers or {})
    if exc.status_code == 405:
        # Starlette names only the first route of the path; list every route's methods
        allowed = _allowed_methods(request)
        if allowed:
            headers["Allow"] = ", ".join(allowed)
            message = f"{request.method} is not allowed on {request.url.path}: use " + (
                " or ".join(allowed)
            )
    return error_response(request, exc.status_code, code, message, headers=headers)


def _allowed_methods(request: Request) -> list[str]:
    """The methods of every route whose path matches the request's."""
    path = request.url.path
    methods: set[str] = set()
    for regex, route_methods in getattr(request.app.state, "route_methods", ()):
        if regex.match(path):
            methods |= route_methods
    return sorted(methods)


async def _unexpected(request: Request, exc: Exception) -> Response:
    # this answer is sent from outside the app's middleware: it names the request itself
    rid = current_request_id()
    full = storage_full(exc)
    if full is not None:
        log.error("%s %s: the disk is full: %s", request.method, request.url.path, exc)
        response = await _engine_error(request, full)
        if rid is not None:
            response.headers[REQUEST_ID_HEADER] = rid
        return response
    log.exception("internal error on %s %s", request.method, request.url.path, exc_info=exc)
    # Starlette re-raises after this answer and the server then drops the connection:
    # say so, so that a keep-alive client opens a new one for its next request
    return error_response(
        request,
        500,
        "internal",
        f"internal error ({type(exc).__name__}); see the service log",
        headers={"Connection": "close", **({REQUEST_ID_HEADER: rid} if rid else {})},
    )


def install_error_handlers(app: FastAPI) -> None:
    """Register the handlers that turn every error into the documented body."""
    app.add_exception_handler(ApiError, _api_error)
    app.add_exception_handler(SgvlocError, _engine_error)
    app.add_exception_handler(WireError, _wire_error)
    app.add_exception_handler(RequestValidationError, _request_validation)
    app.add_exception_handler(ValidationError, _request_validation)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(Exception, _unexpected)
