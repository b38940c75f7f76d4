"""``sgvloc bench`` sections http and scaling on tiny sizes, against a real service
subprocess (uvicorn on 127.0.0.1) loaded from a second process: the figures are there,
no request failed, the PNG is written and no process or temporary folder is left
behind. No timing is asserted."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest

from sgvloc.tools.bench import http as bs
from sgvloc.tools.service_process import ServiceProcess


def _gone(pid: int) -> bool:
    """True when no process has this id (ours are reaped by ``wait``)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_http_section_tiny(tmp_path: Path) -> None:
    res = bs.bench_http(
        keyframes=40,
        clients=[1, 2],
        duration_s=1.0,
        batch=20,
        raw_scans=2,
        raw_batch=1,
        points=12_000,
        compare=True,
        batch_wait_ms=50.0,
        work_dir=tmp_path,
    )
    json.dumps(res)
    assert [r["clients"] for r in res["localize"]] == [1, 2]
    for r in res["localize"]:
        assert r["errors"] == 0 and r["refused"] == 0, r["error_samples"]
        assert r["ok"] > 0 and r["ok"] == r["requests"]
        assert 0 < r["p50_ms"] <= r["p99_ms"] and r["qps"] > 0
        # the service's own stage times come back with every answer
        assert set(r["server_median_ms"]) == {"encode", "retrieve", "rerank", "pose", "total"}
        assert r["server_median_ms"]["total"] <= r["p50_ms"] * 1.5 + 50
    ins, raw = res["insert_features"], res["insert_raw"]
    assert ins["keyframes"] == 40 and ins["batches"] == 2 and ins["median_kf_s"] > 0
    assert raw["keyframes"] == 2 and raw["batches"] == 2
    assert raw["kib_per_keyframe"] > 100  # 12k float32 points
    m = res["map"]
    assert m["encoder"] == "bevnet" and m["global_dim"] == 876 and m["local_dim"] == 64
    assert m["store_mib"] > 0
    # the raw-scan map localized with ICP and without, and the earlier path's map
    icp = [(r["path"], r["refine"], r["clients"]) for r in res["icp"]]
    assert icp == [("default", "icp", 1), ("default", "none", 1), ("earlier", "icp", 1)]
    for r in res["icp"]:
        assert r["errors"] == 0 and r["refused"] == 0 and r["ok"] > 0, r["error_samples"]
    assert {t["unit"] for t in res["targets"]} == {"ms", "keyframes/s"}  # no 4-client row
    assert any("with ICP" in t["name"] for t in res["targets"])
    # a second service with dynamic batching, loaded at every client count
    assert [(r["path"], r["clients"]) for r in res["batching"]] == [
        ("batching off", 1),
        ("batching 50 ms", 1),
        ("batching off", 2),
        ("batching 50 ms", 2),
    ]
    for r in res["batching"]:
        assert r["errors"] == 0 and r["ok"] > 0, r["error_samples"]
        if r["path"] == "batching off":
            assert r["mean_batch_forward"] is None  # that service does not batch
        else:
            assert r["mean_batch_forward"] >= 1.0
    table = bs.format_http(res)
    assert "p99 ms" in table and "kf/s median" in table and "ratio" in table
    assert "earlier" in table and "refine" in table and "batch (sgv)" in table
    assert res["notes"]
    # the service was stopped and its temporary data directory removed
    assert res["server"]["pids"] and all(_gone(p) for p in res["server"]["pids"])
    assert list(tmp_path.iterdir()) == []


