"""`sgvloc eval` end to end on the shipped real fixture: tables, JSON and PNGs, all methods."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from sgvloc.cli import app
from sgvloc.core.encoders import EncoderSpec, make_encoder
from sgvloc.core.rerank import METHODS
from sgvloc.core.sequence import KittiSequence
from sgvloc.tools.evaluation.cache import FeatureCache
from sgvloc.tools.evaluation.diagnostics import pair_match_stats

ARGS = ["--min-gap", "30", "--topk", "2,3", "--sweep", "1,2,3", "--sweep-rir", "2"]


@pytest.fixture(scope="module")
def first_run(balm_mini_dir, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("eval")
    cache, out = tmp / "cache", tmp / "out"
    args = ["eval", "--data", str(balm_mini_dir), *ARGS, "--no-progress"]
    args += ["--cache-dir", str(cache), "--out", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    return res, json.loads((out / "eval.json").read_text()), args, out


def test_eval_writes_table_json_and_plot_with_every_method(first_run):
    res, report, _, out = first_run
    png = (out / "ntopk.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    rows = report["rows"]
    assert {(r["method"], r["k"]) for r in rows} == {(m, k) for m in METHODS for k in (2, 3)}
    for m in METHODS:
        assert f"| {m} | 2 |" in res.output
    # the fixture's three queries (scans 125, 170, 175) are the revisits; the rest dropped
    assert report["split"]["queries"] == 3 and report["split"]["dropped_queries"] == 7
    for r in rows:
        assert r["queries"] == 3
        assert r["R@5_5m"] >= r["R@1_5m"] and r["R@1_20m"] >= r["R@1_5m"]
        assert 0.0 <= r["success_pct"] <= 100.0 and r["mean_rte_m"] >= 0.0
        assert r["rerank_median_ms"] >= 0.0
        # pose success among the queries whose top-1 is a true match, from the per-query
        # records: the same figure recomputed
        recs = report["per_query"][f"{r['method']}@{r['k']}"]
        true1 = [q for q in recs if q["rank@5m"] == 1]
        if true1:
            ok = [q["rte"] <= 2.0 and q["rre"] <= 5.0 for q in true1]
            assert r["success_true_top1_pct"] == pytest.approx(100.0 * sum(ok) / len(ok))
    none2 = next(r for r in rows if r["method"] == "none" and r["k"] == 2)
    assert none2["R@1_20m"] == 100.0 and none2["success_pct"] >= 66.0
    # the sweep: cheap methods at every sweep k, RIR only at --sweep-rir plus the table's k
    assert [p["k"] for p in report["sweep"]["sgv"]] == [1, 2, 3]
    assert [p["k"] for p in report["sweep"]["ransac-rir"]] == [2, 3]
    cfg = report["config"]
    assert cfg["min_gap"] == 30 and cfg["topk"] == [2, 3] and cfg["encoder_fingerprint"]
    assert report["timings"]["feature_cache"]["misses"] == 15
    # the report is readable as the figures beside it are (the umask's mode), no temp left
    mode = (out / "eval.json").stat().st_mode & 0o777
    assert mode == (out / "ntopk.png").stat().st_mode & 0o777
    assert not list(out.glob("*.tmp"))


def test_eval_reports_local_matches_and_sgv_score_separation(first_run, balm_mini_dir):
    res, report, _, out = first_run
    png = (out / "sgv_scores.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    m = report["matches"]
    assert m["pairs"] == 3 and not m["planar"] and m["radius_m"] == 1.0
    assert m["query_keypoints_mean"] > 100 and m["db_keypoints_mean"] > 100
    for key in ("nn_ratio", "mutual_ratio", "repeatability", "chance_ratio"):
        assert 0.0 <= m[f"{key}_mean"] <= 1.0 and 0.0 <= m[f"{key}_median"] <= 1.0
    # matching beats chance by far, and no matcher beats repeatability
    assert m["nn_ratio_mean"] > 5 * m["chance_ratio_mean"]
    assert m["nn_ratio_mean"] <= m["repeatability_mean"]
    # the true pair is the nearest *visible* database scan: query 13 (85 s) sees scans up to
    # 55 s, so not 11 (56.5 s), its nearest overall (fixture README)
    assert [(p["query"], p["db"]) for p in m["per_pair"]] == [(12, 0), (13, 10), (14, 11)]
    s = report["sgv_scores"]
    assert s["k"] == 3 and s["threshold_m"] == 5.0
    # 3 queries x the top-3 of each of the default descriptor's two blocks, merged
    sgv_recs = [q for q in report["per_query"]["sgv@3"] if q["in_coverage"]]
    assert s["true"]["count"] + s["false"]["count"] == sum(q["candidates"] for q in sgv_recs)
    assert all(3 <= q["candidates"] <= 6 for q in sgv_recs)
    assert s["true"]["count"] >= 3 and 0.5 <= s["auc"] <= 1.0
    assert s["true"]["p10"] <= s["true"]["p50"] <= s["true"]["p90"]
    # the scores are the sgv re-ranking's own: its top-1 has the query's highest score
    sgv3 = {r["query"]: r["ranked"] for r in report["per_query"]["sgv@3"]}
    for q in s["per_query"]:
        assert q["ids"][int(np.argmax(q["scores"]))] == sgv3[q["query"]][0]
    assert "Local matches on true pairs" in res.output and "ROC AUC" in res.output


def test_match_ratio_drops_with_a_wrong_ground_truth(first_run, balm_mini_dir):
    """The real pair against the same pair with its pose off by 90 degrees of yaw."""
    _, report, args, _ = first_run
    cache = FeatureCache(args[args.index("--cache-dir") + 1], make_encoder(EncoderSpec()))
    seq = KittiSequence(balm_mini_dir)
    fq, fd = cache.get(seq.paths[12]), cache.get(seq.paths[0])
    T = np.linalg.inv(seq.poses[0]) @ seq.poses[12]
    turn = np.eye(4)
    turn[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]
    args = (fq.keypoints, fq.local_features, fd.keypoints, fd.local_features)
    good = pair_match_stats(*args, T)
    assert good["nn_ratio"] == report["matches"]["per_pair"][0]["nn_ratio"]
    assert pair_match_stats(*args, T @ turn)["nn_ratio"] < good["nn_ratio"] / 3


def test_second_run_reuses_cached_features(first_run):
    _, _, args, out = first_run
    args = [a for a in args] + ["--methods", "none,sgv", "--refine", "none"]
    # --config takes the JSON itself as well as a file
    res = CliRunner().invoke(app, [*args, "--config", '{"pose": {"min_inliers": 7}}'])
    assert res.exit_code == 0, res.output
    report = json.loads((out / "eval.json").read_text())
    assert report["config"]["localizer"]["pose"]["min_inliers"] == 7
    assert report["timings"]["feature_cache"] == {
        **report["timings"]["feature_cache"],
        "hits": 15,
        "misses": 0,
    }
    assert {r["method"] for r in report["rows"]} == {"none", "sgv"}


def test_eval_refuses_bad_arguments(balm_mini_dir, tmp_path):
    base = ["eval", "--data", str(balm_mini_dir), "--no-progress", "--out", str(tmp_path)]
    res = CliRunner().invoke(app, [*base, "--min-gap", "30", "--methods", "magic"])
    assert res.exit_code == 2 and "magic" in res.output
    res = CliRunner().invoke(app, [*base, "--min-gap", "30", "--db-until", "40"])
    assert res.exit_code == 2 and "exactly one" in res.output
    res = CliRunner().invoke(app, [*base, "--db-range", "0:8", "--query-range", "5:"])
    assert res.exit_code == 2 and "overlaps" in res.output
    res = CliRunner().invoke(app, [*base, "--db-range", "0-8"])
    assert res.exit_code == 2 and "--db-range" in res.output
    res = CliRunner().invoke(app, [*base, "--min-gap", "30", "--query-range", "9:"])
    assert res.exit_code == 2 and "query_range needs db_range" in res.output
    # a zero-byte scan is named
    import shutil

    data = tmp_path / "seq"
    shutil.copytree(balm_mini_dir, data)
    (data / "velodyne" / "000003.bin").write_bytes(b"")
    args = ["eval", "--data", str(data), "--no-progress", "--out", str(tmp_path / "o")]
    res = CliRunner().invoke(app, [*args, "--min-gap", "30", "--encoder", "bev"])
    assert res.exit_code == 2 and "000003.bin: scan is empty" in res.output, res.output


def test_eval_by_frame_ranges_with_merged_descriptors(balm_mini_dir, tmp_path):
    """--db-range/--query-range split by frame index; with the learned encoder's two
    descriptor blocks each (method, k) starts from the merge of each block's top-k, and
    the ceiling is the share of queries with a true match among those candidates."""
    out = tmp_path / "out"
    enc = '{"kind": "learned", "learned": {"global_descriptor": "polar+network"}}'
    args = ["eval", "--data", str(balm_mini_dir), "--db-range", "0:12", "--query-range", "12:"]
    args += ["--methods", "none,sgv", "--topk", "3", "--sweep", "1,3", "--encoder", enc]
    args += ["--no-progress", "--cache-dir", str(tmp_path / "cache"), "--out", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    report = json.loads((out / "eval.json").read_text())
    assert report["split"]["db_range"] == [0, 12] and report["split"]["query_range"] == [12, 15]
    assert report["split"]["database_scans"] == 12
    assert "(--db-range 0:12 --query-range 12:15)" in res.output
    assert "Recall ceiling and R@1 at 5 m over the n_topk sweep" in res.output
    for r in report["rows"]:
        recs = [q for q in report["per_query"][f"{r['method']}@{r['k']}"] if q["in_coverage"]]
        assert recs and all(3 <= q["candidates"] <= 6 for q in recs)
        assert all(len(set(q["ranked"])) == len(q["ranked"]) == q["candidates"] for q in recs)
        share = sum(q["rank@5m"] is not None for q in recs) / len(recs)
        assert r["ceiling_5m"] == pytest.approx(100.0 * share)
        assert r["candidates_mean"] == pytest.approx(np.mean([q["candidates"] for q in recs]))
    sweep = {p["k"]: p for p in report["sweep"]["sgv"]}
    assert 1 <= sweep[1]["candidates_mean"] <= 2 <= 3 <= sweep[3]["candidates_mean"]
    assert sweep[1]["ceiling_5m"] <= sweep[3]["ceiling_5m"]
    assert any("descriptor blocks" in n for n in report["notes"])


def test_eval_keeps_out_of_coverage_queries_for_the_verdict(first_run):
    res, report, _, out = first_run
    png = (out / "verdict.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    # the 7 scans without a database scan within 5 m are negatives, not recall queries
    assert report["split"]["negative_queries"] == 7
    assert "Verdict over all 10 queries (3 in coverage, 7 out of coverage)" in res.output
    for r in report["rows"]:
        recs = report["per_query"][f"{r['method']}@{r['k']}"]
        assert len(recs) == 10 and sum(q["in_coverage"] for q in recs) == 3
        assert r["queries"] == 3 and r["out_of_coverage"] == 7 and r["all_queries"] == 10
        for q in recs:
            assert 0.0 <= q["confidence"] <= 1.0 and q["verdict"]
            assert q["accepted"] == (q["verdict"] == "localized")
            assert q["correct"] == (q["rte"] <= 2.0 and q["rre"] <= 5.0)
            if not q["in_coverage"]:
                assert q["rank@5m"] is None and q["rank@20m"] is None
        fa = [q for q in recs if q["accepted"] and not q["correct"]]
        assert r["false_accepts"] == len(fa)
        assert r["false_accept_pct"] == pytest.approx(100.0 * len(fa) / 10)
        correct = [q for q in recs if q["correct"]]
        if correct:
            share = sum(q["accepted"] for q in correct) / len(correct)
            assert r["accepted_of_correct_pct"] == pytest.approx(100.0 * share)
        assert 0.0 <= r["ece"] <= 1.0


def test_eval_with_a_prior_and_scans_of_another_place(balm_mini_dir, tmp_path):
    from sgvloc.tools.synth import SynthConfig, generate

    town = tmp_path / "town"
    generate(town, SynthConfig(scans=3, seed=2))
    out = tmp_path / "out"
    args = ["eval", "--data", str(balm_mini_dir), "--min-gap", "30", "--topk", "3"]
    args += ["--sweep", "3", "--methods", "none,sgv", "--no-progress", "--no-negatives"]
    args += ["--prior-noise", "1.0", "--prior-radius", "8", "--foreign", str(town)]
    args += ["--cache-dir", str(tmp_path / "cache"), "--out", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    report = json.loads((out / "eval.json").read_text())
    assert report["split"]["negative_queries"] == 0
    assert report["split"]["foreign_queries"] == {str(town): 3}
    assert any("prior" in n and "radius 8 m" in n for n in report["notes"])
    poses = np.loadtxt(balm_mini_dir / "poses.txt").reshape(-1, 3, 4)[:, :, 3]
    for r in report["rows"]:
        recs = report["per_query"][f"{r['method']}@{r['k']}"]
        assert len(recs) == 3 + 3 and r["out_of_coverage"] == 3
        for q in recs:
            if "foreign" in q:
                # a scan of another world is never correct
                assert not q["correct"] and not q["in_coverage"]
                continue
            # every candidate lies within the prior radius of the noisy position, so
            # within radius + a few sigma of the truth
            d = np.linalg.norm(poses[q["ranked"], :2] - poses[q["query"], :2], axis=1)
            assert (d <= 8.0 + 6.0).all()


def test_eval_crops_every_scan_to_a_field_of_view(balm_mini_dir, tmp_path, first_run):
    """--fov 180 encodes each scan cropped to 180 degrees ahead (features cached apart
    from the full scans'), so the local matches see fewer keypoints; a query is in
    coverage only with a map scan facing within half the view: at 70 degrees none of the
    fixture's three revisits is."""
    cache, out = tmp_path / "cache", tmp_path / "out"
    args = ["eval", "--data", str(balm_mini_dir), "--min-gap", "30", "--topk", "3"]
    args += ["--sweep", "3", "--methods", "none,sgv", "--fov", "180", "--no-progress"]
    args += ["--cache-dir", str(cache), "--out", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    report = json.loads((out / "eval.json").read_text())
    assert report["config"]["fov"] == 180.0
    cropped = "field of view: every scan cropped to 180 deg"
    assert any(n.startswith(cropped) for n in report["notes"])
    assert [p.name.endswith("-fov180") for p in cache.iterdir()] == [True]
    assert report["split"]["coverage_heading_deg"] == 90.0
    full = first_run[1]["matches"]
    assert report["split"]["queries"] == first_run[1]["split"]["queries"] == 3
    assert report["matches"]["query_keypoints_mean"] < full["query_keypoints_mean"]
    # a true match shares the view: within 5 m and facing within 90 degrees of the query
    poses = KittiSequence(balm_mini_dir).poses
    heading = np.degrees(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    checked = 0
    for recs in report["per_query"].values():
        for r in recs:
            if r["rank@5m"] is not None:
                kf = r["ranked"][r["rank@5m"] - 1]
                turn = abs((heading[kf] - heading[r["query"]] + 180.0) % 360.0 - 180.0)
                assert (
                    turn <= 90.0
                    and np.linalg.norm(poses[kf][:3, 3] - poses[r["query"]][:3, 3]) <= 5.0
                )
                checked += 1
    assert checked
    narrow = [a if a != "180" else "70" for a in args[:-1]]
    res = CliRunner().invoke(app, [*narrow, str(tmp_path / "n")])
    assert res.exit_code == 0, res.output
    split = json.loads((tmp_path / "n" / "eval.json").read_text())["split"]
    assert split["queries"] == 0 and split["negative_queries"] == 10
    assert split["coverage_heading_deg"] == 35.0
    res = CliRunner().invoke(app, [*args[:-4], "--fov", "400", "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "--fov" in res.output


def test_scans_the_encoder_cannot_describe_are_left_out_not_fatal(balm_mini_dir, tmp_path):
    """A scan too sparse for the encoder (here flat ground only: no column of the BEV
    image holds two voxels) neither stops the run nor enters the database; as a query it
    is an answer without an estimate."""
    import shutil

    data = tmp_path / "seq"
    shutil.copytree(balm_mini_dir, data)
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-10, 10, (300, 2)), np.full(300, -1.5), np.ones(300)]
    for i in (1, 12):  # a database scan and the first revisit query (scan 125)
        ground.astype(np.float32).tofile(data / "velodyne" / f"{i:06d}.bin")
    out = tmp_path / "out"
    args = ["eval", "--data", str(data), "--min-gap", "30", "--topk", "3", "--sweep", "3"]
    args += ["--methods", "none,sgv", "--no-progress", "--cache-dir", str(tmp_path / "c")]
    res = CliRunner().invoke(app, [*args, "--out", str(out)])
    assert res.exit_code == 0, res.output
    report = json.loads((out / "eval.json").read_text())
    assert any(n.startswith("2 scans could not be encoded") for n in report["notes"])
    for key, recs in report["per_query"].items():
        by_query = {q["query"]: q for q in recs}
        assert all(1 not in q["ranked"] for q in recs), key
        empty = by_query[12]
        assert empty["ranked"] == [] and empty["rank@5m"] is None, key
        assert empty["verdict"] == "no_features" and not empty["accepted"], key
        assert by_query[13]["ranked"], key  # the other revisits are answered
