"""A prior pose (e.g. from GNSS) and the spatial index of keyframe positions it queries.

A :class:`Prior` says "the sensor is within ``radius_m`` of ``position``" (x/y, or x/y/z
when three values are given, in map coordinates), optionally "heading ``yaw_deg`` within
``yaw_tolerance_deg``". The localizer then retrieves only among the keyframes inside the
radius (:class:`PositionGrid`) and rejects an estimate outside the region.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from .errors import InputError

#: default heading tolerance when a prior gives ``yaw_deg`` without one
DEFAULT_YAW_TOLERANCE_DEG = 30.0


def yaw_deg(T: np.ndarray) -> float:
    """Heading of a 4x4 pose: the angle of its x axis in the map's x/y plane (degrees)."""
    return math.degrees(math.atan2(T[1, 0], T[0, 0]))


@dataclass(frozen=True)
class Prior:
    """Where the sensor is believed to be (see the module docstring)."""

    position: tuple[float, ...]
    radius_m: float
    yaw_deg: float | None = None
    yaw_tolerance_deg: float = DEFAULT_YAW_TOLERANCE_DEG

    def __post_init__(self) -> None:
        pos = tuple(float(x) for x in self.position)
        if len(pos) not in (2, 3) or not all(math.isfinite(x) for x in pos):
            raise InputError("prior.position must be 2 or 3 finite numbers [x, y(, z)]")
        object.__setattr__(self, "position", pos)
        if not (math.isfinite(self.radius_m) and self.radius_m > 0):
            raise InputError(f"prior.radius_m must be a positive number, got {self.radius_m}")
        if self.yaw_deg is not None and not math.isfinite(self.yaw_deg):
            raise InputError("prior.yaw_deg must be a finite number")
        if not (0 < self.yaw_tolerance_deg <= 180):
            raise InputError(
                f"prior.yaw_tolerance_deg must be in (0, 180], got {self.yaw_tolerance_deg}"
            )

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Distances ``[M]`` of positions ``[M, 3]`` from the prior (x/y only for 2 values)."""
        d = len(self.position)
        return np.linalg.norm(np.asarray(points)[:, :d] - np.asarray(self.position), axis=1)

    def rejects(self, T_map_sensor: np.ndarray) -> str | None:
        """Why an estimate lies outside the prior region, or None if it lies inside."""
        dist = float(self.distance(T_map_sensor[None, :3, 3])[0])
        if dist > self.radius_m:
            return (
                f"the estimate is {dist:.1f} m from the prior position (radius {self.radius_m:g} m)"
            )
        if self.yaw_deg is not None:
            off = abs((yaw_deg(T_map_sensor) - self.yaw_deg + 180.0) % 360.0 - 180.0)
            if off > self.yaw_tolerance_deg:
                return (
                    f"the estimate's heading is {off:.0f} deg from the prior's "
                    f"(tolerance {self.yaw_tolerance_deg:g} deg)"
                )
        return None


class PositionGrid:
    """Keyframe positions hashed into square x/y cells, for radius queries.

    Updates are O(1) per keyframe; a query visits the cells that overlap the radius (or
    every occupied cell, if there are fewer) and filters by exact distance. Not
    thread-safe: the localizer calls it under its own lock.
    """

    def __init__(self, cell_m: float = 10.0) -> None:
        self.cell_m = float(cell_m)
        self._cells: dict[tuple[int, int], set[int]] = defaultdict(set)
        self._pos: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self._pos)

    def _cell(self, p: np.ndarray) -> tuple[int, int]:
        return (math.floor(p[0] / self.cell_m), math.floor(p[1] / self.cell_m))

    def add(self, keyframe_id: int, position: np.ndarray) -> None:
        p = np.asarray(position, dtype=np.float64)[:3]
        self.remove(keyframe_id)
        self._pos[int(keyframe_id)] = p
        self._cells[self._cell(p)].add(int(keyframe_id))

    def remove(self, keyframe_id: int) -> None:
        p = self._pos.pop(int(keyframe_id), None)
        if p is not None:
            cell = self._cell(p)
            self._cells[cell].discard(int(keyframe_id))
            if not self._cells[cell]:
                del self._cells[cell]

    def clear(self) -> None:
        self._cells.clear()
        self._pos.clear()

    def within(self, prior: Prior) -> np.ndarray:
        """Ids of the keyframes inside the prior's radius, sorted ``[M]`` int64."""
        x, y = prior.position[:2]
        r = prior.radius_m
        # one cell more each way: a keyframe exactly on the radius may round into the
        # next cell; the exact distance test below decides
        lo = tuple(c - 1 for c in self._cell(np.array([x - r, y - r])))
        hi = tuple(c + 1 for c in self._cell(np.array([x + r, y + r])))
        span = (hi[0] - lo[0] + 1) * (hi[1] - lo[1] + 1)
        if span > len(self._cells):
            cells = [c for c in self._cells if lo[0] <= c[0] <= hi[0] and lo[1] <= c[1] <= hi[1]]
        else:
            cells = [
                (i, j)
                for i in range(lo[0], hi[0] + 1)
                for j in range(lo[1], hi[1] + 1)
                if (i, j) in self._cells
            ]
        ids = np.fromiter((i for c in cells for i in self._cells[c]), dtype=np.int64)
        if len(ids) == 0:
            return ids
        pos = np.stack([self._pos[int(i)] for i in ids])  # [M, 3]
        return np.sort(ids[prior.distance(pos) <= r])
