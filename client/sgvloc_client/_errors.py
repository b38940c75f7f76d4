"""Exceptions raised by the sgvloc client.

Every exception derives from :class:`SgvlocError`::

    SgvlocError              anything raised by the client
    ├── TransportError       the service could not be reached, the connection broke or a
    │                        timeout passed (after the retries allowed for the call);
    │                        ``.attempts`` is how many times the request was sent
    ├── ScanFileError        a local scan file cannot be read (:mod:`sgvloc_client.scans`);
    │                        also a ``ValueError``
    └── APIError             the service answered with an error status; carries
        │                    ``.status`` (HTTP status), ``.code`` (machine code such as
        │                    ``"not_found"``), ``.message`` and ``.field`` (the offending
        │                    request field such as ``"keyframes[3].points"``, or None)
        │                    and ``.request_id`` (the id of the request in the service's
        │                    log; a TransportError carries the id it was sent with)
        ├── BadRequest       400 / 415 / 422: undecodable body, wrong shapes, bad values
        ├── NotFound         404: unknown map or keyframe
        ├── Conflict         409 ``conflict``: e.g. a map with that name exists
        ├── EncoderMismatch  409 ``encoder_mismatch``: features from another encoder
        ├── Unauthorized     401: no key, or one the service does not know
        ├── Forbidden        403: the key's role or maps do not allow this
        ├── PayloadTooLarge  413: the body is over the service's limit
        ├── Overloaded       429 / 503: too busy or not ready; try again later
        └── ServerError      other 5xx: a fault in the service

Other error statuses (405, ...) raise :class:`APIError` itself. The service's
error body is ``{"error": {"code", "message", "field"}}``; a body of another shape (from a
proxy, say) still gives an :class:`APIError` with ``code = "http_<status>"``.
"""

from __future__ import annotations

from typing import Any


class SgvlocError(Exception):
    """Base class of every exception raised by the client."""


class TransportError(SgvlocError):
    """The request got no answer of the service: the connection was refused, reset or
    timed out, a load balancer answered 502/504 (no replica answered), or what answered
    was not an sgvloc service (a captive portal's page, say)."""

    def __init__(self, message: str, *, attempts: int = 1, request_id: str | None = None) -> None:
        super().__init__(message)
        self.attempts = attempts
        #: the ``X-Request-ID`` the call was sent with (the service's log names it)
        self.request_id = request_id


class ScanFileError(SgvlocError, ValueError):
    """A local scan file cannot be read; the message names the file and the problem."""


class APIError(SgvlocError):
    """The service answered with an error status (see the module docstring)."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        field: str | None = None,
        body: Any = None,
        request_id: str | None = None,
    ) -> None:
        self.status = status
        self.code = code
        self.message = message
        self.field = field
        self.body = body
        #: the request's id in the service's log (its ``X-Request-ID`` answer)
        self.request_id = request_id
        where = f" (field {field})" if field else ""
        rid = f" [request id {request_id}]" if request_id else ""
        super().__init__(f"{status} {code}: {message}{where}{rid}")


class BadRequest(APIError):
    """400 / 415 / 422: the request is malformed or its values are invalid."""


class NotFound(APIError):
    """404: the map or keyframe does not exist."""


class Conflict(APIError):
    """409: the request conflicts with existing state (e.g. a duplicate map name)."""


class EncoderMismatch(APIError):
    """409 ``encoder_mismatch``: features come from another encoder than the map's."""


class Unauthorized(APIError):
    """401: no API key was sent, or the service does not know it."""


class Forbidden(APIError):
    """403: the API key's role or maps do not allow this request."""


class PayloadTooLarge(APIError):
    """413: the request body is larger than the service accepts."""


class Overloaded(APIError):
    """429 / 503: the service is busy or not ready yet."""


class MapUnavailable(Overloaded):
    """503 ``map_unavailable``: the service could not load this map; an operator must fix
    it (no Retry-After, not resent). Other maps of the service are served."""


class EmptyScan(BadRequest):
    """422 ``empty_scan``: the map's encoder found nothing to describe in the scan (too
    sparse for it, or nothing but ground): a well-formed scan, not a client bug."""


class ServerError(APIError):
    """5xx (other than 503): a fault in the service."""


_BY_STATUS: dict[int, type[APIError]] = {
    400: BadRequest,
    401: Unauthorized,
    403: Forbidden,
    404: NotFound,
    409: Conflict,
    413: PayloadTooLarge,
    415: BadRequest,
    422: BadRequest,
    429: Overloaded,
    503: Overloaded,
}


def error_class(status: int, code: str) -> type[APIError]:
    """The exception class for an error status and machine code."""
    if status == 409 and code == "encoder_mismatch":
        return EncoderMismatch
    if status == 503 and code == "map_unavailable":
        return MapUnavailable
    if status == 422 and code == "empty_scan":
        return EmptyScan
    if status in _BY_STATUS:
        return _BY_STATUS[status]
    return ServerError if status >= 500 else APIError
