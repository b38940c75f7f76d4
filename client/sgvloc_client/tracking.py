"""Tracking a moving vehicle: seeds from the last fix and a motion model.

The service is stateless; the state of a track lives here, in the client. Each scan is
sent with a :class:`~sgvloc_client.Seed`, the pose predicted from the last fix by a
constant-velocity model over the scans' timestamps (or by the vehicle's own odometry
increment, when given), with uncertainties that grow with the time since that fix. The
service registers the scan against the map around the seed (``mode == "tracked"``),
falling back to its global path when the fit fails. After ``max_misses`` answers in a row
that were not localized, the next scan is sent without a seed: a global relocalization
(start-up, a kidnapped vehicle, a gap in the map).

    tracker = Tracker(client, "campus")
    for stamp, points in scans:
        fix = tracker.update(points, stamp)
        if fix.localized:
            use(fix.T_map_sensor)
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ._errors import EmptyScan
from ._models import Localization, Seed

if TYPE_CHECKING:
    from ._async import AsyncClient
    from ._client import Client


def _log_rotation(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle) of a rotation matrix."""
    cos = float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    angle = math.acos(cos)
    if angle < 1e-9:
        return np.zeros(3)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if math.pi - angle < 1e-6:  # near 180 deg: the axis from the symmetric part
        axis = np.sqrt(np.clip((np.diag(R) + 1.0) / 2.0, 0.0, None))
        axis *= np.sign(w) + (w == 0)
        return axis / np.linalg.norm(axis) * angle
    return w / (2.0 * math.sin(angle)) * angle


