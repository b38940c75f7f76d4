"""What :class:`Client` and :class:`AsyncClient` share: building requests, parsing answers.

Every API operation is a builder here that returns a :class:`Call` (method, path, encoded
body, whether it is safe to resend, and how to turn the answer into a result). The two
client classes only send calls, sync or async, and sleep between retries; all request and
response logic lives in this module.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import email.utils
import itertools
import json
import logging
import os
import random
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from importlib import metadata
from typing import Any, BinaryIO, Generic, Literal, TypeVar
from urllib.parse import quote, urlencode

import httpx

from . import wire
from ._errors import APIError, SgvlocError, TransportError, error_class
from ._models import (
    InsertResult,
    Keyframe,
    KeyframeDeleted,
    KeyframeIn,
    KeyframePage,
    KeyframesDeleted,
    Localization,
    MapInfo,
    MapPage,
    MapStats,
    Prior,
    RecentLocalization,
    Seed,
    features_body,
    points_array,
)

log = logging.getLogger("sgvloc_client")


def _page_limit(limit: int) -> int:
    """A listing's ``limit`` (maps or keyframes per page), checked: 1..1000."""
    if not 1 <= int(limit) <= 1000:
        raise ValueError(f"limit must be within 1..1000, got {limit}")
    return int(limit)


def _from_gateway(status: int, body: Any) -> bool:
    """A 502 or 504 that is not the service's own error answer: a load balancer or proxy
    found no replica to answer (no sgvloc answer came, as after a connection error)."""
    err = body.get("error") if isinstance(body, dict) else None
    return status in (502, 504) and not isinstance(err, dict)


T = TypeVar("T")

DEFAULT_BASE_URL = "http://127.0.0.1:8470"
WireFormat = Literal["msgpack", "json"]

try:
    __version__ = metadata.version("sgvloc")
except metadata.PackageNotFoundError:  # running from a source tree
    __version__ = "0+unknown"

# Failures after which resending is worthwhile; others (bad URL scheme, proxy set-up)
# would fail the same way again.
_RETRYABLE = (httpx.TimeoutException, httpx.NetworkError, httpx.RemoteProtocolError)
#: a base URL that failed is skipped by new calls for this long (seconds), unless all failed
DOWN_FOR_S = 5.0


@dataclass(frozen=True)
class Call(Generic[T]):
    """One request ready to send and the way to read its answer.

    ``idempotent``: resending after a connection error cannot change the outcome, so the
    client may retry; ``resend_unanswered``: also after the request was sent and its
    answer did not come in time (False for work the service may still be doing: a resend
    would do it again). ``parse(status, body)`` turns a success (or a status listed in
    ``passthrough``) into the result; any other error status raises an :class:`APIError`.
    """

    method: str
    path: str
    parse: Callable[[int, Any], T]
    content: bytes | None = None
    headers: Mapping[str, str] | None = None
    idempotent: bool = False
    passthrough: tuple[int, ...] = ()
    resend_unanswered: bool = True
    #: seconds for this call instead of the client's timeout (a long-running request;
    #: None waits as long as it takes), when ``own_timeout``
    timeout: float | None = None
    own_timeout: bool = False
    #: sent as ``X-Request-ID`` with every attempt, so that the service's log lines of
    #: the call can be found from its error
    request_id: str = dataclasses.field(default_factory=lambda: uuid.uuid4().hex)

    @property
    def request_headers(self) -> dict[str, str]:
        """The call's headers with its ``X-Request-ID``."""
        return {**(self.headers or {}), REQUEST_ID_HEADER: self.request_id}

    @property
    def http_timeout(self) -> Any:
        """The ``timeout`` argument for httpx: this call's own, or the client's."""
        return self.timeout if self.own_timeout else httpx.USE_CLIENT_DEFAULT


#: the header carrying a call's id, answered by the service with the id its log uses
REQUEST_ID_HEADER = "X-Request-ID"


