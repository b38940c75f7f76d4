"""Scan clean-up before encoding: finite filter, range crop, voxel grid, ground removal."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import numpy as np

from .config import PreprocessConfig
from .errors import EmptyScanError, InputError

log = logging.getLogger(__name__)


def as_points(points: np.ndarray, name: str = "scan") -> np.ndarray:
    """Validate a scan array ``[P, 3+]`` and return its xyz as float32 ``[P, 3]``."""
    try:
        arr = np.asarray(points)
    except ValueError:  # a ragged nested list
        raise InputError(f"{name} must be a rectangular array [P, 3+]") from None
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise InputError(f"{name} must have shape [P, 3] or [P, 3+C], got {list(arr.shape)}")
    if arr.dtype.kind not in "fiu":
        raise InputError(f"{name} must be numeric, got dtype {arr.dtype}")
    return np.ascontiguousarray(arr[:, :3], dtype=np.float32)


def finite(points: np.ndarray) -> np.ndarray:
    """Drop rows with NaN or inf coordinates."""
    return points[all_columns(np.isfinite, points)]


def all_columns(test: Callable[[np.ndarray], np.ndarray], points: np.ndarray) -> np.ndarray:
    """``test(points).all(axis=1)`` for ``[P, C]``, column by column (NumPy reduces a
    narrow array along its rows about ten times more slowly)."""
    keep = test(points[:, 0])
    for d in range(1, points.shape[1]):
        keep &= test(points[:, d])
    return keep


def column_min_max(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column minimum and maximum of ``[P, C]`` (column by column, as above)."""
    cols = [values[:, d] for d in range(values.shape[1])]
    return np.array([c.min() for c in cols]), np.array([c.max() for c in cols])


def crop_range(points: np.ndarray, min_range: float, max_range: float) -> np.ndarray:
    """Keep points whose distance from the sensor is in ``[min_range, max_range]``."""
    r = np.linalg.norm(points, axis=1)
    return points[(r >= min_range) & (r <= max_range)]


def in_azimuth_window(x: np.ndarray, y: np.ndarray, fov_deg: float) -> np.ndarray:
    """Whether each ``(x, y)`` lies in a horizontal field of view of ``fov_deg`` centred on
    the sensor's forward axis (+x): ``|atan2(y, x)| <= fov_deg / 2``. Raises InputError
    unless ``fov_deg`` is positive."""
    if not 0.0 < fov_deg:
        raise InputError(f"field of view must be positive, got {fov_deg} deg")
    return np.abs(np.degrees(np.arctan2(y, x))) <= fov_deg / 2.0


