"""Tracking: localize a scan by registering it against the map around a seed pose.

A vehicle that localized a moment ago knows roughly where it is. Instead of a global
search (encode, retrieve, re-rank, RANSAC), the scan is registered (VGICP against the
submap's coarse Gaussian voxels, then GICP against its points or VGICP against finer
voxels; :mod:`sgvloc.core.gicp_numba`, without the interpreter lock) against a
*submap*: the stored clouds of the keyframes within ``submap_radius_m`` of the seed, put
into map coordinates, downsampled, indexed and voxelised once and cached per map cell.
The fit is trusted only if enough scan points lie on the submap (``min_fitness``),
closely (``max_rmse_m``), and the pose lies within ``seed_sigmas`` of the seed;
otherwise the caller falls back to the global path.
"""

from __future__ import annotations

import functools
import json
import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sgvloc.about import PACKAGE_DIR

from .config import TrackingConfig
from .errors import InputError
from .gicp_numba import Cloud, GaussianVoxels, voxel_centroids
from .pose import check_rigid, rotation_angle_deg
from .preprocess import as_points


@dataclass(frozen=True)
class Seed:
    """Where the sensor is believed to be: a pose and its uncertainty (1 sigma)."""

    T_map_sensor: np.ndarray
    sigma_m: float
    sigma_yaw_deg: float

    def __post_init__(self) -> None:
        T = check_rigid(self.T_map_sensor, "seed.T_map_sensor")
        object.__setattr__(self, "T_map_sensor", T)
        for name in ("sigma_m", "sigma_yaw_deg"):
            value = getattr(self, name)
            real = isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_)
            if not (real and math.isfinite(value) and value > 0):
                raise InputError(f"seed.{name} must be a positive number, got {value!r}")
            object.__setattr__(self, name, float(value))
        if self.sigma_yaw_deg > 180:
            raise InputError(f"seed.sigma_yaw_deg must be at most 180, got {self.sigma_yaw_deg}")


@dataclass
class Submap:
    """The map around a cell: keyframe clouds in map coordinates, ready for GICP and
    (``voxels``, when the settings ask for VGICP) for VGICP."""

    cloud: Cloud  # points, KD-tree and covariances (GICP, and the fitness of either)
    keyframe_ids: list[int]
    points: int
    voxels: GaussianVoxels | None = None  # of vgicp_voxel_m
    coarse: GaussianVoxels | None = None  # of vgicp_coarse_voxel_m


@dataclass
class TrackResult:
    """One seeded registration and what the checks made of it."""

    ok: bool
    why: str
    T_map_sensor: np.ndarray | None = None
    fitness: float = 0.0
    fitness_fine: float = 0.0  # share of scan points within FINE_M of the map
    rmse_m: float = float("inf")
    conditioning: float = float("nan")  # log10 of the smallest / largest eigenvalue of the
    #   fit's translation information (GICP Hessian): near 0 well constrained, very negative
    #   when the scene lets the scan slide one way (a corridor, a long wall)
    information: float = float("nan")  # log10 of the smallest such eigenvalue per inlier
    iterations: int = 0
    submap_keyframes: int = 0
    submap_points: int = 0
    scan_points: int = 0
    seed_offset_m: float = float("nan")
    seed_offset_deg: float = float("nan")
    nearest_keyframe: int | None = None
    #: the nearest keyframe's pose and the map's version, as the submap was taken (the
    #: keyframe may be gone by the time the answer is made)
    T_map_nearest: np.ndarray | None = None
    map_version: int = 0
    confidence: float = 0.0  # set by the localizer once the fit passed its checks
    timings_ms: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "fitness": self.fitness,
            "fitness_fine": self.fitness_fine,
            "rmse_m": self.rmse_m,
            "conditioning": self.conditioning,
            "information": self.information,
            "iterations": self.iterations,
            "submap_keyframes": self.submap_keyframes,
            "submap_points": self.submap_points,
            "scan_points": self.scan_points,
            "seed_offset_m": self.seed_offset_m,
            "seed_offset_deg": self.seed_offset_deg,
            "why": self.why,
        }


FINE_M = 0.2  # the "fine" fitness: scan points this close to the map
#: fewest scan points (after the scan's voxel grid) and matched correspondences a fit
#: is trusted on: one or two points always fit, however wrong the pose
MIN_FIT_POINTS = 30
#: neighbours of a submap point's covariance
SUBMAP_NEIGHBOURS = 10

