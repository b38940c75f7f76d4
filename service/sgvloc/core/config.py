"""One typed configuration tree for the engine (pydantic).

Every stage reads its own section; the defaults are the ones docs/API.md documents.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class PreprocessConfig(_Section):
    """Scan clean-up before encoding."""

    min_range: float = Field(0.5, ge=0.0, le=1000.0, description="drop points closer than this (m)")
    max_range: float = Field(
        60.0, gt=0.0, le=1000.0, description="drop points farther than this (m)"
    )
    voxel_size: float = Field(
        0.3, ge=0.0, le=100.0, description="voxel downsampling size (m); 0 = off"
    )
    remove_ground: bool = Field(False, description="remove the dominant ground plane")
    ground_distance: float = Field(
        0.2, gt=0.0, le=10.0, description="RANSAC plane inlier distance (m)"
    )
    ground_max_tilt_deg: float = Field(
        20.0, ge=0.0, le=90.0, description="only planes within this tilt of horizontal are ground"
    )

    @model_validator(mode="after")
    def _range(self) -> PreprocessConfig:
        if self.min_range >= self.max_range:  # every scan would be empty
            raise ValueError(
                f"min_range {self.min_range:g} must be below max_range {self.max_range:g}"
            )
        return self


class HandcraftedEncoderConfig(_Section):
    """Built-in encoder: ScanContext-style yaw-invariant global descriptor + FPFH keypoints."""

    num_keypoints: int = Field(512, ge=1, le=20000)
    fpfh_radius: float = Field(2.0, gt=0.0, le=50.0, description="FPFH feature radius (m)")
    normal_radius: float = Field(0.75, gt=0.0, le=50.0, description="normal estimation radius (m)")
    rings: int = Field(20, ge=2, le=256, description="radial bins of the polar grid")
    sectors: int = Field(60, ge=4, le=720, description="angular bins of the polar grid")
    max_radius: float = Field(40.0, gt=0.0, le=1000.0, description="polar grid radius (m)")
    seed: int = Field(0, ge=0, le=2**32 - 1)


#: the retrieval settings the index is built with
INDEX_SETTINGS = ("index", "nlist", "nprobe", "hnsw_m", "ef_search")


class RetrievalConfig(_Section):
    """FAISS index over global descriptors (inner product on L2-normalised vectors)."""

    index: Literal["flat", "ivf", "hnsw"] = "flat"
    nlist: int = Field(256, ge=1, le=65536, description="IVF: number of coarse cells")
    nprobe: int = Field(16, ge=1, le=65536, description="IVF: cells visited per search")
    hnsw_m: int = Field(32, ge=4, le=128, description="HNSW: neighbours per node")
    ef_search: int = Field(128, ge=1, le=4096, description="HNSW: search breadth")
    combine: Literal["merge", "concat"] = Field(
        "merge",
        description="a global descriptor of several blocks (learned 'polar+network'): "
        "'merge' retrieves top_k by each block's own similarity and unites them (each "
        "keyframe once, between top_k and blocks x top_k candidates, ordered by the whole "
        "descriptor's similarity); 'concat' retrieves top_k by the whole descriptor's "
        "similarity (the mean of the blocks' cosines)",
    )
    offset_m: float = Field(
        4.0,
        ge=0.0,
        le=20.0,
        description="a query's polar/FFT descriptor (learned and bev encoders) is "
        "also computed about `offsets` points this far from its sensor, on a circle, and "
        "each keyframe is retrieved by its best similarity over these centres: a revisit "
        "that passes a few metres to the side, or in the opposite direction, is still "
        "among the candidates; 0 = about the sensor only, as maps made before this "
        "setting do",
    )
    offsets: int = Field(8, ge=1, le=32, description="how many centres on the circle of `offset_m`")

    def index_settings(self) -> dict[str, Any]:
        """The settings the FAISS index is built with (:data:`INDEX_SETTINGS`); the others
        shape each query's search and may change on a stored map."""
        return {k: getattr(self, k) for k in INDEX_SETTINGS}

    def centres(self) -> np.ndarray | None:
        """The displaced centres ``[offsets, 2]`` (metres; the first straight ahead,
        then counter-clockwise), or None when ``offset_m`` is 0."""
        if self.offset_m <= 0.0:
            return None
        a = np.arange(self.offsets) * (2.0 * np.pi / self.offsets)
        return self.offset_m * np.column_stack([np.cos(a), np.sin(a)])


