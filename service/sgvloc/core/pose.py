"""Pose estimation: RANSAC on local-feature correspondences, optional ICP refinement.

Frames are named as in ``T_target_source``: the transform that maps points of the source
(the query scan) into the target (the keyframe), 4x4 float64. The map pose of the query is
``T_map_sensor = T_map_keyframe @ T_keyframe_sensor``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import cores, icp_numba
from .config import PoseConfig
from .deadline import check as check_deadline
from .errors import InputError
from .o3d import open3d
from .preprocess import voxel_centroids

log = logging.getLogger(__name__)


@dataclass
class PoseResult:
    """Outcome of registering a source to a target, with diagnostics.

    ``verdict`` is ``"localized"`` when the estimate passes the configured inlier-count and
    fitness thresholds, otherwise ``"not_localized"`` with ``reason`` saying why.
    ``fitness`` is the share of correspondences that are inliers; ``inlier_rmse`` is in
    metres. ``refined`` tells whether ICP ran and converged into ``T_target_source``.
    """

    T_target_source: np.ndarray
    num_correspondences: int
    inliers: int
    fitness: float
    inlier_rmse: float
    verdict: str
    reason: str
    refined: bool = False
    icp: dict = field(default_factory=dict)

    @property
    def localized(self) -> bool:
        return self.verdict == "localized"


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle of a rotation matrix (degrees, 0..180), from its sine and cosine: accurate
    near 0, where ``arccos`` of the trace turns rounding of 1e-16 into angles of 1e-6 deg."""
    sin = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    cos = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arctan2(sin, cos)))


