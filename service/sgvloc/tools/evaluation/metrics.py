"""Evaluation metrics, exactly as docs/EVALUATION.md defines them.

Place recognition, per query: the 1-based rank of the first retrieved keyframe within the
revisit threshold (``None`` when none of the top-k is). Over queries:

- Recall@N: share of queries with a true positive among the first N (percent);
- MRR: mean of ``1 / rank`` of the first true positive in the top-k, 0 if none (percent).

Metric localization on the re-ranked top-1:

- RTE = ``||t_est - t_gt||`` (m);
- RRE = ``degrees(arccos(clip((trace(R_est^T R_gt) - 1) / 2, -1, 1)))``;
- success: RTE <= 2 m and RRE <= 5 degrees.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from sgvloc.core.confidence import CORRECT_DEG, CORRECT_M
from sgvloc.core.errors import InputError

#: docs/EVALUATION.md: success thresholds on the re-ranked top-1 pose
MAX_RTE_M, MAX_RRE_DEG = CORRECT_M, CORRECT_DEG


def first_true_rank(
    ranked_positions: np.ndarray,
    query_position: np.ndarray,
    radius: float,
    eligible: np.ndarray | None = None,
) -> int | None:
    """1-based rank of the first candidate within ``radius`` metres of the query, or None.

    ``ranked_positions``: ``[k, 3]`` candidate positions, best first; ``query_position``:
    ``[3]`` ground-truth position of the query; ``eligible``: ``[k]`` which candidates may
    count at all (``--fov``: those facing the query's way), default all.
    """
    pos = np.asarray(ranked_positions, dtype=np.float64).reshape(-1, 3)  # [k, 3]
    if len(pos) == 0:
        return None
    d = np.linalg.norm(pos - np.asarray(query_position, dtype=np.float64)[None], axis=1)  # [k]
    near = d <= radius
    if eligible is not None:
        near &= np.asarray(eligible, dtype=bool).reshape(-1)
    hits = np.flatnonzero(near)
    return int(hits[0]) + 1 if len(hits) else None


def _ranks(ranks: Iterable[int | None]) -> list[int | None]:
    out = list(ranks)
    for r in out:
        if r is not None and (int(r) != r or r < 1):
            raise InputError(f"ranks must be positive integers or None, got {r!r}")
    return out


def recall_at(ranks: Iterable[int | None], n: int) -> float:
    """Recall@n in percent: share of queries whose first true positive has rank <= n.

    ``ranks``: per query the 1-based rank of the first true positive, None if none was
    retrieved. An empty list gives NaN.
    """
    if n < 1:
        raise InputError(f"Recall@N needs N >= 1, got {n}")
    rs = _ranks(ranks)
    if not rs:
        return float("nan")
    return 100.0 * sum(1 for r in rs if r is not None and r <= n) / len(rs)


def mrr(ranks: Iterable[int | None]) -> float:
    """Mean reciprocal rank in percent: mean of ``1 / rank`` (0 for None). Empty: NaN."""
    rs = _ranks(ranks)
    if not rs:
        return float("nan")
    return 100.0 * sum(0.0 if r is None else 1.0 / r for r in rs) / len(rs)


def _check_pose(T: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(T, dtype=np.float64)
    if a.shape[-2:] != (4, 4):
        raise InputError(f"{name} must have shape [..., 4, 4], got {list(a.shape)}")
    return a


def rte(T_est: np.ndarray, T_gt: np.ndarray, planar: bool = False) -> np.ndarray | float:
    """Relative translation error ``||t_est - t_gt||`` in metres for ``[..., 4, 4]`` poses
    (``planar``: in x/y only, for pipelines that estimate x, y and yaw)."""
    e, g = _check_pose(T_est, "T_est"), _check_pose(T_gt, "T_gt")
    d = 2 if planar else 3
    out = np.linalg.norm(e[..., :d, 3] - g[..., :d, 3], axis=-1)
    return float(out) if out.ndim == 0 else out


def rre(T_est: np.ndarray, T_gt: np.ndarray, planar: bool = False) -> np.ndarray | float:
    """Relative rotation error in degrees for ``[..., 4, 4]`` poses (docs/EVALUATION.md);
    ``planar``: the heading (yaw) difference only."""
    e, g = _check_pose(T_est, "T_est"), _check_pose(T_gt, "T_gt")
    if planar:
        yaw = np.arctan2(e[..., 1, 0], e[..., 0, 0]) - np.arctan2(g[..., 1, 0], g[..., 0, 0])
        out = np.abs(np.degrees((yaw + np.pi) % (2 * np.pi) - np.pi))
        return float(out) if out.ndim == 0 else out
    # trace(R_est^T R_gt) = sum_ij R_est[i, j] * R_gt[i, j]
    tr = np.einsum("...ij,...ij->...", e[..., :3, :3], g[..., :3, :3])
    out = np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))
    return float(out) if out.ndim == 0 else out


def success(
    rte_m: Sequence[float] | np.ndarray,
    rre_deg: Sequence[float] | np.ndarray,
    max_rte: float = MAX_RTE_M,
    max_rre: float = MAX_RRE_DEG,
) -> np.ndarray:
    """Per query: RTE <= ``max_rte`` and RRE <= ``max_rre`` (``[Q]`` bool; NaN fails)."""
    t = np.asarray(rte_m, dtype=np.float64)
    r = np.asarray(rre_deg, dtype=np.float64)
    if t.shape != r.shape:
        raise InputError(f"RTE and RRE must have the same shape, got {t.shape} and {r.shape}")
    with np.errstate(invalid="ignore"):
        return (t <= max_rte) & (r <= max_rre)


def success_rate(rte_m: Sequence[float], rre_deg: Sequence[float]) -> float:
    """Pose success in percent over all queries (NaN for no queries)."""
    ok = success(rte_m, rre_deg)
    return float("nan") if ok.size == 0 else 100.0 * float(ok.mean())


def expected_calibration_error(
    confidence: Sequence[float] | np.ndarray, correct: Sequence[bool] | np.ndarray, bins: int = 10
) -> float:
    """Expected calibration error: over ``bins`` equal-width confidence bins, the mean of
    ``|accuracy - mean confidence|`` weighted by the share of answers in the bin."""
    c = np.asarray(confidence, dtype=np.float64)
    y = np.asarray(correct, dtype=np.float64)
    if c.shape != y.shape or c.ndim != 1:
        raise InputError("confidence and correct must be 1-D of equal length")
    if c.size == 0:
        return float("nan")
    which = np.minimum((c * bins).astype(np.int64), bins - 1)  # [Q] bin of each answer
    err = 0.0
    for b in range(bins):
        m = which == b
        if m.any():
            err += m.mean() * abs(y[m].mean() - c[m].mean())
    return float(err)


def verdict_curve(
    confidence: Sequence[float] | np.ndarray,
    correct: Sequence[bool] | np.ndarray,
    thresholds: Sequence[float] | np.ndarray,
) -> dict[str, list[float]]:
    """Per confidence threshold t (answers accepted when confidence >= t): precision
    (correct among accepted), recall (accepted among correct) and the false-accept rate
    (accepted but wrong, over all answers), in percent; NaN where undefined."""
    c = np.asarray(confidence, dtype=np.float64)
    y = np.asarray(correct, dtype=bool)
    out: dict[str, list[float]] = {
        "threshold": [],
        "precision": [],
        "recall": [],
        "false_accept": [],
    }
    for t in thresholds:
        acc = c >= t
        out["threshold"].append(float(t))
        out["precision"].append(100.0 * float(y[acc].mean()) if acc.any() else float("nan"))
        out["recall"].append(100.0 * float(acc[y].mean()) if y.any() else float("nan"))
        out["false_accept"].append(100.0 * float((acc & ~y).mean()) if c.size else float("nan"))
    return out
