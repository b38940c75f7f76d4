"""The SDK's motion model: seeds from the last fixes, odometry, misses, gaps."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sgvloc_client import Localization, MotionModel
from sgvloc_client.tracking import _exp_rotation, _log_rotation


def _pose(x: float, y: float, yaw_deg: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = _exp_rotation(np.array([0.0, 0.0, math.radians(yaw_deg)]))
    T[:2, 3] = [x, y]
    return T


def _fix(T: np.ndarray | None) -> Localization:
    return Localization.from_body(
        {
            "map": "m",
            "map_version": 1,
            "localized": T is not None,
            "T_map_sensor": None if T is None else T.tolist(),
        }
    )


@pytest.mark.parametrize("angle", [0.0, 0.3, 2.0, math.pi - 1e-3, math.pi])
def test_rotation_log_and_exp_are_inverse(angle: float) -> None:
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    R = _exp_rotation(axis * angle)
    np.testing.assert_allclose(_exp_rotation(_log_rotation(R)), R, atol=1e-6)


def test_constant_velocity_prediction_and_growing_sigmas() -> None:
    m = MotionModel(
        sigma_m=0.5, sigma_yaw_deg=2.0, growth_m_per_s=1.0, growth_yaw_deg_per_s=10, turn_factor=1
    )
    assert m.seed(0.0) is None and m.lost  # nothing to seed from: global
    m.observe(_fix(_pose(0, 0, 0)), 0.0)
    s = m.seed(0.5)  # one fix: no velocity yet, the last pose
    np.testing.assert_allclose(s.T_map_sensor, _pose(0, 0, 0))
    assert s.sigma_m == pytest.approx(1.0) and s.sigma_yaw_deg == pytest.approx(7.0)
    m.observe(_fix(_pose(1, 0, 10)), 0.5)  # 2 m/s forward, turning 20 deg/s
    s = m.seed(1.0)
    # the same step again from the last pose: forward 1 m in its frame, 10 deg more
    np.testing.assert_allclose(s.T_map_sensor, _pose(1, 0, 10) @ _pose(1, 0, 10), atol=1e-9)
    s = m.seed(0.75)  # half a period: half the step
    np.testing.assert_allclose(s.T_map_sensor, _pose(1, 0, 10) @ _pose(0.5, 0, 5), atol=1e-9)
    m.turn_factor = 0.5  # the default: half the turn carried over
    s = m.seed(1.0)
    np.testing.assert_allclose(s.T_map_sensor, _pose(1, 0, 10) @ _pose(1, 0, 5), atol=1e-9)


def test_odometry_replaces_the_motion_model_and_accumulates_over_misses() -> None:
    m = MotionModel()
    m.observe(_fix(_pose(5, 5, 90)), 0.0)
    step = _pose(1, 0, 0)
    s = m.seed(0.1, odom_delta=step)
    np.testing.assert_allclose(s.T_map_sensor, _pose(5, 5, 90) @ step, atol=1e-12)
    m.max_misses = 3
    m.observe(_fix(None), 0.1)  # a miss: the odometry since the fix keeps adding up
    s = m.seed(0.2, odom_delta=step)
    np.testing.assert_allclose(s.T_map_sensor, _pose(5, 5, 90) @ step @ step, atol=1e-12)
    assert s.sigma_m > m.sigma_m * m.widen  # widened after the miss


def test_a_bad_odometry_sample_is_refused_and_spoils_no_later_seed() -> None:
    """A NaN, non-rigid or misshapen odom_delta is a ValueError naming it, before it
    enters the track: the next scan with good odometry is seeded as if it never came.
    Odometry a little off orthonormal (float32) is straightened, not refused."""
    m = MotionModel()
    m.observe(_fix(_pose(5, 5, 90)), 0.0)
    step = _pose(1, 0, 0)
    nan = step.copy()
    nan[0, 3] = np.nan
    skew = step.copy()
    skew[0, 1] = 0.5
    for bad, match in [
        (nan, "finite"),
        (skew, "not a rigid transform"),
        (np.eye(3), "got shape"),
        ("forward", "4x4 transform"),
        (_pose(1e5, 0, 0), "at most"),
    ]:
        with pytest.raises(ValueError, match=match) as info:
            m.seed(0.1, odom_delta=bad)
        assert "odom_delta" in str(info.value)
    s = m.seed(0.1, odom_delta=step)
    np.testing.assert_allclose(s.T_map_sensor, _pose(5, 5, 90) @ step, atol=1e-12)
    drifted = _pose(0, 1, 30).astype(np.float32) * np.float32(1.0001)
    drifted[3] = [0, 0, 0, 1]
    s = m.seed(0.2, odom_delta=drifted)
    R = s.T_map_sensor[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)  # a rigid seed for the service


def test_predict_changes_nothing_and_fixes_close_in_time_give_no_velocity() -> None:
    m = MotionModel()
    m.observe(_fix(_pose(0, 0, 0)), 0.0)
    step = _pose(1, 0, 0)
    first, again = m.predict(0.1, odom_delta=step), m.predict(0.1, odom_delta=step)
    np.testing.assert_allclose(first, again)  # a preview does not count the odometry
    np.testing.assert_allclose(m.seed(0.1, odom_delta=step).T_map_sensor, first)
    # two fixes 1 ms apart, 2 cm of registration noise: no 20 m/s velocity from them
    m = MotionModel()
    m.observe(_fix(_pose(0, 0, 0)), 10.0)
    m.observe(_fix(_pose(0.02, 0, 0)), 10.001)
    np.testing.assert_allclose(m.seed(10.1).T_map_sensor, _pose(0.02, 0, 0), atol=1e-12)
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match="stamp"):
            m.seed(bad)


def test_misses_and_gaps_send_the_next_scan_global() -> None:
    m = MotionModel(max_misses=2, max_gap_s=5.0)
    m.observe(_fix(_pose(0, 0, 0)), 0.0)
    first = m.seed(0.1)
    m.observe(_fix(None), 0.1)
    wider = m.seed(0.2)
    assert wider is not None and wider.sigma_m > first.sigma_m * 2
    m.observe(_fix(None), 0.2)
    assert m.lost and m.seed(0.3) is None  # two misses: relocalize globally
    m.observe(_fix(_pose(3, 0, 0)), 0.3)
    assert not m.lost and m.seed(0.4) is not None
    assert m.seed(10.0) is None  # too long since the last fix
    m.reset()
    assert m.pose is None and m.seed(0.5) is None


def test_bad_settings_are_refused() -> None:
    with pytest.raises(ValueError):
        MotionModel(sigma_m=0)
    with pytest.raises(ValueError):
        MotionModel(max_misses=0)
    with pytest.raises(ValueError):
        MotionModel(turn_factor=2)
