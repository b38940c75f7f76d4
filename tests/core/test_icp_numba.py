"""The GIL-free point-to-plane ICP (sgvloc.core.icp_numba): exact nearest neighbours,
the same fitness as small_gicp's search, a known motion recovered, the same bits every
time, and other Python threads running while it works."""

from __future__ import annotations

import numpy as np
import pytest
from pose_helpers import assert_other_threads_run_during, planar_pose

from sgvloc.core import icp_numba
from sgvloc.core.pose import IcpTarget, _fit_quality


def _scene(rng: np.random.Generator, n: int = 6000) -> np.ndarray:
    """Points on a ground plane, two walls and a box: structure in every direction."""
    ground = np.c_[rng.uniform(-20, 20, (n // 2, 2)), rng.normal(0, 0.01, n // 2)]
    wall_x = np.c_[np.full(n // 6, 8.0), rng.uniform(-20, 20, n // 6), rng.uniform(0, 4, n // 6)]
    wall_y = np.c_[rng.uniform(-20, 20, n // 6), np.full(n // 6, -6.0), rng.uniform(0, 4, n // 6)]
    box = rng.uniform([-3, 2, 0], [-1, 5, 2], (n - n // 2 - 2 * (n // 6), 3))
    return np.vstack([ground, wall_x, wall_y, box])


def _motion(yaw_deg: float, t: list[float]) -> np.ndarray:
    T = planar_pose(t[0], t[1], yaw_deg)
    T[2, 3] = t[2]
    return T


@pytest.mark.parametrize("m", [0, 1, 31, 32, 33, 65, 500, 5000])
def test_nearest_is_the_brute_force_nearest_within_the_radius(m: int) -> None:
    rng = np.random.default_rng(m)
    pts = np.round(rng.uniform(-5, 5, (m, 3)), 1)  # rounded: many ties on an axis
    tree = icp_numba.Tree(pts)
    order_pts = tree.points
    for q in rng.uniform(-6, 6, (200, 3)):
        for r in (0.3, 1.0, 50.0):
            j, s = icp_numba.nearest(order_pts, *tree.nodes, q[0], q[1], q[2], r * r)
            d2 = ((pts - q) ** 2).sum(axis=1) if m else np.zeros(0)
            if m == 0 or d2.min() > r * r:
                assert j == -1 and s == np.inf
            else:
                assert s == pytest.approx(d2.min(), abs=1e-12)
                assert ((order_pts[j] - q) ** 2).sum() == pytest.approx(d2.min(), abs=1e-12)


def test_fitness_and_rmse_match_small_gicps_search() -> None:
    rng = np.random.default_rng(1)
    cloud = _scene(rng)
    query = cloud[rng.choice(len(cloud), 4000)] + rng.normal(0, 0.4, (4000, 3))
    T = _motion(3.0, [0.3, -0.2, 0.05])
    mine = icp_numba.Tree(cloud).fit_quality(query, T, 1.0)
    assert mine[2] is None  # a tree without normals
    theirs = _fit_quality(IcpTarget(cloud).tree, query, T, 1.0)
    assert mine[0] == theirs[0]  # the same points within the distance
    assert mine[1] == pytest.approx(theirs[1], rel=1e-12)
    assert icp_numba.Tree(cloud).fit_quality(query + 1000.0, T, 1.0) == (0.0, 0.0, None)
    # the matched normals' moment: the same normals (to 1e-9) at the same nearest points
    small, numba = IcpTarget(cloud), IcpTarget(cloud, "numba")
    assert numba.numba is not None
    mine = numba.numba.fit_quality(query, T, 1.0)[2]
    theirs = _fit_quality(small.tree, query, T, 1.0, small.cloud.normals())[2]
    np.testing.assert_allclose(mine, theirs, atol=1e-6)
    assert np.trace(mine) == pytest.approx(1.0)  # unit normals


def test_align_recovers_a_known_motion_the_same_every_time() -> None:
    rng = np.random.default_rng(2)
    target_cloud = _scene(rng)
    T_true = _motion(4.0, [0.6, -0.4, 0.1])  # target <- source
    source = (target_cloud[rng.choice(len(target_cloud), 3000)] - T_true[:3, 3]) @ T_true[:3, :3]
    source += rng.normal(0, 0.01, source.shape)
    target = IcpTarget(target_cloud, "numba")
    tree = target.numba
    assert tree is not None
    runs = [tree.align(source, np.eye(4), 1.0, 30, 1e-4, np.radians(0.01)) for _ in range(3)]
    T, iterations = runs[0]
    assert 1 < iterations < 30
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 0.01
    cos = (np.trace(T[:3, :3].T @ T_true[:3, :3]) - 1) / 2
    assert np.degrees(np.arccos(min(1.0, cos))) < 0.05
    assert all(np.array_equal(T, other) and n == iterations for other, n in runs[1:])
    # no correspondence within the distance: the start comes back unchanged
    far = _motion(0.0, [500.0, 0.0, 0.0])
    assert np.array_equal(tree.align(source, far, 1.0, 30, 1e-4, 1e-4)[0], far)


def test_other_threads_run_while_it_aligns() -> None:
    """The kernels release the interpreter lock: while a long alignment (or fitness
    pass) runs on one thread, another thread runs Python and finds it still running.
    With the lock held, as small_gicp's binding holds it, the other thread could not run
    again until the call had returned."""
    rng = np.random.default_rng(3)
    cloud = _scene(rng, 60_000)
    tree = IcpTarget(cloud, "numba").numba
    assert tree is not None
    source = cloud + rng.normal(0, 0.05, cloud.shape)
    icp_numba.warm_up()
    calls = {
        "align": lambda: tree.align(source, np.eye(4), 1.0, 30, 0.0, 0.0),  # 30 iterations
        "fit_quality": lambda: tree.fit_quality(np.tile(source, (16, 1)), np.eye(4), 1.0),
    }
    assert_other_threads_run_during(calls)