def test_scaling_section_through_the_cli(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from typer.testing import CliRunner

    from sgvloc.cli import app

    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(work))  # the service's data directory
    out = tmp_path / "out" / "b.json"
    out.parent.mkdir()
    args = ["bench", "--only", "scaling", "--out", str(out), "--scale-sizes", "50,20"]
    args += ["--scale-clients", "1", "--scale-duration", "1", "--scale-batch", "20"]
    args += ["--scale-keypoints", "16"]
    run = CliRunner().invoke(app, args)
    assert run.exit_code == 0, run.output
    assert "insert kf/s" in run.output and "p50 x first" in run.output
    res = json.loads(out.read_text())["scaling"]
    rows = res["rows"]
    assert [r["keyframes"] for r in rows] == [20, 50]  # sorted
    assert rows[0]["insert"]["keyframes"] == 20 and rows[1]["insert"]["keyframes"] == 30
    for r in rows:
        lo = r["localize"]["1"]
        assert lo["errors"] == 0 and lo["ok"] > 0, lo["error_samples"]
        assert r["rss_mib"] > 50 and r["peak_rss_mib"] >= r["rss_mib"]
    assert rows[1]["disk_mib"] > rows[0]["disk_mib"] > 0
    assert res["map"]["num_keypoints"] == 16 and res["reload_s"] > 0
    png = out.parent / "b-scaling.png"  # next to --out by default
    assert res["plot"] == str(png) and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # two service processes (start and restart), both gone; nothing left on disk
    assert len(res["server"]["pids"]) == 2 and all(_gone(p) for p in res["server"]["pids"])
    assert list(work.iterdir()) == []


