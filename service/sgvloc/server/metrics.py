"""Prometheus metrics of one service process (its own registry, see docs/API.md and
docs/OPERATIONS.md, "Monitoring").

One process per container (threads for CPU work), so no multiprocess mode is needed.
Label values stay few: ``map`` only ever names a loaded map (a deleted map's series are
removed), ``key_name`` the configured name of an API key (``development`` in development
mode, ``anonymous`` on open routes), never a key.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable, Iterator

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    Info,
    ProcessCollector,
    disable_created_metrics,
    generate_latest,
)
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector

from sgvloc.about import __version__
from sgvloc.core.confidence import VERDICT_CODES
from sgvloc.core.localizer import LocalizationResult

_HTTP_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)
_STAGE_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
_WAIT_BUCKETS = (0.001, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
STAGES = ("encode", "retrieve", "rerank", "pose", "verify", "track")
MODES = ("global", "tracked", "relocalized")
VERDICTS = ("localized", "not_localized")

#: ``(name, keyframes, version)`` of every loaded map, read at each scrape
MapSizes = Callable[[], Iterable[tuple[str, int, int]]]

# No ``*_created`` sample per counter and histogram child (a start timestamp that
# Prometheus stores as one more series each: a fifth of a map's series): the process
# collector's start time says when the counters began. The switch is the client
# library's, for the whole process, which serves nothing else.
disable_created_metrics()


class _MapGauges(Collector):
    """``sgvloc_map_keyframes{map}`` and ``sgvloc_map_version{map}``, read from the
    loaded maps at scrape time (so they always match what is served)."""

    def __init__(self, sizes: MapSizes) -> None:
        self.sizes = sizes

    def collect(self) -> Iterator[GaugeMetricFamily]:
        keyframes = GaugeMetricFamily(
            "sgvloc_map_keyframes", "Keyframes per loaded map", labels=["map"]
        )
        version = GaugeMetricFamily(
            "sgvloc_map_version",
            "Keyframe version per loaded map (+1 per insert batch or keyframe delete)",
            labels=["map"],
        )
        for name, count, ver in self.sizes():
            keyframes.add_metric([name], count)
            version.add_metric([name], ver)
        yield keyframes
        yield version


class Metrics:
    """The service's series, registered in a private :class:`CollectorRegistry`."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.http_requests = Counter(
            "sgvloc_http_requests",
            "HTTP requests by route template, method and status",
            ["route", "method", "status"],
            registry=r,
        )
        self.http_duration = Histogram(
            "sgvloc_http_request_duration_seconds",
            "HTTP request duration by route template and method",
            ["route", "method"],
            buckets=_HTTP_BUCKETS,
            registry=r,
        )
        self.stage_duration = Histogram(
            "sgvloc_stage_duration_seconds",
            "Localization stage duration per map (encode, retrieve, rerank, pose, verify; "
            "track for a seeded request)",
            ["map", "stage"],
            buckets=_STAGE_BUCKETS,
            registry=r,
        )
        self.localize_total = Counter(
            "sgvloc_localize", "Localizations per map by verdict", ["map", "verdict"], registry=r
        )
        self.localize_reason = Counter(
            "sgvloc_localize_reason",
            "Localizations per map by verdict code (localized, low_confidence, ...)",
            ["map", "reason"],
            registry=r,
        )
        self.localize_mode = Counter(
            "sgvloc_localize_mode",
            "Localizations per map by how they were found (global, tracked, relocalized)",
            ["map", "mode"],
            registry=r,
        )
        self.localize_by_key = Counter(
            "sgvloc_localize_by_key",
            "Localizations by the caller's API key name and verdict",
            ["key_name", "verdict"],
            registry=r,
        )
        self.confidence = Histogram(
            "sgvloc_localize_confidence",
            "Calibrated confidence of answers that had an estimate",
            buckets=(0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.99),
            registry=r,
        )
        self.top1_changed = Counter(
            "sgvloc_rerank_top1_changed",
            "Localizations where re-ranking put another keyframe first",
            registry=r,
        )
        self.localize_inflight = Gauge(
            "sgvloc_localize_inflight",
            "Localize requests admitted and not answered yet (max_inflight_localize bounds it)",
            registry=r,
        )
        self.body_bytes = Gauge(
            "sgvloc_body_bytes",
            "Bytes of request bodies held in memory now (max_body_memory_bytes bounds it)",
            registry=r,
        )
        self.errors = Counter(
            "sgvloc_errors",
            "Error answers by route template and error code (store_unavailable, "
            "queue_timeout, map_unavailable, invalid_input, ...): what a 4xx or 5xx was",
            ["route", "code"],
            registry=r,
        )
        self.connections_cut = Counter(
            "sgvloc_connections_cut",
            "Connections the service closed for a deadline: header_timeout (headers too "
            "slow), unread_body (a body still trickling after its answer), send_timeout "
            "(the client took none of an answer)",
            ["reason"],
            registry=r,
        )
        for reason in ("header_timeout", "unread_body", "send_timeout"):
            self.connections_cut.labels(reason)
        self.maps_failed = Gauge(
            "sgvloc_maps_failed",
            "Map folders that could not be loaded (/readyz names them to a key holder)",
            registry=r,
        )
        self.store_up = Gauge(
            "sgvloc_store_up",
            "1 while the map store answers this replica (always with SQLite), 0 while a "
            "shared PostgreSQL store does not (loading waits, writes fail, localizations go "
            "on from memory)",
            registry=r,
        )
        Info("sgvloc_build", "The service's version", registry=r).info({"version": __version__})
        ProcessCollector(registry=r)  # memory, CPU time, open files of the process
        self.queue_waiting = Gauge(
            "sgvloc_queue_waiting",
            "Requests waiting for a free worker thread now",
            registry=r,
        )
        self.queue_wait = Histogram(
            "sgvloc_queue_wait_seconds",
            "Time requests waited for a free worker thread (also those that timed out)",
            buckets=_WAIT_BUCKETS,
            registry=r,
        )
        self.batch_size = Histogram(
            "sgvloc_batch_size",
            "Localizations per dynamic batch, by stage (forward: the network; sgv: re-ranking)",
            ["stage"],
            buckets=(1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 64),
            registry=r,
        )
        self.batch_wait = Histogram(
            "sgvloc_batch_wait_seconds",
            "Time the first localization of a dynamic batch waited for the others",
            ["stage"],
            buckets=_STAGE_BUCKETS,
            registry=r,
        )
        self._lock = threading.Lock()
        self._maps: set[str] = set()  # maps with per-map series

    def observe_batch(self, stage: str, size: int, waited_s: float) -> None:
        """A dynamic batch ran (:class:`sgvloc.core.batching.MicroBatcher`'s observer)."""
        self.batch_size.labels(stage).observe(size)
        self.batch_wait.labels(stage).observe(waited_s)

    def watch_maps(self, sizes: MapSizes) -> None:
        """Export the map gauges, read from ``sizes`` at every scrape."""
        self.registry.register(_MapGauges(sizes))

    def set_map_keyframes(self, name: str, keyframes: int | None) -> None:
        """The map manager's ``on_change``: a map loaded or changed gets its per-map series
        (at 0 from the start); a deleted one (``keyframes`` None) loses them. The map
        gauges themselves are read at scrape time (:meth:`watch_maps`)."""
        with self._lock:
            if keyframes is None:
                if name in self._maps:
                    self._maps.discard(name)
                    for labels, metric in self._per_map(name):
                        metric.remove(*labels)
            elif name not in self._maps:
                self._maps.add(name)
                for labels, metric in self._per_map(name):
                    metric.labels(*labels)

    def _per_map(self, name: str) -> Iterator[tuple[tuple[str, str], Counter | Histogram]]:
        for stage in STAGES:
            yield (name, stage), self.stage_duration
        for verdict in VERDICTS:
            yield (name, verdict), self.localize_total
        for code in VERDICT_CODES:
            yield (name, code), self.localize_reason
        for mode in MODES:
            yield (name, mode), self.localize_mode

    def observe_localization(
        self, result: LocalizationResult, map_name: str, key_name: str
    ) -> None:
        """Record one localization: stage timings and verdict (per map, unless the map was
        deleted meanwhile), verdict per key name, confidence, top-1 change."""
        verdict = VERDICTS[0] if result.localized else VERDICTS[1]
        with self._lock:
            if map_name in self._maps:
                for stage in STAGES:
                    ms = result.timings_ms.get(stage)
                    if ms:  # a stage that did not run has no time
                        self.stage_duration.labels(map_name, stage).observe(ms / 1e3)
                self.localize_total.labels(map_name, verdict).inc()
                self.localize_reason.labels(map_name, result.verdict).inc()
                self.localize_mode.labels(map_name, result.mode).inc()
        self.localize_by_key.labels(key_name, verdict).inc()
        if result.T_map_sensor_estimate is not None:
            self.confidence.observe(result.confidence)
        if result.top1_changed:
            self.top1_changed.inc()

    def render(self) -> tuple[bytes, str]:
        """The exposition text and its content type."""
        return generate_latest(self.registry), CONTENT_TYPE_LATEST
