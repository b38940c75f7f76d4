"""Pose estimation on real scans with ground truth (tests/fixtures/balm_mini)."""

import numpy as np
import pytest
from pose_helpers import planar_pose

from sgvloc.core.config import HandcraftedEncoderConfig, PoseConfig, PreprocessConfig
from sgvloc.core.encoders import HandcraftedEncoder
from sgvloc.core.errors import InputError
from sgvloc.core.pose import (
    IcpTarget,
    PoseResult,
    check_rigid,
    constraint,
    fgr_pose,
    icp_stages,
    is_rigid,
    ransac_pose,
    refine_icp,
)
from sgvloc.core.sequence import KittiSequence, relative_pose


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    cos = (np.trace(R_est.T @ R_gt) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def translation_error(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    return float(np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3]))


@pytest.fixture(scope="module")
def pair(balm_mini_dir):
    """Files 0 and 1 (source scans 0 and 30): 1.1 m apart, 77 degrees of yaw."""
    seq = KittiSequence(balm_mini_dir)
    # dense keypoints: RANSAC on every downsampled point with FPFH
    enc = HandcraftedEncoder(
        HandcraftedEncoderConfig(num_keypoints=20000),
        PreprocessConfig(voxel_size=0.25),
    )
    src_cloud, dst_cloud = enc.prepare(seq[0].scan().points), enc.prepare(seq[1].scan().points)
    src, dst = enc.encode_cloud(src_cloud), enc.encode_cloud(dst_cloud)
    T_gt = relative_pose(seq[0].T_world_sensor, seq[1].T_world_sensor)  # T_1_0
    return src, dst, src_cloud, dst_cloud, T_gt


def test_ransac_recovers_known_transform_between_real_scans(pair):
    src, dst, _, _, T_gt = pair
    res = ransac_pose(src.keypoints, src.local_features, dst.keypoints, dst.local_features)
    assert res.localized, res.reason
    assert translation_error(res.T_target_source, T_gt) < 0.3
    assert rotation_error_deg(res.T_target_source[:3, :3], T_gt[:3, :3]) < 2.0
    assert is_rigid(res.T_target_source)
    assert res.inliers >= PoseConfig().min_inliers
    assert 0.0 < res.fitness <= 1.0 and res.inlier_rmse <= PoseConfig().max_correspondence_distance


def test_ransac_is_reproducible(pair):
    src, dst, *_ = pair
    a = ransac_pose(src.keypoints, src.local_features, dst.keypoints, dst.local_features)
    b = ransac_pose(src.keypoints, src.local_features, dst.keypoints, dst.local_features)
    assert np.array_equal(a.T_target_source, b.T_target_source)
    assert a.inliers == b.inliers


def test_ransac_finds_a_known_pose_among_outliers():
    rng = np.random.default_rng(3)
    src = rng.uniform(-20, 20, size=(300, 3))
    yaw = np.radians(70.0)
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, [4.0, -2.0, 0.5]
    dst = src @ R.T + T[:3, 3] + rng.normal(0, 0.05, size=src.shape)
    feats = rng.normal(size=(300, 16))
    dst_feats = feats.copy()
    wrong = rng.permutation(300)[:210]  # 70% of the matches point elsewhere
    dst_feats[wrong] = feats[np.roll(wrong, 1)]
    res = ransac_pose(src, feats, dst, dst_feats)
    assert res.localized and 80 <= res.inliers <= 100
    assert translation_error(res.T_target_source, T) < 0.1
    assert rotation_error_deg(res.T_target_source[:3, :3], R) < 0.5
    # all-outlier matches: no pose with enough inliers
    shuffled = feats[rng.permutation(300)]
    assert not ransac_pose(src, feats, dst, shuffled).localized


ICP_VARIANTS = {
    "default (numba point-to-plane, 0.6 m source voxels)": {},
    "small_gicp point-to-plane, 0.6 m source voxels": {"icp_backend": "small_gicp"},
    "small_gicp point-to-point, every point": {
        "icp_backend": "small_gicp",
        "icp_method": "point_to_point",
        "icp_source_voxel_m": 0.0,
    },
    "Open3D point-to-point, every point (the earlier path)": {
        "icp_backend": "open3d",
        "icp_method": "point_to_point",
        "icp_source_voxel_m": 0.0,
        "ransac_first_batch": 1000,
    },
    "Open3D point-to-plane": {"icp_backend": "open3d"},
    "numba point-to-point, every point": {"icp_method": "point_to_point", "icp_source_voxel_m": 0},
}


