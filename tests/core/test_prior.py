"""Prior poses and the keyframe position grid they query."""

from __future__ import annotations

import numpy as np
import pytest
from pose_helpers import planar_pose as _T

from sgvloc.core.errors import InputError
from sgvloc.core.prior import PositionGrid, Prior, yaw_deg


def test_grid_finds_exactly_the_keyframes_inside_the_radius() -> None:
    rng = np.random.default_rng(1)
    pos = rng.uniform(-200, 200, size=(2000, 3))
    grid = PositionGrid(cell_m=10.0)
    for i, p in enumerate(pos):
        grid.add(i + 1, p)
    for center, r in [((0.0, 0.0), 20.0), ((150.0, -120.0), 7.5), ((0.0, 0.0), 1000.0)]:
        prior = Prior(center, r)
        want = np.flatnonzero(np.linalg.norm(pos[:, :2] - center, axis=1) <= r) + 1
        np.testing.assert_array_equal(grid.within(prior), want)
    # three values: distance in 3-D
    prior3 = Prior((0.0, 0.0, 50.0), 60.0)
    want3 = np.flatnonzero(np.linalg.norm(pos - [0, 0, 50], axis=1) <= 60) + 1
    np.testing.assert_array_equal(grid.within(prior3), want3)
    # removals and moves
    inside = grid.within(Prior((0.0, 0.0), 20.0))
    grid.remove(int(inside[0]))
    grid.add(int(inside[1]), np.array([500.0, 500.0, 0.0]))
    after = grid.within(Prior((0.0, 0.0), 20.0))
    assert set(after) == set(inside[2:].tolist())
    assert len(grid) == 1999
    grid.clear()
    assert len(grid.within(Prior((0.0, 0.0), 1e6))) == 0


def test_a_keyframe_exactly_on_the_radius_at_a_cell_edge_is_found() -> None:
    """x - r rounds into the next cell although the keyframe, a hair below the cell
    edge, lies exactly on the radius: the search still looks in its cell."""
    grid = PositionGrid(cell_m=10.0)
    p = float(np.nextafter(10.0, -np.inf))
    grid.add(1, np.array([p, 0.0, 0.0]))
    x, r = 50.92423645144843, 40.92423645144843
    assert abs(p - x) <= r and np.floor((x - r) / 10.0) > np.floor(p / 10.0)
    assert grid.within(Prior((x, 0.0), r)).tolist() == [1]


def test_prior_rejects_estimates_outside_its_region() -> None:
    p = Prior((10.0, 0.0), 5.0)
    assert p.rejects(_T(12, 3)) is None
    assert "m from the prior position" in p.rejects(_T(20, 0))
    yawed = Prior((10.0, 0.0), 5.0, yaw_deg=90.0, yaw_tolerance_deg=20.0)
    assert yawed.rejects(_T(10, 0, 100)) is None
    assert "heading" in yawed.rejects(_T(10, 0, 130))
    wrap = Prior((0.0, 0.0), 5.0, yaw_deg=179.0, yaw_tolerance_deg=5.0)
    assert wrap.rejects(_T(0, 0, -178)) is None  # 3 deg apart across +-180
    assert yaw_deg(_T(0, 0, 45)) == pytest.approx(45.0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"position": (1.0,), "radius_m": 5.0}, "2 or 3"),
        ({"position": (1.0, float("nan")), "radius_m": 5.0}, "finite"),
        ({"position": (1.0, 2.0), "radius_m": 0.0}, "radius_m"),
        ({"position": (1.0, 2.0), "radius_m": 5.0, "yaw_tolerance_deg": 0.0}, "tolerance"),
        ({"position": (1.0, 2.0), "radius_m": 5.0, "yaw_deg": float("inf")}, "yaw_deg"),
    ],
)
def test_prior_validation(kwargs: dict, match: str) -> None:
    with pytest.raises(InputError, match=match):
        Prior(**kwargs)