def is_rigid(T: np.ndarray, tol: float = 1e-4) -> bool:
    """True if ``T`` is a 4x4 rigid transform (orthonormal R with det +1, last row 0 0 0 1)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        return False
    R = T[:3, :3]
    return (
        np.allclose(R.T @ R, np.eye(3), atol=tol)
        and abs(np.linalg.det(R) - 1.0) < tol
        and np.allclose(T[3], [0, 0, 0, 1], atol=tol)
    )


#: the largest translation a pose may have (m): beyond any map frame on Earth (ECEF
#: coordinates are below 6.4e6 m); larger ones overflow spatial indexes downstream
MAX_TRANSLATION_M = 1e8


def check_rigid(T: np.ndarray, name: str) -> np.ndarray:
    """Return ``T`` as float64 4x4 or raise :class:`InputError` naming ``name``."""
    arr = np.asarray(T, dtype=np.float64)
    if arr.shape != (4, 4):
        raise InputError(f"{name} must be a 4x4 matrix, got shape {list(arr.shape)}")
    if not is_rigid(arr):
        raise InputError(
            f"{name} is not a rigid transform (rotation must be orthonormal with det +1 and "
            "the last row 0 0 0 1)"
        )
    if np.abs(arr[:3, 3]).max() > MAX_TRANSLATION_M:
        raise InputError(f"{name}: its translation is beyond {MAX_TRANSLATION_M:g} m")
    return arr


def to_cloud(points: np.ndarray):
    o3d = open3d()

    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))


#: entries of one block of the feature-distance matrix in :func:`feature_correspondences`
_FEATURE_BLOCK = 2**20


def feature_correspondences(
    src_feats: np.ndarray, dst_feats: np.ndarray, mutual: bool
) -> np.ndarray:
    """Nearest neighbours in feature space ``[C, 2]`` (src index, dst index), optionally mutual.

    Squared L2 distances ``|a|^2 + |b|^2 - 2 a.b`` in float64, a block of source rows at a
    time (at most ``_FEATURE_BLOCK`` entries, 8 MB); ties go to the lowest index. One
    matrix product: several times faster than a KD-tree in 33 to 64 dimensions.
    """
    a = np.asarray(src_feats, dtype=np.float64)
    b = np.asarray(dst_feats, dtype=np.float64)
    if len(a) == 0 or len(b) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    bb = np.einsum("ij,ij->i", b, b)  # [Nd]
    fwd = np.empty(len(a), dtype=np.int64)  # [Ns] nearest dst of each src
    back = np.zeros(len(b), dtype=np.int64)  # [Nd] nearest src of each dst
    back_d2 = np.full(len(b), np.inf)
    cols = np.arange(len(b))
    rows = max(1, _FEATURE_BLOCK // len(b))
    for r0 in range(0, len(a), rows):
        blk = a[r0 : r0 + rows]
        d2 = np.einsum("ij,ij->i", blk, blk)[:, None] + bb[None, :] - 2.0 * (blk @ b.T)
        fwd[r0 : r0 + rows] = d2.argmin(axis=1)
        if mutual:
            m = d2.argmin(axis=0)  # [Nd] within this block
            v = d2[m, cols]
            better = v < back_d2  # strictly: an earlier block keeps a tie
            back_d2[better], back[better] = v[better], m[better] + r0
    pairs = np.stack([np.arange(len(a)), fwd], axis=1)
    if mutual:
        pairs = pairs[back[fwd] == pairs[:, 0]]
    return pairs.astype(np.int64)


def inlier_ratio(
    src: np.ndarray, dst: np.ndarray, T_dst_src: np.ndarray, max_distance: float
) -> tuple[int, float, float]:
    """Inliers among paired points ``src[i] <-> dst[i]`` under ``T``: (count, ratio, rmse)."""
    if len(src) == 0:
        return 0, 0.0, 0.0
    moved = src @ T_dst_src[:3, :3].T + T_dst_src[:3, 3]
    err = np.linalg.norm(moved - dst, axis=1)
    ok = err <= max_distance
    n_in = int(ok.sum())
    rmse = float(np.sqrt(np.mean(err[ok] ** 2))) if n_in else 0.0
    return n_in, n_in / len(src), rmse


def _validate(name: str, kp: np.ndarray, feats: np.ndarray) -> None:
    if kp.ndim != 2 or kp.shape[1] != 3:
        raise InputError(f"{name} keypoints must have shape [N, 3], got {list(kp.shape)}")
    if feats.ndim != 2 or feats.shape[0] != kp.shape[0]:
        raise InputError(f"{name} features must have one row per keypoint")


def _not_localized(n_corr: int, reason: str) -> PoseResult:
    return PoseResult(np.eye(4), n_corr, 0, 0.0, 0.0, "not_localized", reason)


Estimator = Callable[[np.ndarray, np.ndarray, np.ndarray, PoseConfig], np.ndarray]


def _register(
    estimate: Estimator,
    src_kp: np.ndarray,
    src_feats: np.ndarray,
    dst_kp: np.ndarray,
    dst_feats: np.ndarray,
    cfg: PoseConfig | None,
) -> PoseResult:
    """Match features, run ``estimate(src, dst, pairs, cfg) -> T``, score the inliers."""
    cfg = cfg or PoseConfig()
    src_kp, dst_kp = np.asarray(src_kp, np.float64), np.asarray(dst_kp, np.float64)
    src_feats, dst_feats = np.asarray(src_feats), np.asarray(dst_feats)
    _validate("source", src_kp, src_feats)
    _validate("target", dst_kp, dst_feats)
    if min(len(src_kp), len(dst_kp)) < cfg.ransac_n:
        return _not_localized(
            0, f"too few keypoints to register (source {len(src_kp)}, target {len(dst_kp)})"
        )
    # 1. correspondences: nearest neighbours in feature space (mutual if configured)
    pairs = feature_correspondences(src_feats, dst_feats, cfg.mutual_filter)  # [C, 2]
    if len(pairs) < cfg.ransac_n:
        return _not_localized(
            len(pairs), f"only {len(pairs)} feature correspondences survive the mutual filter"
        )
    # 2. robust estimate over the correspondences
    T = estimate(src_kp, dst_kp, pairs, cfg)
    # 3. inliers among the correspondences under that estimate
    n_in, ratio, rmse = inlier_ratio(
        src_kp[pairs[:, 0]], dst_kp[pairs[:, 1]], T, cfg.max_correspondence_distance
    )
    return judge(T, len(pairs), n_in, ratio, rmse, cfg)


def kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid fits of batches of paired points ``[B, n, 3]`` -> ``R`` ``[B, 3, 3]``
    and ``t`` ``[B, 3]`` with ``dst ~ src @ R.T + t`` (proper rotations, det +1)."""
    cs, cd = src.mean(axis=1), dst.mean(axis=1)
    H = np.einsum("bni,bnj->bij", src - cs[:, None], dst - cd[:, None])  # [B, 3, 3]
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, 1, 2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, 1, 2)))
    V[:, :, 2] *= np.where(d == 0, 1.0, d)[:, None]
    R = V @ np.swapaxes(U, 1, 2)
    return R, cd - np.einsum("bij,bj->bi", R, cs)