@pytest.mark.parametrize("settings", list(ICP_VARIANTS.values()), ids=list(ICP_VARIANTS))
def test_icp_refines_and_verifies(pair, settings):
    src, dst, src_cloud, dst_cloud, T_gt = pair
    cfg = PoseConfig(**settings)
    res = ransac_pose(src.keypoints, src.local_features, dst.keypoints, dst.local_features, cfg)
    before = translation_error(res.T_target_source, T_gt)
    res = refine_icp(res, src_cloud, dst_cloud, cfg)
    assert res.refined and res.localized, res.reason
    assert res.icp["fitness"] >= cfg.min_icp_fitness
    assert translation_error(res.T_target_source, T_gt) <= before
    assert translation_error(res.T_target_source, T_gt) < 0.1
    assert rotation_error_deg(res.T_target_source[:3, :3], T_gt[:3, :3]) < 1.0


def test_icp_backends_agree_on_the_fit(pair):
    """Fitness and RMSE mean the same in every implementation: over every point of the
    query cloud under the final pose (within 1 % and 2 cm here)."""
    src, dst, src_cloud, dst_cloud, _ = pair
    fits = {}
    for name, settings in ICP_VARIANTS.items():
        cfg = PoseConfig(**settings)
        res = ransac_pose(src.keypoints, src.local_features, dst.keypoints, dst.local_features)
        fits[name] = refine_icp(res, src_cloud, dst_cloud, cfg).icp
    fitness = [f["fitness"] for f in fits.values()]
    rmse = [f["inlier_rmse"] for f in fits.values()]
    pinned = [f["constraint"] for f in fits.values()]
    assert max(fitness) - min(fitness) < 0.01, fits
    assert max(rmse) - min(rmse) < 0.02, fits
    assert max(pinned) - min(pinned) < 0.01 and min(pinned) > 0.1, fits  # a street corner


@pytest.mark.parametrize("backend", ["small_gicp", "numba"])
def test_a_prepared_target_gives_the_same_answer(pair, backend):
    src, dst, src_cloud, dst_cloud, _ = pair
    cfg = PoseConfig(icp_backend=backend)
    a = ransac_pose(src.keypoints, src.local_features, dst.keypoints, dst.local_features, cfg)
    b = ransac_pose(src.keypoints, src.local_features, dst.keypoints, dst.local_features, cfg)
    a = refine_icp(a, src_cloud, dst_cloud, cfg)
    b = refine_icp(b, src_cloud, dst_cloud, cfg, IcpTarget(dst_cloud, backend))
    assert np.array_equal(a.T_target_source, b.T_target_source)
    assert a.icp == b.icp and a.icp["iterations"] >= 1


@pytest.mark.parametrize("backend", ["numba", "small_gicp", "open3d"])
def test_the_coarse_stage_pulls_a_rough_estimate_into_the_fit(pair, backend):
    """Started 2 m off along the street (a RANSAC estimate from a few inliers), ICP with
    1 m correspondences settles 2 m off, where a good share of the scan still fits; the
    coarse stage at 3 m first brings it to the truth, with a better fitness."""
    _, _, src_cloud, dst_cloud, T_gt = pair
    start = planar_pose(2.0, 0.0, 0.0) @ T_gt
    fits = {}
    for coarse in (0.0, 3.0):
        cfg = PoseConfig(icp_backend=backend, icp_coarse_m=coarse)
        assert len(icp_stages(cfg)) == (2 if coarse else 1)
        res = PoseResult(start.copy(), 40, 12, 0.3, 0.2, "localized", "")
        res = refine_icp(res, src_cloud, dst_cloud, cfg)
        fits[coarse] = (translation_error(res.T_target_source, T_gt), res.icp["fitness"])
    assert fits[0.0][0] > 1.5 and fits[3.0][0] < 0.1, fits
    assert fits[3.0][1] > fits[0.0][1] + 0.1, fits
    assert PoseConfig().icp_coarse_m == 3.0  # on by default for new maps
    assert icp_stages(PoseConfig(icp_coarse_m=1.0)) == [(1.0, 30)]  # not wider: one stage


