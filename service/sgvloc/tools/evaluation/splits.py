"""Database/query splits of one sequence (docs/EVALUATION.md).

Two modes:

- ``time`` (``--db-until SECONDS``): scans up to ``db_until`` seconds after the first scan
  form the database (the map), every later scan is a query;
- ``loop`` (``--min-gap SECONDS``): loop-closure style; a query's database is every scan
  at least ``min_gap`` seconds older than it, so no query can match its own recent past.
  Every scan with such an older scan is a query candidate.

A query without any database scan within ``threshold`` metres (the smallest revisit
threshold, 5 m by default) has nothing to find: it is out of coverage. It is dropped from
recall, and with ``negatives=True`` kept as a negative for the verdict (an answer for it
that is accepted and wrong is a false accept).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from sgvloc.core.errors import InputError


@dataclass(frozen=True)
class Split:
    """A database/query split. Indices refer to the sequence's scans.

    - ``times``: ``[F]`` seconds since the first scan; ``positions``: ``[F, 3]`` metres;
    - ``queries``: kept queries in time order; ``dropped``: query candidates without a
      database scan within ``threshold`` metres (out of coverage; no recall);
    - ``negatives``: the out-of-coverage queries evaluated as negatives for the verdict
      (empty unless asked for);
    - ``database``: every scan that is in the database of at least one evaluated query.
    """

    mode: Literal["time", "loop"]
    times: np.ndarray
    positions: np.ndarray
    queries: np.ndarray
    dropped: np.ndarray
    database: np.ndarray
    threshold: float
    db_until: float | None = None
    min_gap: float | None = None
    negatives: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def database_for(self, query: int) -> np.ndarray:
        """Database scan indices (sorted) visible to ``query``."""
        return _database_mask(self, int(query)).nonzero()[0]

    def summary(self) -> dict[str, Any]:
        """Counts and parameters, for reports."""
        return {
            "mode": self.mode,
            "db_until_s": self.db_until,
            "min_gap_s": self.min_gap,
            "drop_threshold_m": self.threshold,
            "scans": int(len(self.times)),
            "database_scans": int(len(self.database)),
            "queries": int(len(self.queries)),
            "dropped_queries": int(len(self.dropped)),
            "negative_queries": int(len(self.negatives)),
        }


def _database_mask(split: Split, q: int) -> np.ndarray:
    t = split.times
    if split.mode == "time":
        return t <= split.db_until
    return t <= t[q] - split.min_gap


def make_split(
    times: np.ndarray,
    positions: np.ndarray,
    *,
    db_until: float | None = None,
    min_gap: float | None = None,
    threshold: float = 5.0,
    query_stride: int = 1,
    max_queries: int | None = None,
    negatives: bool = False,
) -> Split:
    """Split a sequence by time (``db_until``) or loop-closure gap (``min_gap``).

    Exactly one of ``db_until`` / ``min_gap`` must be given. ``times`` are seconds (any
    origin: they are taken relative to the first scan), ``positions`` ``[F, 3]`` the
    ground-truth sensor positions. Kept queries can be thinned to every ``query_stride``-th
    and capped at ``max_queries`` (evenly spaced) for quick runs; with ``negatives`` the
    out-of-coverage queries are kept as negatives, thinned the same way.
    """
    t = np.asarray(times, dtype=np.float64)
    pos = np.asarray(positions, dtype=np.float64)
    if t.ndim != 1 or pos.shape != (len(t), 3):
        raise InputError(
            f"times must be [F] and positions [F, 3], got {list(t.shape)} and {list(pos.shape)}"
        )
    if (db_until is None) == (min_gap is None):
        raise InputError("give exactly one of db_until (time split) or min_gap (loop split)")
    if query_stride < 1:
        raise InputError(f"query_stride must be >= 1, got {query_stride}")
    if threshold <= 0:
        raise InputError(f"threshold must be positive, got {threshold}")
    t = t - t[0] if len(t) else t
    if db_until is not None:
        mode: Literal["time", "loop"] = "time"
        candidates = np.flatnonzero(t > db_until)
        if not (t <= db_until).any():
            raise InputError(f"no scan within the first {db_until} s: the database is empty")
    else:
        if min_gap <= 0:
            raise InputError(f"min_gap must be positive, got {min_gap}")
        mode = "loop"
        candidates = np.flatnonzero(t >= min_gap)
    proto = Split(
        mode, t, pos, candidates, candidates[:0], candidates[:0], threshold, db_until, min_gap
    )

    kept, dropped = [], []
    for q in candidates:
        db = proto.database_for(q)
        d = np.linalg.norm(pos[db] - pos[q], axis=1) if len(db) else np.zeros(0)
        (kept if (d <= threshold).any() else dropped).append(int(q))

    def thin(idx: list[int]) -> np.ndarray:
        out = np.asarray(idx, dtype=np.int64)[::query_stride]
        if max_queries is not None and len(out) > max_queries:
            pick = np.linspace(0, len(out) - 1, max_queries).round().astype(np.int64)
            out = out[np.unique(pick)]
        return out

    queries = thin(kept)
    negative = thin(dropped) if negatives else np.zeros(0, dtype=np.int64)
    if mode == "time":
        database = np.flatnonzero(t <= db_until)
    else:
        evaluated = np.concatenate([queries, negative])
        last = t[evaluated].max() - min_gap if len(evaluated) else -np.inf
        database = np.flatnonzero(t <= last)
    return Split(
        mode,
        t,
        pos,
        queries,
        np.asarray(dropped, dtype=np.int64),
        database,
        threshold,
        db_until,
        min_gap,
        negative,
    )
