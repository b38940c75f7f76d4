"""The registrations of seeded localization on real scans: coarse VGICP then GICP (the
default), coarse then fine VGICP, and GICP alone all recover a pose from a seed 1 m and
5 degrees off; the scan filter drops non-finite and far points."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sgvloc.core.config import TrackingConfig
from sgvloc.core.encoders import EncoderSpec, make_encoder
from sgvloc.core.errors import InputError
from sgvloc.core.sequence import KittiSequence
from sgvloc.core.tracking import Seed, build_submap, register, scan_cloud


@pytest.fixture(scope="module")
def scans(balm_mini_dir: Path):
    seq = KittiSequence(balm_mini_dir)
    encoder = make_encoder(EncoderSpec())
    clouds = [
        (i, seq[i].T_world_sensor, encoder.prepare(seq[i].scan().xyzi()))
        for i in range(0, len(seq), 2)
    ]
    return seq, clouds


@pytest.mark.parametrize(
    "settings",
    [{}, {"registration": "vgicp"}, {"vgicp_coarse_voxel_m": 0.0}],
    ids=["coarse-vgicp-then-gicp", "coarse-then-fine-vgicp", "gicp-alone"],
)
def test_a_seed_1m_and_5deg_off_is_recovered(scans, settings: dict) -> None:
    seq, clouds = scans
    cfg = TrackingConfig(**settings)
    submap = build_submap(clouds, cfg)
    assert (submap.voxels is None) == (cfg.registration == "gicp")
    assert (submap.coarse is not None) == (cfg.vgicp_coarse_voxel_m > 0)
    for i in (1, 7, 13):  # not in the map
        T = seq[i].T_world_sensor
        c, s = np.cos(np.radians(5.0)), np.sin(np.radians(5.0))
        S = T.copy()
        S[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ S[:3, :3]
        S[0, 3] += 1.0
        out = register(seq[i].scan().xyzi(), Seed(S, 1.0, 5.0), submap, cfg)
        D = np.linalg.inv(T) @ out.T_map_sensor
        assert out.ok, out.why
        assert np.linalg.norm(D[:3, 3]) < 0.15
        assert np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))) < 1.0


def test_a_scan_of_a_few_points_is_not_trusted(scans) -> None:
    """Twelve points of a 0.6 m patch keep one or two on the scan's voxel grid: they fit
    anywhere, so the fit is refused whatever its fitness (it was accepted 10 m off)."""
    seq, clouds = scans
    cfg = TrackingConfig()
    submap = build_submap(clouds, cfg)
    pts = seq[7].scan().xyzi()
    near = pts[np.argsort(np.linalg.norm(pts[:, :3] - [5.0, 0.0, 0.0], axis=1))[:12]]
    out = register(near, Seed(seq[7].T_world_sensor, 4.0, 45.0), submap, cfg)
    assert not out.ok and "too few to fix a pose" in out.why and out.scan_points < 30


def _corridor(rng: np.random.Generator, n: int = 6000) -> np.ndarray:
    """Ground and two walls 3 m either side, 60 m long, nothing across: a scan of it
    fits as well anywhere along x."""
    x = rng.uniform(-30.0, 30.0, n)
    side = rng.integers(0, 3, n)  # 0 ground, 1 and 2 the walls
    y = np.where(side == 0, rng.uniform(-3.0, 3.0, n), np.where(side == 1, -3.0, 3.0))
    z = np.where(side == 0, 0.0, rng.uniform(0.0, 3.0, n))
    return np.column_stack([x, y, z]) + rng.normal(0.0, 0.01, (n, 3))


@pytest.mark.parametrize("floor", [-1.4, None])
def test_a_fit_free_to_slide_along_a_corridor_is_not_trusted(floor: float | None) -> None:
    """Every check but the conditioning passes a fit in a corridor, wherever along it the
    seed put the scan (such fits were accepted 2-3 m off); min_conditioning refuses it,
    None (maps stored before the setting) does not."""
    rng = np.random.default_rng(5)
    cfg = TrackingConfig(min_conditioning=floor)
    submap = build_submap([(0, np.eye(4), _corridor(rng))], cfg)
    seed = np.eye(4)
    seed[0, 3] = 1.0
    out = register(_corridor(rng), Seed(seed, 1.0, 5.0), submap, cfg)
    assert out.conditioning < -1.4 and out.fitness > 0.9, out
    if floor is None:
        assert out.ok, out.why
    else:
        assert not out.ok and "free to slide" in out.why, out.why


def test_a_scan_with_too_few_usable_points_is_a_failed_fit(scans) -> None:
    """Not a 422: the localizer falls back as for any failed fit (docs/API.md)."""
    seq, clouds = scans
    cfg = TrackingConfig(max_range_m=12.0)
    submap = build_submap(clouds, cfg)
    pts = np.zeros((16, 4), np.float32)
    pts[:, 0] = np.arange(16) + 20.0  # every point beyond max_range_m
    out = register(pts, Seed(seq[7].T_world_sensor, 1.0, 5.0), submap, cfg)
    assert not out.ok and out.T_map_sensor is None and "usable points" in out.why, out


def test_scan_cloud_drops_non_finite_and_far_points() -> None:
    cfg = TrackingConfig(max_range_m=12.0)
    pts = np.zeros((16, 4), np.float32)
    pts[:, 0] = np.arange(16)  # 0..15 m along x
    pts[2, 1] = np.nan
    pts[3, 2] = np.inf
    out = scan_cloud(pts, cfg)
    assert out.dtype == np.float64 and out.shape == (11, 3)  # 0..12 m less the two bad rows
    assert set(out[:, 0]) == {0, 1, *range(4, 13)}


def test_a_seed_takes_numpy_numbers_but_not_booleans() -> None:
    seed = Seed(np.eye(4), np.float32(1.5), np.int64(5))
    assert seed.sigma_m == 1.5 and isinstance(seed.sigma_m, float) and seed.sigma_yaw_deg == 5.0
    with pytest.raises(InputError, match="sigma_m"):
        Seed(np.eye(4), True, 5.0)
