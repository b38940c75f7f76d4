"""The GIL-free GICP / VGICP of tracking (sgvloc.core.gicp_numba): small_gicp's voxel
grid and covariances reproduced, exact nearest neighbours, known motions recovered the
same every time, and other Python threads running while it registers."""

from __future__ import annotations

import numpy as np
import pytest
import small_gicp
from pose_helpers import assert_other_threads_run_during, planar_pose

from sgvloc.core import gicp_numba
from sgvloc.core.gicp_numba import Cloud, GaussianVoxels, voxel_centroids


def _scene(rng: np.random.Generator, n: int = 8000) -> np.ndarray:
    """Points on a ground plane, two walls, a box and a pole: structure in every
    direction, some of it thin."""
    ground = np.c_[rng.uniform(-20, 20, (n // 2, 2)), rng.normal(0, 0.01, n // 2)]
    k = n // 6
    wall_x = np.c_[np.full(k, 8.0), rng.uniform(-20, 20, k), rng.uniform(0, 4, k)]
    wall_y = np.c_[rng.uniform(-20, 20, k), np.full(k, -6.0), rng.uniform(0, 4, k)]
    pole = np.c_[rng.normal(3, 0.02, 200), rng.normal(3, 0.02, 200), rng.uniform(0, 5, 200)]
    box = rng.uniform([-3, 2, 0], [-1, 5, 2], (n - n // 2 - 2 * k - 200, 3))
    return np.vstack([ground, wall_x, wall_y, pole, box])


def _motion(yaw_deg: float, t: list[float]) -> np.ndarray:
    T = planar_pose(t[0], t[1], yaw_deg)
    T[2, 3] = t[2]
    return T


def test_voxel_grid_covariances_and_normals_are_small_gicps() -> None:
    rng = np.random.default_rng(0)
    pts = _scene(rng)
    ours = voxel_centroids(pts, 0.5)
    theirs = np.asarray(small_gicp.voxelgrid_sampling(pts, 0.5, num_threads=1).points())[:, :3]
    assert len(ours) == len(theirs)
    np.testing.assert_allclose(
        ours[np.lexsort(ours.T)], theirs[np.lexsort(theirs.T)], rtol=0, atol=1e-9
    )
    assert np.array_equal(voxel_centroids(pts, 0.5), ours)  # same order every time

    cloud = Cloud.of(ours, 10)
    ref = small_gicp.PointCloud(cloud.points)
    small_gicp.estimate_covariances(ref, small_gicp.KdTree(ref), num_neighbors=10)
    np.testing.assert_allclose(cloud.covs, np.asarray(ref.covs())[:, :3, :3], rtol=0, atol=1e-7)
    # plane-regularised: eigenvalues (EPS, 1, 1)
    w = np.linalg.eigvalsh(cloud.covs)
    np.testing.assert_allclose(w, np.tile([gicp_numba.EPS, 1.0, 1.0], (len(w), 1)), atol=1e-9)
    # normals (point-to-plane ICP's targets): small_gicp's, facing the sensor at the origin
    small_gicp.estimate_normals(ref, small_gicp.KdTree(ref), num_neighbors=10)
    ours = gicp_numba.normals(cloud.points, *cloud.nodes, 10)
    np.testing.assert_allclose(ours, np.asarray(ref.normals())[:, :3], rtol=0, atol=1e-7)
    assert (np.einsum("ij,ij->i", ours, cloud.points) <= 0).all()


@pytest.mark.parametrize("m", [3, 5, 33, 700])
def test_k_nearest_are_the_brute_force_nearest(m: int) -> None:
    rng = np.random.default_rng(m)
    pts = rng.uniform(-5, 5, (m, 3))
    cloud = Cloud.of(pts, 5)
    k = 5
    bi, bd = np.empty(k, np.int64), np.empty(k)
    stack, gaps = np.empty(64, np.int64), np.empty(64)
    for q in rng.uniform(-6, 6, (50, 3)):
        n = gicp_numba._knn(cloud.points, *cloud.nodes, *q, bi, bd, stack, gaps)
        d = np.sort(((cloud.points - q) ** 2).sum(axis=1))[:k]
        assert n == min(k, m)
        np.testing.assert_allclose(bd[:n], d[:n], rtol=1e-12)
    # too few neighbours for a covariance of its own: the identity
    if m < gicp_numba.MIN_NEIGHBOURS + 1:
        few = Cloud.of(pts[:3], 10)
        assert np.array_equal(few.covs, np.tile(np.eye(3), (3, 1, 1)))


@pytest.mark.parametrize("target", ["points", "voxels"])
def test_a_known_motion_is_recovered_the_same_every_time(target: str) -> None:
    rng = np.random.default_rng(1)
    world = _scene(rng, 30_000)
    T_true = _motion(4.0, [0.6, -0.4, 0.1])
    # the scan: the world seen from T_true, with noise, at 0.5 m voxels
    scan = (world - T_true[:3, 3]) @ T_true[:3, :3] + rng.normal(0, 0.01, world.shape)
    src = Cloud.of(voxel_centroids(scan, 0.5), 10)
    submap = Cloud.of(voxel_centroids(world, 0.2), 10)
    tgt = submap if target == "points" else GaussianVoxels.of(submap, 3.0)
    T0 = np.eye(4)
    T, iterations, H, used = tgt.align(src, T0, 1.5, 50, 1e-4, 1e-5)
    D = np.linalg.inv(T_true) @ T
    assert np.linalg.norm(D[:3, 3]) < 0.05, D
    # small_gicp's GICP / VGICP (Levenberg-Marquardt) from the same start lands there too
    ref_t, ref_s = small_gicp.PointCloud(submap.points), small_gicp.PointCloud(src.points)
    tree = small_gicp.KdTree(ref_t)
    small_gicp.estimate_covariances(ref_t, tree, num_neighbors=10)
    small_gicp.estimate_covariances(ref_s, small_gicp.KdTree(ref_s), num_neighbors=10)
    opts = {"max_correspondence_distance": 1.5, "max_iterations": 50}
    if target == "points":
        ref = small_gicp.align(ref_t, ref_s, tree, registration_type="GICP", **opts)
    else:
        voxelmap = small_gicp.GaussianVoxelMap(3.0)
        voxelmap.insert(ref_t)
        ref = small_gicp.align(voxelmap, ref_s, **opts)
    assert np.linalg.norm(np.asarray(ref.T_target_source)[:3, 3] - T[:3, 3]) < 0.01
    assert 1 < iterations < 50 and used > 0.5 * len(src)
    assert np.allclose(H, H.T) and np.linalg.eigvalsh(H).min() > 0
    again = tgt.align(src, T0, 1.5, 50, 1e-4, 1e-5)
    assert np.array_equal(again[0], T) and np.array_equal(again[2], H)
    # the fitness pass: most of the scan lies on the submap under the recovered pose
    sq = submap.nearest_squared(src.points, T)
    assert np.mean(sq <= 0.3**2) > 0.9


def test_map_coordinates_far_from_the_origin_change_nothing() -> None:
    """A map in UTM-like coordinates (millions of metres) is voxelised and registered as
    the same map at the origin: voxel keys count from the cloud's own lowest voxel, so
    they neither collide nor run out of bits."""
    rng = np.random.default_rng(4)
    world = _scene(rng, 30_000)
    far = np.array([500_000.0, 4_000_000.0, 0.0])  # a whole number of 0.5 m and 3 m voxels
    near_vox, far_vox = voxel_centroids(world, 0.5), voxel_centroids(world + far, 0.5)
    assert len(far_vox) == len(near_vox)
    np.testing.assert_allclose(far_vox - far, near_vox, rtol=0, atol=1e-6)
    T_true = _motion(3.0, [0.5, -0.3, 0.05])
    scan = (world - T_true[:3, 3]) @ T_true[:3, :3]
    src = Cloud.of(voxel_centroids(scan, 0.5), 10)
    poses = []
    for shift in (np.zeros(3), far):
        submap = Cloud.of(voxel_centroids(world + shift, 0.2), 10)
        T0 = np.eye(4)
        T0[:3, 3] = shift
        for target in (GaussianVoxels.of(submap, 3.0), submap):
            T, *_ = target.align(src, T0, 1.5, 50, 1e-4, 1e-5)
            T0 = T
        T[:3, 3] -= shift
        poses.append(T)
    for T in poses:
        assert np.linalg.norm((np.linalg.inv(T_true) @ T)[:3, 3]) < 0.05
    assert np.linalg.norm(poses[1][:3, 3] - poses[0][:3, 3]) < 1e-3  # the same within 1 mm


def test_other_threads_run_while_it_registers() -> None:
    """The kernels release the interpreter lock: while a long registration runs on one
    thread, another thread runs Python and finds it still running (small_gicp's binding
    holds the lock until it returns)."""
    rng = np.random.default_rng(3)
    submap = Cloud.of(_scene(rng, 200_000), 10)
    src = Cloud.of(submap.points + rng.normal(0, 0.05, submap.points.shape), 10)
    voxels = GaussianVoxels.of(submap, 1.0)
    gicp_numba.warm_up()
    calls = {
        "gicp": lambda: submap.align(src, np.eye(4), 1.0, 30, 0.0, 0.0),  # 30 iterations
        "vgicp": lambda: [voxels.align(src, np.eye(4), 1.0, 30, 0.0, 0.0) for _ in range(5)],
    }
    assert_other_threads_run_during(calls)
