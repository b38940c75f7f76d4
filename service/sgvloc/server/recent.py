"""The most recent localizations of each map, in memory (for the status page).

A bounded ring per map: the last :data:`DEFAULT_SIZE` answers, newest last. Nothing is
stored on disk and nothing survives a restart; a deleted map's ring is dropped. Each
entry is what an operator needs to see where vehicles were placed and how sure the
service was: the time, the estimated position (if any), the verdict and its confidence,
the matched keyframe and the map version that answered.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any

from sgvloc.core.localizer import LocalizationResult

DEFAULT_SIZE = 500


@dataclass(frozen=True)
class RecentLocalization:
    """One localize answer, as the status page shows it."""

    time: str  # ISO 8601 UTC, milliseconds
    translation: list[float] | None  # the estimate's position in the map, if any
    localized: bool
    verdict: str
    confidence: float
    keyframe_id: int | None
    map_version: int

    @classmethod
    def of(cls, result: LocalizationResult, now: datetime | None = None) -> RecentLocalization:
        now = now or datetime.now(timezone.utc)
        T = result.T_map_sensor_estimate
        confidence = float(result.confidence)
        return cls(
            time=now.isoformat(timespec="milliseconds").replace("+00:00", "Z"),
            translation=None if T is None else [float(v) for v in T[:3, 3]],
            localized=bool(result.localized),
            verdict=str(result.verdict),
            confidence=confidence if confidence == confidence else 0.0,  # NaN: none
            keyframe_id=None if result.keyframe_id is None else int(result.keyframe_id),
            map_version=int(result.map_version),
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "time": self.time,
            "translation": self.translation,
            "localized": self.localized,
            "verdict": self.verdict,
            "confidence": self.confidence,
            "keyframe_id": self.keyframe_id,
            "map_version": self.map_version,
        }


class RecentLocalizations:
    """Per map, the last ``size`` localizations. Thread-safe (one short lock)."""

    def __init__(self, size: int = DEFAULT_SIZE) -> None:
        if size < 1:
            raise ValueError(f"size must be >= 1, got {size}")
        self.size = size
        self._rings: dict[str, deque[RecentLocalization]] = {}
        self._lock = threading.Lock()

    def record(
        self, name: str, result: LocalizationResult, alive: Callable[[], bool] | None = None
    ) -> None:
        """Remember one answer of map ``name`` (the oldest falls out past ``size``), unless
        ``alive()`` says the map that answered is gone (deleted while the answer was made:
        a map of the same name made since must not inherit it)."""
        entry = RecentLocalization.of(result)
        with self._lock:  # a delete closes the map before it drops the ring
            if alive is not None and not alive():
                return
            ring = self._rings.get(name)
            if ring is None:
                ring = self._rings[name] = deque(maxlen=self.size)
            ring.append(entry)

    def newest(self, name: str, limit: int | None = None) -> list[RecentLocalization]:
        """At most ``limit`` (default all) answers of map ``name``, newest first."""
        with self._lock:
            ring = list(self._rings.get(name, ()))
        ring.reverse()
        return ring if limit is None else ring[: max(0, limit)]

    def drop(self, name: str) -> None:
        """Forget map ``name`` (it was deleted)."""
        with self._lock:
            self._rings.pop(name, None)

    def on_change(self, name: str, keyframes: int | None) -> None:
        """A :class:`~sgvloc.server.maps.MapManager` ``on_change`` hook: drops a deleted
        map's ring (``keyframes`` None)."""
        if keyframes is None:
            self.drop(name)
