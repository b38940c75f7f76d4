"""The synchronous client."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator, Mapping, Sequence
from types import TracebackType
from typing import Any, BinaryIO, TypeVar

import httpx

from ._base import (
    ARCHIVE_TYPE,
    DEFAULT_BASE_URL,
    REQUEST_ID_HEADER,
    BaseClient,
    Call,
    WireFormat,
    _chunks,
    _map_path,
    _open_dest,
    _open_src,
)
from ._errors import TransportError
from ._models import (
    InsertResult,
    Keyframe,
    KeyframeDeleted,
    KeyframeIn,
    KeyframePage,
    KeyframesDeleted,
    KeyframeSummary,
    Localization,
    MapInfo,
    MapPage,
    MapStats,
    Prior,
    RecentLocalization,
    Seed,
)

T = TypeVar("T")


class Client(BaseClient):
    """A connection to an sgvloc service.

    Args:
        base_url: where the service listens, or a list of replicas' base URLs (one
            store, see docs/SCALING.md): calls take turns over them, and a call safe to
            resend (see ``retries``) moves to the next replica at once after a
            connection error or a 429, 503 or gateway (502, 504) answer (that one is busy,
            loading or unreachable; another may not be); any call moves when its connection was
            refused (nothing was sent). A replica that failed is skipped for 5 s.
        timeout: seconds (or an ``httpx.Timeout``) for connecting, sending and reading;
            None waits forever.
        retries: how many times a call is resent after a connection error or timeout,
            with exponential backoff (``backoff * 2**n`` seconds, at most
            ``max_backoff``; with ``jitter``, a random half to all of it). Only calls
            that are safe to resend are: GET, PATCH, localize, and inserts whose
            keyframes all carry a ``key`` (those not after a read timeout: the service
            may still be doing the work); never ``create_map``, a DELETE or a keyless
            insert. Error answers (4xx/5xx) are not retried,
            except as ``retry_overloaded`` says.
        api_key: sent as ``Authorization: Bearer <key>``.
        transport: an ``httpx.BaseTransport`` to send through (tests, custom TLS).
        wire_format: ``"msgpack"`` (default; arrays travel as raw float32 bytes) or
            ``"json"``.
        retry_overloaded: also resend those calls after a 429 or 503 answer (too busy,
            still loading), waiting the answer's ``Retry-After`` seconds; counts against
            ``retries``. Off by default: a vehicle may prefer a fresh scan to a late answer.
        max_retry_after: a ``Retry-After`` longer than this (seconds) is not waited for:
            the :class:`Overloaded` error is raised at once.
        total_timeout: seconds for a call with all its tries and waits: each try's
            connect, send and read timeouts are cut to the time left when it starts, and
            no try or wait goes past it (:class:`TransportError`). ``timeout`` bounds each
            try; None (the default): no bound over the tries. An answer still arriving is
            not cut (a server sending a byte at a time keeps each read within its
            timeout), and map exports and imports keep their own ``timeout``.
        jitter: wait a random half to all of each backoff (the default), so that
            vehicles that lost a replica together do not all resend at the same moment;
            False waits the backoff exactly. A ``Retry-After`` is waited as given.

    Use as a context manager (or call :meth:`close`). Errors are the exceptions of
    :mod:`sgvloc_client._errors` (see :class:`~sgvloc_client.SgvlocError`).
    """

    def __init__(
        self,
        base_url: str | Sequence[str] = DEFAULT_BASE_URL,
        timeout: float | httpx.Timeout | None = 30.0,
        retries: int = 3,
        api_key: str | None = None,
        transport: httpx.BaseTransport | None = None,
        *,
        backoff: float = 0.2,
        max_backoff: float = 5.0,
        wire_format: WireFormat = "msgpack",
        retry_overloaded: bool = False,
        max_retry_after: float = 30.0,
        total_timeout: float | None = None,
        jitter: bool = True,
    ) -> None:
        super().__init__(
            base_url,
            timeout,
            retries,
            api_key,
            backoff=backoff,
            max_backoff=max_backoff,
            wire_format=wire_format,
            retry_overloaded=retry_overloaded,
            max_retry_after=max_retry_after,
            total_timeout=total_timeout,
            jitter=jitter,
        )
        self._http = httpx.Client(transport=transport, **self._http_options())

    def __enter__(self) -> Client:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Close the connection pool."""
        self._http.close()

    def _send(self, call: Call[T]) -> T:
        attempt = 0
        i = self._pick()
        tried = {i}
        end = self._deadline()
        while True:
            try:
                response = self._http.request(
                    call.method,
                    self._url(i, call.path),
                    content=call.content,
                    headers=call.request_headers,
                    timeout=self._attempt_timeout(call, end, attempt),
                )
            except httpx.TransportError as exc:
                sent = not isinstance(exc, httpx.ConnectError)
                j = self._failover(call, attempt, i, tried, sent=sent, exc=exc)
                if j is None:
                    wait = self._retry_delay(call, attempt, exc, i)
                    time.sleep(self._wait_within(call, end, wait, attempt + 1, exc))
                else:
                    i = j
                    tried.add(j)
                attempt += 1
                continue
            status = response.status_code
            if status in (429, 502, 503, 504) and status not in call.passthrough:
                j = self._failover(call, attempt, i, tried, sent=True, status=status)
                if j is not None:  # another replica may be ready, caught up or connected
                    i = j
                    tried.add(j)
                    attempt += 1
                    continue
            delay = self._overload_delay(call, attempt, response)
            if delay >= 0 and (end is None or time.monotonic() + delay < end):
                time.sleep(delay)
                attempt += 1
                continue
            return self._finish(call, response)

    # ----------------------------------------------------------------------------------
    # Probes

    def health(self) -> dict[str, Any]:
        """``GET /healthz``: ``{"status": "ok"}`` while the process is alive."""
        return self._send(self._health())

    def ready(self) -> bool:
        """``GET /readyz``: True once every map is loaded, False while loading (503)."""
        return self._send(self._ready())

    def wait_until_ready(self, timeout: float = 30.0, interval: float = 0.2) -> None:
        """Poll ``/readyz`` until the service serves its maps: ready, or degraded (a map
        failed to load; the others are served, and a call to that map answers
        :class:`MapUnavailable`). Raise :class:`TransportError` after ``timeout`` seconds
        (the service is unreachable, still loading, or failed)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                status = self._send(self._ready_poll(deadline))
                if status in ("ready", "degraded"):
                    return
                last = f"the service's status is {status!r}"
            except TransportError as exc:
                last = str(exc)
            if time.monotonic() >= deadline:
                raise TransportError(f"{self.base_url} not ready after {timeout} s: {last}")
            time.sleep(interval)

    # ----------------------------------------------------------------------------------
    # Maps

    def create_map(
        self,
        name: str,
        encoder: str | Mapping[str, Any] | None = None,
        retrieval: str | Mapping[str, Any] | None = None,
        localizer: Mapping[str, Any] | None = None,
        calibration: Mapping[str, Any] | None = None,
        self_test: Mapping[str, Any] | None = None,
        keep_clouds: bool | None = None,
    ) -> MapInfo:
        """Create an empty map.

        ``encoder`` is an EncoderSpec (``{"kind": "learned" | "handcrafted" | "bev" |
        "torchscript" | "precomputed", ...}``) or just its kind; default: the learned
        encoder. ``retrieval`` is ``{"index": "flat" | "ivf" | "hnsw", ...}`` or just the
        index name; ``localizer`` the map's default localize settings (``top_k``,
        ``rerank``, ``sgv``, ``pose``, ``verdict``); ``calibration`` a confidence model
        written by ``sgvloc calibrate`` (default: the one shipped for the encoder kind);
        ``self_test`` an encoder self-test to record with the map
        (:func:`sgvloc.tools.self_test.self_test` makes one); ``keep_clouds`` False keeps
        no keyframe clouds (less memory and disk; no ICP, free-space check or tracking).
        Raises :class:`Conflict` if the name is taken.
        """
        return self._send(
            self._create_map(
                name, encoder, retrieval, localizer, calibration, self_test, keep_clouds
            )
        )

    def list_maps(self, *, prefix: str | None = None) -> list[MapInfo]:
        """Every map the key may use (whose name starts with ``prefix``, if given), by
        name, read page by page."""
        out: list[MapInfo] = []
        cursor = None
        while True:
            page = self.list_maps_page(limit=1000, cursor=cursor, prefix=prefix)
            out.extend(page.maps)
            cursor = self._next_maps_cursor(page, cursor)
            if cursor is None:
                return out

    def list_maps_page(
        self, *, limit: int = 100, cursor: str | None = None, prefix: str | None = None
    ) -> MapPage:
        """One page of maps by name (``limit`` 1..1000); pass the page's ``next_cursor``
        for the next one."""
        return self._send(self._list_maps(limit, cursor, prefix))

    def get_map(self, name: str) -> MapInfo:
        """One map; raises :class:`NotFound` if there is none of that name."""
        return self._send(self._get_map(name))

    def update_map(
        self,
        name: str,
        localizer: Mapping[str, Any] | None = None,
        calibration: str | Mapping[str, Any] | None = None,
    ) -> MapInfo:
        """Change a map's settings after creation; its keyframes and version stay.

        ``localizer`` is merged into the current settings, e.g.
        ``{"verdict": {"min_confidence": 0.9}, "top_k": 30}`` (retrieval cannot change);
        ``calibration`` is a model written by ``sgvloc calibrate`` or ``"shipped"``.
        Needs a mapper or admin key.
        """
        return self._send(self._update_map(name, localizer, calibration))

    def self_test_map(
        self,
        name: str,
        *,
        queries: int = 50,
        gap_s: float = 30.0,
        gap_keyframes: int = 30,
        radius_m: float = 5.0,
        encoders: Sequence[str] | None = None,
        timeout: float | None = 600.0,
    ) -> dict[str, Any]:
        """Localize a sample of the map's own keyframes against the others (each one's
        own stretch of the drive left out: ``gap_s`` seconds by ``metadata.timestamp``,
        else ``gap_keyframes`` in insertion order): the report's ``figures`` hold
        Recall@1, pose success, the share of correct answers accepted and false accepts;
        ``records`` one entry per query. ``encoders`` (e.g. ``["learned", "handcrafted",
        "bev", "learned-fpfh"]``) also measures those encoders on the same queries, each
        from the keyframes' stored clouds encoded again (the map's own encoder among
        them, as served): the report's ``encoders`` holds their figures and ``chosen``
        the best (the map's own on a tie). The summary is recorded with the map
        (``MapInfo.last_self_test``). ``timeout``: seconds for this call (a few per
        hundred queries on two cores, and per encoder compared about what encoding the
        map's keyframes takes). Needs a mapper or admin key.
        """
        return self._send(
            self._self_test_map(name, queries, gap_s, gap_keyframes, radius_m, encoders, timeout)
        )

    def delete_map(self, name: str, force: bool = False) -> None:
        """Delete a map and its keyframes; raises :class:`NotFound` if it does not exist.
        A map the service could not load is deleted (unread) only with ``force``."""
        self._send(self._delete_map(name, force))

    # ----------------------------------------------------------------------------------
    # Keyframes

    def insert_keyframes(
        self, map: str, keyframes: Sequence[KeyframeIn | Mapping[str, Any]]
    ) -> InsertResult:
        """Insert keyframes (:class:`KeyframeIn` or dicts with its fields) in one request.

        All or nothing: if one keyframe is bad none is stored, and the
        :class:`BadRequest` names it (``field = "keyframes[3].points"``). Keyframes whose
        ``key`` is already in the map are not inserted again (``created`` False).
        """
        return self._send(self._insert_keyframes(map, keyframes))

    def insert_keyframe(
        self,
        map: str,
        T_map_sensor: Any,
        points: Any = None,
        features: Mapping[str, Any] | None = None,
        key: str | None = None,
        metadata: Mapping[str, Any] | None = None,
    ) -> InsertResult:
        """Insert one keyframe; see :class:`KeyframeIn` for the arguments."""
        kf = KeyframeIn(T_map_sensor, points, features, key, metadata)
        return self._send(self._insert_keyframes(map, [kf]))

    def get_keyframe(self, map: str, keyframe_id: int) -> Keyframe:
        """One keyframe's pose, key and metadata."""
        return self._send(self._get_keyframe(map, keyframe_id))

    def delete_keyframe(self, map: str, keyframe_id: int) -> KeyframeDeleted:
        """Delete one keyframe; returns the map's new version."""
        return self._send(self._delete_keyframe(map, keyframe_id))

    def recent_localizations(self, map: str, limit: int = 100) -> list[RecentLocalization]:
        """The map's most recent localize answers (at most ``limit``, 1..500), newest
        first. The service keeps the last 500 per map in memory, not across restarts."""
        return self._send(self._recent_localizations(map, limit))

    # ----------------------------------------------------------------------------------
    # Map management

    def list_keyframes(
        self,
        map: str,
        *,
        limit: int = 100,
        cursor: str | None = None,
        key_prefix: str | None = None,
        bbox: Sequence[float] | None = None,
        time_min: float | None = None,
        time_max: float | None = None,
        sequence: str | None = None,
    ) -> KeyframePage:
        """One page of keyframes (id order) matching every given filter: key prefix,
        ``bbox`` = (x_min, y_min, x_max, y_max) of the position, metadata ``timestamp``
        range, metadata ``sequence``. Pass the page's ``next_cursor`` for the next one."""
        filters = dict(
            key_prefix=key_prefix,
            bbox=bbox,
            time_min=time_min,
            time_max=time_max,
            sequence=sequence,
        )
        return self._send(self._list_keyframes(map, limit, cursor, filters))

    def iter_keyframes(
        self, map: str, *, page_size: int = 1000, **filters: Any
    ) -> Iterator[KeyframeSummary]:
        """Every keyframe matching the filters of :meth:`list_keyframes`, page by page."""
        cursor = None
        while True:
            page = self.list_keyframes(map, limit=page_size, cursor=cursor, **filters)
            yield from page.keyframes
            if page.next_cursor is None:
                return
            cursor = page.next_cursor

    def delete_keyframes(
        self,
        map: str,
        *,
        all: bool = False,
        key_prefix: str | None = None,
        bbox: Sequence[float] | None = None,
        time_min: float | None = None,
        time_max: float | None = None,
        sequence: str | None = None,
    ) -> KeyframesDeleted:
        """Delete every keyframe matching the filters (see :meth:`list_keyframes`) in one
        transaction; without filters only with ``all=True``."""
        filters = dict(
            key_prefix=key_prefix,
            bbox=bbox,
            time_min=time_min,
            time_max=time_max,
            sequence=sequence,
        )
        return self._send(self._delete_keyframes(map, all, filters))

    def map_stats(self, map: str) -> MapStats:
        """Keyframes, extent, disk and memory use, index kind and last write of a map."""
        return self._send(self._map_stats(map))

    def export_map(
        self, map: str, dest: str | os.PathLike[str] | BinaryIO, *, timeout: float | None = 600.0
    ) -> int:
        """Download map ``map`` as an archive into ``dest`` (a path or a binary file),
        streamed; returns the bytes written. ``timeout``: seconds without data. A refused
        connection moves to the next replica (or is tried again, within ``retries``)."""
        i = self._pick()
        tried, attempt = {i}, 0
        with _open_dest(dest) as out:
            while True:
                url = self._url(i, f"{_map_path(map)}/export")
                try:
                    with self._http.stream("GET", url, timeout=timeout) as r:
                        if r.status_code >= 400:
                            r.read()
                            rid = r.headers.get(REQUEST_ID_HEADER)
                            raise self._error(r.status_code, self._decode(r), rid)
                        size = 0
                        for block in r.iter_bytes():
                            out.write(block)
                            size += len(block)
                        return size
                except httpx.ConnectError as exc:
                    i, wait = self._after_refusal(i, tried, attempt, "GET", exc)
                    attempt += 1
                    time.sleep(wait)
                except httpx.TransportError as exc:
                    raise self._unanswered("GET", url, exc) from exc

    def import_map(
        self,
        src: str | os.PathLike[str] | BinaryIO,
        name: str | None = None,
        *,
        timeout: float | None = 600.0,
    ) -> MapInfo:
        """Create a map from an archive made by :meth:`export_map` (streamed from ``src``,
        a path or a binary file), under ``name`` or its archived name. A refused
        connection moves to the next replica (or is tried again, within ``retries``) when
        ``src`` can be read again from its start (a path, or a seekable file)."""
        i = self._pick()
        tried, attempt = {i}, 0
        with _open_src(src) as f:
            start = f.tell() if f.seekable() else None
            while True:
                url = self._url(i, self._import_path(name))
                try:
                    r = self._http.post(
                        url,
                        content=_chunks(f),
                        headers={"Content-Type": ARCHIVE_TYPE},
                        timeout=timeout,
                    )
                    break
                except httpx.ConnectError as exc:
                    if start is None:
                        raise self._unanswered("POST", url, exc) from exc
                    i, wait = self._after_refusal(i, tried, attempt, "POST", exc)
                    attempt += 1
                    f.seek(start)
                    time.sleep(wait)
                except httpx.TransportError as exc:
                    raise self._unanswered("POST", url, exc) from exc
        return self._finish(self._import_call(), r)

    # ----------------------------------------------------------------------------------
    # Localize

    def localize(
        self,
        map: str,
        points: Any = None,
        features: Mapping[str, Any] | None = None,
        top_k: int | None = None,
        rerank: str | None = None,
        refine: str | None = None,
        prior: Prior | Mapping[str, Any] | None = None,
        min_confidence: float | None = None,
        seed: Seed | Mapping[str, Any] | None = None,
        min_map_version: int | None = None,
    ) -> Localization:
        """Localize a scan (``points`` ``[P, 3|4]`` in the sensor frame) or precomputed
        ``features`` in a map.

        ``top_k``, ``rerank`` (``"none" | "average-qe" | "alpha-qe" | "ransac-rir" |
        "fgr-rir" | "sgv"``), ``refine`` (``"none" | "icp"``) and ``min_confidence`` (the
        acceptance threshold of the calibrated confidence) override the map's defaults.
        ``prior`` (:class:`Prior` or a dict with its fields) restricts the search to the
        keyframes near a believed position. ``seed`` (:class:`Seed` or a dict) tracks:
        the scan is registered against the map around a predicted pose, much faster than
        a global search; :class:`Tracker` keeps the seeds for a moving vehicle. A scan
        that cannot be localized returns ``localized=False`` with the reason and its best
        ``estimate``; it is not an error. ``min_map_version``: answer from that map
        version or later (the ``map_version`` of an insert made through another replica);
        a replica still behind after a short wait answers 503 ``stale``, and a client with
        several base URLs then asks the next.
        """
        return self._send(
            self._localize(
                map,
                points,
                features,
                top_k,
                rerank,
                refine,
                prior,
                min_confidence,
                seed,
                min_map_version,
            )
        )
