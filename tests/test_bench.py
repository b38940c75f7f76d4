"""``sgvloc bench`` building blocks on tiny sizes: they run, agree on the winner and
produce JSON-serialisable results and tables (no timing is asserted)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sgvloc.tools.bench import engine as bench


def test_rerank_section_runs_all_methods_on_the_same_inputs():
    res = bench.bench_rerank([2, 3], [40], repeats=1, rir_repeats=1, rir_max_k=2)
    rows = {(r["n"], r["k"]): r for r in res["rows"]}
    assert set(rows) == {(40, 2), (40, 3)}
    small = rows[(40, 2)]
    for key in ("sgv_torch", "nn", "sgv_total", "ransac_rir", "fgr_rir", "ratio_ransac_rir"):
        assert key in small
    assert "ransac_rir" not in rows[(40, 3)]  # above rir_max_k
    assert all(r["sgv_top1_is_revisit"] for r in res["rows"])
    assert res["growth"]
    json.dumps(res)
    table = bench.format_rerank(res)
    assert "RANSAC/SGV" in table and table.count("\n") >= 3


def test_rerank_inputs_revisit_is_consistent():
    qk, qf, kps, fts = bench.rerank_inputs(np.random.default_rng(0), 50, 3, dim=8)
    assert qk.shape == (50, 3) and qf.shape == (50, 8) and len(kps) == len(fts) == 3
    assert all(k.shape == (50, 3) and f.shape == (50, 8) for k, f in zip(kps, fts, strict=True))


def test_memory_probe_reports_peak():
    res = bench.sgv_memory_probe(300, 1, "torch")
    assert "error" not in res, res.get("error")
    assert res["peak_rss_mib"] > 10 and res["delta_rss_mib"] >= 0 and res["path"] == "dense"


def test_retrieval_section_recall_and_tables():
    res = bench.bench_retrieval([2000], dim=16, queries=20, flat_queries=5, hnsw_max=2000)
    (row,) = res["rows"]
    assert row["size"] == 2000 and row["dim"] == 16
    assert row["ivf"]["nlist"] <= 2000 // 39
    recalls = [s["recall"] for s in row["ivf"]["sweep"]]
    assert all(0.0 <= r <= 1.0 for r in recalls)
    assert recalls[-1] >= recalls[0]  # more probes never find less
    assert "hnsw" in row
    json.dumps(res)
    assert "IVF recall@20" in bench.format_retrieval(res)


def test_large_sizes_use_the_smaller_dimension():
    db, q = bench.descriptors(np.random.default_rng(0), 500, 12, 7)
    assert db.shape == (500, 12) and q.shape == (7, 12) and db.dtype == np.float32


def test_encoding_section_per_stage():
    res = bench.bench_encoding([12000], repeats=1)
    (row,) = res["rows"]
    assert row["points"] == 12000 and row["keypoints"] > 0
    stages = ("preprocess_ms", "global_ms", "normals_ms", "keypoints_ms", "fpfh_ms")
    assert row["total_ms"] == pytest.approx(sum(row[s] for s in stages), rel=0.25)
    # the BEV image encoders on the same scan, the learned one with the shipped weights
    assert [r["encoder"] for r in res["image_encoders"]] == ["bev", "learned"]
    for r in res["image_encoders"]:
        assert r["points"] == 12000 and r["keypoints"] > 0
        parts = r["prepare_ms"] + r["raster_ms"] + r["describe_ms"]
        assert r["total_ms"] == pytest.approx(parts, rel=0.25)
    assert res["image_encoders"][1]["identity"] == "bevnet"
    text = bench.format_encoding(res)
    assert "FPFH ms" in text and "describe ms" in text


def test_densify():
    scan = np.random.default_rng(0).normal(size=(100, 3)).astype(np.float32)
    out = bench.densify(scan, 250, np.random.default_rng(1))
    assert out.shape == (250, 3) and out.dtype == np.float32


def test_prior_section_answers_the_same_queries_with_and_without():
    res = bench.bench_prior([900], radius_m=10.0, noise_m=1.0, queries=6, dim=32)
    (row,) = res["rows"]
    assert row["size"] == 900 and row["queries"] == 6
    # a 10 m radius on a 30 x 30 m lattice of 1 m holds at most pi * 10^2 keyframes
    assert 0 < row["keyframes_in_radius_median"] <= np.pi * 100 + 40
    assert row["same_top1"] == 6  # the query's own keyframe is inside the radius
    for name in ("none", "prior"):
        assert row[name]["localize_median_ms"] > 0 and row[name]["retrieve_median_ms"] > 0
    json.dumps(res)
    assert "same top-1" in bench.format_prior(res) and "6/6" in bench.format_prior(res)


def test_the_earlier_pipeline_path_has_one_icp_stage() -> None:
    """The --compare path is the one before the coarse ICP stage too."""
    from sgvloc.core.config import PoseConfig
    from sgvloc.core.pose import icp_stages
    from sgvloc.tools.bench.pipeline import EARLIER_POSE

    cfg = PoseConfig(**EARLIER_POSE)
    assert icp_stages(cfg) == [(cfg.icp_max_distance, cfg.icp_iterations)]


def test_sigterm_ends_a_command_through_its_finally_blocks(tmp_path) -> None:
    """What bench and loadtest install: a SIGTERM runs their clean-up, as Ctrl-C does."""
    import subprocess
    import sys

    done = tmp_path / "cleaned"
    code = (
        "import os, signal, time\n"
        "from sgvloc.cli import _exit_on_sigterm\n"
        "_exit_on_sigterm()\n"
        "try:\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    time.sleep(10)\n"
        "finally:\n"
        f"    open({str(done)!r}, 'w').write('ok')\n"
    )
    run = subprocess.run([sys.executable, "-c", code], timeout=60)
    assert run.returncode == 143 and done.read_text() == "ok"