class SGVConfig(_Section):
    """Spectral Geometric Verification settings (see :mod:`sgvloc.core.sgv`)."""

    d_thr: float = Field(0.4, gt=0.0, le=100.0, description="compatibility length tolerance (m)")
    iterations: int = Field(5, ge=1, le=100, description="power iterations from all-ones")
    diagonal: Literal["one", "zero"] = Field("one", description="M_ii = 1 (reference) or 0")
    normalise: Literal["n", "none"] = Field(
        "n", description="'n': s = v^T M v / n (reference); 'none': raw v^T M v"
    )
    chunk_size: int = Field(
        2048, ge=16, le=65536, description="rows of M built at once for large n"
    )
    device: Literal["auto", "cpu", "cuda"] = "auto"
    backend: Literal["auto", "torch", "numba"] = Field(
        "auto",
        description="kernel: 'numba' (fused CPU kernel), 'torch' (batched, CPU or CUDA); "
        "'auto' = numba on CPU when importable, torch on CUDA",
    )
    tie_tolerance: float = Field(
        0.1,
        ge=0.0,
        lt=1.0,
        description="after re-ranking, one of the next 5 candidates whose score is within "
        "this fraction of the top-1's and whose SpectralGV pose puts the query at the same "
        "place (2 m, 5 deg) but at least tie_gain_m nearer to it takes the first place: "
        "the keyframe of that place with the most overlap for the pose step (sgvloc.core."
        "confidence.nearest_of_place); 0 keeps the scores' order, as maps made before this "
        "setting do",
    )
    tie_gain_m: float = Field(
        # chosen on the training sequence (kitti-bev 05); docs/RESULTS.md, "The nearest
        # keyframe of a place", has what 0, 0.5 and 1 give
        0.0,
        ge=0.0,
        le=10.0,
        description="see tie_tolerance: how much nearer to the query (m, by its SpectralGV "
        "pose) a keyframe of the same place must be to take the first place",
    )


class PoseConfig(_Section):
    """RANSAC on feature correspondences, then optional ICP refinement."""

    max_correspondence_distance: float = Field(0.5, gt=0.0, le=100.0)
    ransac_n: int = Field(3, ge=3, le=10)
    edge_length_ratio: float = Field(0.8, gt=0.0, lt=1.0)
    max_iterations: int = Field(10000, ge=1, le=1_000_000)
    ransac_first_batch: int = Field(
        64,
        ge=1,
        le=1000,
        description="hypotheses in RANSAC's first batch; each next batch doubles (up to "
        "1000); the confidence stop is checked after every batch",
    )
    confidence: float = Field(0.999, gt=0.0, le=1.0)
    mutual_filter: bool = True
    seed: int = Field(0, ge=0, le=2**32 - 1)
    refine: Literal["none", "icp"] = "icp"
    icp_max_distance: float = Field(
        1.0, gt=0.0, le=100.0, description="ICP correspondence distance (m)"
    )
    icp_iterations: int = Field(30, ge=1, le=1000)
    icp_coarse_m: float = Field(
        # chosen on the calibration's training frames (docs/VERDICT.md, "Coarse ICP")
        3.0,
        ge=0.0,
        le=100.0,
        description="ICP first runs icp_coarse_iterations with this correspondence "
        "distance (m), which pulls a rough RANSAC estimate (a few inliers, a metre or "
        "more off) towards the fit before the icp_max_distance stage sharpens it; 0, or "
        "a value not above icp_max_distance, skips the coarse stage",
    )
    icp_coarse_iterations: int = Field(
        10, ge=1, le=1000, description="iterations of the coarse ICP stage (icp_coarse_m)"
    )
    icp_method: Literal["point_to_plane", "point_to_point"] = Field(
        "point_to_plane",
        description="ICP error: distance to the keyframe cloud's local plane (normals from "
        "10 neighbours) or to its nearest point",
    )
    icp_source_voxel_m: float = Field(
        0.6,
        ge=0.0,
        le=10.0,
        description="the query cloud is downsampled to this voxel size for the ICP "
        "iterations (0 = every point); fitness and RMSE are always over every point",
    )
    icp_stop_m: float = Field(
        0.005,
        gt=0.0,
        le=1.0,
        description="numba, small_gicp: ICP stops once an iteration moves the pose less "
        "than this (m) and turns it less than icp_stop_deg",
    )
    icp_stop_deg: float = Field(
        0.25, gt=0.0, le=10.0, description="numba, small_gicp: see icp_stop_m"
    )
    icp_backend: Literal["numba", "small_gicp", "open3d"] = Field(
        "numba",
        description="ICP implementation: numba (sgvloc.core.icp_numba: Gauss-Newton "
        "point-to-plane without the interpreter lock, so concurrent localizations refine "
        "in parallel), small_gicp (its Python binding holds the lock) or Open3D (its "
        "OpenMP pool); the keyframe's index and normals are cached for the first two",
    )
    min_icp_fitness: float = Field(
        # a floor under the calibrated confidence, which weighs the fitness with the
        # free-space check; correct answers far from the mapped path reach 0.38-0.5
        # (docs/VERDICT.md)
        0.3,
        ge=0.0,
        le=1.0,
        description="after ICP: share of query points within icp_max_distance of the "
        "keyframe cloud needed to call the pose localized (replaces the RANSAC thresholds)",
    )
    min_icp_constraint: float = Field(
        # the middle of the floors that keep every accepted correct answer of the
        # calibration's training frames, whole and cropped to 70 degrees (the least
        # constrained: 0.041) and reject 2 of their 3 false accepts (docs/VERDICT.md)
        0.035,
        ge=0.0,
        le=1.0 / 3.0,
        description="after ICP: the weakest direction's share of the fit's point-to-plane "
        "constraint (smallest eigenvalue of the mean n n^T of the matched keyframe normals, "
        "0 to 1/3) needed to call the pose localized; below it the matched surfaces leave "
        "the position free along one direction (a corridor seen along its axis, open "
        "ground) and the fit is as good anywhere along it; 0 disables the check",
    )
    min_inliers: int = Field(
        10, ge=3, le=100_000, description="fewer RANSAC inliers = not localized"
    )
    min_fitness: float = Field(0.05, ge=0.0, le=1.0, description="lower fitness = not localized")