def _retry_after_s(header: str | None) -> float | None:
    """``Retry-After`` in seconds from now: delay-seconds or an HTTP date (a date already
    past is 0); None when absent or unreadable."""
    if header is None:
        return None
    try:
        return float(header)
    except ValueError:
        pass
    try:
        when = email.utils.parsedate_to_datetime(header)
    except (TypeError, ValueError):
        return None
    if when.tzinfo is None:  # an HTTP date is GMT
        when = when.replace(tzinfo=datetime.timezone.utc)
    return max(0.0, (when - datetime.datetime.now(datetime.timezone.utc)).total_seconds())


def _may_resend(call: Call[Any], exc: httpx.TransportError | None) -> bool:
    """Whether ``call``, sent, may be sent again after ``exc`` (None: a 503 answer)."""
    return call.idempotent and (call.resend_unanswered or not isinstance(exc, httpx.ReadTimeout))


def _body_only(fn: Callable[[Any], T]) -> Callable[[int, Any], T]:
    return lambda _status, body: fn(body)


def _map_path(name: str) -> str:
    if not isinstance(name, str) or not name:
        raise ValueError(f"map name must be a non-empty string, got {name!r}")
    return f"/v1/maps/{quote(name, safe='')}"


ARCHIVE_TYPE = "application/x-tar"  # map archives (export_map / import_map)


@contextmanager
def _open_dest(dest: str | os.PathLike[str] | BinaryIO) -> Iterator[BinaryIO]:
    """A binary file to write: ``dest`` itself, or for a path a new file beside it that
    replaces the path only when the block ends without error (a failed download leaves
    an existing file as it was)."""
    if not isinstance(dest, str | os.PathLike):
        yield dest
        return
    final = os.fspath(dest)
    part = f"{final}.{uuid.uuid4().hex[:8]}.part"
    try:
        with open(part, "xb") as f:
            yield f
        os.replace(part, final)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(part)
        raise


@contextmanager
def _open_src(src: str | os.PathLike[str] | BinaryIO) -> Iterator[BinaryIO]:
    """A binary file to read: ``src`` itself, or the path opened (and closed after)."""
    if isinstance(src, str | os.PathLike):
        with open(src, "rb") as f:
            yield f
    else:
        yield src


def _chunks(f: BinaryIO, size: int = 1 << 20) -> Iterator[bytes]:
    """A file's content in blocks (uploads stream; the file is never read whole)."""
    while block := f.read(size):
        yield block


def _filter_params(filters: Mapping[str, Any]) -> dict[str, Any]:
    """Keyframe filters as query parameters (None values left out; bbox joined)."""
    out: dict[str, Any] = {}
    for name in ("key_prefix", "bbox", "time_min", "time_max", "sequence"):
        value = filters.get(name)
        if value is None:
            continue
        if name == "bbox":
            box = [float(v) for v in value]
            if len(box) != 4:
                raise ValueError(f"bbox must be (x_min, y_min, x_max, y_max), got {value!r}")
            value = ",".join(repr(v) for v in box)
        out[name] = value
    return out


def _shorthand(value: str | Mapping[str, Any] | None, key: str) -> dict[str, Any] | None:
    """``"hnsw"`` -> ``{"index": "hnsw"}``; a mapping is copied; None stays None."""
    if value is None:
        return None
    if isinstance(value, str):
        return {key: value}
    return dict(value)


