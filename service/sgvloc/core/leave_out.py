"""A map's leave-out self-test: its own keyframes localized against the others.

Each sampled keyframe is a query: its stored features and cloud (what ``encoder.prepare``
and ``encode_cloud`` made of its scan, the same as a live query's, with its descriptor
about the displaced centres computed again from the cloud) are localized with
the map's settings against every keyframe except its own stretch of the drive: those
closer than ``gap_s`` seconds to it (``metadata.timestamp``, as ``sgvloc build-map``
records it) or, when not every keyframe has a timestamp, closer than ``gap_keyframes``
in insertion order (ids). A query is *in coverage* if a keyframe left to search lies
within ``radius_m`` of it; such a query should be found and posed. Out-of-coverage
queries are sampled alike: accepting one of them with a wrong pose is a false accept.

Figures (:func:`summarise`): Recall@1 (re-ranked top-1 within ``radius_m``) and pose
success (within 2 m and 5 deg of the keyframe's recorded pose) over the in-coverage
queries, the share of correct answers accepted, and false accepts over all queries:
the figures of ``sgvloc eval``, on the map as it is served.

Other encoders (:data:`CANDIDATES`) can be measured on the same plan from the keyframes'
stored clouds, each encoded again by the candidate; :func:`choose` picks the encoder a
vehicle could act on most often (:data:`RULE`), as ``sgvloc build-map --choose-encoder``
does from the raw scans.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .confidence import CORRECT_DEG, CORRECT_M
from .errors import InputError
from .pose import rotation_angle_deg

#: format tag of a map's self-test report
FORMAT = "sgvloc-map-self-test/1"
#: the encoders a self-test compares by default, by name, in the order that breaks ties
CANDIDATES = ("learned", "handcrafted", "bev", "learned-fpfh")
#: the candidates that are not a plain encoder kind: name -> EncoderSpec (JSON)
SPECS: dict[str, dict[str, Any]] = {
    # the network's global descriptor with FPFH keypoints: narrow or sparse scans
    "learned-fpfh": {"kind": "learned", "learned": {"local_features": "fpfh"}},
}
#: how :func:`choose` ranks encoders
RULE = (
    "most queries localized correctly (in coverage), then fewest false accepts (all "
    "sampled queries), then most correct poses (in coverage), then highest R@1 at 5 m, "
    "then the candidates' order"
)


def spec_of(name: str) -> dict[str, Any]:
    """The EncoderSpec (JSON) of a candidate: :data:`SPECS`, else the kind ``name``."""
    return dict(SPECS.get(name, {"kind": name}))


def choose(figures: dict[str, dict[str, Any]], order: tuple[str, ...]) -> str:
    """The encoder :data:`RULE` picks from per-encoder ``figures`` (``localized_correct``,
    ``false_accepts``, ``correct_poses``, ``recall_at_1``); deterministic."""

    def key(name: str) -> tuple[float, ...]:
        f = figures[name]
        return (
            f["localized_correct"],
            -f["false_accepts"],
            f["correct_poses"],
            f["recall_at_1"] or 0.0,
            -order.index(name),
        )

    return max((k for k in order if k in figures), key=key)


def warning(figures: dict[str, dict[str, Any]], chosen: str) -> str | None:
    """What to tell before serving a map on ``chosen``: None when it localizes at least
    half of the queries with a revisit correctly, else why its figures need a look."""
    f = figures[chosen]
    n, q = f["localized_correct"], f["queries"]
    if 2 * n >= q:
        return None
    head = (
        f"no encoder localizes any of the {q} scans with a revisit correctly (the choice "
        "rests on the rule's later figures)"
        if n == 0
        else f"{chosen}, the best, localizes only {n} of the {q} scans with a revisit correctly"
    )
    return (
        f"{head}: revisits that face other ways (a narrow field of view), scans far apart "
        "or a sensor unlike the calibration's leave few answers to act on; look at the "
        "figures before serving this map"
    )


@dataclass(frozen=True)
class Plan:
    """The queries of one self-test: keyframe ids in and out of coverage; what each
    searches comes from :meth:`searched` (not stored: that is a map-sized array each)."""

    in_coverage: list[int]
    out_of_coverage: list[int]
    basis: str  # "timestamp" or "insertion order"
    ids: np.ndarray  # [N] every keyframe id, ascending
    key: np.ndarray  # [N] their timestamps (s) or ranks in insertion order
    gap: float

    def searched(self, keyframe_id: int) -> np.ndarray:
        """The keyframe ids a query searches: every one at least ``gap`` away from it."""
        i = int(np.searchsorted(self.ids, keyframe_id))
        return self.ids[np.abs(self.key - self.key[i]) >= self.gap]


def plan(
    ids: np.ndarray,
    positions: np.ndarray,
    timestamps: np.ndarray | None,
    *,
    queries: int = 50,
    gap_s: float = 30.0,
    gap_keyframes: int = 30,
    radius_m: float = 5.0,
) -> Plan:
    """Choose the queries: at most ``queries`` in coverage and as many out of coverage,
    each set evenly spaced over the map's keyframes (the same map gives the same plan).

    ``ids`` ``[N]``, ``positions`` ``[N, 3]`` (metres), ``timestamps`` ``[N]`` seconds
    or None (then the gap is ``gap_keyframes`` in id order). A KD-tree finds each
    keyframe's neighbours within ``radius_m``, so large maps plan in ``N log N``.
    """
    from scipy.spatial import cKDTree

    if queries < 1:
        raise InputError(f"queries must be at least 1, got {queries}")
    ids = np.asarray(ids, dtype=np.int64)
    order = np.argsort(ids, kind="stable")
    ids, positions = ids[order], np.asarray(positions, dtype=np.float64).reshape(-1, 3)[order]
    if timestamps is not None:
        key, gap, basis = np.asarray(timestamps, dtype=np.float64)[order], gap_s, "timestamp"
    else:
        key, gap, basis = np.arange(len(ids), dtype=np.float64), gap_keyframes, "insertion order"
    inside, outside = [], []
    if len(ids):
        # something to search at all: a keyframe at least the gap away, before or after
        searchable = np.maximum(key - key.min(), key.max() - key) >= gap
        near = cKDTree(positions).query_ball_point(positions, radius_m)
        for i in np.flatnonzero(searchable):
            nb = np.asarray(near[i], dtype=np.int64)
            revisit = (np.abs(key[nb] - key[i]) >= gap).any()
            (inside if revisit else outside).append(int(i))

    def spaced(rows: list[int]) -> list[int]:
        if len(rows) <= queries:
            return [int(ids[r]) for r in rows]
        pick = np.linspace(0, len(rows) - 1, queries).round().astype(int)
        return [int(ids[rows[p]]) for p in pick]

    chosen_in, chosen_out = spaced(inside), spaced(outside)
    if not chosen_in:
        raise InputError(
            f"no keyframe has a revisit: none lies within {radius_m:g} m of a keyframe "
            f"at least {gap:g} {'s' if basis == 'timestamp' else 'keyframes'} away from it "
            f"({basis}); a self-test needs a map whose drive passes a place twice, or a "
            "shorter gap (gap_s, gap_keyframes)"
        )
    return Plan(chosen_in, chosen_out, basis, ids, key, float(gap))


def record(
    keyframe_id: int,
    in_coverage: bool,
    T_true: np.ndarray,
    result: Any,
    top1_position: np.ndarray | None,
    radius_m: float,
) -> dict[str, Any]:
    """One query's record from its :class:`~sgvloc.core.localizer.LocalizationResult`
    and the position of its re-ranked top-1 keyframe (None: nothing retrieved)."""
    T_est = result.T_map_sensor_estimate
    rte = rre = None
    correct = False
    if T_est is not None:
        rte = float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
        rre = rotation_angle_deg(T_est[:3, :3].T @ T_true[:3, :3])
        correct = rte <= CORRECT_M and rre <= CORRECT_DEG
    top1 = result.reranked[0].keyframe_id if result.reranked else None
    found = top1_position is not None and bool(
        np.linalg.norm(top1_position - T_true[:3, 3]) <= radius_m
    )
    return {
        "keyframe": int(keyframe_id),
        "in_coverage": bool(in_coverage),
        "top1": top1,
        "found": found,
        "localized": bool(result.localized),
        "confidence": round(float(result.confidence), 4),
        "correct": bool(correct),
        "rte_m": None if rte is None else round(rte, 3),
        "rre_deg": None if rre is None else round(rre, 3),
        "ms": round(float(result.timings_ms.get("total", 0.0)), 1),
    }


def unanswered(keyframe_id: int, in_coverage: bool) -> dict[str, Any]:
    """The record of a query that could not be asked: an encoder compared on the map's
    stored clouds found nothing to describe in its cloud (or it has none)."""
    return {
        "keyframe": int(keyframe_id),
        "in_coverage": bool(in_coverage),
        "top1": None,
        "found": False,
        "localized": False,
        "confidence": 0.0,
        "correct": False,
        "rte_m": None,
        "rre_deg": None,
        "ms": 0.0,
    }


def summarise(records: list[dict[str, Any]]) -> dict[str, Any]:
    """The self-test's figures over its per-query records (percentages to 0.1)."""

    def pct(n: int, d: int) -> float | None:
        return round(100.0 * n / d, 1) if d else None

    inside = [r for r in records if r["in_coverage"]]
    correct = [r for r in records if r["correct"]]
    ms = [r["ms"] for r in records]
    return {
        "queries": len(inside),
        "negatives": len(records) - len(inside),
        "recall_at_1": pct(sum(r["found"] for r in inside), len(inside)),
        "pose_success": pct(sum(r["correct"] for r in inside), len(inside)),
        "correct_poses": sum(r["correct"] for r in inside),
        "localized_correct": sum(r["correct"] and r["localized"] for r in inside),
        "accepted_of_correct": pct(sum(r["localized"] for r in correct), len(correct)),
        "false_accepts": sum(r["localized"] and not r["correct"] for r in records),
        "median_ms": round(float(np.median(ms)), 1) if ms else None,
    }