@pytest.mark.parametrize("settings", list(ICP_VARIANTS.values()), ids=list(ICP_VARIANTS))
def test_icp_rejects_a_wrong_pose(pair, settings):
    _, _, src_cloud, dst_cloud, T_gt = pair
    wrong = T_gt.copy()
    wrong[:3, 3] += [20.0, -15.0, 0.0]  # beyond the reach of the coarse stage (3 m)
    res = ransac_pose(np.zeros((0, 3)), np.zeros((0, 33)), np.zeros((0, 3)), np.zeros((0, 33)))
    assert not res.localized and "too few keypoints" in res.reason
    res.T_target_source = wrong
    res.inliers = 12  # as if RANSAC had held a (wrong) hypothesis
    res = refine_icp(res, src_cloud, dst_cloud, PoseConfig(**settings))
    assert not res.localized
    assert "min_icp_fitness" in res.reason


def test_icp_from_no_ransac_hypothesis_is_not_localized(pair):
    """However well ICP fits from where it started, without a RANSAC hypothesis (fewer
    than ransac_n inliers) the pose is not an estimate of the place."""
    _, _, src_cloud, dst_cloud, T_gt = pair
    cfg = PoseConfig()
    res = PoseResult(T_gt.copy(), 40, cfg.ransac_n - 1, 0.05, 0.3, "not_localized", "")
    res = refine_icp(res, src_cloud, dst_cloud, cfg)
    assert res.icp["fitness"] >= cfg.min_icp_fitness  # the fit itself is good
    assert not res.localized and "no hypothesis" in res.reason
    res = PoseResult(T_gt.copy(), 40, cfg.ransac_n, 0.1, 0.3, "not_localized", "")
    assert refine_icp(res, src_cloud, dst_cloud, cfg).localized


def test_ransac_batches_stop_early_on_an_easy_match(pair):
    """The first batch of 64 hypotheses settles a clean match: the same pose as batches
    of 1000 within a few centimetres."""
    src, dst, *_ = pair
    args = (src.keypoints, src.local_features, dst.keypoints, dst.local_features)
    small = ransac_pose(*args, PoseConfig())
    large = ransac_pose(*args, PoseConfig(ransac_first_batch=1000))
    assert small.localized and large.localized
    assert translation_error(small.T_target_source, large.T_target_source) < 0.1
    assert small.inliers >= 0.9 * large.inliers


def test_fgr_runs_on_the_same_matches(pair):
    src, dst, _, _, T_gt = pair
    res = fgr_pose(src.keypoints, src.local_features, dst.keypoints, dst.local_features)
    assert is_rigid(res.T_target_source)
    assert 0 <= res.inliers <= res.num_correspondences


def test_synthetic_transform_exact():
    rng = np.random.default_rng(0)
    src = rng.uniform(-20, 20, (300, 3))
    feats = rng.normal(size=(300, 33))
    a = np.radians(40)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = [1.0, 2.0, 0.3]
    dst = src @ T[:3, :3].T + T[:3, 3]
    dst_feats = feats.copy()
    dst_feats[100:] = rng.normal(size=(200, 33))  # two thirds of the matches are wrong
    res = ransac_pose(src, feats, dst, dst_feats)
    assert res.localized
    assert np.allclose(res.T_target_source, T, atol=1e-6)
    assert 100 <= res.inliers <= 110  # a random match may land within 0.5 m by chance


def test_shape_errors_and_rigidity_checks():
    with pytest.raises(InputError, match="source keypoints"):
        ransac_pose(np.zeros((5, 2)), np.zeros((5, 33)), np.zeros((5, 3)), np.zeros((5, 33)))
    with pytest.raises(InputError, match="target features"):
        ransac_pose(np.zeros((5, 3)), np.zeros((5, 33)), np.zeros((5, 3)), np.zeros((4, 33)))
    scaled = np.eye(4)
    scaled[:3, :3] *= 2.0
    with pytest.raises(InputError, match="not a rigid transform"):
        check_rigid(scaled, "T_map_sensor")
    reflect = np.diag([1.0, 1.0, -1.0, 1.0])
    assert not is_rigid(reflect)
    with pytest.raises(InputError, match="4x4"):
        check_rigid(np.eye(3), "T")


