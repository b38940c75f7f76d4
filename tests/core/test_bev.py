"""BEV raster (kitti-bev density image) and pixel <-> metre mapping, on hand-made points."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sgvloc.core.bev import (
    KITTI_BEV,
    BEVRasterConfig,
    crop_image_azimuth,
    density_image,
    ground_rotation,
    load_bev_image,
    metres_to_pixel,
    pixel_to_metres,
    prepare_points,
    rasterize,
)
from sgvloc.core.errors import InputError


def column(x: float, y: float, n_voxels: int, z0: float = 0.1) -> np.ndarray:
    """Points filling ``n_voxels`` stacked 0.4 m voxels of the column at (x, y), 3 per voxel."""
    z = z0 + 0.4 * np.repeat(np.arange(n_voxels), 3) + np.tile([0.0, 0.05, 0.1], n_voxels)
    return np.c_[np.full(len(z), x), np.full(len(z), y), z]


def test_pixel_metre_mapping_matches_the_readme() -> None:
    # x = (75 - r + 0.5) * 0.4, y = (75 - c + 0.5) * 0.4
    xy = pixel_to_metres(np.array([75, 0, 150, 13]), np.array([75, 0, 150, 100]))
    np.testing.assert_allclose(
        xy, [[0.2, 0.2], [30.2, 30.2], [-29.8, -29.8], [25.0, -9.8]], atol=1e-12
    )
    rng = np.random.default_rng(0)
    pts = rng.uniform(-25, 25, size=(200, 2))
    rows, cols = metres_to_pixel(pts)
    np.testing.assert_allclose(pixel_to_metres(rows, cols), pts, atol=1e-9)
    # the pixel a point falls in contains it (within half a cell of its centre)
    r_int, c_int = np.floor(rows + 0.5), np.floor(cols + 0.5)
    assert np.all(np.abs(pixel_to_metres(r_int, c_int) - pts) <= 0.2 + 1e-9)


def test_raster_counts_voxels_per_column_by_hand() -> None:
    pts = np.concatenate(
        [
            column(0.1, 0.1, 3),  # pixel (75, 75): 3 voxels -> level 2
            column(-0.3, 10.1, 12),  # r = 75 - floor(-0.75) = 76, c = 75 - 25 = 50: capped
            column(
                5.1, -5.1, 1
            ),  # r = 75 - 12 = 63, c = 75 + 13 = 88: one voxel (ground-like) -> 0
            column(24.9, 0.1, 6),  # r = 75 - 62 = 13: level 5
            column(25.1, 0.1, 6),  # |x| >= 25: cropped
            [[0.1, 0.1, 24.1], [0.1, 0.1, 25.3], [0.1, 0.1, -25.5]],  # |z| >= 25: cropped
        ]
    )
    raster = rasterize(pts)
    assert raster.image.shape == (151, 151) and raster.image.dtype == np.uint8
    counts = raster.counts
    assert counts[75, 75] == 3 + 1  # and the voxel at z = 24.1
    assert counts[76, 50] == 12
    assert counts[63, 88] == 1
    assert counts[13, 75] == 6
    assert counts.sum() == 4 + 12 + 1 + 6
    img = raster.image
    # levels clip(n - 1, 0, 10) * 10, normalised by the maximum (100), rounded half to even
    assert img[76, 50] == 255
    assert img[75, 75] == 76  # level 3: 76.5 -> 76
    assert img[63, 88] == 0
    assert img[13, 75] == 128  # level 5: 127.5 -> 128
    assert np.count_nonzero(img) == 3
    # the mean voxel height is kept per column; empty columns are NaN
    assert raster.height[63, 88] == pytest.approx(0.15, abs=1e-6)
    assert np.isnan(raster.height[0, 0])
    # and the lowest voxel's height: voxel centroids of the column at (-0.3, 10.1) from z 0.1
    assert raster.low[76, 50] == pytest.approx(0.15, abs=1e-6)
    assert raster.low[75, 75] == pytest.approx(0.15, abs=1e-6)
    assert np.isnan(raster.low[0, 0])


def test_density_image_levels_and_empty_image() -> None:
    counts = np.zeros((151, 151), dtype=np.int32)
    assert not density_image(counts).any()
    counts[0, :11] = np.arange(11)  # 0..10 voxels -> levels 0,0,1..9
    img = density_image(counts)
    # maximum level is 9 -> 90 maps to 255; level k -> rint(k * 10 / 90 * 255)
    expected = np.rint(np.clip(np.arange(11) - 1, 0, 10) * 10 / 90 * 255)
    np.testing.assert_array_equal(img[0, :11], expected.astype(np.uint8))


def test_prepare_points_crops_and_voxelises() -> None:
    pts = np.array([[0.01, 0.01, 0.01], [0.02, 0.03, 0.05], [30.0, 0.0, 0.0], [np.nan, 0, 0]])
    cloud = prepare_points(np.c_[pts, np.ones(4)])  # intensity column ignored
    np.testing.assert_allclose(cloud, [[0.015, 0.02, 0.03]], atol=1e-6)
    with pytest.raises(InputError, match="nothing to rasterise"):
        prepare_points(np.array([[30.0, 0.0, 0.0]]))
    with pytest.raises(InputError):
        prepare_points(np.zeros((4, 2)))


def test_raster_geometry_is_configurable() -> None:
    cfg = BEVRasterConfig(resolution=0.5, extent=10.0, half_cells=20)
    assert cfg.size == 41
    pts = np.array([[0.1, -0.1, z] for z in (0.1, 0.6, 1.1, 1.6)])
    raster = rasterize(pts, cfg)
    assert raster.image.shape == (41, 41)
    assert raster.counts[20, 21] == 4  # x: 20 - floor(0.2) = 20; y: 20 - floor(-0.2) = 21
    assert KITTI_BEV.size == 151


def test_load_bev_image(tmp_path: Path) -> None:
    cv2 = pytest.importorskip("cv2")
    img = np.zeros((151, 151), dtype=np.uint8)
    img[10, 20] = 255
    cv2.imwrite(str(tmp_path / "a.png"), img)
    np.testing.assert_array_equal(load_bev_image(tmp_path / "a.png"), img)
    cv2.imwrite(str(tmp_path / "small.png"), img[:100])
    with pytest.raises(InputError, match="expected"):
        load_bev_image(tmp_path / "small.png")
    cv2.imwrite(str(tmp_path / "rgb.png"), np.zeros((151, 151, 3), np.uint8))
    with pytest.raises(InputError, match="channels"):
        load_bev_image(tmp_path / "rgb.png")
    with pytest.raises(InputError, match="does not exist"):
        load_bev_image(tmp_path / "missing.png")


def _rot(roll_deg: float, pitch_deg: float) -> np.ndarray:
    a, b = np.radians(roll_deg), np.radians(pitch_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    return ry @ rx


def test_ground_rotation_levels_a_tilted_scan() -> None:
    rng = np.random.default_rng(1)
    g = rng.uniform(-14, 14, size=(3000, 2))
    ground = np.c_[g, -1.7 + rng.normal(0, 0.02, len(g))]
    wall = np.c_[np.full(1500, 6.0), rng.uniform(-10, 10, 1500), rng.uniform(-1.7, 4, 1500)]
    ceiling = np.c_[rng.uniform(-5, 5, size=(2000, 2)), np.full(2000, 2.5)]  # above: not ground
    world = np.concatenate([ground, wall, ceiling])
    tilt = _rot(20.0, -10.0)  # sensor -> level frame
    sensor = world @ tilt  # the points as the tilted sensor sees them (tilt.T applied)
    R, deg = ground_rotation(sensor)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    # the levelled ground normal is +z, and the tilt is the angle between the z axes
    np.testing.assert_allclose(R @ (tilt.T @ [0, 0, 1.0]), [0, 0, 1.0], atol=5e-3)
    assert deg == pytest.approx(np.degrees(np.arccos(tilt[2, 2])), abs=0.3)
    levelled = sensor @ R.T
    assert np.abs(levelled[: len(ground), 2] + 1.7).max() < 0.15
    # the same points give the same rotation (seeded); a level scan is left as it is
    np.testing.assert_array_equal(ground_rotation(sensor)[0], R)
    R0, deg0 = ground_rotation(world)
    assert deg0 < 0.3 and np.abs(R0 - np.eye(3)).max() < 1e-2


def test_ground_rotation_without_ground_is_identity() -> None:
    rng = np.random.default_rng(2)
    wall = np.c_[np.full(2000, 3.0), rng.uniform(-10, 10, 2000), rng.uniform(-2, 4, 2000)]
    few = np.c_[rng.uniform(-5, 5, size=(50, 2)), np.full(50, -1.7)]
    for pts in (wall, few, np.concatenate([wall, few]), np.zeros((0, 3))):
        R, deg = ground_rotation(pts)
        np.testing.assert_array_equal(R, np.eye(3))
        assert deg == 0.0


def test_image_azimuth_crop_blanks_the_pixels_outside_the_window():
    img = np.full((KITTI_BEV.size, KITTI_BEV.size), 200, dtype=np.uint8)
    out = crop_image_azimuth(img, 70.0)
    assert out.dtype == np.uint8 and out.shape == img.shape
    rows, cols = np.nonzero(out)
    xy = pixel_to_metres(rows, cols)
    az = np.degrees(np.arctan2(xy[:, 1], xy[:, 0]))
    assert (np.abs(az[np.hypot(*xy.T) > 0]) <= 35.0).all()
    rows, cols = np.nonzero(out == 0)
    az = np.degrees(np.arctan2(*pixel_to_metres(rows, cols)[:, ::-1].T))
    assert (np.abs(az) > 35.0).all()
    # the window holds about 70/360 of the pixels; points ahead (+x) are rows above the centre
    assert 0.15 < (out > 0).mean() < 0.25
    r, c = metres_to_pixel(np.array([[20.0, 0.0], [-20.0, 0.0]]))
    assert (
        out[int(r[0] + 0.5), int(c[0] + 0.5)] == 200 and out[int(r[1] + 0.5), int(c[1] + 0.5)] == 0
    )
    np.testing.assert_array_equal(crop_image_azimuth(img, 360.0), img)
