"""Per-encoder diagnostics of an evaluation run: local matches and SGV score separation.

Local feature matches on true pairs (:func:`match_stats`): a query and the database scan
nearest to it in position. Each query keypoint is matched to its nearest neighbour (L2 in
feature space) among the database scan's keypoints; the match is correct when the query
keypoint moved by the ground-truth relative pose ``T_db_query`` lies within ``radius``
(1 m) of the matched keypoint. Per pair:

- ``nn_ratio``: correct NN matches / query keypoints;
- ``mutual_ratio``: correct mutual-NN matches / mutual-NN matches (NaN if none);
- ``repeatability``: share of query keypoints with *any* database keypoint within
  ``radius`` (the ceiling of ``nn_ratio``: a keypoint with no partner cannot match);
- ``chance_ratio``: expected ``nn_ratio`` of a matcher that picks a database keypoint at
  random (share of database keypoints within ``radius``, averaged over query keypoints).

When every keypoint of both scans has ``z == 0`` (image encoders), distances are taken
in x/y only: the keypoints carry no height to compare.

SGV score separation (:func:`score_separation`): summary statistics of scores of true
and false candidates and the ROC AUC (probability that a random true candidate scores
above a random false one, ties counting one half).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from sgvloc.core.errors import InputError

#: a match is correct within this distance (m) after the ground-truth pose
MATCH_RADIUS_M = 1.0


def _sq_dists(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared L2 distances ``[Na, Nb]`` (float64, clipped at 0)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    d = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * (a @ b.T)
    return np.maximum(d, 0.0)


def is_planar(*keypoints: np.ndarray) -> bool:
    """True when every keypoint of every array has ``z == 0`` (and there is at least one)."""
    kps = [np.asarray(k).reshape(-1, 3) for k in keypoints]
    return sum(len(k) for k in kps) > 0 and all(not np.any(k[:, 2]) for k in kps)


def pair_match_stats(
    query_kp: np.ndarray,
    query_feats: np.ndarray,
    db_kp: np.ndarray,
    db_feats: np.ndarray,
    T_db_query: np.ndarray,
    radius: float = MATCH_RADIUS_M,
    planar: bool | None = None,
) -> dict[str, Any]:
    """Match statistics of one true pair (see the module docstring).

    ``query_kp`` ``[N, 3]``, ``query_feats`` ``[N, D]``, ``db_kp`` ``[M, 3]``, ``db_feats``
    ``[M, D]``, ``T_db_query`` ``[4, 4]`` maps query-frame points into the database frame.
    ``planar`` None: decided by :func:`is_planar`. Ratios are NaN when either scan has no
    keypoint.
    """
    qk = np.asarray(query_kp, dtype=np.float64).reshape(-1, 3)
    dk = np.asarray(db_kp, dtype=np.float64).reshape(-1, 3)
    qf, df = np.asarray(query_feats), np.asarray(db_feats)
    T = np.asarray(T_db_query, dtype=np.float64)
    if T.shape != (4, 4):
        raise InputError(f"T_db_query must be [4, 4], got {list(T.shape)}")
    if qf.shape[0] != len(qk) or df.shape[0] != len(dk):
        raise InputError("one local feature row per keypoint is required")
    if planar is None:
        planar = is_planar(qk, dk)
    out: dict[str, Any] = {
        "query_keypoints": len(qk),
        "db_keypoints": len(dk),
        "nn_ratio": float("nan"),
        "mutual_ratio": float("nan"),
        "mutual_matches": 0,
        "repeatability": float("nan"),
        "chance_ratio": float("nan"),
    }
    if len(qk) == 0 or len(dk) == 0:
        return out
    if qf.shape[1] != df.shape[1]:
        raise InputError(f"feature dimensions differ: {qf.shape[1]} and {df.shape[1]}")
    moved = qk @ T[:3, :3].T + T[:3, 3]  # [N, 3] query keypoints in the database frame
    dims = 2 if planar else 3
    near = _sq_dists(moved[:, :dims], dk[:, :dims]) <= radius * radius  # [N, M]
    fd = _sq_dists(qf, df)  # [N, M] feature distances
    nn = fd.argmin(axis=1)  # [N] (ties: lowest index)
    back = fd.argmin(axis=0)  # [M]
    correct = near[np.arange(len(qk)), nn]  # [N]
    mutual = back[nn] == np.arange(len(qk))  # [N]
    out["nn_ratio"] = float(correct.mean())
    out["mutual_matches"] = int(mutual.sum())
    if mutual.any():
        out["mutual_ratio"] = float(correct[mutual].mean())
    out["repeatability"] = float(near.any(axis=1).mean())
    out["chance_ratio"] = float(near.mean())
    return out


def _stat(xs: Sequence[float], fn) -> float:
    a = np.asarray([x for x in xs if x is not None and np.isfinite(x)], dtype=np.float64)
    return float(fn(a)) if a.size else float("nan")


def summarise_pairs(pairs: list[dict[str, Any]], planar: bool, radius: float) -> dict[str, Any]:
    """Means and medians over pairs of :func:`pair_match_stats` results (NaNs skipped)."""
    scored = [p for p in pairs if np.isfinite(p["nn_ratio"])]
    out: dict[str, Any] = {
        "radius_m": radius,
        "planar": planar,
        "pairs": len(scored),
        "pairs_without_keypoints": len(pairs) - len(scored),
    }
    for key in ("nn_ratio", "mutual_ratio", "repeatability", "chance_ratio"):
        vals = [p[key] for p in scored]
        out[f"{key}_mean"] = _stat(vals, np.mean)
        out[f"{key}_median"] = _stat(vals, np.median)
    for key in ("query_keypoints", "db_keypoints", "mutual_matches"):
        out[f"{key}_mean"] = _stat([p[key] for p in pairs], np.mean)
    out["pair_distance_m_mean"] = _stat([p.get("distance_m", np.nan) for p in pairs], np.mean)
    return out


def roc_auc(true_scores: Sequence[float], false_scores: Sequence[float]) -> float:
    """ROC AUC of scores separating true (positive) from false: P(s_true > s_false) + ties/2.

    NaN if either group is empty. Computed from average ranks (Mann-Whitney U).
    """
    t = np.asarray(true_scores, dtype=np.float64).ravel()
    f = np.asarray(false_scores, dtype=np.float64).ravel()
    if t.size == 0 or f.size == 0:
        return float("nan")
    ranks = _average_ranks(np.concatenate([t, f]))
    u = ranks[: t.size].sum() - t.size * (t.size + 1) / 2.0
    return float(u / (t.size * f.size))


def _average_ranks(x: np.ndarray) -> np.ndarray:
    """1-based ranks of ``x``, tied values sharing their average rank."""
    _, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
    last = np.cumsum(counts)  # rank of the last member of each group of equal values
    return (last - (counts - 1) / 2.0)[inverse]


def _describe(xs: np.ndarray) -> dict[str, Any]:
    if xs.size == 0:
        nan = float("nan")
        return {"count": 0, "mean": nan, "p10": nan, "p50": nan, "p90": nan}
    p10, p50, p90 = np.percentile(xs, [10, 50, 90])
    return {
        "count": int(xs.size),
        "mean": float(xs.mean()),
        "p10": float(p10),
        "p50": float(p50),
        "p90": float(p90),
    }


def score_separation(per_query: list[dict[str, Any]]) -> dict[str, Any]:
    """Statistics of SGV scores of true vs false candidates.

    ``per_query``: one dict per query with ``scores`` (list of floats) and ``true`` (list
    of bools, same length). Returns ``true`` and ``false`` (count, mean, p10/p50/p90),
    ``auc`` (pooled over every query's candidates) and ``auc_per_query_mean`` (mean of the
    per-query AUCs over queries with both true and false candidates: how well the score
    orders one query's candidates, which is what re-ranking needs) with their count.
    """
    s_true = [s for q in per_query for s, t in zip(q["scores"], q["true"], strict=True) if t]
    s_false = [s for q in per_query for s, t in zip(q["scores"], q["true"], strict=True) if not t]
    per_q = []
    for q in per_query:
        t = [s for s, ok in zip(q["scores"], q["true"], strict=True) if ok]
        f = [s for s, ok in zip(q["scores"], q["true"], strict=True) if not ok]
        if t and f:
            per_q.append(roc_auc(t, f))
    return {
        "true": _describe(np.asarray(s_true, dtype=np.float64)),
        "false": _describe(np.asarray(s_false, dtype=np.float64)),
        "auc": roc_auc(s_true, s_false),
        "auc_per_query_mean": float(np.mean(per_q)) if per_q else float("nan"),
        "auc_queries": len(per_q),
    }