@pytest.mark.parametrize("block", [2**20, 37])
@pytest.mark.parametrize("mutual", [True, False])
def test_feature_matching_equals_a_kd_tree_search(pair, monkeypatch, block, mutual):
    """Nearest neighbours by one matrix product (in blocks of rows) are the KD-tree's."""
    from scipy.spatial import cKDTree

    from sgvloc.core import pose

    monkeypatch.setattr(pose, "_FEATURE_BLOCK", block)
    src, dst, *_ = pair
    a, b = src.local_features[:900], dst.local_features[:700]
    fwd = cKDTree(b).query(a, k=1)[1]
    want = np.stack([np.arange(len(a)), fwd], axis=1)
    if mutual:
        back = cKDTree(a).query(b, k=1)[1]
        want = want[back[fwd] == want[:, 0]]
    got = pose.feature_correspondences(a, b, mutual)
    assert np.array_equal(got, want) and len(got) > 50
    assert pose.feature_correspondences(a[:0], b, mutual).shape == (0, 2)


def _corridor(rng: np.random.Generator, n: int = 6000, closed: bool = False) -> np.ndarray:
    """Ground and two long walls along x, 6 m apart; ``closed``: a wall across the end
    (x = 15 m) as well."""
    k = n // 3
    ground = np.c_[rng.uniform(-30, 30, k), rng.uniform(-3, 3, k), rng.normal(0, 0.01, k)]
    left = np.c_[rng.uniform(-30, 30, k), np.full(k, 3.0), rng.uniform(0, 4, k)]
    right = np.c_[rng.uniform(-30, 30, k), np.full(k, -3.0), rng.uniform(0, 4, k)]
    parts = [ground, left, right]
    if closed:
        parts.append(np.c_[np.full(k, 15.0), rng.uniform(-3, 3, k), rng.uniform(0, 4, k)])
    return np.vstack(parts)


@pytest.mark.parametrize("backend", ["numba", "small_gicp", "open3d"])
def test_a_fit_along_a_corridor_is_not_a_position(backend):
    """Seen along a corridor, the scan fits as well 8 m further on: ICP's fitness is high
    either way, the constraint on the free direction is near 0 and the pose step says
    so; with a wall across the corridor the position is pinned down."""
    rng = np.random.default_rng(7)
    cfg = PoseConfig(icp_backend=backend)
    for closed, start_m in ((False, 8.0), (True, 0.5)):  # the truth is the identity
        world = _corridor(rng, closed=closed)
        scan = world[np.abs(world[:, 0]) < 20]
        scan = scan + rng.normal(0, 0.02, scan.shape)
        res = PoseResult(planar_pose(start_m, 0.0, 0.0), 40, 12, 0.3, 0.2, "localized", "")
        res = refine_icp(res, scan, world, cfg)
        assert res.icp["fitness"] > 0.75, res.icp
        if closed:
            assert res.icp["constraint"] > 0.1, res.icp
            assert res.localized, res.reason
            assert translation_error(res.T_target_source, np.eye(4)) < 0.2
            continue
        assert res.icp["constraint"] < 0.02 < cfg.min_icp_constraint, res.icp
        assert not res.localized and "min_icp_constraint" in res.reason
        assert translation_error(res.T_target_source, np.eye(4)) > 5.0  # wrong, yet it fits
        # the floor off: the fitness alone would have accepted it
        res = PoseResult(planar_pose(start_m, 0.0, 0.0), 40, 12, 0.3, 0.2, "localized", "")
        loose = PoseConfig(icp_backend=backend, min_icp_constraint=0.0)
        assert refine_icp(res, scan, world, loose).localized


def test_the_constraint_is_the_weakest_direction_of_the_normals():
    assert constraint(None) is None
    assert constraint(np.diag([0.5, 0.5, 0.0])) == 0.0  # nothing along z
    assert constraint(np.eye(3) / 3.0) == pytest.approx(1.0 / 3.0)
    # turned: the same spread in other axes
    R = planar_pose(0.0, 0.0, 30.0)[:3, :3]
    assert constraint(R @ np.diag([0.6, 0.3, 0.1]) @ R.T) == pytest.approx(0.1)