def _ransac(src: np.ndarray, dst: np.ndarray, pairs: np.ndarray, cfg: PoseConfig) -> np.ndarray:
    """Seeded RANSAC over correspondences (deterministic: the same inputs, the same pose).

    Hypotheses from ``ransac_n`` distinct correspondences, drawn in batches; a sample is
    kept when every pair of its points has lengths within ``edge_length_ratio`` in both
    clouds and its fit moves each sampled point within ``max_correspondence_distance`` of
    its partner (the checkers of the SpectralGV reference code). The best hypothesis has
    the most inliers (then the smallest squared error); the loop stops at
    ``max_iterations`` or once ``confidence`` is reached for the best inlier share,
    checked after each batch (``ransac_first_batch`` hypotheses, then twice as many each
    time up to 1000, so that an easy match stops after a few dozen). The result is
    refitted on its inliers unless that loses inliers.
    """
    ps, pd = src[pairs[:, 0]], dst[pairs[:, 1]]  # [C, 3]
    C, n = len(pairs), cfg.ransac_n
    thr2 = cfg.max_correspondence_distance**2
    ratio = cfg.edge_length_ratio
    iu, ju = np.triu_indices(n, 1)
    rng = np.random.default_rng(cfg.seed)
    batch = int(max(16, min(1000, 4_000_000 // max(C, 1))))  # [batch, C] stays small
    best = (-1, np.inf)  # (inliers, squared error)
    best_T = np.eye(4)
    done, needed, size = 0, cfg.max_iterations, cfg.ransac_first_batch
    while done < needed:
        check_deadline("RANSAC")
        b = min(size, batch, needed - done)
        size *= 2
        done += b
        idx = rng.integers(0, C, size=(b, n))  # [b, n]
        s, d = ps[idx], pd[idx]  # [b, n, 3]
        ls = np.linalg.norm(s[:, iu] - s[:, ju], axis=2)  # [b, pairs]
        ld = np.linalg.norm(d[:, iu] - d[:, ju], axis=2)
        ok = ((ls >= ratio * ld) & (ld >= ratio * ls) & (ls > 0)).all(axis=1)
        srt = np.sort(idx, axis=1)
        ok &= (srt[:, 1:] != srt[:, :-1]).all(axis=1)  # distinct correspondences
        if not ok.any():
            continue
        s, d = s[ok], d[ok]
        R, t = kabsch(s, d)
        fit = ((np.einsum("bij,bnj->bni", R, s) + t[:, None] - d) ** 2).sum(axis=2)
        keep = (fit <= thr2).all(axis=1)
        if not keep.any():
            continue
        R, t = R[keep], t[keep]
        err = ((np.einsum("bij,cj->bci", R, ps) + t[:, None] - pd) ** 2).sum(axis=2)  # [b', C]
        inl = err <= thr2
        count = inl.sum(axis=1)
        sse = np.where(inl, err, 0.0).sum(axis=1)
        top = np.lexsort((sse, -count))[0]
        if (count[top], -sse[top]) > (best[0], -best[1]):
            best = (int(count[top]), float(sse[top]))
            best_T = np.eye(4)
            best_T[:3, :3], best_T[:3, 3] = R[top], t[top]
            w = best[0] / C
            if w >= 1.0:
                break
            miss = 1.0 - w**n
            if cfg.confidence < 1.0 and 0.0 < miss < 1.0:
                needed = min(
                    cfg.max_iterations, int(np.ceil(np.log(1 - cfg.confidence) / np.log(miss)))
                )
    if best[0] < n:
        return best_T
    moved = ps @ best_T[:3, :3].T + best_T[:3, 3]
    inl = ((moved - pd) ** 2).sum(axis=1) <= thr2
    R, t = kabsch(ps[inl][None], pd[inl][None])
    refit = np.eye(4)
    refit[:3, :3], refit[:3, 3] = R[0], t[0]
    moved = ps @ refit[:3, :3].T + refit[:3, 3]
    if int((((moved - pd) ** 2).sum(axis=1) <= thr2).sum()) >= best[0]:
        return refit
    return best_T


def _fgr(src: np.ndarray, dst: np.ndarray, pairs: np.ndarray, cfg: PoseConfig) -> np.ndarray:
    o3d = open3d()

    reg = o3d.pipelines.registration
    o3d.utility.random.seed(cfg.seed)
    option = reg.FastGlobalRegistrationOption(
        use_absolute_scale=True, maximum_correspondence_distance=cfg.max_correspondence_distance
    )
    result = reg.registration_fgr_based_on_correspondence(
        to_cloud(src), to_cloud(dst), o3d.utility.Vector2iVector(pairs.astype(np.int32)), option
    )
    return np.asarray(result.transformation, dtype=np.float64).copy()


def ransac_pose(
    src_kp: np.ndarray,
    src_feats: np.ndarray,
    dst_kp: np.ndarray,
    dst_feats: np.ndarray,
    cfg: PoseConfig | None = None,
) -> PoseResult:
    """RANSAC registration of source keypoints onto target keypoints via feature matching.

    Reference settings (docs/EVALUATION.md): mutual filter, 0.5 m max correspondence distance,
    3-point samples, edge-length (0.8) and distance checkers, 10000 iterations, 0.999
    confidence. Seeded and deterministic (:func:`_ransac`).
    """
    return _register(_ransac, src_kp, src_feats, dst_kp, dst_feats, cfg)


def fgr_pose(
    src_kp: np.ndarray,
    src_feats: np.ndarray,
    dst_kp: np.ndarray,
    dst_feats: np.ndarray,
    cfg: PoseConfig | None = None,
) -> PoseResult:
    """Fast Global Registration (Open3D) on the same feature matches as :func:`ransac_pose`."""
    return _register(_fgr, src_kp, src_feats, dst_kp, dst_feats, cfg)


def judge(
    T: np.ndarray, n_corr: int, n_in: int, ratio: float, rmse: float, cfg: PoseConfig
) -> PoseResult:
    """Wrap an estimate in a :class:`PoseResult` with its verdict from the thresholds."""
    if n_in < cfg.min_inliers:
        verdict, reason = "not_localized", f"{n_in} inliers < min_inliers {cfg.min_inliers}"
    elif ratio < cfg.min_fitness:
        verdict, reason = "not_localized", f"fitness {ratio:.3f} < min_fitness {cfg.min_fitness}"
    else:
        verdict, reason = "localized", f"{n_in} of {n_corr} correspondences are inliers"
    return PoseResult(T, n_corr, n_in, ratio, rmse, verdict, reason)


#: neighbours per point for the keyframe cloud's normals (point-to-plane ICP)
NORMAL_NEIGHBOURS = 10


class IcpTarget:
    """A keyframe cloud ready for :func:`refine_icp`, built once and reused by every
    localization against that keyframe: its normals (from :data:`NORMAL_NEIGHBOURS`
    neighbours) and the index ``backend`` searches: small_gicp's KD-tree and normals
    (about 0.3 MB for 5k points), or for ``"numba"`` the tree of
    :mod:`sgvloc.core.icp_numba` with the normals of :func:`sgvloc.core.gicp_numba.normals`
    (the same to 1e-9) in its order (about 0.25 MB), built without the interpreter lock."""

    def __init__(self, cloud: np.ndarray, backend: str = "small_gicp") -> None:
        self.source = cloud  # kept alive: the localizer caches targets by its id()
        self.numba: icp_numba.Tree | None = None
        self.cloud = self.tree = None
        if backend == "numba":  # the numba tree answers every search
            from .gicp_numba import normals

            tree = icp_numba.Tree(cloud)
            tree.normals = normals(tree.points, *tree.nodes, NORMAL_NEIGHBOURS)
            self.numba = tree
            return
        import small_gicp

        self.cloud = small_gicp.PointCloud(np.asarray(cloud, dtype=np.float64))
        self.tree = small_gicp.KdTree(self.cloud, num_threads=1)
        small_gicp.estimate_normals(
            self.cloud, self.tree, num_neighbors=NORMAL_NEIGHBOURS, num_threads=1
        )


def _fit_quality(
    tree: Any, pts: np.ndarray, T: np.ndarray, max_distance: float, normals: Any = None
) -> tuple[float, float, np.ndarray | None]:
    """(fitness, RMSE, moment) of every point under ``T`` against a small_gicp ``KdTree``:
    the share with a target point within ``max_distance``, the RMS distance of those, and
    with the target's ``normals`` ``[M, 3+]`` the mean ``n n^T`` of the normals of their
    nearest target points (else None), as :meth:`sgvloc.core.icp_numba.Tree.fit_quality`
    gives. One query per point, on the spare cores (:mod:`sgvloc.core.cores`), with the
    same answer at any thread count."""
    moved = pts @ T[:3, :3].T + T[:3, 3]
    idx, sq = tree.batch_nearest_neighbor_search(moved, num_threads=cores.threads())
    sq = np.asarray(sq, dtype=np.float64)
    inl = sq <= max_distance**2
    if not inl.any():
        return 0.0, 0.0, None
    moment = None
    if normals is not None:
        n = np.asarray(normals)[np.asarray(idx)[inl], :3]
        moment = n.T @ n / len(n)
    return float(inl.mean()), float(np.sqrt(sq[inl].mean())), moment


def constraint(moment: np.ndarray | None) -> float | None:
    """How well an ICP fit pins the position down in its weakest direction: the smallest
    eigenvalue of the mean ``n n^T`` of the matched target normals, from 0 (the matched
    surfaces leave one direction of translation free: a corridor seen along its axis,
    open ground) to 1/3 (normals spread evenly over all directions). The translational
    block of point-to-plane ICP's information matrix, per point. None without a moment."""
    if moment is None:
        return None
    return float(max(np.linalg.eigvalsh(moment)[0], 0.0))


def icp_stages(cfg: PoseConfig) -> list[tuple[float, int]]:
    """The ICP stages as ``(correspondence distance m, iterations)``: the coarse stage
    (``icp_coarse_m``) when it is wider than ``icp_max_distance``, then the fine one."""
    fine = (cfg.icp_max_distance, cfg.icp_iterations)
    if cfg.icp_coarse_m > cfg.icp_max_distance:
        return [(cfg.icp_coarse_m, cfg.icp_coarse_iterations), fine]
    return [fine]


def _icp_small_gicp(
    src: np.ndarray, target: IcpTarget, T0: np.ndarray, cfg: PoseConfig
) -> tuple[np.ndarray, float, float, np.ndarray | None, int]:
    import small_gicp

    pts = np.asarray(src, dtype=np.float64)
    source = (
        small_gicp.voxelgrid_sampling(pts, cfg.icp_source_voxel_m, num_threads=1)
        if cfg.icp_source_voxel_m > 0
        else small_gicp.PointCloud(pts)
    )
    T, iterations = np.asarray(T0, dtype=np.float64), 0
    for distance, max_iterations in icp_stages(cfg):
        res = small_gicp.align(
            target.cloud,
            source,
            target.tree,
            init_T_target_source=T,
            registration_type="PLANE_ICP" if cfg.icp_method == "point_to_plane" else "ICP",
            max_correspondence_distance=distance,
            max_iterations=max_iterations,
            translation_epsilon=cfg.icp_stop_m,
            rotation_epsilon=math.radians(cfg.icp_stop_deg),
            num_threads=1,
        )
        T = np.asarray(res.T_target_source, dtype=np.float64).copy()
        iterations += int(res.iterations)
    fit = _fit_quality(target.tree, pts, T, cfg.icp_max_distance, target.cloud.normals())
    return (T, *fit, iterations)


def _icp_numba(
    src: np.ndarray, target: IcpTarget, T0: np.ndarray, cfg: PoseConfig
) -> tuple[np.ndarray, float, float, np.ndarray | None, int]:
    tree = target.numba
    assert tree is not None, "an IcpTarget built for the numba backend"
    pts = np.asarray(src, dtype=np.float64)
    source = voxel_centroids(src, cfg.icp_source_voxel_m) if cfg.icp_source_voxel_m > 0 else pts
    T, iterations = T0, 0
    for distance, max_iterations in icp_stages(cfg):
        T, n = tree.align(
            source,
            T,
            distance,
            max_iterations,
            cfg.icp_stop_m,
            math.radians(cfg.icp_stop_deg),
            plane=cfg.icp_method == "point_to_plane",
        )
        iterations += n
    return (T, *tree.fit_quality(pts, T, cfg.icp_max_distance), iterations)


def _icp_open3d(
    src: np.ndarray, dst: np.ndarray, T0: np.ndarray, cfg: PoseConfig
) -> tuple[np.ndarray, float, float, np.ndarray | None, int]:
    o3d = open3d()

    reg = o3d.pipelines.registration
    source, target = to_cloud(src), to_cloud(dst)
    if cfg.icp_method == "point_to_plane":
        target.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBOURS))
        estimation = reg.TransformationEstimationPointToPlane()
    else:
        estimation = reg.TransformationEstimationPointToPoint(False)
    if cfg.icp_source_voxel_m > 0:
        source = source.voxel_down_sample(cfg.icp_source_voxel_m)
    T = np.asarray(T0, dtype=np.float64)
    for distance, max_iterations in icp_stages(cfg):
        icp = reg.registration_icp(
            source,
            target,
            distance,
            T,
            estimation,
            reg.ICPConvergenceCriteria(max_iteration=max_iterations),
        )
        T = np.asarray(icp.transformation, dtype=np.float64).copy()
    # the normals' moment as the other backends measure it (small_gicp's normals)
    indexed = IcpTarget(dst)
    moment = _fit_quality(
        indexed.tree, np.asarray(src, np.float64), T, cfg.icp_max_distance, indexed.cloud.normals()
    )[2]
    if cfg.icp_source_voxel_m > 0:  # fitness and RMSE over every point, as documented
        ev = reg.evaluate_registration(to_cloud(src), target, cfg.icp_max_distance, T)
        return T, float(ev.fitness), float(ev.inlier_rmse), moment, -1
    return T, float(icp.fitness), float(icp.inlier_rmse), moment, -1


def refine_icp(
    result: PoseResult,
    src_cloud: np.ndarray,
    dst_cloud: np.ndarray,
    cfg: PoseConfig,
    target: IcpTarget | None = None,
) -> PoseResult:
    """ICP from the RANSAC estimate on the clouds (the encoder's voxel clouds).

    Sparse keypoint matches often give a roughly right pose with few inliers; ICP on the
    clouds both sharpens it and verifies it far better than the keypoint inlier count.
    So once ICP has run the verdict is taken from its fitness (the share of the query
    cloud's points with a keyframe point within ``icp_max_distance`` under the final
    pose) against ``min_icp_fitness``, provided RANSAC found a hypothesis at all (at
    least ``ransac_n`` inliers) for ICP to start from. The error is ``icp_method``
    (point-to-plane by default), iterated on the query cloud downsampled to
    ``icp_source_voxel_m``, first with the coarse correspondence distance
    ``icp_coarse_m`` (:func:`icp_stages`), then with ``icp_max_distance``;
    ``icp_backend`` picks the implementation. A fit that leaves
    the position free along one direction (:func:`constraint` below
    ``min_icp_constraint``) is not localized either, however high its fitness. With small_gicp,
    ``target`` is the keyframe cloud already indexed (:class:`IcpTarget`; built here when
    not given). Diagnostics go to ``result.icp``.
    """
    if len(src_cloud) < 3 or len(dst_cloud) < 3:
        result.icp = {"used": False, "why": "clouds too small for ICP"}
        return result
    T0 = result.T_target_source
    if cfg.icp_backend == "open3d":
        T, fitness, rmse, moment, iterations = _icp_open3d(src_cloud, dst_cloud, T0, cfg)
    elif cfg.icp_backend == "numba":
        if target is None or target.numba is None:
            target = IcpTarget(dst_cloud, "numba")
        T, fitness, rmse, moment, iterations = _icp_numba(src_cloud, target, T0, cfg)
    else:
        if target is None or target.tree is None:
            target = IcpTarget(dst_cloud)
        T, fitness, rmse, moment, iterations = _icp_small_gicp(src_cloud, target, T0, cfg)
    pinned = constraint(moment)
    result.icp = {"used": True, "fitness": fitness, "inlier_rmse": rmse, "constraint": pinned}
    if iterations >= 0:
        result.icp["iterations"] = iterations
    result.refined = True
    result.T_target_source = T
    if result.inliers < cfg.ransac_n:
        # no RANSAC hypothesis held: ICP started from an arbitrary pose, and a fit found
        # from there (on ground alone, say) is no evidence of the place
        result.verdict = "not_localized"
        result.reason = (
            f"RANSAC found no hypothesis ({result.inliers} inliers < ransac_n "
            f"{cfg.ransac_n}); ICP fitness {fitness:.2f} from its starting pose"
        )
    elif fitness < cfg.min_icp_fitness:
        result.verdict = "not_localized"
        result.reason = f"ICP fitness {fitness:.2f} < min_icp_fitness {cfg.min_icp_fitness}"
    elif (pinned or 0.0) < cfg.min_icp_constraint:
        # a fit along a corridor or over open ground is as good anywhere along the free
        # direction: its fitness says nothing of where along it the scan was taken
        result.verdict = "not_localized"
        result.reason = (
            f"ICP constraint {pinned or 0.0:.3f} < min_icp_constraint "
            f"{cfg.min_icp_constraint}: the matched surfaces leave the position free along "
            "one direction (a corridor seen along its axis, open ground)"
        )
    else:
        result.verdict = "localized"
        result.reason = (
            f"ICP fitness {fitness:.2f} (rmse {rmse:.2f} m, constraint {pinned or 0.0:.3f}) "
            "after RANSAC"
        )
    return result