#: what a tracking confidence model may use, from a fit's :meth:`TrackResult.to_dict`;
#: oriented so that larger means more likely correct (the fit's weights are >= 0)
TRACK_FEATURES: dict[str, Callable[[Mapping[str, Any]], float]] = {
    "fitness": lambda e: float(e["fitness"]),
    "fitness_fine": lambda e: float(e["fitness_fine"]),
    "neg_rmse_m": lambda e: -min(float(e["rmse_m"]), 10.0),
    "neg_seed_offset_m": lambda e: -min(float(e["seed_offset_m"]), 100.0),
    "conditioning": lambda e: float(e["conditioning"]),
    "information": lambda e: float(e["information"]),
}


@dataclass(frozen=True)
class TrackConfidence:
    """P(a seeded fit is within 2 m and 5 deg) as a logistic model of its evidence:
    ``sigmoid(bias + sum w_i (x_i - mean_i) / scale_i)`` over the named
    :data:`TRACK_FEATURES`. Fitted by ``sgvloc calibrate-track`` (docs/EVALUATION.md,
    "Tracking"); the fitted one ships as ``sgvloc/calibration/tracking.json``."""

    features: tuple[str, ...]
    mean: tuple[float, ...]
    scale: tuple[float, ...]
    weights: tuple[float, ...]
    bias: float
    fitted_on: dict[str, Any] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        unknown = [f for f in self.features if f not in TRACK_FEATURES]
        n = len(self.features)
        if unknown or not n:
            raise InputError(f"tracking confidence model: unknown features {unknown}")
        if not (len(self.mean) == len(self.scale) == len(self.weights) == n):
            raise InputError("tracking confidence model: one mean, scale, weight per feature")
        if any(not v > 0 for v in self.scale) or any(w < 0 for w in self.weights):
            raise InputError("tracking confidence model: scales > 0 and weights >= 0 needed")

    @staticmethod
    def row(evidence: Mapping[str, Any], features: Sequence[str]) -> np.ndarray:
        """The feature vector of one fit's evidence (unstandardised)."""
        return np.array([TRACK_FEATURES[f](evidence) for f in features], dtype=np.float64)

    def predict(self, evidence: Mapping[str, Any]) -> float:
        x = self.row(evidence, self.features)
        if not np.isfinite(x).all():
            return 0.0
        z = self.bias + float(np.dot(self.weights, (x - self.mean) / np.asarray(self.scale)))
        return float(1.0 / (1.0 + math.exp(-max(min(z, 50.0), -50.0))))

    def to_dict(self) -> dict[str, Any]:
        return {
            "features": list(self.features),
            "mean": list(self.mean),
            "scale": list(self.scale),
            "weights": list(self.weights),
            "bias": self.bias,
            "fitted_on": self.fitted_on,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> TrackConfidence:
        try:
            return cls(
                tuple(str(f) for f in d["features"]),
                tuple(float(v) for v in d["mean"]),
                tuple(float(v) for v in d["scale"]),
                tuple(float(v) for v in d["weights"]),
                float(d["bias"]),
                dict(d.get("fitted_on") or {}),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"tracking confidence model: {exc}") from None


@functools.cache
def shipped_track_confidence() -> TrackConfidence:
    """The tracking confidence model shipped with this installation."""
    path = PACKAGE_DIR / "calibration" / "tracking.json"
    return TrackConfidence.from_dict(json.loads(path.read_text()))


def tracked_confidence(r: TrackResult, model: TrackConfidence | None = None) -> float:
    """The calibrated confidence of a seeded fit (0 without a pose)."""
    if r.T_map_sensor is None:
        return 0.0
    return (model or shipped_track_confidence()).predict(r.to_dict())


def build_submap(
    clouds: list[tuple[int, np.ndarray, np.ndarray]], cfg: TrackingConfig
) -> Submap | None:
    """A submap from ``(keyframe id, T_map_sensor, cloud in the sensor frame)``; None
    when there are fewer than ``min_submap_keyframes`` clouds."""
    if len(clouds) < cfg.min_submap_keyframes:
        return None
    pts = np.concatenate(
        [c.astype(np.float64) @ T[:3, :3].T + T[:3, 3] for _, T, c in clouds if len(c)]
    )
    cloud = Cloud.of(voxel_centroids(pts, cfg.submap_voxel_m), SUBMAP_NEIGHBOURS)
    voxels = coarse = None
    if cfg.registration == "vgicp":
        voxels = GaussianVoxels.of(cloud, cfg.vgicp_voxel_m)
    if cfg.vgicp_coarse_voxel_m > 0:
        coarse = GaussianVoxels.of(cloud, cfg.vgicp_coarse_voxel_m)
    return Submap(cloud, [i for i, _, _ in clouds], len(cloud), voxels, coarse)


#: fewest usable scan points (finite, within max_range_m) a fit is tried on
MIN_SCAN_POINTS = 10


def scan_cloud(points: np.ndarray, cfg: TrackingConfig) -> np.ndarray:
    """The scan's finite points within ``max_range_m`` ``[M, 3]`` float64 (tested column
    by column: a NaN or inf coordinate fails the range test)."""
    p = as_points(points)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    return p[x * x + y * y + z * z <= np.float32(cfg.max_range_m) ** 2].astype(np.float64)


def register(points: np.ndarray, seed: Seed, submap: Submap, cfg: TrackingConfig) -> TrackResult:
    """VGICP (or GICP) of the scan against the submap from the seed, and the checks. A
    scan with fewer than :data:`MIN_SCAN_POINTS` usable points is a failed fit without a
    pose (the localizer then falls back as for any failed fit)."""
    usable = scan_cloud(points, cfg)
    if len(usable) < MIN_SCAN_POINTS:
        return TrackResult(
            ok=False,
            why=f"the scan has {len(usable)} usable points within max_range_m "
            f"{cfg.max_range_m:g}; tracking needs at least {MIN_SCAN_POINTS}",
            submap_keyframes=len(submap.keyframe_ids),
            submap_points=submap.points,
            scan_points=len(usable),
        )
    source = Cloud.of(voxel_centroids(usable, cfg.scan_voxel_m), cfg.scan_neighbors)
    stop = (cfg.max_iterations, cfg.stop_m, math.radians(cfg.stop_deg))
    T = seed.T_map_sensor
    if submap.coarse is not None:  # a rough fit against large voxels first
        T, *_ = submap.coarse.align(source, T, 2 * cfg.max_correspondence_m, *stop)
    target = submap.voxels if cfg.registration == "vgicp" and submap.voxels else submap.cloud
    T, iterations, H, used = target.align(source, T, cfg.max_correspondence_m, *stop)
    sq = submap.cloud.nearest_squared(source.points, T)
    inl = sq <= cfg.inlier_distance_m**2
    fitness = float(inl.mean()) if len(sq) else 0.0
    fine = float((sq <= FINE_M**2).mean()) if len(sq) else 0.0
    rmse = float(np.sqrt(sq[inl].mean())) if inl.any() else float("inf")
    eig = np.linalg.eigvalsh(H[3:, 3:])  # the translation block
    low, high = max(float(eig[0]), 1e-12), max(float(eig[-1]), 1e-12)
    offset = float(np.linalg.norm(T[:3, 3] - seed.T_map_sensor[:3, 3]))
    dyaw = rotation_angle_deg(seed.T_map_sensor[:3, :3].T @ T[:3, :3])  # heading and tilt
    out = TrackResult(
        ok=False,
        why="",
        T_map_sensor=T,
        fitness=fitness,
        fitness_fine=fine,
        rmse_m=rmse,
        conditioning=math.log10(low / high),
        information=math.log10(low / max(int(used), 1)),
        iterations=int(iterations),
        submap_keyframes=len(submap.keyframe_ids),
        submap_points=submap.points,
        scan_points=len(source),
        seed_offset_m=offset,
        seed_offset_deg=dyaw,
    )
    k = cfg.seed_sigmas
    if len(source) < MIN_FIT_POINTS or int(used) < MIN_FIT_POINTS:
        out.why = (
            f"the scan keeps {len(source)} points on the {cfg.scan_voxel_m:g} m grid, "
            f"{int(used)} of them matched: too few to fix a pose (at least {MIN_FIT_POINTS})"
        )
    elif fitness < cfg.min_fitness:
        out.why = f"only {fitness:.0%} of the scan fits the map (min_fitness {cfg.min_fitness:g})"
    elif rmse > cfg.max_rmse_m:
        out.why = f"the fit's RMSE {rmse:.2f} m exceeds max_rmse_m {cfg.max_rmse_m:g}"
    elif cfg.min_conditioning is not None and out.conditioning < cfg.min_conditioning:
        out.why = (
            f"the scene leaves the fit free to slide one way (conditioning "
            f"{out.conditioning:.2f} < min_conditioning {cfg.min_conditioning:g}: a corridor "
            "or a long wall)"
        )
    elif offset > k * seed.sigma_m + cfg.scan_voxel_m:
        out.why = f"the fit lies {offset:.1f} m from the seed (more than {k:g} sigma_m)"
    elif dyaw > k * seed.sigma_yaw_deg + 1.0:
        out.why = f"the fit turns {dyaw:.1f} deg from the seed (more than {k:g} sigma_yaw_deg)"
    else:
        out.ok, out.why = True, "the scan fits the map around the seed"
    return out
