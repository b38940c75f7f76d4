"""The leave-out self-test's plan: which keyframes are queries and what each searches."""

from __future__ import annotations

import numpy as np
import pytest

from sgvloc.core import leave_out
from sgvloc.core.errors import InputError


def _loop(n: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """A drive of ``n`` keyframes, one per second along a 20 m circle driven twice."""
    a = np.linspace(0, 4 * np.pi, n, endpoint=False)
    xyz = np.column_stack([10 * np.cos(a), 10 * np.sin(a), np.zeros(n)])
    return np.arange(1, n + 1) * 10, xyz  # ids 10, 20, ...


def test_each_query_searches_only_keyframes_outside_its_gap() -> None:
    ids, xyz = _loop()
    times = np.arange(len(ids), dtype=float)
    plan = leave_out.plan(ids, xyz, times, queries=100, gap_s=15, radius_m=2.0)
    assert plan.basis == "timestamp"
    for q in plan.in_coverage + plan.out_of_coverage:
        searched = plan.searched(q)
        t = times[list(ids).index(q)]
        left = times[np.isin(ids, searched)]
        assert np.all(np.abs(left - t) >= 15)
        assert len(searched) == np.sum(np.abs(times - t) >= 15)  # nothing else left out
    # every keyframe is on the circle twice, 20 s apart: all are revisits
    assert sorted(plan.in_coverage) == sorted(int(i) for i in ids)
    assert plan.out_of_coverage == []


def test_without_timestamps_the_gap_counts_keyframes_and_far_ones_are_negatives() -> None:
    ids, xyz = _loop()
    xyz[:5] += [0.0, 0.0, 50.0]  # the first five stand apart, and so their second passes
    plan = leave_out.plan(ids, xyz, None, queries=3, gap_keyframes=10, radius_m=2.0)
    assert plan.basis == "insertion order"
    assert len(plan.in_coverage) == 3 and len(plan.out_of_coverage) == 3
    assert set(plan.out_of_coverage) <= {10, 20, 30, 40, 50, 210, 220, 230, 240, 250}
    q = plan.in_coverage[0]
    rank = list(ids).index(q)
    assert set(plan.searched(q)) == {int(i) for k, i in enumerate(ids) if abs(k - rank) >= 10}
    # the same map gives the same plan
    again = leave_out.plan(ids, xyz, None, queries=3, gap_keyframes=10, radius_m=2.0)
    assert again.in_coverage == plan.in_coverage and again.out_of_coverage == plan.out_of_coverage


def test_a_drive_without_a_revisit_is_refused_with_the_reason() -> None:
    x = np.arange(30, dtype=float) * 3.0
    xyz = np.column_stack([x, np.zeros(30), np.zeros(30)])  # a straight line, never back
    with pytest.raises(InputError, match="no keyframe has a revisit.*or a shorter gap"):
        leave_out.plan(np.arange(30), xyz, np.arange(30.0), gap_s=10)
    with pytest.raises(InputError, match="queries must be at least 1"):
        leave_out.plan(np.arange(30), xyz, None, queries=0)


def test_summary_counts_false_accepts_over_every_query() -> None:
    def rec(inside, found, correct, localized):
        return {
            "in_coverage": inside,
            "found": found,
            "correct": correct,
            "localized": localized,
            "ms": 10.0,
        }

    figs = leave_out.summarise(
        [
            rec(True, True, True, True),
            rec(True, True, True, False),
            rec(True, False, False, True),  # in coverage, wrong, accepted
            rec(False, False, False, True),  # out of coverage, accepted: a false accept
            rec(False, False, True, True),  # out of coverage but posed right: fine
        ]
    )
    assert figs["queries"] == 3 and figs["negatives"] == 2
    assert figs["recall_at_1"] == 66.7 and figs["pose_success"] == 66.7
    assert figs["accepted_of_correct"] == 66.7  # 2 of the 3 correct answers
    assert figs["false_accepts"] == 2
