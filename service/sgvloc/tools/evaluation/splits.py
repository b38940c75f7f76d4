"""Database/query splits of one sequence (docs/EVALUATION.md).

Four modes:

- ``time`` (``--db-until SECONDS``): scans up to ``db_until`` seconds after the first scan
  form the database (the map), every later scan is a query;
- ``loop`` (``--min-gap SECONDS``): loop-closure style; a query's database is every scan
  at least ``min_gap`` seconds older than it, so no query can match its own recent past.
  Every scan with such an older scan is a query candidate;
- ``leave-out`` (``--leave-out SECONDS``): a map's self-test; every scan is a query
  candidate and its database is every other scan at least ``leave_out`` seconds away in
  time, before or after it (its own stretch of the drive left out);
- ``range`` (``--db-range START:STOP``, ``--query-range START:STOP``): by frame index, the
  database is the frames of one range and the query candidates those of the other (by
  default every frame after the database range), as published splits define them (e.g.
  database 0:3000 and queries 3200: of a KITTI sequence).

A query without any database scan within ``threshold`` metres (the smallest revisit
threshold, 5 m by default) has nothing to find: it is out of coverage. It is dropped from
recall, and with ``negatives=True`` kept as a negative for the verdict (an answer for it
that is accepted and wrong is a false accept).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
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
    - ``database``: every scan that is in the database of at least one evaluated query;
    - ``max_heading_deg``: coverage also needs that database scan to face within this
      many degrees of the query (a narrow field of view: else it sees something else);
      None: any heading.
    """

    mode: Literal["time", "loop", "range", "leave-out"]
    times: np.ndarray
    positions: np.ndarray
    queries: np.ndarray
    dropped: np.ndarray
    database: np.ndarray
    threshold: float
    db_until: float | None = None
    min_gap: float | None = None
    negatives: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    db_range: tuple[int, int] | None = None
    query_range: tuple[int, int] | None = None
    leave_out: float | None = None
    max_heading_deg: float | None = None

    def database_for(self, query: int) -> np.ndarray:
        """Database scan indices (sorted) visible to ``query``."""
        return _database_mask(self, int(query)).nonzero()[0]

    def summary(self) -> dict[str, Any]:
        """Counts and parameters, for reports."""
        return {
            "mode": self.mode,
            "db_until_s": self.db_until,
            "min_gap_s": self.min_gap,
            "leave_out_s": self.leave_out,
            "db_range": list(self.db_range) if self.db_range else None,
            "query_range": list(self.query_range) if self.query_range else None,
            "drop_threshold_m": self.threshold,
            "coverage_heading_deg": self.max_heading_deg,
            "scans": int(len(self.times)),
            "database_scans": int(len(self.database)),
            "queries": int(len(self.queries)),
            "dropped_queries": int(len(self.dropped)),
            "negative_queries": int(len(self.negatives)),
        }


def _database_mask(split: Split, q: int) -> np.ndarray:
    t = split.times
    if split.mode == "range":
        a, b = split.db_range
        idx = np.arange(len(t))
        return (idx >= a) & (idx < b)
    if split.mode == "leave-out":
        return np.abs(t - t[q]) >= split.leave_out
    if split.mode == "time":
        return t <= split.db_until
    return t <= t[q] - split.min_gap


