"""Prometheus metrics of one service process (its own registry, see docs/API.md).

One process per container (threads for CPU work), so no multiprocess mode is needed.
"""

from __future__ import annotations

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
)

from sgvloc.core.confidence import VERDICT_CODES
from sgvloc.core.localizer import LocalizationResult

_HTTP_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)
_STAGE_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
STAGES = ("encode", "retrieve", "rerank", "pose", "verify")


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
            "Localization stage duration (encode, retrieve, rerank, pose)",
            ["stage"],
            buckets=_STAGE_BUCKETS,
            registry=r,
        )
        self.localize_total = Counter(
            "sgvloc_localize", "Localizations by verdict", ["verdict"], registry=r
        )
        self.localize_reason = Counter(
            "sgvloc_localize_reason",
            "Localizations by verdict code (localized, low_confidence, outside_prior, ...)",
            ["reason"],
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
        self.map_keyframes = Gauge(
            "sgvloc_map_keyframes", "Keyframes per loaded map", ["map"], registry=r
        )
        for verdict in ("localized", "not_localized"):  # present from the start, at 0
            self.localize_total.labels(verdict)
        for code in VERDICT_CODES:
            self.localize_reason.labels(code)
        for stage in STAGES:
            self.stage_duration.labels(stage)

    def observe_localization(self, result: LocalizationResult) -> None:
        """Record one localization: stage timings, verdict, top-1 change."""
        for stage in STAGES:
            ms = result.timings_ms.get(stage)
            if ms is not None:
                self.stage_duration.labels(stage).observe(ms / 1e3)
        self.localize_total.labels("localized" if result.localized else "not_localized").inc()
        self.localize_reason.labels(result.verdict).inc()
        if result.T_map_sensor_estimate is not None:
            self.confidence.observe(result.confidence)
        if result.top1_changed:
            self.top1_changed.inc()

    def set_map_keyframes(self, name: str, count: int | None) -> None:
        """Set a map's keyframe gauge; ``None`` removes the map's series."""
        if count is None:
            try:
                self.map_keyframes.remove(name)
            except KeyError:
                pass
        else:
            self.map_keyframes.labels(name).set(count)

    def render(self) -> tuple[bytes, str]:
        """The exposition text and its content type."""
        return generate_latest(self.registry), CONTENT_TYPE_LATEST
