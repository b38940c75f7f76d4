"""Request ids and the access line: the outermost middleware of the app.

Every HTTP request gets an id (its sane ``X-Request-ID``, or a new one; see
:mod:`sgvloc.server.logs`), set in the logging context before anything else runs and
sent back in the response's ``X-Request-ID``. When the answer is complete one access
line is logged: method, route template, status, duration, the caller's key name
(never the key), the error code of an error answer and the client's address.
"""

from __future__ import annotations

import time

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from ..logs import REQUEST_ID_HEADER, log_access, request_id, request_id_from

_HEADER = REQUEST_ID_HEADER.lower().encode()


class RequestIdMiddleware:
    """Sets the request id, answers it in ``X-Request-ID``, logs the access line."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        incoming = None
        for name, value in scope["headers"]:
            if name == _HEADER:
                incoming = value.decode("latin-1")
                break
        rid = request_id_from(incoming)
        # each request runs in its own task, so the value ends with it; it is not reset
        # here, so that the error handler's log of a failed request still carries it
        request_id.set(rid)
        state = scope.setdefault("state", {})  # the route's request.state (the caller)
        start = time.perf_counter()
        status = 500

        async def send_with_id(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
                headers = [(k, v) for k, v in message.get("headers", []) if k.lower() != _HEADER]
                headers.append((_HEADER, rid.encode()))
                message = {**message, "headers": headers}
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        finally:
            route = getattr(scope.get("route"), "path", None)
            # no caller identified: a route open to all (the status page, /docs) that
            # answered, else a request refused before a key was accepted
            principal = state.get("principal")
            key_name = getattr(principal, "name", None)
            if key_name is None and route is not None and status < 400:
                settings = getattr(getattr(scope.get("app"), "state", None), "settings", None)
                key_name = "development" if getattr(settings, "dev", False) else "anonymous"
            peer = scope.get("client")
            log_access(
                scope["method"],
                route or "unmatched",
                status,
                (time.perf_counter() - start) * 1e3,
                key_name,
                state.get("error_code"),
                peer[0] if peer else None,
            )
