"""Encoder diagnostics: match ratios on true pairs, SGV score separation, ROC AUC."""

import math

import numpy as np
import pytest

from sgvloc.core.errors import InputError
from sgvloc.tools.evaluation.diagnostics import (
    is_planar,
    pair_match_stats,
    roc_auc,
    score_separation,
    summarise_pairs,
)


def _yaw(deg: float, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    a = math.radians(deg)
    T = np.eye(4)
    T[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    T[:3, 3] = t
    return T


@pytest.fixture
def pair(rng):
    """A query seen from a database scan: 200 keypoints, 150 shared (same descriptor)."""
    n, shared, dim = 200, 150, 32
    q_kp = rng.uniform(-20, 20, (n, 3)) * [1, 1, 0.1]
    q_ft = rng.normal(size=(n, dim))
    T_db_q = _yaw(30.0, (3.0, -1.0, 0.2))
    moved = q_kp @ T_db_q[:3, :3].T + T_db_q[:3, 3]
    # database: the shared keypoints (jittered 0.2 m, descriptor noise) + 50 others
    db_kp = np.concatenate(
        [moved[:shared] + rng.normal(0, 0.1, (shared, 3)), rng.uniform(-20, 20, (50, 3))]
    )
    db_ft = np.concatenate(
        [q_ft[:shared] + rng.normal(0, 0.05, (shared, dim)), rng.normal(size=(50, dim))]
    )
    return q_kp, q_ft, db_kp, db_ft, T_db_q


def test_true_pose_gives_the_shared_share_and_a_wrong_one_much_less(pair, rng):
    q_kp, q_ft, db_kp, db_ft, T = pair
    good = pair_match_stats(q_kp, q_ft, db_kp, db_ft, T)
    assert good["nn_ratio"] == pytest.approx(0.75, abs=0.02)  # 150 of 200 have a partner
    assert good["mutual_ratio"] > 0.95 and good["mutual_matches"] >= 145
    assert good["repeatability"] >= good["nn_ratio"]
    assert 0.0 <= good["chance_ratio"] < 0.05
    assert good["query_keypoints"] == 200 and good["db_keypoints"] == 200
    # wrong ground truth (off by 90 degrees) or shuffled descriptors: near chance
    wrong = pair_match_stats(q_kp, q_ft, db_kp, db_ft, _yaw(120.0, (3.0, -1.0, 0.2)))
    shuffled = pair_match_stats(q_kp, q_ft[rng.permutation(len(q_ft))], db_kp, db_ft, T)
    for bad in (wrong, shuffled):
        assert bad["nn_ratio"] < 0.1 < good["nn_ratio"]


def test_planar_keypoints_are_compared_in_xy(pair):
    q_kp, q_ft, db_kp, db_ft, T = pair
    q2, d2 = q_kp * [1, 1, 0], db_kp * [1, 1, 0]
    assert is_planar(q2, d2) and not is_planar(q_kp, d2) and not is_planar(np.zeros((0, 3)))
    # the ground truth moves z by 10 m: a 3-D comparison finds nothing, x/y finds the pairs
    T_up = T.copy()
    T_up[2, 3] = 10.0
    assert pair_match_stats(q2, q_ft, d2, db_ft, T_up)["nn_ratio"] > 0.7
    assert pair_match_stats(q2, q_ft, d2, db_ft, T_up, planar=False)["nn_ratio"] == 0.0


def test_empty_scans_and_bad_shapes():
    kp, ft = np.zeros((0, 3)), np.zeros((0, 8))
    s = pair_match_stats(kp, ft, np.ones((4, 3)), np.ones((4, 8)), np.eye(4))
    assert math.isnan(s["nn_ratio"]) and s["query_keypoints"] == 0
    summary = summarise_pairs([{**s, "distance_m": 1.0}], planar=False, radius=1.0)
    assert summary["pairs"] == 0 and summary["pairs_without_keypoints"] == 1
    with pytest.raises(InputError, match="4, 4"):
        pair_match_stats(
            np.ones((2, 3)), np.ones((2, 8)), np.ones((2, 3)), np.ones((2, 8)), np.eye(3)
        )
    with pytest.raises(InputError, match="one local feature row"):
        pair_match_stats(
            np.ones((2, 3)), np.ones((3, 8)), np.ones((2, 3)), np.ones((2, 8)), np.eye(4)
        )


def test_roc_auc_counts_ties_half_and_matches_pairwise_definition(rng):
    assert roc_auc([3, 4], [1, 2]) == 1.0
    assert roc_auc([1, 2], [3, 4]) == 0.0
    assert roc_auc([1, 1], [1]) == 0.5
    assert math.isnan(roc_auc([], [1.0]))
    t, f = rng.integers(0, 20, 50).astype(float), rng.integers(0, 20, 70).astype(float)
    pairwise = ((t[:, None] > f[None]) + 0.5 * (t[:, None] == f[None])).mean()
    assert roc_auc(t, f) == pytest.approx(pairwise)


def test_score_separation_pooled_and_per_query():
    per_query = [
        {"scores": [0.9, 0.2, 0.1], "true": [True, False, False]},
        {"scores": [0.3, 0.4], "true": [True, False]},  # this query's order is wrong
        {"scores": [0.5], "true": [True]},  # no false candidate: not in the per-query mean
    ]
    s = score_separation(per_query)
    assert s["true"]["count"] == 3 and s["false"]["count"] == 3
    assert s["true"]["mean"] == pytest.approx(np.mean([0.9, 0.3, 0.5]))
    assert s["false"]["p50"] == pytest.approx(0.2)
    assert s["auc_queries"] == 2 and s["auc_per_query_mean"] == pytest.approx(0.5)
    # pooled: true {0.9, 0.3, 0.5} vs false {0.2, 0.1, 0.4}: 8 of 9 pairs ordered right
    assert s["auc"] == pytest.approx(8 / 9)
