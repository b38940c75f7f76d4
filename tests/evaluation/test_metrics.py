"""Metric functions against hand-computed cases (docs/EVALUATION.md)."""

import math

import numpy as np
import pytest

from sgvloc.core.errors import InputError
from sgvloc.tools.evaluation.metrics import (
    first_true_rank,
    mrr,
    recall_at,
    rre,
    rte,
    success,
    success_rate,
)


def yaw(deg: float, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    a = math.radians(deg)
    T = np.eye(4)
    T[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    T[:3, 3] = t
    return T


def test_first_true_rank_finds_the_first_candidate_within_the_radius():
    q = np.array([0.0, 0.0, 0.0])
    cands = np.array([[30.0, 0, 0], [9.0, 0, 0], [4.0, 0, 0], [1.0, 0, 0]])
    assert first_true_rank(cands, q, 5.0) == 3
    assert first_true_rank(cands, q, 20.0) == 2
    assert first_true_rank(cands, q, 0.5) is None
    assert first_true_rank(np.zeros((0, 3)), q, 5.0) is None


def test_mrr_rank_three_gives_one_third_and_none_gives_zero():
    assert mrr([3]) == pytest.approx(100.0 / 3)
    assert mrr([None]) == 0.0
    assert mrr([1, 2, None, 4]) == pytest.approx(100.0 * (1 + 0.5 + 0 + 0.25) / 4)


def test_recall_at_n_hand_computed_and_monotone():
    ranks = [1, 3, None, 5, 2, 6]
    assert recall_at(ranks, 1) == pytest.approx(100 / 6)
    assert recall_at(ranks, 5) == pytest.approx(400 / 6)
    rng = np.random.default_rng(0)
    for _ in range(20):
        rs = [None if r == 0 else int(r) for r in rng.integers(0, 8, size=15)]
        assert recall_at(rs, 5) >= recall_at(rs, 1)
        assert recall_at(rs, 1) <= mrr(rs) <= recall_at(rs, 20)


def test_empty_and_bad_ranks():
    assert math.isnan(recall_at([], 1)) and math.isnan(mrr([]))
    with pytest.raises(InputError):
        recall_at([0], 1)
    with pytest.raises(InputError):
        recall_at([1], 0)


def test_rre_of_a_90_degree_yaw_is_90_and_rte_is_the_offset():
    assert rre(yaw(90), np.eye(4)) == pytest.approx(90.0)
    assert rre(yaw(-30), yaw(150)) == pytest.approx(180.0)
    assert rre(yaw(17), yaw(17)) == pytest.approx(0.0, abs=1e-5)
    assert rte(yaw(90, (3, 4, 0)), np.eye(4)) == pytest.approx(5.0)
    batch = np.stack([yaw(10, (1, 0, 0)), yaw(0, (0, 0, 2))])
    assert np.allclose(rre(batch, np.eye(4)[None]), [10.0, 0.0], atol=1e-6)
    assert np.allclose(rte(batch, np.eye(4)[None]), [1.0, 2.0])
    with pytest.raises(InputError):
        rte(np.eye(3), np.eye(4))


def test_success_needs_both_thresholds():
    ok = success([1.0, 2.0, 2.1, 0.5, float("nan")], [4.0, 5.0, 1.0, 5.1, 0.0])
    assert ok.tolist() == [True, True, False, False, False]
    assert success_rate([1.0, 3.0], [1.0, 1.0]) == 50.0


def test_ceiling_counts_a_true_match_anywhere_in_the_candidates():
    from sgvloc.tools.evaluation.runner import _aggregate, ceiling

    # four queries: true match re-ranked to 1, found at rank 7 of 8, none, rank 2
    ranks = [1, 7, None, 2]
    assert ceiling(ranks) == 75.0 and math.isnan(ceiling([]))
    recs = [
        {"in_coverage": True, "rank@5m": r, "ms": 1.0, "top1_changed": False, "candidates": 8}
        for r in ranks
    ]
    recs.append({"in_coverage": False, "rank@5m": None, "ms": 1.0, "top1_changed": False})
    agg = _aggregate("sgv", 5, recs, [5.0], with_pose=False)
    # the ceiling is not capped at k: merged retrieval starts from up to 2k candidates
    assert agg["ceiling_5m"] == 75.0 and agg["R@1_5m"] == 25.0 and agg["R@5_5m"] == 50.0
    assert agg["candidates_mean"] == 8.0 and agg["queries"] == 4


def test_a_rows_ceiling_counts_the_starting_candidates_and_unanswered_queries_leave_the_means():
    """Query expansion answers from a search of its own, so the ceiling is counted in the
    candidates re-ranking started from; a query without any candidate fails S and has no
    RTE to average (it no longer turns the row's means into NaN)."""
    from sgvloc.tools.evaluation.runner import _aggregate

    base = {"in_coverage": True, "ms": 1.0, "top1_changed": False, "candidates": 3}
    base |= {"accepted": False, "correct": False, "confidence": 0.0, "localized": False}
    recs = [
        {**base, "rank@5m": None, "start_rank": 2, "rte": 1.0, "rre": 1.0, "has_estimate": True},
        {**base, "rank@5m": 1, "start_rank": 1, "rte": 3.0, "rre": 3.0, "has_estimate": True},
        {**base, "rank@5m": None, "start_rank": None, "rte": np.nan, "rre": np.nan}
        | {"has_estimate": False, "candidates": 0},
    ]
    out = _aggregate("average-qe", 3, recs, [5.0], with_pose=True)
    assert out["ceiling_5m"] == pytest.approx(200.0 / 3) and out["R@1_5m"] == pytest.approx(
        100.0 / 3
    )
    assert out["mean_rte_m"] == pytest.approx(2.0) and out["mean_rre_deg"] == pytest.approx(2.0)
    assert out["success_pct"] == pytest.approx(100.0 / 3) and out["no_estimate"] == 1