def _exp_rotation(v: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    angle = float(np.linalg.norm(v))
    if angle < 1e-12:
        return np.eye(3)
    k = v / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


#: the largest seed uncertainty the service takes (seed.sigma_m); beyond it the tracker
#: asks for a global localization instead
MAX_SEED_SIGMA_M = 1e4
#: the longest odometry step taken (m): beyond any vehicle's motion between two scans
MAX_ODOMETRY_M = 1e4
#: fixes closer in time than this give no velocity (their registration noise, divided by
#: a tiny interval, would read as a fast motion)
MIN_STEP_S = 0.02


#: a stamp above this many seconds (year 5138) is taken for one in nanoseconds
MAX_STAMP_S = 1e11


def _check_stamp(stamp: float) -> None:
    if not math.isfinite(stamp):
        raise ValueError(f"stamp must be a finite number of seconds, got {stamp!r}")
    if abs(stamp) > MAX_STAMP_S:  # ROS stamps in ns would make every gap look too long
        raise ValueError(f"stamp must be in seconds, got {stamp!r} (nanoseconds? divide by 1e9)")


def _odometry_step(odom_delta: Any) -> np.ndarray:
    """``odom_delta`` as a rigid 4x4 float64 transform (its rotation re-orthonormalised,
    as float32 odometry drifts slightly off), or ValueError naming it: a bad sample must
    be refused before it enters the track, where it would spoil every later seed."""
    try:
        step = np.asarray(odom_delta, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(
            f"odom_delta must be a 4x4 transform (T_prev_curr), got {type(odom_delta).__name__}"
        ) from None
    if step.shape != (4, 4):
        raise ValueError(
            f"odom_delta must be a 4x4 transform (T_prev_curr), got shape {list(step.shape)}"
        )
    if not np.isfinite(step).all() or np.abs(step[:3, 3]).max() > MAX_ODOMETRY_M:
        raise ValueError(
            f"odom_delta must hold finite values and move at most {MAX_ODOMETRY_M:g} m"
        )
    R = step[:3, :3]
    if not (
        np.allclose(R.T @ R, np.eye(3), atol=1e-2)
        and np.linalg.det(R) > 0
        and np.allclose(step[3], [0.0, 0.0, 0.0, 1.0])
    ):
        raise ValueError(
            "odom_delta is not a rigid transform: its rotation must be orthonormal with "
            "determinant +1 and its last row 0 0 0 1"
        )
    u, _, vt = np.linalg.svd(R)
    step = step.copy()
    step[:3, :3] = u @ vt
    step[3] = [0.0, 0.0, 0.0, 1.0]
    return step


@dataclass
class MotionModel:
    """The prediction half of a tracker, free of any transport.

    ``sigma_m`` / ``sigma_yaw_deg``: the seed's uncertainty right after a fix; they grow
    by ``growth_m_per_s`` / ``growth_yaw_deg_per_s`` per second since that fix, and are
    multiplied by ``widen`` for every answer in a row that was not localized. After
    ``max_misses`` such answers, or ``max_gap_s`` seconds without a fix, :meth:`seed`
    returns None: relocalize globally. ``turn_factor`` scales the rotation carried over from
    the last step (1: constant turn rate); the default 0.5 was chosen on training data (a
    handheld sequence's first 44 s and a synthetic drive): a full turn rate overshot the
    jerky turns of a handheld sensor into a wrong fix, at the cost of a few more global
    fallbacks on a car.
    """

    sigma_m: float = 0.5
    sigma_yaw_deg: float = 3.0
    growth_m_per_s: float = 1.0
    growth_yaw_deg_per_s: float = 30.0
    widen: float = 3.0
    max_misses: int = 1
    max_gap_s: float = 5.0
    turn_factor: float = 0.5

    def __post_init__(self) -> None:
        if not (self.sigma_m > 0 and self.sigma_yaw_deg > 0 and self.widen >= 1):
            raise ValueError("sigma_m and sigma_yaw_deg must be positive, widen at least 1")
        if not 0.0 <= self.turn_factor <= 1.0:
            raise ValueError(f"turn_factor must be in [0, 1], got {self.turn_factor}")
        if self.max_misses < 1:
            raise ValueError(f"max_misses must be at least 1, got {self.max_misses}")
        self.reset()

    def reset(self) -> None:
        """Forget the track: the next scan is localized globally."""
        self.pose: np.ndarray | None = None  # the last fix, T_map_sensor
        self.stamp: float | None = None
        self.misses = 0
        self._delta: np.ndarray | None = None  # motion between the last two fixes
        self._delta_dt = 0.0
        self._pending_odom: np.ndarray | None = None  # odometry since the last fix

    @property
    def lost(self) -> bool:
        """True when the next scan goes to global relocalization."""
        return self.pose is None or self.misses >= self.max_misses

    def predict(self, stamp: float, odom_delta: Any = None) -> np.ndarray | None:
        """The predicted ``T_map_sensor`` at ``stamp`` (None without a usable fix); it
        changes nothing (:meth:`seed` takes the odometry into the track).

        ``odom_delta``: the vehicle's own motion since the previous scan (``T_prev_curr``);
        it replaces the constant-velocity model while given.
        """
        _check_stamp(stamp)
        if self.pose is None or self.stamp is None:
            return None
        return self._predict(stamp, None if odom_delta is None else _odometry_step(odom_delta))

    def _predict(self, stamp: float, step: np.ndarray | None) -> np.ndarray:
        """:meth:`predict` from a fix, with this scan's checked odometry ``step``."""
        assert self.pose is not None and self.stamp is not None
        if step is not None:
            return self.pose @ self._since_fix(step)
        dt = stamp - self.stamp
        if self._delta is None or self._delta_dt <= 0 or dt <= 0:
            return self.pose.copy()
        ratio = dt / self._delta_dt
        motion = np.eye(4)
        turn = _log_rotation(self._delta[:3, :3]) * ratio * self.turn_factor
        motion[:3, :3] = _exp_rotation(turn)
        motion[:3, 3] = self._delta[:3, 3] * ratio
        return self.pose @ motion

    def _since_fix(self, step: np.ndarray) -> np.ndarray:
        """The odometry since the last fix, with this scan's checked ``step``."""
        return (self._pending_odom if self._pending_odom is not None else np.eye(4)) @ step

    def seed(self, stamp: float, odom_delta: Any = None) -> Seed | None:
        """The seed for a scan taken at ``stamp`` (seconds), or None: relocalize. Call
        it once per scan: its ``odom_delta`` adds to the odometry since the last fix
        (ValueError, the track unchanged, if it is not a rigid 4x4 transform)."""
        _check_stamp(stamp)
        # refused before anything else, even while lost
        step = None if odom_delta is None else _odometry_step(odom_delta)
        if self.lost or self.stamp is None or stamp - self.stamp > self.max_gap_s:
            return None
        if stamp < self.stamp - MIN_STEP_S:  # before the last fix (a clock reset, a bag
            return None  # played again): what the track says is of another time
        T = self._predict(stamp, step)  # not lost: there is a fix
        if step is not None:
            self._pending_odom = self._since_fix(step)
        dt = max(0.0, stamp - self.stamp)
        widen = self.widen**self.misses
        sigma_m = (self.sigma_m + self.growth_m_per_s * dt) * widen
        if sigma_m > MAX_SEED_SIGMA_M:  # no seed at all says as much: a global search
            return None
        return Seed(
            T,
            sigma_m,
            min(180.0, (self.sigma_yaw_deg + self.growth_yaw_deg_per_s * dt) * widen),
        )

    def observe(self, result: Localization, stamp: float) -> None:
        """Take an answer for the scan at ``stamp`` into the track."""
        _check_stamp(stamp)
        if not result.localized or result.T_map_sensor is None:
            self.misses += 1
            return
        T = np.asarray(result.T_map_sensor, dtype=np.float64)
        consecutive = self.misses == 0 and self.pose is not None and self.stamp is not None
        if consecutive and stamp - self.stamp >= MIN_STEP_S:  # motion between consecutive fixes
            self._delta = np.linalg.inv(self.pose) @ T
            self._delta_dt = stamp - self.stamp
        elif not consecutive or stamp < self.stamp:  # after misses, or back in time: the
            self._delta, self._delta_dt = None, 0.0  # last motion is stale, assume none
        self.pose, self.stamp, self.misses = T, float(stamp), 0
        self._pending_odom = None


class _TrackerBase:
    """What :class:`Tracker` and :class:`AsyncTracker` share: the model and the seeds."""

    def __init__(
        self,
        client: Any,
        map: str,
        *,
        localize_options: Mapping[str, Any] | None = None,
        **motion: Any,
    ) -> None:
        self.client = client
        self.map = map
        self.model = MotionModel(**motion)
        self.options = dict(localize_options or {})
        taken = {"seed", "points", "features"} & set(self.options)
        if taken:  # the tracker sends these itself
            raise ValueError(f"localize_options may not set {', '.join(sorted(taken))}")
        self.relocalizations = 0  # global searches after the first fix

    @property
    def pose(self) -> np.ndarray | None:
        """The last fix (``T_map_sensor``), None before the first."""
        return self.model.pose

    @property
    def lost(self) -> bool:
        """True when the next scan goes to global relocalization."""
        return self.model.lost

    def reset(self) -> None:
        """Forget the track: the next scan is localized globally."""
        self.model.reset()

    def _seed(self, stamp: float, odom_delta: Any) -> Seed | None:
        seed = self.model.seed(stamp, odom_delta)
        if seed is None and self.model.pose is not None:
            self.relocalizations += 1
        return seed


class Tracker(_TrackerBase):
    """Localizes a stream of scans of one vehicle in map ``map`` through ``client``
    (a :class:`~sgvloc_client.Client`), seeding each from the last fix.

    Keyword arguments go to :class:`MotionModel`. ``localize_options`` (e.g. ``top_k``,
    ``min_confidence``) are sent with every request.
    """

    client: Client

    def update(self, points: Any, stamp: float, odom_delta: Any = None) -> Localization:
        """Localize the scan ``points`` taken at ``stamp`` (seconds); ``odom_delta`` is
        the vehicle's motion since its previous scan (``T_prev_curr``), if it has one.

        A scan with nothing to describe (a blind or blocked sensor) is a miss: while
        tracking, an answer with verdict ``tracking_failed``; in a global search,
        :class:`~sgvloc_client.EmptyScan` (counted as a miss all the same)."""
        seed = self._seed(stamp, odom_delta)
        try:
            result = self.client.localize(self.map, points=points, seed=seed, **self.options)
        except EmptyScan:
            self.model.misses += 1
            raise
        self.model.observe(result, stamp)
        return result


class AsyncTracker(_TrackerBase):
    """:class:`Tracker` for an :class:`~sgvloc_client.AsyncClient`."""

    client: AsyncClient

    async def update(self, points: Any, stamp: float, odom_delta: Any = None) -> Localization:
        """See :meth:`Tracker.update`."""
        seed = self._seed(stamp, odom_delta)
        try:
            result = await self.client.localize(self.map, points=points, seed=seed, **self.options)
        except EmptyScan:
            self.model.misses += 1
            raise
        self.model.observe(result, stamp)
        return result