class TrackingConfig(_Section):
    """Seeded localization (:mod:`sgvloc.core.tracking`): GICP of the scan against the
    keyframe clouds around the seed, checked before it is trusted."""

    submap_radius_m: float = Field(
        40.0, gt=0.0, le=1000.0, description="keyframes within this of the seed form the submap"
    )
    submap_cell_m: float = Field(
        10.0, gt=0.0, le=1000.0, description="submaps are built (and cached) per cell this wide"
    )
    submap_voxel_m: float = Field(0.3, gt=0.0, le=10.0, description="submap downsampling (m)")
    scan_voxel_m: float = Field(1.0, gt=0.0, le=10.0, description="scan downsampling (m)")
    scan_neighbors: int = Field(
        10, ge=5, le=100, description="neighbours of a scan point's covariance (GICP, VGICP)"
    )
    registration: Literal["gicp", "vgicp"] = Field(
        "gicp",
        description="the fine stage: gicp against the submap's points (KD-tree); vgicp "
        "against its Gaussian voxels of vgicp_voxel_m (faster, slides more often along "
        "corridor-like stretches)",
    )
    vgicp_voxel_m: float = Field(
        1.0, gt=0.0, le=20.0, description="registration=vgicp: the submap's voxel size (m)"
    )
    vgicp_coarse_voxel_m: float = Field(
        3.0,
        ge=0.0,
        le=20.0,
        description="the coarse stage: VGICP against the submap's Gaussian voxels this large "
        "first (a wide basin for a rough seed, cheap), then the fine stage; 0 = none",
    )
    max_range_m: float = Field(
        60.0, gt=0.0, le=1000.0, description="scan points beyond are dropped"
    )
    max_correspondence_m: float = Field(
        1.0, gt=0.0, le=50.0, description="GICP correspondence distance (m)"
    )
    max_iterations: int = Field(20, ge=1, le=1000)
    stop_m: float = Field(
        0.005, gt=0.0, le=1.0, description="registration stops when a step moves less (m) ..."
    )
    stop_deg: float = Field(0.25, gt=0.0, le=10.0, description="... and turns less (deg)")
    inlier_distance_m: float = Field(
        0.5, gt=0.0, le=50.0, description="fitness: scan points within this of the submap"
    )
    min_fitness: float = Field(
        0.5, ge=0.0, le=1.0, description="share of scan points that must fit the submap"
    )
    max_rmse_m: float = Field(0.25, gt=0.0, le=10.0, description="RMSE of those points (m)")
    min_conditioning: float | None = Field(
        -1.4,
        ge=-20.0,
        le=0.0,
        description="a fit whose translation the scene pins down this badly (log10 of the "
        "smallest over the largest eigenvalue of its information: a corridor, a long wall) "
        "is not trusted and goes to the fallback; null = no check (docs/EVALUATION.md)",
    )
    seed_sigmas: float = Field(
        3.0, gt=0.0, le=100.0, description="the fit must lie within this many seed sigmas"
    )
    min_submap_keyframes: int = Field(1, ge=1, le=1000)
    cached_submaps: int = Field(8, ge=1, le=256, description="submaps kept per map (LRU)")
    fallback: Literal["global", "none"] = Field(
        "global",
        description="when the fit fails: localize globally with the seed as a prior, or answer "
        "not localized at once",
    )
    fallback_min_radius_m: float = Field(
        15.0, gt=0.0, le=100000.0, description="the fallback prior's radius: at least this"
    )


