"""Preprocessing: finite filter, range crop, voxel grid, ground removal."""

import numpy as np
import pytest

from sgvloc.core.config import PreprocessConfig
from sgvloc.core.errors import InputError
from sgvloc.core.preprocess import (
    crop_azimuth,
    crop_range,
    preprocess,
    remove_ground,
    voxel_downsample,
)


def scene(rng: np.random.Generator) -> np.ndarray:
    """A flat ground at z = -1.7 m plus a 2 m tall wall of points at x = 6 m."""
    ground = np.c_[rng.uniform(-20, 20, (4000, 2)), np.full(4000, -1.7)]
    wall = np.c_[np.full(1000, 6.0), rng.uniform(-3, 3, 1000), rng.uniform(-1.7, 0.3, 1000)]
    return (np.r_[ground, wall] + rng.normal(0, 0.01, (5000, 3))).astype(np.float32)


def test_voxel_downsample_keeps_one_centroid_per_cell():
    pts = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [1.1, 0.1, 0.1]], np.float32)
    out = voxel_downsample(pts, 1.0)
    assert len(out) == 2
    assert np.allclose(sorted(out[:, 0]), [0.15, 1.1])
    # independent of the order of the points
    again = voxel_downsample(pts[::-1].copy(), 1.0)
    assert np.allclose(np.sort(out, axis=0), np.sort(again, axis=0))
    assert voxel_downsample(pts, 0.0) is pts


def test_a_voxel_grid_too_fine_for_one_integer_key_still_averages_each_cell(rng):
    """A 10 micrometre grid over 120 m has more cells than an int64 can number; the
    points are grouped by their cell triples instead (a ValueError, a 500, before)."""
    pts = rng.uniform(-60, 60, (200, 3)).astype(np.float32)
    pts = np.r_[pts, pts[:5]]  # five points twice: one cell each
    out = voxel_downsample(pts, 1e-5)
    assert len(out) == 200
    np.testing.assert_allclose(np.sort(out, axis=0), np.sort(pts[:200], axis=0), atol=1e-5)


def test_ground_removal_is_the_same_from_several_threads_at_once(rng):
    """Open3D's RANSAC draws from one generator per process: scans whose ground is
    removed at the same time in several threads each lose the plane they lose alone."""
    from concurrent.futures import ThreadPoolExecutor

    scans = [scene(np.random.default_rng(i)) for i in range(8)]
    alone = [len(remove_ground(s, 0.2, 20.0)) for s in scans]
    with ThreadPoolExecutor(4) as pool:
        for _ in range(5):
            together = list(pool.map(lambda s: len(remove_ground(s, 0.2, 20.0)), scans))
            assert together == alone


def test_crop_range_and_finite_filter():
    pts = np.array([[0.1, 0, 0], [5, 0, 0], [100, 0, 0], [np.nan, 0, 0], [np.inf, 1, 1]])
    cfg = PreprocessConfig(min_range=0.5, max_range=60, voxel_size=0)
    out = preprocess(pts.astype(np.float32), cfg)
    assert out.shape == (1, 3) and out[0, 0] == 5.0
    assert len(crop_range(pts[:3], 0.0, 200.0)) == 3


def test_extra_columns_are_ignored_and_output_is_float32(rng):
    pts = np.c_[rng.uniform(-10, 10, (100, 3)), rng.uniform(0, 1, 100)]  # x y z intensity
    out = preprocess(pts, PreprocessConfig(voxel_size=0))
    assert out.dtype == np.float32 and out.shape[1] == 3


def test_ground_removal_removes_the_floor_not_the_wall(rng):
    pts = scene(rng)
    out = remove_ground(pts, distance=0.2, max_tilt_deg=20)
    assert (out[:, 2] < -1.5).sum() < 0.05 * 4000  # the floor is gone
    # the wall stays, but for its lowest 0.2 m (within the ground distance): ~90% of it
    assert (np.abs(out[:, 0] - 6.0) < 0.1).sum() > 0.85 * 1000


def test_a_wall_is_not_ground(rng):
    wall = np.c_[np.full(2000, 6.0), rng.uniform(-5, 5, 2000), rng.uniform(-2, 2, 2000)]
    out = remove_ground(wall.astype(np.float32), distance=0.2, max_tilt_deg=20)
    assert len(out) == 2000


def test_preprocess_with_ground_removal(rng):
    cfg = PreprocessConfig(voxel_size=0.3, remove_ground=True)
    out = preprocess(scene(rng), cfg)
    assert 0 < len(out) < 1000


@pytest.mark.parametrize(
    ("scan", "message"),
    [
        (np.zeros((0, 3), np.float32), "empty"),
        (np.zeros((5, 2), np.float32), r"\[P, 3\]"),
        (np.full((5, 3), np.nan, np.float32), "no points left"),
        (np.array([["a", "b", "c"]]), "numeric"),
        ([[1.0, 2.0, 3.0], [1.0, 2.0]], "rectangular"),
    ],
)
def test_bad_scans_raise_clear_errors(scan, message):
    with pytest.raises(InputError, match=message):
        preprocess(scan, PreprocessConfig())


def test_azimuth_crop_keeps_exactly_the_points_inside_the_window():
    rng = np.random.default_rng(4)
    pts = np.c_[rng.uniform(-30, 30, size=(5000, 3)), rng.random(5000)]  # x y z intensity
    # points exactly on the window's edges (+-35 deg) and just outside
    edge = np.radians([35.0, -35.0, 35.01, -35.01, 0.0, 180.0])
    pts[: len(edge), :2] = 10.0 * np.c_[np.cos(edge), np.sin(edge)]
    out = crop_azimuth(pts, 70.0)
    az = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
    np.testing.assert_array_equal(out, pts[np.abs(az) <= 35.0])  # every column kept
    kept = {tuple(p) for p in out[:, :2].round(6)}
    for i, inside in enumerate([True, True, False, False, True, False]):
        assert (tuple(pts[i, :2].round(6)) in kept) == inside
    assert crop_azimuth(pts, 360.0) is pts
    with pytest.raises(InputError, match="field of view"):
        crop_azimuth(pts, 0.0)
