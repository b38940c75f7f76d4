"""The synthetic town: deterministic for a seed; its poses agree with its scans."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from sgvloc.core.errors import InputError
from sgvloc.core.preprocess import voxel_downsample
from sgvloc.core.sequence import KittiSequence, relative_pose
from sgvloc.tools.evaluation.metrics import rre, rte
from sgvloc.tools.synth import SynthConfig, build_town, generate, route_poses

SMALL = dict(scans=6, azimuth_steps=512, beams=32)


def files(root):
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*.*"))}


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth") / "a"
    generate(root, SynthConfig(seed=3, **SMALL))
    return root


def test_same_seed_same_bytes_other_seed_other_world(small, tmp_path):
    generate(tmp_path / "b", SynthConfig(seed=3, **SMALL))
    assert files(small) == files(tmp_path / "b")
    generate(tmp_path / "c", SynthConfig(seed=4, **SMALL))
    assert files(small)["velodyne/000000.bin"] != files(tmp_path / "c")["velodyne/000000.bin"]
    with pytest.raises(InputError):
        generate(small, SynthConfig(seed=3, **SMALL))  # refuses to overwrite


def test_kitti_layout_and_plausible_scans(small):
    seq = KittiSequence(small)
    assert len(seq) == 6 and seq.poses.shape == (6, 4, 4)
    assert np.allclose(np.diff(seq.times), 0.1)
    steps = np.linalg.norm(np.diff(seq.poses[:, :3, 3], axis=0), axis=1)
    assert np.allclose(steps, 1.0, atol=0.05)
    scan = seq[0].scan()
    assert 3000 < len(scan) < 32 * 512
    r = np.linalg.norm(scan.points, axis=1)
    assert r.min() >= 1.0 and r.max() <= 80.0
    assert 0.0 <= scan.intensity.min() and scan.intensity.max() <= 1.0
    # the ground is 1.8 m below the sensor, and something stands above it
    assert np.median(scan.points[:, 2]) == pytest.approx(-1.8, abs=0.3)
    assert (scan.points[:, 2] > 0.5).sum() > 200
    info = json.loads((small / "synth.json").read_text())
    assert info["config"]["seed"] == 3 and info["scans"] == 6


def _icp(src, dst, T0):
    import open3d as o3d

    reg = o3d.pipelines.registration
    pcs = [
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p.astype(np.float64)))
        for p in (src, dst)
    ]
    res = reg.registration_icp(
        pcs[0], pcs[1], 0.5, T0, reg.TransformationEstimationPointToPoint(),
        reg.ICPConvergenceCriteria(max_iteration=50),
    )  # fmt: skip
    return np.asarray(res.transformation)


def _median_nn(src, dst, T):
    from scipy.spatial import cKDTree

    moved = src @ T[:3, :3].T + T[:3, 3]
    return float(np.median(cKDTree(dst).query(moved)[0]))


def test_poses_agree_with_scans(small):
    seq = KittiSequence(small)
    for i in (0, 3):
        a = voxel_downsample(seq[i].scan().points, 0.2)
        b = voxel_downsample(seq[i + 1].scan().points, 0.2)
        T_gt = relative_pose(seq.poses[i], seq.poses[i + 1])  # scan i -> scan i+1
        T_icp = _icp(a, b, T_gt)
        assert rte(T_icp, T_gt) < 0.1 and rre(T_icp, T_gt) < 1.0
        # structure above the ground (ground rings from two places interleave)
        a_up = a[a[:, 2] > -1.3]
        good = _median_nn(a_up, b, T_gt)
        assert good < 0.25  # about the sampling spacing at 512 azimuth steps
        off = T_gt.copy()
        off[:3, 3] += [0.0, 0.5, 0.0]  # half a metre sideways is clearly worse
        assert _median_nn(a_up, b, off) > 2 * good


def test_route_revisits_from_the_opposite_direction():
    cfg = SynthConfig(scans=600, seed=1)
    town = build_town(cfg, 3)
    T = route_poses(cfg, 3, town.pitch)
    pos, heading = T[:, :2, 3], T[:, :2, 0]
    d = np.linalg.norm(pos[:, None] - pos[None], axis=2)  # [F, F]
    gap = np.abs(np.arange(600)[:, None] - np.arange(600)[None])
    revisit = (d < 8.0) & (gap > 100)
    opposite = revisit & (heading @ heading.T < -0.9)
    assert opposite.any(axis=1).sum() > 100
    # opposite-direction revisits run in other lanes: 3.5 m or more apart sideways
    i, j = np.nonzero(opposite & (d < 20.0))
    assert np.median(d[i, j]) > 3.0


def test_bev_images_of_a_scan_sequence(small, tmp_path):
    from typer.testing import CliRunner

    from sgvloc.cli import app
    from sgvloc.core.bev import load_bev_image, rasterize
    from sgvloc.tools.evaluation.data import open_sequence

    out = tmp_path / "bev"
    res = CliRunner().invoke(app, ["bev-images", str(small), str(out), "--no-progress"])
    assert res.exit_code == 0, res.output
    scans, images = KittiSequence(small), open_sequence(out)
    assert images.kind == "bev-images" and len(images.paths) == len(scans)
    np.testing.assert_allclose(images.poses, scans.poses, atol=1e-6)
    np.testing.assert_allclose(images.times, scans.times, atol=1e-6)
    # each image is the project's raster of its scan
    np.testing.assert_array_equal(
        load_bev_image(images.paths[2]), rasterize(scans[2].scan().points).image
    )
    again = CliRunner().invoke(app, ["bev-images", str(small), str(out)])
    assert again.exit_code == 1 and "overwrite" in again.output
    # overwritten by a shorter sequence: no image of the longer one is left
    shorter = tmp_path / "shorter"
    shutil.copytree(small, shorter)
    for path in KittiSequence(shorter).paths[3:]:
        path.unlink()
    for name in ("poses.txt", "times.txt"):
        rows = (shorter / name).read_text().splitlines()[:3]
        (shorter / name).write_text("\n".join(rows) + "\n")
    res = CliRunner().invoke(app, ["bev-images", str(shorter), str(out), "--overwrite"])
    assert res.exit_code == 0, res.output
    assert len(open_sequence(out).paths) == 3
    # a run that fails (a scan with no finite point) names the scan and leaves the
    # previous images as they were
    before = files(out)
    broken = tmp_path / "broken"
    shutil.copytree(small, broken)
    np.full((10, 4), np.nan, np.float32).tofile(broken / "velodyne" / "000004.bin")
    res = CliRunner().invoke(app, ["bev-images", str(broken), str(out), "--overwrite"])
    assert res.exit_code == 1 and "000004.bin" in res.output, res.output
    assert files(out) == before and not list(out.glob(".*"))


def test_staged_outputs_replace_links_and_undo_a_failed_move(tmp_path, monkeypatch):
    from sgvloc.tools.staging import staged

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "old.bin").write_bytes(b"old")
    out = tmp_path / "out"
    out.mkdir()
    (out / "velodyne").symlink_to(elsewhere)
    (out / "poses.txt").write_text("old poses")
    with staged(out, ("velodyne", "poses.txt")) as stage:
        (stage / "velodyne").mkdir()
        (stage / "velodyne" / "new.bin").write_bytes(b"new")
        (stage / "poses.txt").write_text("new poses")
    assert not (out / "velodyne").is_symlink() and (out / "velodyne" / "new.bin").exists()
    assert (elsewhere / "old.bin").read_bytes() == b"old"  # the link's target is kept
    assert (out / "poses.txt").read_text() == "new poses" and not list(out.glob(".*"))
    # a move that fails half-way puts the previous outputs back
    real_rename = Path.rename

    def failing(self, target):  # noqa: ANN001, ANN202
        if self.name == "poses.txt" and ".staging-" in str(self):
            raise OSError("disk gone")
        return real_rename(self, target)

    monkeypatch.setattr(Path, "rename", failing)
    with pytest.raises(OSError, match="disk gone"):
        with staged(out, ("velodyne", "poses.txt")) as stage:
            (stage / "velodyne").mkdir()
            (stage / "poses.txt").write_text("newer")
    monkeypatch.setattr(Path, "rename", real_rename)
    assert (out / "velodyne" / "new.bin").exists()
    assert (out / "poses.txt").read_text() == "new poses" and not list(out.glob(".*"))


def test_an_overwrite_that_fails_leaves_the_previous_sequence(small, tmp_path, monkeypatch):
    import sgvloc.tools.synth as synth

    out = tmp_path / "town"
    shutil.copytree(small, out)
    before = files(out)
    real, calls = synth.Lidar.scan, []

    def interrupted(self, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(self, *args, **kwargs)

    monkeypatch.setattr(synth.Lidar, "scan", interrupted)
    with pytest.raises(KeyboardInterrupt):
        generate(out, SynthConfig(seed=9, **SMALL), overwrite=True)
    assert files(out) == before and not list(out.glob(".*"))
    monkeypatch.setattr(synth.Lidar, "scan", real)
    generate(out, SynthConfig(seed=9, **SMALL), overwrite=True)
    assert files(out) != before and not list(out.glob(".*"))
    assert json.loads((out / "synth.json").read_text())["config"]["seed"] == 9


@pytest.mark.parametrize("pattern", ["spinning", "rosette"])
def test_a_narrow_field_of_view_has_the_configured_extent(tmp_path, pattern):
    """--fov 70: every point lies within 35 deg of the forward axis and the scans span
    most of that window; the rosette covers other lines in each scan."""
    cfg = SynthConfig(seed=3, scans=3, beams=16, azimuth_steps=512, fov_h_deg=70.0, pattern=pattern)
    generate(tmp_path, cfg)
    seq = KittiSequence(tmp_path)
    scans = [seq[i].scan().points for i in range(3)]
    for p in scans:
        az = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
        el = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
        assert np.abs(az).max() <= 35.0 + 1e-3 and az.max() - az.min() > 60.0
        assert el.min() >= -25.0 - 1e-3 and el.max() <= 15.0 + 1e-3
    if pattern == "spinning":  # the azimuth spacing of 512 steps per turn is kept
        full = SynthConfig(seed=3, scans=3, beams=16, azimuth_steps=512)
        generate(tmp_path / "full", full)
        n360 = len(KittiSequence(tmp_path / "full")[0].scan().points)
        assert 0.1 < len(scans[0]) / n360 < 0.35
    else:  # non-repetitive: two scans trace the petals turned differently
        from sgvloc.tools.synth import Lidar, Town

        lidar = Lidar(Town({}, 1, 1.0, {}), cfg)
        (e1, a1), (e2, a2) = (lidar.directions(np.random.default_rng(s)) for s in (1, 2))
        assert e1.shape == a1.shape == (16 * 512,)
        one = np.c_[a1, e1][:, None, :]
        two = np.c_[a2, e2][None, ::16, :]
        gap = np.degrees(np.abs(one - two).sum(axis=2).min(axis=0))  # per ray of the second
        assert np.median(gap) > 0.05
    with pytest.raises(ValueError, match="fov_down_deg"):
        SynthConfig(fov_up_deg=-30.0, fov_down_deg=-25.0)


def test_a_range_that_reaches_nothing_is_refused(tmp_path):
    with pytest.raises(ValueError, match="min_range_m"):
        SynthConfig(min_range_m=3.0, max_range_m=2.0)
    with pytest.raises(InputError, match="holds no point"):
        generate(tmp_path / "s", SynthConfig(scans=2, max_range_m=2.0), progress=False)


def test_sigterm_mid_run_leaves_no_staging_folder(tmp_path):
    """`sgvloc synth` stopped by SIGTERM (a job runner's stop) cleans up as after Ctrl-C:
    the half-written sequence in its staging folder is removed."""
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "town"
    proc = subprocess.Popen(
        [sys.executable, "-m", "sgvloc.cli", "synth", str(out), "--scans", "400", "--no-progress"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    try:
        deadline = time.monotonic() + 120
        while not list(out.glob(".staging-*/velodyne/*.bin")) and time.monotonic() < deadline:
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err.decode()
    assert list(out.iterdir()) == [], list(out.iterdir())