def test_tracking_section_through_the_cli(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from sgvloc.cli import app

    out = tmp_path / "t.json"
    run = CliRunner().invoke(app, ["bench", "--only", "tracking", "--out", str(out)])
    assert run.exit_code == 0, run.output
    assert "global / tracked" in run.output
    res = json.loads(out.read_text())["tracking"]
    assert res["map_keyframes"] == 8 and res["queries"] == 7
    for path in ("in_process", "http"):
        s = res[path]
        assert s["samples"] == 7 * res["repeats"]
        assert s["tracked_share"] == 1.0  # every seeded scan of the fixture was tracked
        assert s["global_p50_ms"] > 0 and s["tracked_p50_ms"] > 0
    rates = res["in_process"]["tracked_per_s"]  # one thread and the service's two workers
    assert set(rates) == {"1", "2"} and all(r > 0 for r in rates.values())
    assert "tracked scans per second in process: 1 thread(s)" in run.output


def test_cluster_section_through_the_cli(tmp_path: Path, postgres) -> None:
    """Every figure of the cluster section, tiny, on a database of the test server."""
    from typer.testing import CliRunner

    from sgvloc.cli import app
    from sgvloc.server.store.postgres import PgBackend

    out = tmp_path / "c.json"
    store = postgres.new_database()
    args = [
        *("bench", "--only", "cluster", "--out", str(out)),
        *("--cluster-store", store, "--cluster-sizes", "300"),
        *("--cluster-visible", "5", "--cluster-duration", "0.5", "--cluster-clients", "2"),
        *("--pipeline-rounds", "1"),
    ]
    run = CliRunner().invoke(app, args)
    assert run.exit_code == 0, run.output
    backend = PgBackend(store)  # the given store is left as it was found: empty
    backend.start()
    try:
        assert backend.catalog() == {}
    finally:
        backend.close()
    assert "insert-to-visible" in run.output and "fetched, cold" in run.output
    res = json.loads(out.read_text())["cluster"]
    assert res["visible"]["inserts"] == 5 and 0 < res["visible"]["p50_ms"] < 5000
    assert res["qps"]["one"] > 0 and res["qps"]["two"] > 0
    paths = res["fetch"]["paths"]
    assert set(paths) == {"memory", "fetched, cold", "fetched, warm"}
    assert paths["fetched, cold"]["fetch_p50_ms"] > 0 and paths["memory"]["fetch_p50_ms"] == 0
    q = res["fetch"]["queries"] * (res["fetch"]["rounds"] + 1)
    assert res["fetch"]["same_answers"] == f"{q}/{q}"
    (row,) = res["catch_up"]
    assert row["keyframes"] == 300
    assert row["memory"]["keyframes"] == row["slim"]["keyframes"] == 300
    assert row["slim"]["memory_mib"] < row["memory"]["memory_mib"]


def test_cli_names_the_sections() -> None:
    from typer.testing import CliRunner

    from sgvloc.cli import app

    run = CliRunner().invoke(app, ["bench", "--only", "http,nope"])
    assert run.exit_code != 0
    assert "nope" in run.output and "'http'" in run.output and "'scaling'" in run.output


def test_service_is_stopped_when_the_body_fails(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    base = {
        "global_descriptor": rng.random(620).astype(np.float32),
        "keypoints": rng.normal(size=(4, 3)).astype(np.float32),
        "local_features": rng.random((4, 33)).astype(np.float32),
    }
    srv = ServiceProcess(tmp_path / "data", tmp_path / "server.log")
    with pytest.raises(RuntimeError, match="client job _insert_features failed.*404"):
        with srv, bs.ClientProcess() as cp:
            # no such map: the client job's error comes back with the service's answer
            cp.run(bs._insert_features, srv.url, "nope", [base], {}, 0, 1, 1, 0)
    assert srv.proc is not None and srv.proc.poll() is not None and _gone(srv.proc.pid)


def test_client_process_refuses_other_functions() -> None:
    with bs.ClientProcess() as cp, pytest.raises(ValueError, match="not a client job"):
        cp.run(os.getcwd)


def test_synthetic_keyframe_is_a_rigid_copy() -> None:
    rng = np.random.default_rng(0)
    base = {
        "global_descriptor": rng.random(8).astype(np.float32),
        "keypoints": rng.normal(size=(30, 3)).astype(np.float32),
        "local_features": rng.random((30, 5)).astype(np.float32),
    }
    kf = bs.synthetic_keyframe([base], rng, 123, {"encoder": "x"})
    f = kf["features"]
    assert kf["key"] == "kf123" and f["encoder"] == "x"
    assert np.allclose(kf["T_map_sensor"][:2, 3], (230.0, 10.0))
    # pairwise distances are kept up to the 2 cm jitter: a rotated, not a random, copy
    d0 = np.linalg.norm(base["keypoints"][:, None] - base["keypoints"][None], axis=-1)
    d1 = np.linalg.norm(f["keypoints"][:, None] - f["keypoints"][None], axis=-1)
    assert np.abs(d0 - d1).max() < 0.2
    assert np.allclose(np.linalg.norm(f["local_features"], axis=1), 1.0, atol=1e-5)


def test_procedural_scans_without_the_fixture(tmp_path: Path) -> None:
    from sgvloc.core.encoders import EncoderSpec

    db, queries, source = bs.source_scans(tmp_path)  # no scans.txt there
    assert len(db) == 12 and len(queries) == 3 and "procedural" in source
    bases, claim = bs.encode_bases(
        db[:1],
        EncoderSpec.model_validate({"kind": "handcrafted", "handcrafted": {"num_keypoints": 32}}),
    )
    assert claim["encoder"] == "handcrafted" and len(claim["fingerprint"]) > 8
    assert bases[0]["keypoints"].shape[0] <= 32 and bases[0]["local_features"].shape[1] == 33


def test_pipeline_section_compares_the_paths_through_the_cli(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from sgvloc.cli import app

    out = tmp_path / "p.json"
    args = ["bench", "--only", "pipeline", "--compare", "--pipeline-rounds", "1"]
    run = CliRunner().invoke(app, [*args, "--out", str(out)])
    assert run.exit_code == 0, run.output
    assert "CPU / default" in run.output
    res = json.loads(out.read_text())["pipeline"]
    assert res["map_keyframes"] == 8 and res["queries"] == 7 and res["default_runtime"] == "onnx"
    paths = {r["path"]: r for r in res["paths"]}
    assert list(paths) == ["default", "default, no ICP", "earlier"]
    for r in paths.values():
        assert r["wall_p50_ms"] > 0 and r["cpu_p50_ms"] > 0
        assert set(r["stages_p50_ms"]) == {"encode", "retrieve", "rerank", "pose", "verify"}
    # the earlier path reaches the same verdicts and keyframes on the fixture's queries
    agree = paths["earlier"]["agreement"]
    assert agree["same_verdict"] == agree["same_keyframe"] == 7
    assert agree["largest_position_difference_m"] < 0.2
    assert paths["default"]["cpu_vs_default"] == 1.0
