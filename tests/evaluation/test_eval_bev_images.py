"""`sgvloc eval` on a kitti-bev-layout folder (imgs/*.png + pose.txt), generated here.

A flat world of random walls and pillars (vertical columns of points) is rasterised with
the project's own BEV raster (:func:`sgvloc.core.bev.rasterize`) from a drive of 1.5 laps
around a circle: the last 15 scans revisit the first lap half a step further on.
"""

import json
import math

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from sgvloc.cli import app
from sgvloc.core.bev import load_bev_image, rasterize
from sgvloc.core.encoders import BEVEncoder
from sgvloc.tools.evaluation.data import open_sequence
from sgvloc.tools.evaluation.diagnostics import pair_match_stats

LAP = 30  # scans per lap: 0.1 s each, so a revisit comes 3 s later
SCANS = 45


def _world(rng: np.random.Generator) -> np.ndarray:
    """Points ``[P, 3]`` of walls and pillars, 0-3 m high, around the origin."""
    pts = []
    z = np.arange(0.1, 3.0, 0.3)
    for _ in range(45):  # walls: 3-10 m segments
        a = rng.uniform(-35, 35, 2)
        ang = rng.uniform(0, np.pi)
        s = np.arange(0, rng.uniform(3, 10), 0.2)
        xy = a + s[:, None] * [math.cos(ang), math.sin(ang)]
        pts.append(np.column_stack([np.repeat(xy, len(z), 0), np.tile(z, len(xy))]))
    for c in rng.uniform(-35, 35, (80, 2)):  # pillars
        pts.append(np.column_stack([np.tile(c, (len(z), 1)), z]))
    return np.concatenate(pts)


