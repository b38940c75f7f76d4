"""Free-space check of a pose estimate: does the query scan, placed in the map, put
points where nearby keyframes saw through?

A keyframe's cloud says more than where surfaces are: along each ray the sensor saw
empty space up to the first return. A :class:`RangeImage` keeps, per
:data:`BIN_DEG` x :data:`BIN_DEG` bin of azimuth and elevation in the keyframe's sensor
frame, the range of the nearest return. A query point under a pose estimate that falls
into a bin at least :data:`MARGIN_M` nearer than that range lies in space the keyframe
observed as empty: the estimate contradicts the map there. Points beyond the first
return (occluded) or in bins without returns say nothing.

:func:`violation` is the share of the query points a keyframe could judge (in front of
or on its surfaces, within the margin) that contradict it, pooled over the estimate's
nearest keyframes (:func:`views_near`) and shrunk towards a prior share when few points
could be judged. Of a correct pose a few percent contradict (moving objects, thin
structures); a wrong pose that still overlaps the keyframe's surfaces in places, which
is what a plausible false answer looks like, puts walls into open space and scores far
higher. Unlike the ICP fitness it does not fall when the query sees much
that the map never did (a scan taken 10-15 m from the mapped path): unobserved space is
not a contradiction. The confidence model uses it as evidence (``free_space`` in
:mod:`sgvloc.core.confidence`); the constants are part of what a calibration was fitted
on, so they are not settings.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

from .preprocess import voxel_centroids

#: angular bin of the range images (degrees, azimuth and elevation)
BIN_DEG = 1.0
#: a query point this much nearer than a keyframe's first return contradicts it (m)
MARGIN_M = 0.5
#: keyframes nearest to the estimate checked (the matched keyframe always is)
NEIGHBOURS = 5
#: ... among those within this distance of the estimated position (m)
RADIUS_M = 30.0
#: query points are thinned to one per voxel of this size (m) before the check
VOXEL_M = 0.6
#: the share is shrunk towards PRIOR_SHARE as if PRIOR_POINTS more points had been
#: judged: a scan that overlaps the keyframes' observed space in a few hundred points
#: (a pose far off the map, or ground alone) has shown little, not a clean record
PRIOR_SHARE, PRIOR_POINTS = 0.3, 500

_AZ_BINS = int(round(360.0 / BIN_DEG))
_EL_BINS = int(round(180.0 / BIN_DEG))


def _bins(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ranges, elevation rows and azimuth columns ``[N]`` of sensor-frame points
    ``[N, 3]``."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    r = np.sqrt(x * x + y * y + z * z)
    az = np.degrees(np.arctan2(y, x)) % 360.0
    el = np.degrees(np.arcsin(np.clip(z / np.maximum(r, 1e-9), -1.0, 1.0)))
    ia = np.minimum((az / BIN_DEG).astype(np.int64), _AZ_BINS - 1)
    ie = np.clip(((el + 90.0) / BIN_DEG).astype(np.int64), 0, _EL_BINS - 1)
    return r, ie, ia


class RangeImage:
    """The nearest return per angular bin of one keyframe cloud (sensor frame);
    ``inf`` where the bin holds no return. Only the band of elevation rows with returns
    is kept: about 130 kB for a spinning LiDAR's 90 degrees."""

    def __init__(self, cloud: np.ndarray) -> None:
        pts = np.asarray(cloud, dtype=np.float64).reshape(-1, 3)
        r, ie, ia = _bins(pts)
        self.row0 = int(ie.min()) if len(ie) else 0
        rows = int(ie.max()) + 1 - self.row0 if len(ie) else 0
        first = np.full(rows * _AZ_BINS, np.inf, dtype=np.float32)
        np.minimum.at(first, (ie - self.row0) * _AZ_BINS + ia, r.astype(np.float32))
        self.first = first

    def judge(self, points: np.ndarray) -> tuple[int, int]:
        """(judged, contradicting) counts of sensor-frame points ``[N, 3]``: judged =
        in a bin with a return and not beyond it by more than the margin; contradicting
        = nearer than it by more than the margin."""
        r, ie, ia = _bins(points)
        row = ie - self.row0
        inside = (row >= 0) & (row * _AZ_BINS < len(self.first))
        first = np.full(len(r), np.inf, dtype=np.float32)
        first[inside] = self.first[row[inside] * _AZ_BINS + ia[inside]]
        seen = np.isfinite(first)
        judged = seen & (r <= first + MARGIN_M)
        return int(judged.sum()), int((seen & (r < first - MARGIN_M)).sum())


def thin(cloud: np.ndarray) -> np.ndarray:
    """The query cloud thinned to the centroids of its :data:`VOXEL_M` voxels ``[M, 3]``."""
    return voxel_centroids(cloud, VOXEL_M)


def views_near(
    position: np.ndarray,
    matched: int,
    candidates: Iterable[int],
    position_of: Callable[[int], np.ndarray],
) -> list[int]:
    """The keyframes to check an estimate at ``position`` against: the ``matched`` one
    first, then up to :data:`NEIGHBOURS` - 1 others of ``candidates`` (ids within
    :data:`RADIUS_M`, any order) nearest to it."""
    others = [int(i) for i in candidates if int(i) != int(matched)]
    if others:
        d = np.linalg.norm(np.stack([position_of(i)[:3] for i in others]) - position[:3], axis=1)
        keep = [others[j] for j in np.argsort(d, kind="stable") if d[j] <= RADIUS_M]
        others = keep[: NEIGHBOURS - 1]
    return [int(matched), *others]


def violation(
    query_points: np.ndarray,
    T_map_query: np.ndarray,
    views: Iterable[tuple[np.ndarray, RangeImage]],
) -> float | None:
    """Share of the judged query points that contradict the keyframes' observed free
    space, pooled over ``views`` ``(T_map_kf, RangeImage)`` and shrunk towards
    :data:`PRIOR_SHARE` (``(contradicting + PRIOR_SHARE * PRIOR_POINTS) / (judged +
    PRIOR_POINTS)``, so :data:`PRIOR_SHARE` when no point could be judged); None
    without views. ``query_points`` ``[N, 3]`` in the query's sensor frame (thinned:
    :func:`thin`)."""
    pts = np.asarray(query_points, dtype=np.float64)
    views = list(views)
    if not views:
        return None
    judged = contradicting = 0
    for T_map_kf, image in views:
        T = np.linalg.solve(T_map_kf, T_map_query)  # T_kf_query
        j, c = image.judge(pts @ T[:3, :3].T + T[:3, 3])
        judged += j
        contradicting += c
    return (contradicting + PRIOR_SHARE * PRIOR_POINTS) / (judged + PRIOR_POINTS)
