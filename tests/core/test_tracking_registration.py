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


def test_scan_cloud_drops_non_finite_and_far_points() -> None:
    cfg = TrackingConfig(max_range_m=12.0)
    pts = np.zeros((16, 4), np.float32)
    pts[:, 0] = np.arange(16)  # 0..15 m along x
    pts[2, 1] = np.nan
    pts[3, 2] = np.inf
    out = scan_cloud(pts, cfg)
    assert out.dtype == np.float64 and out.shape == (11, 3)  # 0..12 m less the two bad rows
    assert set(out[:, 0]) == {0, 1, *range(4, 13)}
    with pytest.raises(InputError, match="usable points"):
        scan_cloud(pts[:11], cfg)


def test_a_seed_takes_numpy_numbers_but_not_booleans() -> None:
    seed = Seed(np.eye(4), np.float32(1.5), np.int64(5))
    assert seed.sigma_m == 1.5 and isinstance(seed.sigma_m, float) and seed.sigma_yaw_deg == 5.0
    with pytest.raises(InputError, match="sigma_m"):
        Seed(np.eye(4), True, 5.0)