class BaseClient:
    """Configuration and request/response logic shared by the sync and async clients."""

    def __init__(
        self,
        base_url: str | Sequence[str] = DEFAULT_BASE_URL,
        timeout: float | httpx.Timeout | None = 30.0,
        retries: int = 3,
        api_key: str | None = None,
        *,
        backoff: float = 0.2,
        max_backoff: float = 5.0,
        wire_format: WireFormat = "msgpack",
        retry_overloaded: bool = False,
        max_retry_after: float = 30.0,
        total_timeout: float | None = None,
        jitter: bool = True,
    ) -> None:
        if total_timeout is not None and not total_timeout > 0:
            raise ValueError(f"total_timeout must be > 0 seconds or None, got {total_timeout}")
        if retries < 0:
            raise ValueError(f"retries must be >= 0, got {retries}")
        if not max_retry_after >= 0:
            raise ValueError(f"max_retry_after must be >= 0, got {max_retry_after}")
        if not (backoff >= 0 and max_backoff >= 0):
            raise ValueError(f"backoff and max_backoff must be >= 0, got {backoff}, {max_backoff}")
        if wire_format not in ("msgpack", "json"):
            raise ValueError(f"wire_format must be 'msgpack' or 'json', got {wire_format!r}")
        urls = [base_url] if isinstance(base_url, str) else list(base_url)
        if not urls:
            raise ValueError("give at least one base URL")
        #: every replica's base URL; calls go round-robin over them and fail over
        self.base_urls = [str(u).rstrip("/") for u in urls]
        self.base_url = self.base_urls[0]
        self._turn = itertools.count()
        self._down_until = [0.0] * len(self.base_urls)
        self._turn_lock = threading.Lock()
        self.timeout = timeout if isinstance(timeout, httpx.Timeout) else httpx.Timeout(timeout)
        self.retries = retries
        self.backoff = backoff
        self.max_backoff = max_backoff
        #: wait a random share of each backoff (half to all of it), so that clients that
        #: failed together do not resend together
        self.jitter = jitter
        self._random = random.Random()  # seeded from the OS: clients differ
        self.wire_format: WireFormat = wire_format
        self.retry_overloaded = retry_overloaded
        self.max_retry_after = max_retry_after
        #: the longest a call may take, all its tries and waits together (None: no bound)
        self.total_timeout = total_timeout
        self._api_key = api_key

    def __repr__(self) -> str:
        urls = self.base_url if len(self.base_urls) == 1 else self.base_urls
        return f"{type(self).__name__}({urls!r})"

    # ----------------------------------------------------------------------------------
    # Several base URLs: spreading and failover

    def _pick(self) -> int:
        """The base URL a new call starts with: the next in turn that has not failed in
        the last ``DOWN_FOR_S`` seconds (the next in turn if all have)."""
        n = len(self.base_urls)
        with self._turn_lock:
            start = next(self._turn) % n
        now = time.monotonic()
        for k in range(n):
            i = (start + k) % n
            if self._down_until[i] <= now:
                return i
        return start

    def _mark_down(self, i: int) -> None:
        self._down_until[i] = time.monotonic() + DOWN_FOR_S

    def _url(self, i: int, path: str) -> str:
        return f"{self.base_urls[i]}{path}"

    def _deadline(self) -> float | None:
        """When a call starting now must be over (``time.monotonic()``), or None."""
        return None if self.total_timeout is None else time.monotonic() + self.total_timeout

    def _attempt_timeout(self, call: Call[Any], end: float | None, sent: int = 0) -> Any:
        """The httpx ``timeout`` of one try of ``call``: its own or the client's, cut to
        the time left before ``end``; :class:`TransportError` when none is left (after
        ``sent`` tries)."""
        if end is None:
            return call.http_timeout
        left = end - time.monotonic()
        if left <= 0:
            raise self._out_of_time(call, sent)
        base = httpx.Timeout(call.timeout) if call.own_timeout else self.timeout

        def cut(value: float | None) -> float:
            return left if value is None else min(value, left)

        return httpx.Timeout(
            connect=cut(base.connect),
            read=cut(base.read),
            write=cut(base.write),
            pool=cut(base.pool),
        )

    def _wait_within(
        self,
        call: Call[Any],
        end: float | None,
        wait: float,
        attempts: int = 1,
        cause: BaseException | None = None,
    ) -> float:
        """``wait`` (seconds before the next try), or :class:`TransportError` when the
        next try would start past ``end`` (``attempts`` sent so far, the last failing
        with ``cause``)."""
        if end is not None and time.monotonic() + wait >= end:
            raise self._out_of_time(call, attempts, cause)
        return wait

    def _out_of_time(
        self, call: Call[Any], attempts: int = 1, cause: BaseException | None = None
    ) -> TransportError:
        last = f"; the last try: {type(cause).__name__}" if cause is not None else ""
        return TransportError(
            f"{call.method} {call.path}: no answer within total_timeout="
            f"{self.total_timeout:g} s after {attempts} attempt{'s' if attempts > 1 else ''}"
            f"{last} (request id {call.request_id})",
            attempts=attempts,
            request_id=call.request_id,
        )

    def _backoff(self, attempt: int) -> float:
        """Seconds to wait before resending after failed try number ``attempt`` (0-based):
        ``backoff * 2**attempt``, at most ``max_backoff``; with ``jitter``, a uniform draw
        from half of that to all of it."""
        wait = min(self.max_backoff, self.backoff * 2**attempt)
        return self._random.uniform(wait / 2, wait) if self.jitter else wait

    def _after_refusal(
        self, i: int, tried: set[int], attempt: int, method: str, exc: httpx.TransportError
    ) -> tuple[int, float]:
        """A streamed call (an export, an import) whose connection to URL ``i`` was
        refused at try ``attempt``, so nothing was sent: the URL to try next (an untried
        replica at once, else the same after the backoff) and the seconds to wait first.
        Raises :class:`TransportError` when ``retries`` are spent."""
        if attempt >= self.retries:
            raise self._unanswered(method, self.base_urls[i], exc) from exc
        why = type(exc).__name__
        if len(self.base_urls) > 1:
            j = self._untried(i, tried)
            if j is not None:
                tried.add(j)
                self._log_resend(method, i, "", why, attempt, to=j)
                return j, 0.0
        wait = self._backoff(attempt)
        self._log_resend(method, i, "", why, attempt, wait=wait)
        return i, wait

    def _failover(
        self,
        call: Call[Any],
        attempt: int,
        i: int,
        tried: set[int],
        *,
        sent: bool,
        exc: httpx.TransportError | None = None,
        status: int = 503,
    ) -> int | None:
        """The base URL to resend ``call`` to at once after try ``attempt`` failed on
        URL ``i`` (a connection error ``exc``, or a 429/502/503/504 answer), or None: only
        with several URLs,
        only an untried one, within ``retries``, and only for calls safe to resend, unless
        the request was never ``sent`` (the connection was refused)."""
        if len(self.base_urls) == 1:
            return None
        if sent and (attempt >= self.retries or not _may_resend(call, exc)):
            return None
        j = self._untried(i, tried)  # a refused connection moves on whatever retries says
        if j is not None:
            why = str(status) if exc is None else type(exc).__name__
            self._log_resend(call.method, i, call.path, why, attempt, to=j)
        return j

    def _log_resend(
        self,
        method: str,
        i: int,
        path: str,
        why: str,
        attempt: int,
        *,
        wait: float = 0.0,
        to: int | None = None,
    ) -> None:
        """Say that a call that failed on URL ``i`` (``why``) is sent again: to URL ``to``
        at once, or to the same after ``wait`` seconds (a WARNING of logger sgvloc_client)."""
        where = f"to {self.base_urls[to]}" if to is not None else f"in {wait:.1f} s"
        log.warning(
            "%s %s%s failed (%s); resending %s (try %d of %d)",
            method,
            self.base_urls[i],
            path,
            why,
            where,
            attempt + 2,
            self.retries + 1,
        )

    def _untried(self, i: int, tried: set[int]) -> int | None:
        """URL ``i`` failed: mark it down and name the next URL after it not ``tried``
        yet (None when every one was)."""
        self._mark_down(i)
        n = len(self.base_urls)
        for k in range(1, n):
            j = (i + k) % n
            if j not in tried:
                return j
        return None

    # ----------------------------------------------------------------------------------
    # Transport settings

    def _http_options(self) -> dict[str, Any]:
        """Keyword arguments for ``httpx.Client`` / ``httpx.AsyncClient``."""
        headers = {
            "Accept": wire.MSGPACK if self.wire_format == "msgpack" else wire.JSON,
            "User-Agent": f"sgvloc-client/{__version__}",
        }
        if self._api_key:
            headers["Authorization"] = f"Bearer {self._api_key}"
        return {"base_url": self.base_url, "timeout": self.timeout, "headers": headers}

    def _encode(self, body: Any) -> tuple[bytes, dict[str, str]]:
        if self.wire_format == "msgpack":
            return wire.packb(body), {"Content-Type": wire.MSGPACK}
        return json.dumps(wire.to_jsonable(body)).encode(), {"Content-Type": wire.JSON}

    def _call(
        self,
        method: str,
        path: str,
        parse: Callable[[int, Any], T],
        body: Any = None,
        *,
        idempotent: bool,
        passthrough: tuple[int, ...] = (),
    ) -> Call[T]:
        content, headers = (None, None) if body is None else self._encode(body)
        return Call(method, path, parse, content, headers, idempotent, passthrough)

    def _ready_poll(self, deadline: float) -> Call[str]:
        """One ``/readyz`` poll of :meth:`wait_until_ready`: not resent, and given no
        more than the time left, so that the wait ends when it said it would."""
        left = max(0.05, deadline - time.monotonic())
        return replace(self._ready_status(), idempotent=False, timeout=left, own_timeout=True)

    def _unanswered(self, method: str, url: str, exc: httpx.TransportError) -> TransportError:
        """A streamed call's connection error as the SDK's :class:`TransportError`."""
        detail = str(exc) or type(exc).__name__
        return TransportError(f"{method} {url} failed: {type(exc).__name__}: {detail}")

    # ----------------------------------------------------------------------------------
    # Retries

    def _retry_delay(
        self, call: Call[Any], attempt: int, exc: httpx.TransportError, i: int = 0
    ) -> float:
        """Seconds to wait before resending ``call`` after failed try number ``attempt``
        (0-based) on base URL ``i``; raises :class:`TransportError` when the call must
        not be resent."""
        tries = attempt + 1
        if _may_resend(call, exc) and isinstance(exc, _RETRYABLE) and attempt < self.retries:
            wait = self._backoff(attempt)
            self._log_resend(call.method, i, call.path, type(exc).__name__, attempt, wait=wait)
            return wait
        kind = type(exc).__name__
        detail = str(exc) or kind
        raise TransportError(
            f"{call.method} {self.base_urls[i]}{call.path} failed after {tries} "
            f"attempt{'s' if tries > 1 else ''}: {kind}: {detail} (request id "
            f"{call.request_id})",
            attempts=tries,
            request_id=call.request_id,
        ) from exc

    def _overload_delay(self, call: Call[Any], attempt: int, response: httpx.Response) -> float:
        """Seconds to wait before resending ``call`` after its answer ``response`` (try
        number ``attempt``, 0-based), or -1 to keep the answer: only with
        ``retry_overloaded``, only for calls safe to resend, only for 429/503 that the call
        does not take as a result, at most ``retries`` times, and only when
        ``Retry-After`` (seconds; without it, the backoff) is within ``max_retry_after``."""
        status = response.status_code
        if not (
            self.retry_overloaded
            and call.idempotent
            and status in (429, 502, 503, 504)
            and status not in call.passthrough
            and attempt < self.retries
        ):
            return -1.0
        body = self._decode(response)
        err = body.get("error") if isinstance(body, dict) else None
        if isinstance(err, dict) and err.get("code") == "map_unavailable":
            return -1.0  # waits on an operator, not on time
        if status in (502, 504) and not _from_gateway(status, body):
            return -1.0
        delay = _retry_after_s(response.headers.get("retry-after"))
        if delay is None:  # none, or garbage: the backoff
            delay = self._backoff(attempt)
        if not 0.0 <= delay <= self.max_retry_after:
            return -1.0
        log.warning(
            "%s %s answered %d; resending in %.1f s (try %d of %d)",
            call.method,
            call.path,
            status,
            delay,
            attempt + 2,
            self.retries + 1,
        )
        return delay

    # ----------------------------------------------------------------------------------
    # Responses

    def _finish(self, call: Call[T], response: httpx.Response) -> T:
        """Decode ``response`` and return the call's result, or raise its error."""
        status = response.status_code
        body = self._decode(response)
        if _from_gateway(status, body) and status not in call.passthrough:
            raise TransportError(
                f"{call.method} {response.url}: the load balancer answered {status} (no "
                f"replica answered it) (request id {call.request_id})",
                request_id=call.request_id,
            )
        if status >= 400 and status not in call.passthrough:
            rid = response.headers.get(REQUEST_ID_HEADER) or call.request_id
            raise self._error(status, body, rid)
        try:
            return call.parse(status, body)
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
            # not an sgvloc answer: a captive portal, a proxy's page, another service
            ctype = response.headers.get("content-type", "?")
            raise TransportError(
                f"{call.method} {response.url}: the answer ({status}, {ctype}) is not the "
                f"service's ({type(exc).__name__}: {exc}); is the URL an sgvloc service? "
                f"(request id {call.request_id})",
                request_id=call.request_id,
            ) from exc

    @staticmethod
    def _decode(response: httpx.Response) -> Any:
        content = response.content
        if response.status_code == 204 or not content:
            return None
        ctype = response.headers.get("content-type", "").split(";")[0].strip().lower()
        try:
            if ctype == wire.MSGPACK:
                return wire.unpackb(content)
            if ctype == wire.JSON or ctype.endswith("+json"):
                return json.loads(content)
        except (wire.WireError, ValueError) as exc:
            if response.status_code >= 400:
                return response.text
            raise SgvlocError(
                f"cannot decode the {ctype} answer to {response.request.method} "
                f"{response.request.url}: {exc}"
            ) from None
        return response.text

    @staticmethod
    def _error(status: int, body: Any, request_id: str | None = None) -> APIError:
        err = body.get("error") if isinstance(body, dict) else None
        if isinstance(err, dict):
            code = str(err.get("code") or f"http_{status}")
            message = str(err.get("message") or "")
            field = err.get("field")
        else:  # not the service's error shape (framework default, proxy page)
            code = f"http_{status}"
            detail = body.get("detail") if isinstance(body, dict) else body
            message = str(detail or httpx.codes.get_reason_phrase(status))[:500]
            field = None
        return error_class(status, code)(status, code, message, field, body, request_id)

    # ----------------------------------------------------------------------------------
    # Requests, one builder per operation (documented on Client)

    def _health(self) -> Call[dict[str, Any]]:
        return self._call("GET", "/healthz", _body_only(dict), idempotent=True)

    def _ready(self) -> Call[bool]:
        return self._call(
            "GET", "/readyz", lambda status, _b: status == 200, idempotent=True, passthrough=(503,)
        )

    def _ready_status(self) -> Call[str]:
        """``/readyz``'s status: ready, loading, degraded (up, some map failed to load) or
        failed."""

        def status_of(status: int, body: Any) -> str:
            s = body.get("status") if isinstance(body, dict) else None
            return str(s) if s else ("ready" if status == 200 else "loading")

        return self._call("GET", "/readyz", status_of, idempotent=True, passthrough=(503,))

    def _create_map(
        self,
        name: str,
        encoder: str | Mapping[str, Any] | None,
        retrieval: str | Mapping[str, Any] | None,
        localizer: Mapping[str, Any] | None,
        calibration: Mapping[str, Any] | None = None,
        self_test: Mapping[str, Any] | None = None,
        keep_clouds: bool | None = None,
    ) -> Call[MapInfo]:
        body: dict[str, Any] = {"name": name}
        for key, value in (
            ("encoder", _shorthand(encoder, "kind")),
            ("retrieval", _shorthand(retrieval, "index")),
            ("localizer", None if localizer is None else dict(localizer)),
            ("keep_clouds", None if keep_clouds is None else bool(keep_clouds)),
            ("calibration", None if calibration is None else dict(calibration)),
            ("self_test", None if self_test is None else dict(self_test)),
        ):
            if value is not None:
                body[key] = value
        # Not idempotent: a resent create that had succeeded would answer 409.
        return self._call("POST", "/v1/maps", _body_only(MapInfo.from_body), body, idempotent=False)

    def _list_maps(self, limit: int, cursor: str | None, prefix: str | None) -> Call[MapPage]:
        params: dict[str, Any] = {"limit": _page_limit(limit)}
        if cursor is not None:
            params["cursor"] = cursor
        if prefix:
            params["prefix"] = prefix

        def page(body: Any) -> MapPage:
            got = MapPage.from_body(body)
            if prefix and got.total is None:  # a service from before paging lists them all
                kept = [m for m in got.maps if m.name.startswith(prefix)]
                got = replace(got, maps=kept, total=len(kept))
            return got

        return self._call("GET", f"/v1/maps?{urlencode(params)}", _body_only(page), idempotent=True)

    @staticmethod
    def _next_maps_cursor(page: MapPage, cursor: str | None) -> str | None:
        """The cursor of the page after ``page`` (None: it was the last); a service that
        hands back a cursor that does not move on would loop for ever: an error."""
        nxt = page.next_cursor
        if nxt is not None and cursor is not None and nxt <= cursor:
            raise SgvlocError(f"the map listing did not move on past {cursor!r}")
        return nxt

    def _get_map(self, name: str) -> Call[MapInfo]:
        return self._call("GET", _map_path(name), _body_only(MapInfo.from_body), idempotent=True)

    def _update_map(
        self,
        name: str,
        localizer: Mapping[str, Any] | None,
        calibration: str | Mapping[str, Any] | None,
    ) -> Call[MapInfo]:
        if localizer is None and calibration is None:
            raise ValueError("give localizer settings and/or a calibration to change")
        body: dict[str, Any] = {}
        if localizer is not None:
            body["localizer"] = dict(localizer)
        if calibration is not None:
            body["calibration"] = calibration if isinstance(calibration, str) else dict(calibration)
        # Setting the same values again changes nothing more: safe to resend.
        return self._call(
            "PATCH", _map_path(name), _body_only(MapInfo.from_body), body, idempotent=True
        )

    def _self_test_map(
        self,
        name: str,
        queries: int,
        gap_s: float,
        gap_keyframes: int,
        radius_m: float,
        encoders: Sequence[str] | None,
        timeout: float | None,
    ) -> Call[dict[str, Any]]:
        body: dict[str, Any] = {
            "queries": queries,
            "gap_s": gap_s,
            "gap_keyframes": gap_keyframes,
            "radius_m": radius_m,
        }
        if encoders is not None:
            body["encoders"] = list(encoders)
        # Not resent: it only records a summary, but a timed-out one may still be running
        # on the server, and each try would start another.
        call = self._call(
            "POST", _map_path(name) + "/self-test", lambda _s, b: dict(b), body, idempotent=False
        )
        return replace(call, timeout=timeout, own_timeout=True)

    def _delete_map(self, name: str, force: bool = False) -> Call[None]:
        # Not resent: a delete that went through but whose answer was lost would answer
        # 404 the second time, reporting a failure for a success.
        path = _map_path(name) + ("?force=true" if force else "")
        return self._call("DELETE", path, lambda _s, _b: None, idempotent=False)

    def _insert_keyframes(
        self, map: str, keyframes: Sequence[KeyframeIn | Mapping[str, Any]]
    ) -> Call[InsertResult]:
        if isinstance(keyframes, KeyframeIn | Mapping):
            raise TypeError("keyframes must be a list; use insert_keyframe for one")
        kfs = [KeyframeIn.coerce(k) for k in keyframes]
        if not kfs:
            raise ValueError("keyframes is empty")
        # Keyed inserts are idempotent on the service, so a resend is harmless, but not
        # after a read timeout: the service may still be encoding the batch, and a resend
        # would encode it again on another worker.
        keyed = all(k.key is not None for k in kfs)
        body = {"keyframes": [k.to_body() for k in kfs]}
        call = self._call(
            "POST",
            f"{_map_path(map)}/keyframes",
            _body_only(InsertResult.from_body),
            body,
            idempotent=keyed,
        )
        return replace(call, resend_unanswered=False)

    def _get_keyframe(self, map: str, keyframe_id: int) -> Call[Keyframe]:
        return self._call(
            "GET",
            f"{_map_path(map)}/keyframes/{int(keyframe_id)}",
            _body_only(Keyframe.from_body),
            idempotent=True,
        )

    def _delete_keyframe(self, map: str, keyframe_id: int) -> Call[KeyframeDeleted]:
        return self._call(
            "DELETE",
            f"{_map_path(map)}/keyframes/{int(keyframe_id)}",
            _body_only(KeyframeDeleted.from_body),
            idempotent=False,  # as delete_map: a resend would answer 404
        )

    def _list_keyframes(
        self, map: str, limit: int, cursor: str | None, filters: dict[str, Any]
    ) -> Call[KeyframePage]:
        params = {"limit": _page_limit(limit), **_filter_params(filters)}
        if cursor is not None:
            params["cursor"] = cursor
        return self._call(
            "GET",
            f"{_map_path(map)}/keyframes?{urlencode(params)}",
            _body_only(KeyframePage.from_body),
            idempotent=True,
        )

    def _delete_keyframes(
        self, map: str, all: bool, filters: dict[str, Any]
    ) -> Call[KeyframesDeleted]:
        params = _filter_params(filters)
        if not params and not all:
            raise ValueError("give at least one filter, or all=True to delete every keyframe")
        if all:
            params["all"] = "true"
        # Not resent: a second try would report 0 deleted after the first went through,
        # and would delete keyframes inserted in between that match.
        return self._call(
            "DELETE",
            f"{_map_path(map)}/keyframes?{urlencode(params)}",
            _body_only(KeyframesDeleted.from_body),
            idempotent=False,
        )

    def _map_stats(self, map: str) -> Call[MapStats]:
        return self._call(
            "GET", f"{_map_path(map)}/stats", _body_only(MapStats.from_body), idempotent=True
        )

    def _import_call(self) -> Call[MapInfo]:
        """How an import's answer is read (its body is streamed, not a Call's)."""
        return self._call(
            "POST", "/v1/map-archives", _body_only(MapInfo.from_body), idempotent=False
        )

    def _import_path(self, name: str | None) -> str:
        return "/v1/map-archives" + ("" if name is None else f"?{urlencode({'name': name})}")

    def _recent_localizations(self, map: str, limit: int) -> Call[list[RecentLocalization]]:
        if not 1 <= int(limit) <= 500:
            raise ValueError(f"limit must be within 1..500, got {limit}")
        return self._call(
            "GET",
            f"{_map_path(map)}/localizations?limit={int(limit)}",
            _body_only(lambda b: [RecentLocalization.from_body(x) for x in b["localizations"]]),
            idempotent=True,
        )

    def _localize(
        self,
        map: str,
        points: Any,
        features: Mapping[str, Any] | None,
        top_k: int | None,
        rerank: str | None,
        refine: str | None,
        prior: Prior | Mapping[str, Any] | None = None,
        min_confidence: float | None = None,
        seed: Seed | Mapping[str, Any] | None = None,
        min_map_version: int | None = None,
    ) -> Call[Localization]:
        if (points is None) == (features is None):
            raise ValueError("give exactly one of points or features")
        body: dict[str, Any] = {}
        if points is not None:
            body["points"] = points_array(points)
        else:
            body["features"] = features_body(features)
        for key, value in (
            ("top_k", top_k),
            ("rerank", rerank),
            ("refine", refine),
            ("prior", None if prior is None else Prior.coerce(prior).to_body()),
            ("min_confidence", min_confidence),
            ("seed", None if seed is None else Seed.coerce(seed).to_body()),
        ):
            if value is not None:
                body[key] = value
        query = ""
        if min_map_version is not None:
            if isinstance(min_map_version, bool) or int(min_map_version) != min_map_version:
                raise ValueError(f"min_map_version must be an integer, got {min_map_version!r}")
            if int(min_map_version) < 0:
                raise ValueError(f"min_map_version must be >= 0, got {min_map_version}")
            query = f"?min_map_version={int(min_map_version)}"
        # Localizing reads the map and changes nothing: safe to resend.
        return self._call(
            "POST",
            f"{_map_path(map)}/localize{query}",
            _body_only(Localization.from_body),
            body,
            idempotent=True,
        )