class VerdictConfig(_Section):
    """When an answer counts as localized (:mod:`sgvloc.core.confidence`)."""

    min_confidence: float = Field(
        0.8,  # the smallest tenth with <= 1% false accepts on held-out data (docs/VERDICT.md)
        ge=0.0,
        le=1.0,
        description="accept an answer when its calibrated confidence (the probability that "
        "its pose is within 2 m and 5 deg) is at least this; the pose step's minimums "
        "(min_inliers, min_fitness, min_icp_fitness, min_icp_constraint) must hold as well",
    )


RerankMethod = Literal["none", "average-qe", "alpha-qe", "ransac-rir", "fgr-rir", "sgv"]


class LocalizerConfig(_Section):
    """Retrieval, re-ranking and pose settings of one map.

    Encoder settings (preprocessing included) live in the encoder's spec
    (:class:`sgvloc.core.encoders.EncoderSpec`), which is part of the encoder's identity.
    """

    retrieval: RetrievalConfig = RetrievalConfig()
    sgv: SGVConfig = SGVConfig()
    pose: PoseConfig = PoseConfig()
    verdict: VerdictConfig = VerdictConfig()
    tracking: TrackingConfig = TrackingConfig()
    top_k: int = Field(
        20,
        ge=1,
        le=1000,
        description="candidates retrieved for re-ranking (per descriptor block when "
        "retrieval merges several: retrieval.combine)",
    )
    rerank: RerankMethod = "sgv"
    qe_k: int = Field(3, ge=1, le=100, description="query expansion: neighbours averaged")
    qe_alpha: float = Field(3.0, ge=0.0, le=100.0, description="alpha-QE weight exponent")

    @classmethod
    def stored(cls, data: str | bytes | Mapping[str, Any]) -> LocalizerConfig:
        """The settings a map was stored with (JSON text or its parsed form). A setting
        added since has the value that keeps the map answering as it did
        (:data:`ADDED_SETTINGS`), not the default of new maps."""
        d = json.loads(data) if isinstance(data, (str, bytes)) else json.loads(json.dumps(data))
        if isinstance(d, dict):
            for (section, key), value in ADDED_SETTINGS.items():
                if isinstance(d.setdefault(section, {}), dict):
                    d[section].setdefault(key, value)
        return cls.model_validate(d)


#: settings added after maps were first stored, with the value that keeps such a map's
#: answers as they were
ADDED_SETTINGS: dict[tuple[str, str], Any] = {
    ("sgv", "tie_tolerance"): 0.0,
    ("sgv", "tie_gain_m"): 1.0,
    ("retrieval", "offset_m"): 0.0,
    ("pose", "min_icp_constraint"): 0.0,
    ("pose", "icp_coarse_m"): 0.0,
    ("tracking", "min_conditioning"): None,
    # before these four, RANSAC drew hypotheses 1000 at a time and ICP was Open3D's
    # point-to-point on every point of the query cloud
    ("pose", "ransac_first_batch"): 1000,
    ("pose", "icp_backend"): "open3d",
    ("pose", "icp_method"): "point_to_point",
    ("pose", "icp_source_voxel_m"): 0.0,
}