def make_split(
    times: np.ndarray,
    positions: np.ndarray,
    *,
    db_until: float | None = None,
    min_gap: float | None = None,
    db_range: tuple[int, int | None] | None = None,
    query_range: tuple[int, int | None] | None = None,
    leave_out: float | None = None,
    threshold: float = 5.0,
    query_stride: int = 1,
    max_queries: int | None = None,
    negatives: bool = False,
    headings_deg: np.ndarray | None = None,
    max_heading_deg: float | None = None,
) -> Split:
    """Split a sequence by time (``db_until``), loop-closure gap (``min_gap``), frame
    ranges (``db_range``, ``query_range``) or for a self-test (``leave_out``).

    Exactly one of ``db_until`` / ``min_gap`` / ``db_range`` / ``leave_out`` must be given;
    frame ranges are ``(start, stop)`` indices, stop exclusive, None = to the end.
    ``times`` are seconds (any origin: they are taken relative to the first scan),
    ``positions`` ``[F, 3]`` the ground-truth sensor positions. Kept queries can be
    thinned to every ``query_stride``-th and capped at ``max_queries`` (evenly spaced) for
    quick runs; with ``negatives`` the out-of-coverage queries are kept as negatives,
    thinned the same way. With ``max_heading_deg`` (and the scans' ``headings_deg``
    ``[F]``, yaw in degrees) a query is in coverage only if a database scan within
    ``threshold`` also faces within that many degrees of it.
    """
    t = np.asarray(times, dtype=np.float64)
    pos = np.asarray(positions, dtype=np.float64)
    if t.ndim != 1 or pos.shape != (len(t), 3):
        raise InputError(
            f"times must be [F] and positions [F, 3], got {list(t.shape)} and {list(pos.shape)}"
        )
    if sum(x is not None for x in (db_until, min_gap, db_range, leave_out)) != 1:
        raise InputError(
            "give exactly one of db_until (time split), min_gap (loop split), db_range "
            "(frame ranges) or leave_out (self-test)"
        )
    if query_range is not None and db_range is None:
        raise InputError("query_range needs db_range")
    if query_stride < 1:
        raise InputError(f"query_stride must be >= 1, got {query_stride}")
    if threshold <= 0:
        raise InputError(f"threshold must be positive, got {threshold}")
    if max_heading_deg is not None:
        if not 0 < max_heading_deg <= 180:
            raise InputError(f"max_heading_deg must be in (0, 180], got {max_heading_deg}")
        if headings_deg is None or np.shape(headings_deg) != (len(t),):
            raise InputError("max_heading_deg needs the scans' headings_deg [F]")
    t = t - t[0] if len(t) else t
    dbr = qr = None
    mode: Literal["time", "loop", "range", "leave-out"]
    if db_range is not None:
        mode = "range"
        dbr = _frame_range(db_range, len(t), "db_range")
        qr = _frame_range(query_range or (dbr[1], None), len(t), "query_range")
        if qr[0] < dbr[1] and dbr[0] < qr[1]:
            raise InputError(
                f"query_range {list(qr)} overlaps db_range {list(dbr)}: a query would find itself"
            )
        candidates = np.arange(*qr)
    elif leave_out is not None:
        if leave_out <= 0:
            raise InputError(f"leave_out must be positive, got {leave_out}")
        mode = "leave-out"
        # only scans with a database at all (another scan at least the gap away), as the
        # map's leave-out self-test plans them (sgvloc.core.leave_out.plan)
        far = np.maximum(t - t.min(initial=0.0), t.max(initial=0.0) - t) >= leave_out
        candidates = np.flatnonzero(far)
    elif db_until is not None:
        mode = "time"
        candidates = np.flatnonzero(t > db_until)
        if not (t <= db_until).any():
            raise InputError(f"no scan within the first {db_until} s: the database is empty")
    else:
        if min_gap <= 0:
            raise InputError(f"min_gap must be positive, got {min_gap}")
        mode = "loop"
        candidates = np.flatnonzero(t >= min_gap)
    proto = Split(
        mode,
        t,
        pos,
        candidates,
        candidates[:0],
        candidates[:0],
        threshold,
        db_until,
        min_gap,
        db_range=dbr,
        query_range=qr,
        leave_out=leave_out,
        max_heading_deg=max_heading_deg,
    )

    kept, dropped = [], []
    for q in candidates:
        db = proto.database_for(q)
        near = np.linalg.norm(pos[db] - pos[q], axis=1) <= threshold
        if max_heading_deg is not None:
            turn = np.abs((np.asarray(headings_deg)[db] - headings_deg[q] + 180.0) % 360.0 - 180.0)
            near &= turn <= max_heading_deg
        (kept if near.any() else dropped).append(int(q))

    def thin(idx: list[int]) -> np.ndarray:
        out = np.asarray(idx, dtype=np.int64)[::query_stride]
        if max_queries is not None and len(out) > max_queries:
            pick = np.linspace(0, len(out) - 1, max_queries).round().astype(np.int64)
            out = out[np.unique(pick)]
        return out

    queries = thin(kept)
    negative = thin(dropped) if negatives else np.zeros(0, dtype=np.int64)
    if mode == "range":
        database = np.arange(*dbr)
    elif mode == "leave-out":  # at least leave_out from the earliest or latest evaluated
        te = t[np.concatenate([queries, negative])]
        far = (
            np.maximum(np.abs(t - te.min()), np.abs(t - te.max()))
            if len(te)
            else np.full(len(t), -np.inf)
        )
        database = np.flatnonzero(far >= leave_out)
    elif mode == "time":
        database = np.flatnonzero(t <= db_until)
    else:
        evaluated = np.concatenate([queries, negative])
        last = t[evaluated].max() - min_gap if len(evaluated) else -np.inf
        database = np.flatnonzero(t <= last)
    return replace(
        proto,
        queries=queries,
        dropped=np.asarray(dropped, dtype=np.int64),
        database=database,
        negatives=negative,
    )


def _frame_range(r: tuple[int, int | None], n: int, name: str) -> tuple[int, int]:
    """A ``(start, stop)`` frame range of a sequence of ``n`` frames, checked (stop None =
    the end); raises InputError naming ``name`` when it is empty or outside the sequence."""
    start, stop = int(r[0]), n if r[1] is None else int(r[1])
    if not 0 <= start < stop <= n:
        raise InputError(
            f"{name} {start}:{'' if r[1] is None else stop} is not a non-empty range of the "
            f"sequence's {n} frames"
        )
    return start, stop