def _poses() -> np.ndarray:
    """``[SCANS, 4, 4]`` T_world_lidar along a circle (radius 12 m), heading along it."""
    out = np.tile(np.eye(4), (SCANS, 1, 1))
    for i in range(SCANS):
        a = 2 * np.pi * (i + (0.5 if i >= LAP else 0.0)) / LAP
        yaw = a + np.pi / 2
        out[i, :2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        out[i, :3, 3] = [12 * math.cos(a), 12 * math.sin(a), 0.0]
    return out


@pytest.fixture(scope="module")
def bev_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("kitti_bev") / "seq"
    (root / "imgs").mkdir(parents=True)
    world, poses = _world(np.random.default_rng(7)), _poses()
    for i, T in enumerate(poses):
        local = (world - T[:3, 3]) @ T[:3, :3]  # world -> lidar frame
        assert cv2.imwrite(str(root / "imgs" / f"{i:06d}.png"), rasterize(local).image)
    np.savetxt(root / "pose.txt", poses[:, :3, :].reshape(SCANS, 12))
    return root


def _eval(bev_dir, tmp_path, *extra):
    out = tmp_path / "out"
    args = ["eval", "--data", str(bev_dir), "--no-progress", "--cache-dir", str(tmp_path / "c")]
    args += ["--out", str(out), "--topk", "2,5", "--sweep", "1,2,5", "--methods", "none,sgv"]
    args += extra
    res = CliRunner().invoke(app, args)
    return res, out


def test_open_sequence_reads_images_poses_and_10hz_times(bev_dir):
    seq = open_sequence(bev_dir)
    assert seq.kind == "bev-images" and len(seq.paths) == SCANS
    assert seq.paths[3].name == "000003.png" and seq.poses.shape == (SCANS, 4, 4)
    np.testing.assert_allclose(seq.times[:3], [0.0, 0.1, 0.2])


def test_eval_on_bev_images_with_the_bev_encoder(bev_dir, tmp_path):
    res, out = _eval(bev_dir, tmp_path, "--min-gap", "2.5", "--encoder", '{"kind":"bev"}')
    assert res.exit_code == 0, res.output
    report = json.loads((out / "eval.json").read_text())
    assert (out / "sgv_scores.png").read_bytes()[:4] == b"\x89PNG"
    assert (out / "ntopk.png").exists()
    cfg = report["config"]
    assert cfg["data_kind"] == "bev-images" and cfg["refine_effective"] == "none"
    assert any("forced to 'none'" in n for n in report["notes"])
    # queries (an older-by-2.5 s scan within 5 m): the second lap, and scans 28, 29 that
    # close the first lap 5 m (two 2.5 m steps) before scans 0, 1
    assert report["split"]["query_indices"] == [28, 29, *range(LAP, SCANS)]
    split = report["split"]  # database: scans 0-19 (2.5 s before the last query)
    assert split["database_scans"] == 20
    scans = set(range(20)) | set(split["query_indices"]) | set(split["negative_indices"])
    assert report["timings"]["feature_cache"]["misses"] == len(scans)
    rows = {(r["method"], r["k"]): r for r in report["rows"]}
    # revisits half a step (1.3 m) from a first-lap scan: retrieval and pose are easy
    assert rows[("none", 5)]["R@5_5m"] >= 90.0
    for method in ("none", "sgv"):
        r = rows[(method, 2)]
        assert r["R@1_5m"] >= 80.0, r
        assert r["mean_rte_m"] < 2.0 and r["mean_rre_deg"] < 5.0, r
    m = report["matches"]
    assert m["planar"] and m["pairs"] == SCANS - LAP + 2
    assert 0.3 < m["nn_ratio_mean"] <= m["repeatability_mean"] <= 1.0
    assert m["chance_ratio_mean"] < 0.1
    assert "x/y" in res.output and "forced to 'none'" in res.output
    s = report["sgv_scores"]
    assert s["k"] == 5 and s["true"]["count"] > 0 and s["false"]["count"] > 0
    assert s["auc"] > 0.7 and s["true"]["p50"] > s["false"]["p50"]


def test_wrong_ground_truth_lowers_the_planar_match_ratio(bev_dir):
    seq, enc = open_sequence(bev_dir), BEVEncoder()
    q, db = LAP + 2, 2  # the revisit of scan 2, half a step on
    fq, fd = (enc.encode_image(load_bev_image(seq.paths[i])) for i in (q, db))
    T = np.linalg.inv(seq.poses[db]) @ seq.poses[q]
    kp = (fq.keypoints, fq.local_features, fd.keypoints, fd.local_features)
    good = pair_match_stats(*kp, T)
    off = T.copy()
    off[:3, 3] += [3.0, 0.0, 0.0]  # the pose 3 m off
    assert good["nn_ratio"] > 0.3 and pair_match_stats(*kp, off)["nn_ratio"] < good["nn_ratio"] / 3


def test_an_encoder_without_encode_image_is_refused(bev_dir, tmp_path):
    res, _ = _eval(bev_dir, tmp_path, "--min-gap", "2.5", "--encoder", '{"kind":"handcrafted"}')
    assert res.exit_code == 2  # handcrafted: scans only
    assert "cannot encode images" in res.output and "handcrafted" in res.output


def test_a_bev_folder_with_missing_poses_is_refused(bev_dir, tmp_path):
    bad = tmp_path / "bad"
    (bad / "imgs").mkdir(parents=True)
    for f in sorted((bev_dir / "imgs").iterdir())[:5]:
        (bad / "imgs" / f.name).write_bytes(f.read_bytes())
    res, _ = _eval(bad, tmp_path, "--min-gap", "0.2", "--encoder", '{"kind":"bev"}')
    assert res.exit_code == 2 and "pose.txt" in res.output
    lines = (bev_dir / "pose.txt").read_text().splitlines()[:4]
    (bad / "pose.txt").write_text("\n".join(lines) + "\n")
    res, _ = _eval(bad, tmp_path, "--min-gap", "0.2", "--encoder", '{"kind":"bev"}')
    assert res.exit_code == 2 and "5 images" in res.output and "4 poses" in res.output


def test_planar_distance_ignores_heights_that_disagree_between_passes(bev_dir, tmp_path):
    """The second lap's ground truth 6 m higher (an image cannot show it): measured in
    3-D its revisits are out of coverage; in the plane they are queries again."""
    high = tmp_path / "high"
    (high / "imgs").mkdir(parents=True)
    for f in (bev_dir / "imgs").iterdir():
        (high / "imgs" / f.name).write_bytes(f.read_bytes())
    poses = np.loadtxt(bev_dir / "pose.txt").reshape(SCANS, 3, 4)
    poses[LAP:, 2, 3] += 6.0
    np.savetxt(high / "pose.txt", poses.reshape(SCANS, 12))
    common = ("--min-gap", "2.5", "--encoder", '{"kind":"bev"}', "--no-negatives")

    res, out = _eval(high, tmp_path / "3d", *common)
    assert res.exit_code == 0, res.output
    report = json.loads((out / "eval.json").read_text())
    assert report["split"]["query_indices"] == [28, 29]
    assert report["config"]["planar_distance"] is False

    res, out = _eval(high, tmp_path / "plane", *common, "--planar-distance")
    assert res.exit_code == 0, res.output
    report = json.loads((out / "eval.json").read_text())
    assert report["config"]["planar_distance"] is True
    assert report["split"]["query_indices"] == [28, 29, *range(LAP, SCANS)]
    assert any("in the plane, heights ignored" in n for n in report["notes"])
    rows = {(r["method"], r["k"]): r for r in report["rows"]}
    assert rows[("sgv", 2)]["R@1_5m"] >= 80.0 and rows[("sgv", 2)]["mean_rte_m"] < 2.0