def crop_azimuth(points: np.ndarray, fov_deg: float) -> np.ndarray:
    """The points inside a horizontal field of view centred on the sensor's forward axis
    (:func:`in_azimuth_window`), other columns kept. ``fov_deg >= 360`` keeps every point;
    a narrower window emulates a forward-looking (solid-state) sensor."""
    if fov_deg >= 360.0:
        return points
    return points[in_azimuth_window(points[:, 0], points[:, 1], fov_deg)]


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """One point per occupied voxel: the centroid of the points that fall in it.

    Deterministic (independent of point order up to float rounding); ``voxel_size <= 0``
    returns the input.
    """
    if voxel_size <= 0 or len(points) == 0:
        return points
    cells = np.floor(points / voxel_size).astype(np.int64)  # [P, 3]
    lo, hi = column_min_max(cells)
    cells -= lo
    dims = hi - lo + 1
    if float(np.prod(dims.astype(np.float64))) < 2.0**62:
        # one integer key per cell: np.unique on a 1-D key is several times faster
        key = np.ravel_multi_index(cells.T, tuple(dims))  # [P]
        _, inverse = np.unique(key, return_inverse=True)
    else:  # a grid too fine for one integer key (a tiny voxel over a long range)
        _, inverse = np.unique(cells, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
    counts = np.bincount(inverse)
    sums = np.stack([np.bincount(inverse, weights=points[:, d]) for d in range(3)], axis=1)
    return (sums / counts[:, None]).astype(np.float32)


#: how :func:`remove_ground` fits the plane; part of the identity of an encoder whose
#: preprocessing removes the ground (features made another way are not comparable)
GROUND_FIT = "numpy-ransac-200"
#: points the plane hypotheses are scored on at most (an even subsample beyond)
GROUND_SAMPLE = 4000


def ground_fit(cfg: PreprocessConfig) -> dict[str, str]:
    """What an encoder's identity records of the ground fit: nothing unless the
    preprocessing removes the ground (so that other maps keep their fingerprints)."""
    return {"ground_fit": GROUND_FIT} if cfg.remove_ground else {}


def even_subsample(points: np.ndarray, at_most: int) -> np.ndarray:
    """At most ``at_most`` rows of ``points``, evenly spaced in order (deterministic)."""
    if len(points) <= at_most:
        return points
    return points[np.linspace(0, len(points) - 1, at_most).astype(np.int64)]


def plane_hypotheses(
    points: np.ndarray, count: int, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Planes through ``count`` seeded random triples of ``points`` ``[M, 3]``: unit
    normals ``[H, 3]`` facing up (``n_z >= 0``) and offsets ``[H]`` (``n . p + d = 0``);
    degenerate triples are left out, so ``H <= count``."""
    rng = np.random.default_rng(seed)
    tri = points[rng.integers(0, len(points), size=(count, 3))]  # [count, 3, 3]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    n = n[ok] / norm[ok, None]
    n *= np.where(n[:, 2] < 0, -1.0, 1.0)[:, None]
    return n, -np.einsum("ij,ij->i", n, tri[ok, 0])


def remove_ground(
    points: np.ndarray, distance: float, max_tilt_deg: float, seed: int = 0
) -> np.ndarray:
    """Remove the dominant near-horizontal plane (seeded RANSAC: 200 point triples,
    scored on at most :data:`GROUND_SAMPLE` evenly spaced points; deterministic).

    If the best plane is tilted more than ``max_tilt_deg`` from horizontal, nothing is
    removed: a wall is not ground.
    """
    if len(points) < 50:
        return points
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    sample = even_subsample(pts, GROUND_SAMPLE)
    n, d = plane_hypotheses(sample, 200, seed)
    if not len(n):
        return points
    best = int((np.abs(sample @ n.T + d) <= distance).sum(axis=0).argmax())
    normal, offset = n[best], d[best]
    tilt = np.degrees(np.arccos(min(1.0, abs(normal[2]))))
    if tilt > max_tilt_deg:
        log.debug("largest plane tilted %.1f deg: not treated as ground", tilt)
        return points
    return points[np.abs(pts @ normal + offset) > distance]


def preprocess(points: np.ndarray, cfg: PreprocessConfig) -> np.ndarray:
    """Run the whole clean-up on a raw scan ``[P, 3+]`` and return ``[M, 3]`` float32.

    Raises :class:`InputError` if the scan is malformed or empty, :class:`EmptyScanError`
    if nothing is left (every point out of range: a blocked sensor, say).
    """
    pts = as_points(points)
    if len(pts) == 0:
        raise InputError("scan is empty")
    pts = finite(pts)
    pts = crop_range(pts, cfg.min_range, cfg.max_range)
    pts = voxel_downsample(pts, cfg.voxel_size)
    if cfg.remove_ground:
        pts = remove_ground(pts, cfg.ground_distance, cfg.ground_max_tilt_deg)
    if len(pts) == 0:
        raise EmptyScanError(
            f"scan has no points left after preprocessing (range {cfg.min_range}-"
            f"{cfg.max_range} m, finite values only)"
        )
    return pts


_last_thinned = threading.local()


def voxel_centroids(cloud: np.ndarray, voxel_m: float) -> np.ndarray:
    """The centroids of ``cloud``'s voxels of ``voxel_m`` ``[M, 3]`` float64, in the order
    of the voxels' keys (:func:`sgvloc.core.gicp_numba.voxel_centroids`, without the
    interpreter lock). The calling thread's last answer is kept with the array it came
    from, so that the ICP source and the free-space check, which thin the same query cloud
    at the same size within one localization, share one pass."""
    last = getattr(_last_thinned, "entry", None)
    if last is not None and last[0] is cloud and last[1] == voxel_m:
        return last[2]
    from .gicp_numba import voxel_centroids as centroids

    pts = np.ascontiguousarray(np.asarray(cloud, dtype=np.float64).reshape(-1, 3))
    out = pts if len(pts) == 0 else centroids(pts, float(voxel_m))
    _last_thinned.entry = (cloud, voxel_m, out)
    return out
