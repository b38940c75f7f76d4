"""``build_map`` and ``sgvloc build-map``: a KITTI-layout sequence into a running service
or a data directory."""

from __future__ import annotations

import concurrent.futures
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path

import httpx
import numpy as np
import pytest
from typer.testing import CliRunner

from sgvloc.cli import app
from sgvloc.core.errors import ConflictError, InputError, NotFoundError
from sgvloc.core.retrieval import FaissIndex
from sgvloc.core.sequence import KittiSequence
from sgvloc.server.store import INDEX_NAME
from sgvloc.tools.build_map import build_map, parse_encoder, select_frames
from sgvloc_client import Client


@pytest.fixture(scope="module")
def num_database(balm_mini_roles: list[tuple[int, str]]) -> int:
    """The database scans of balm_mini are its first files (queries come last)."""
    roles = [role for _, role in balm_mini_roles]
    n = roles.count("database")
    assert roles[:n] == ["database"] * n
    return n


def test_select_frames_and_encoder_option() -> None:
    assert select_frames(10) == list(range(10))
    assert select_frames(10, every=3) == [0, 3, 6, 9]
    assert select_frames(10, every=3, limit=2) == [0, 3]
    assert select_frames(10, limit=0) == []
    with pytest.raises(InputError, match="every"):
        select_frames(10, every=0)
    # a time window counted from the first scan's time, as eval --db-until
    times = 100.0 + np.arange(10) * 0.5
    assert select_frames(10, until=2.0, times=times) == [0, 1, 2, 3, 4]
    assert select_frames(10, every=2, limit=2, until=2.0, times=times) == [0, 2]
    with pytest.raises(InputError, match="times.txt"):
        select_frames(10, until=2.0)
    assert parse_encoder(None) is None
    assert parse_encoder("handcrafted") == {"kind": "handcrafted"}
    learned_fpfh = {"kind": "learned", "learned": {"local_features": "fpfh"}}
    assert parse_encoder("learned-fpfh") == learned_fpfh  # the self-test's names too
    assert parse_encoder('{"kind": "handcrafted", "num_keypoints": 64}')["num_keypoints"] == 64
    with pytest.raises(InputError, match="JSON"):
        parse_encoder("{kind")


def test_build_map_inserts_database_scans_once(
    service_url: str, balm_mini_dir: Path, num_database: int
) -> None:
    first = build_map(
        balm_mini_dir, service_url, "built", batch_size=5, limit=num_database, progress=False
    )
    assert (first.scans, first.created, first.existing) == (num_database, num_database, 0)
    assert first.keyframes == num_database

    # Re-running inserts nothing new: every key is already in the map.
    again = build_map(
        balm_mini_dir, service_url, "built", batch_size=7, limit=num_database, progress=False
    )
    assert (again.created, again.existing, again.keyframes) == (0, num_database, num_database)

    with Client(service_url) as c:
        assert c.get_map("built").keyframes == num_database
        # keys and poses come from the sequence
        poses = np.loadtxt(balm_mini_dir / "poses.txt").reshape(-1, 3, 4)
        times = np.loadtxt(balm_mini_dir / "times.txt")
        res = c.insert_keyframe("built", np.eye(4), points=np.ones((10, 3)), key="balm_mini/000003")
        assert res.created == [False]
        kf = c.get_keyframe("built", res.ids[0])
        np.testing.assert_allclose(kf.T_map_sensor[:3], poses[3], atol=1e-9)
        assert kf.metadata["sequence"] == "balm_mini"
        assert kf.metadata["timestamp"] == pytest.approx(times[3])
        c.delete_map("built")


def test_build_map_resumes_and_respects_create(
    service_url: str, balm_mini_dir: Path, num_database: int
) -> None:
    with pytest.raises(NotFoundError, match="does not exist"):
        build_map(balm_mini_dir, service_url, "resumed", create=False, progress=False)
    part = build_map(balm_mini_dir, service_url, "resumed", every=2, limit=3, progress=False)
    assert part.created == 3 and part.keyframes == 3  # scans 0, 2, 4
    with Client(service_url) as c:
        rest = build_map(
            balm_mini_dir, c, "resumed", create=False, limit=num_database, progress=False
        )
        assert c.get_map("resumed").keyframes == num_database
        c.delete_map("resumed")
    assert (rest.created, rest.existing) == (num_database - 3, 3)


def test_build_map_command(service_url: str, balm_mini_dir: Path) -> None:
    runner = CliRunner()
    args = ["build-map", str(balm_mini_dir), "--map", "cli-built", "--url", service_url]
    args += ["--limit", "2", "--no-progress"]
    out = runner.invoke(app, args)
    assert out.exit_code == 0, out.output
    assert "2 new keyframes" in out.output
    out = runner.invoke(app, args)
    assert out.exit_code == 0, out.output
    assert "0 new keyframes, 2 already present" in out.output

    missing = ["build-map", str(balm_mini_dir), "--map", "nope", "--url", service_url]
    out = runner.invoke(app, [*missing, "--no-create", "--no-progress"])
    assert out.exit_code == 1 and "does not exist" in out.output
    # --data is the folder's option (as in eval and train); --until a time window
    times = np.loadtxt(balm_mini_dir / "times.txt")
    n_until = int((times - times[0] <= 10.0).sum())
    assert 0 < n_until < len(times)
    args = ["build-map", "--data", str(balm_mini_dir), "--map", "cli-until", "--url"]
    out = runner.invoke(app, [*args, service_url, "--until", "10", "--no-progress"])
    assert out.exit_code == 0, out.output
    assert f"{n_until} scans sent, {n_until} new keyframes" in out.output
    both = ["build-map", str(balm_mini_dir), "--data", str(balm_mini_dir), "--map", "x"]
    out = runner.invoke(app, both)
    assert out.exit_code == 2 and "--data" in out.output
    with Client(service_url) as c:
        c.delete_map("cli-built")
        c.delete_map("cli-until")


def test_build_map_needs_poses(tmp_path: Path, balm_mini_dir: Path) -> None:
    (tmp_path / "velodyne").mkdir()
    src = balm_mini_dir / "velodyne" / "000000.bin"
    (tmp_path / "velodyne" / "000000.bin").write_bytes(src.read_bytes())
    with pytest.raises(InputError, match="poses.txt"):
        build_map(tmp_path, "http://127.0.0.1:9", "m", progress=False)


# -- into a data directory (no service running; MapManager writes the stores) --------------


def test_build_map_into_data_dir_then_serve(
    tmp_path: Path,
    balm_mini_dir: Path,
    num_database: int,
    balm_mini_roles: list[tuple[int, str]],
    start_service: Callable[..., AbstractContextManager[str]],
) -> None:
    data_dir = tmp_path / "data"
    first = build_map(
        balm_mini_dir, data_dir, "offline", batch_size=5, limit=num_database, progress=False
    )
    assert (first.scans, first.created, first.existing) == (num_database, num_database, 0)
    assert first.keyframes == num_database and first.map_version > 0
    # The FAISS snapshot is saved at the end and holds exactly the stored keyframes.
    index_path = data_dir / "maps" / "offline" / INDEX_NAME
    assert len(FaissIndex.load(index_path).ids()) == num_database
    saved = index_path.stat().st_mtime_ns

    # Re-running inserts nothing new and leaves the map as it was.
    again = build_map(
        balm_mini_dir, data_dir, "offline", batch_size=7, limit=num_database, progress=False
    )
    assert (again.created, again.existing) == (0, num_database)
    assert (again.keyframes, again.map_version) == (num_database, first.map_version)

    queries = [i for i, (_, role) in enumerate(balm_mini_roles) if role == "query"]
    seq = KittiSequence(balm_mini_dir)
    with start_service(data_dir) as url, Client(url) as c:
        info = c.get_map("offline")
        assert (info.keyframes, info.version) == (num_database, first.map_version)
        assert info.encoder.kind == "learned"  # the default encoder
        frame = seq[queries[0]]  # a revisit, never inserted
        loc = c.localize("offline", points=frame.scan().xyzi())
        assert loc.localized, loc.reason
        # Keys and metadata are those of the URL mode.
        res = c.insert_keyframe(
            "offline", np.eye(4), points=np.ones((10, 3)), key="balm_mini/000003"
        )
        assert res.created == [False]
        kf = c.get_keyframe("offline", res.ids[0])
        assert kf.metadata["sequence"] == "balm_mini"
        np.testing.assert_allclose(kf.T_map_sensor, seq[3].T_world_sensor, atol=1e-9)
    # the re-run and the service used the snapshot: a rebuilt one would have been saved again
    assert index_path.stat().st_mtime_ns == saved


def test_build_map_data_dir_errors(tmp_path: Path, balm_mini_dir: Path) -> None:
    data_dir = tmp_path / "data"
    with pytest.raises(NotFoundError, match="does not exist"):
        build_map(balm_mini_dir, data_dir, "m", create=False, progress=False)
    with pytest.raises(InputError, match="encoder"):
        build_map(balm_mini_dir, data_dir, "m", encoder="nope", limit=1, progress=False)
    build_map(balm_mini_dir, data_dir, "m", limit=1, progress=False)
    with pytest.raises(ConflictError, match="encoder kind"):
        build_map(balm_mini_dir, data_dir, "m", encoder="precomputed", limit=1, progress=False)
    with pytest.raises(InputError, match="invalid"):
        build_map(balm_mini_dir, data_dir, "bad name", limit=1, progress=False)
    (tmp_path / "file").write_text("")
    with pytest.raises(InputError, match="not a directory"):
        build_map(balm_mini_dir, tmp_path / "file", "m", progress=False)


def test_build_map_command_data_dir(tmp_path: Path, balm_mini_dir: Path) -> None:
    runner = CliRunner()
    data_dir = tmp_path / "data"
    args = ["build-map", str(balm_mini_dir), "--map", "cli-dir", "--data-dir", str(data_dir)]
    args += ["--limit", "3", "--batch-size", "2", "--no-progress"]
    # SGVLOC_URL in the environment does not conflict: only an explicit --url does
    out = runner.invoke(app, args, env={"SGVLOC_URL": "http://127.0.0.1:9"})
    assert out.exit_code == 0, out.output
    assert "3 scans sent, 3 new keyframes, 0 already present; 3 keyframes" in out.output
    out = runner.invoke(app, args)
    assert out.exit_code == 0, out.output
    assert "0 new keyframes, 3 already present" in out.output
    assert (data_dir / "maps" / "cli-dir" / INDEX_NAME).is_file()

    out = runner.invoke(app, [*args, "--url", "http://127.0.0.1:9"])
    assert out.exit_code == 2  # a usage error, before anything is written
    said = " ".join(out.output.replace("\u2502", " ").split())  # without the box borders
    assert "give either --url (a running service) or --data-dir" in said, out.output

    out = runner.invoke(app, [*args[:-5], "--map", "nope", "--no-create", "--no-progress"])
    assert out.exit_code == 1 and "does not exist" in out.output


def test_build_map_reports_the_services_conflict(
    tmp_path: Path, balm_mini_dir: Path, start_service
) -> None:
    """A map folder that failed to load: build-map shows the service's reason (503
    map_unavailable with what to do), not a bare 404."""
    (tmp_path / "maps" / "broken").mkdir(parents=True)
    with start_service(tmp_path) as url:
        args = ["build-map", "--data", str(balm_mini_dir), "--map", "broken", "--url", url]
        out = CliRunner().invoke(app, [*args, "--limit", "1", "--no-progress"])
    assert out.exit_code == 1
    assert "map_unavailable" in out.output and "could not be loaded" in out.output, out.output
    assert "reload" in out.output


def test_choose_encoder_runs_the_self_test_and_records_it(
    service_url: str, balm_mini_dir: Path, tmp_path: Path
) -> None:
    """--choose-encoder --dry-run reports a figure per encoder and builds nothing; without
    --dry-run the map gets the chosen encoder and records the self-test."""
    import json

    runner = CliRunner()
    base = ["build-map", "--data", str(balm_mini_dir), "--map", "chosen", "--url", service_url]
    base += ["--choose-encoder", "--self-test-queries", "4", "--no-progress"]
    base += ["--self-test-out", str(tmp_path / "st.json")]
    out = runner.invoke(app, [*base, "--dry-run"])
    assert out.exit_code == 0, out.output
    report = json.loads((tmp_path / "st.json").read_text())
    assert set(report["encoders"]) == {"learned", "handcrafted", "bev", "learned-fpfh"}
    fpfh = report["encoders"]["learned-fpfh"]
    assert fpfh["encoder"] == {"kind": "learned", "learned": {"local_features": "fpfh"}}
    assert fpfh["encoder_fingerprint"] != report["encoders"]["learned"]["encoder_fingerprint"]
    assert f"| {report['chosen']} (chosen) |" in out.output
    for f in report["encoders"].values():
        assert f["queries"] == 4 and 0 <= f["pose_success_pct"] <= 100 and f["false_accepts"] >= 0
        assert 0 <= f["localized_correct"] <= f["correct_poses"] <= f["queries"]
    with Client(service_url) as c:
        assert "chosen" not in {m.name for m in c.list_maps()}
    out = runner.invoke(app, base)
    assert out.exit_code == 0, out.output
    again = json.loads((tmp_path / "st.json").read_text())
    assert again["chosen"] == report["chosen"]  # deterministic
    for kind, f in report["encoders"].items():
        g = again["encoders"][kind]
        assert {k: v for k, v in f.items() if k != "seconds"} == {
            k: v for k, v in g.items() if k != "seconds"
        }
    with Client(service_url) as c:
        info = c.get_map("chosen")
        spec = again["encoders"][again["chosen"]]["encoder"]
        assert info.encoder.kind == spec["kind"]
        assert info.encoder.fingerprint == again["encoders"][again["chosen"]]["encoder_fingerprint"]
        assert info.self_test["chosen"] == again["chosen"]
        assert info.self_test["encoders"] == again["encoders"]
        c.delete_map("chosen")
    out = runner.invoke(app, [*base, "--encoder", "bev"])
    assert out.exit_code == 2 and "--encoder" in out.output
    dry = ["build-map", "--data", str(balm_mini_dir), "--map", "x", "--url", service_url]
    out = runner.invoke(app, [*dry, "--dry-run"])
    assert out.exit_code == 2 and "--choose-encoder" in out.output


def test_self_test_choice_rule() -> None:
    from sgvloc.tools.self_test import choose

    def fig(localized: int, fa: int, correct: int, r1: float) -> dict:
        return {
            "localized_correct": localized,
            "false_accepts": fa,
            "correct_poses": correct,
            "recall_at_1_pct": r1,
        }

    order = ("learned", "handcrafted", "bev")
    # most queries localized correctly wins, whatever the rest: a correct pose the
    # verdict rejects is not an answer to act on
    figs = {"learned": fig(8, 0, 10, 90), "handcrafted": fig(9, 3, 9, 50)}
    assert choose(figs, order) == "handcrafted"
    # then fewest false accepts, then most correct poses, then R@1, then the order given
    figs = {"learned": fig(9, 2, 9, 90), "handcrafted": fig(9, 1, 9, 50), "bev": fig(9, 1, 9, 60)}
    assert choose(figs, order) == "bev"
    figs["handcrafted"] = fig(9, 1, 10, 50)
    assert choose(figs, order) == "handcrafted"
    figs["handcrafted"] = fig(9, 1, 9, 60)
    assert choose(figs, order) == "handcrafted"
    assert choose(figs, ("bev", "handcrafted", "learned")) == "bev"


def test_a_self_test_that_localizes_little_warns() -> None:
    """A map whose best encoder localizes under half of the scans with a revisit
    correctly is built with a warning that says so, in the report and its table."""
    from sgvloc.tools.self_test import report_table, warning

    def fig(localized: int) -> dict:
        return {"queries": 10, "localized_correct": localized, "recall_at_1_pct": 30.0}

    assert warning({"learned": fig(5)}, "learned") is None
    few = warning({"learned": fig(4), "bev": fig(1)}, "learned")
    assert few and few.startswith("learned, the best, localizes only 4 of the 10 scans")
    none = warning({"learned": fig(0), "bev": fig(0)}, "bev")
    assert none and none.startswith("no encoder localizes any of the 10 scans")
    row = fig(0) | {"ceiling_pct": 90.0, "pose_success_pct": 0.0, "false_accepts": 0}
    row |= {"localized_correct_pct": 0.0, "seconds": 1}
    report = {"data": "d", "queries": 10, "negatives": 3, "leave_out_s": 30, "seconds": 1}
    report |= {"pipeline": "p", "encoders": {"bev": row}, "chosen": "bev"}
    report |= {"rule": "r", "warning": none}
    assert report_table(report).endswith(f"warning: {none}")
    assert "warning" not in report_table(report | {"warning": None})


def test_self_test_of_a_served_map(service_url: str, balm_mini_dir: Path) -> None:
    """POST /v1/maps/{map}/self-test localizes the map's own keyframes against the rest
    (each one's 30 s of the drive left out), reports figures that follow from its
    per-query records, records the summary with the map and gives the same figures twice;
    bad settings get a 422 naming the field, a drive without a revisit one saying so."""
    from sgvloc_client import BadRequest

    runner = CliRunner()
    args = ["build-map", "--data", str(balm_mini_dir), "--map", "st", "--url", service_url]
    out = runner.invoke(app, [*args, "--no-progress"])
    assert out.exit_code == 0, out.output
    with Client(service_url) as c:
        rep = c.self_test_map("st", queries=4)
        figs, recs = rep["figures"], rep["records"]
        assert rep["basis"] == "timestamp" and rep["encoder"] == "learned"
        inside = [r for r in recs if r["in_coverage"]]
        assert figs["queries"] == len(inside) == 4
        assert figs["negatives"] == len(recs) - 4
        assert figs["pose_success"] == round(100 * sum(r["correct"] for r in inside) / 4, 1)
        assert figs["false_accepts"] == sum(r["localized"] and not r["correct"] for r in recs)
        # a real sequence with revisits: the pipeline finds and poses them
        assert figs["recall_at_1"] >= 75 and figs["pose_success"] >= 75
        for r in recs:  # no query is answered by a keyframe of its own 30 s
            assert r["top1"] is None or r["top1"] != r["keyframe"]
        info = c.get_map("st")
        assert info.last_self_test["figures"] == figs
        out = runner.invoke(app, ["map", "self-test", "st", "--queries", "4", "--url", service_url])
        assert out.exit_code == 0, out.output
        row = (
            f"| 4 | {figs['negatives']} | {figs['recall_at_1']:.1f} | {figs['pose_success']:.1f} |"
        )
        assert row in out.output and "gap by timestamp" in out.output
        out = runner.invoke(app, ["map", "self-test", "nope", "--url", service_url])
        assert out.exit_code == 1 and "nope" in out.output
        assert info.version == rep["map_version"]
        again = c.self_test_map("st", queries=4)
        strip = [{k: v for k, v in r.items() if k != "ms"} for r in recs]
        assert [{k: v for k, v in r.items() if k != "ms"} for r in again["records"]] == strip
        with pytest.raises(BadRequest) as err:
            c.self_test_map("st", queries=0)
        assert err.value.status == 422 and "queries" in str(err.value)
        with pytest.raises(BadRequest) as err:
            c.self_test_map("st", gap_s=1000)  # the drive lasts 88 s: no revisit
        assert err.value.status == 422 and "no keyframe has a revisit" in str(err.value)
        c.delete_map("st")


def test_a_served_map_compares_encoders_on_its_stored_clouds(
    service_url: str, balm_mini_dir: Path
) -> None:
    """With ``encoders``, the self-test measures each on the same queries from the
    keyframes' stored clouds encoded again (the map's own encoder as served), names the
    best by the build's rule and records the comparison without its records; unknown or
    repeated names, and a map that keeps no clouds, get a 422 naming ``encoders``."""
    from sgvloc.core import leave_out
    from sgvloc.core.encoders import EncoderSpec, make_encoder
    from sgvloc_client import BadRequest

    runner = CliRunner()
    args = ["build-map", "--data", str(balm_mini_dir), "--map", "st-enc", "--url", service_url]
    out = runner.invoke(app, [*args, "--no-progress"])
    assert out.exit_code == 0, out.output
    order = ["handcrafted", "learned", "bev", "learned-fpfh"]
    with Client(service_url) as c:
        rep = c.self_test_map("st-enc", queries=4, encoders=order)
        info = c.get_map("st-enc")
        enc = rep["encoders"]
        ranked = ("learned", "handcrafted", "bev", "learned-fpfh")  # the map's own first
        assert tuple(enc) == ranked
        own = enc["learned"]  # the map's own encoder: its answers as served
        assert own["fingerprint"] == info.encoder.fingerprint
        assert own["records"] == rep["records"] and own["figures"] == rep["figures"]
        queried = [r["keyframe"] for r in rep["records"]]
        for name in order:
            e = enc[name]
            assert e["encoder"] == leave_out.spec_of(name) and e["unencoded"] == 0
            made = make_encoder(EncoderSpec(**leave_out.spec_of(name)))
            assert e["fingerprint"] == made.identity.fingerprint
            assert [r["keyframe"] for r in e["records"]] == queried  # the same queries
            assert e["figures"] == leave_out.summarise(e["records"])
            for r in e["records"]:  # none answered by a keyframe of its own 30 s
                assert r["top1"] is None or r["top1"] != r["keyframe"]
        assert len({e["fingerprint"] for e in enc.values()}) == 4
        # real scans with revisits: every encoder finds most of them from the clouds
        assert all(e["figures"]["recall_at_1"] >= 50 for e in enc.values())
        figures = {n: e["figures"] for n, e in enc.items()}
        assert rep["chosen"] == leave_out.choose(figures, ranked)  # ties: the map's own
        assert rep["warning"] == leave_out.warning(figures, rep["chosen"])
        kept = info.last_self_test
        assert kept["chosen"] == rep["chosen"] and kept["rule"] == leave_out.RULE
        assert kept["encoders"]["bev"] == {k: v for k, v in enc["bev"].items() if k != "records"}
        out = runner.invoke(
            app,
            [
                "map",
                "self-test",
                "st-enc",
                "--queries",
                "4",
                "--encoders",
                "all",
                "--url",
                service_url,
            ],
        )
        assert out.exit_code == 0, out.output
        chosen = rep["chosen"]
        assert f"| {chosen} (chosen) |" in out.output and f"chosen: {chosen} (" in out.output
        # asked for one other encoder, the map's own is measured too and wins ties
        one = c.self_test_map("st-enc", queries=4, encoders=["bev"])
        assert list(one["encoders"]) == ["learned", "bev"]
        assert one["encoders"]["learned"]["records"] == one["records"]
        pair = {n: e["figures"] for n, e in one["encoders"].items()}
        assert one["chosen"] == leave_out.choose(pair, ("learned", "bev"))
        for bad in (["nope"], ["bev", "bev"], []):
            with pytest.raises(BadRequest) as err:
                c.self_test_map("st-enc", queries=4, encoders=bad)
            assert err.value.status == 422 and err.value.field == "encoders", bad
        out = runner.invoke(
            app, ["map", "self-test", "st-enc", "--encoders", ",", "--url", service_url]
        )
        assert out.exit_code == 2 and "--encoders" in out.output
        # one comparison at a time: another meanwhile is a 429, a plain self-test is not
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            first = pool.submit(c.self_test_map, "st-enc", queries=4, encoders=order)
            time.sleep(1.0)
            r = httpx.post(f"{service_url}/v1/maps/st-enc/self-test", json={"encoders": ["bev"]})
            plain = c.self_test_map("st-enc", queries=4)
            assert first.result()["chosen"] == rep["chosen"]
        assert r.status_code == 429 and r.json()["error"]["code"] == "overloaded", r.text
        assert "one runs at a time" in r.json()["error"]["message"] and r.headers["Retry-After"]
        untimed = [
            {k: v for k, v in x["figures"].items() if k != "median_ms"} for x in (plain, rep)
        ]
        assert untimed[0] == untimed[1]
        # a client that gives up stops the job: the summary it would record never is
        from sgvloc_client import TransportError

        before = c.get_map("st-enc").last_self_test
        with pytest.raises(TransportError):
            c.self_test_map("st-enc", queries=4, encoders=["handcrafted"], timeout=0.3)
        time.sleep(8)  # the whole run takes about 3 s here
        assert c.get_map("st-enc").last_self_test == before
        metrics = httpx.get(f"{service_url}/metrics").text
        gone = 'sgvloc_errors_total{code="caller_gone",route="/v1/maps/{map}/self-test"} 1.0'
        assert gone in metrics
        c.create_map("st-nc", keep_clouds=False)
        build_map(balm_mini_dir, c, "st-nc", create=False, progress=False)
        assert c.self_test_map("st-nc", queries=4)["figures"]["queries"] == 4
        with pytest.raises(BadRequest) as err:
            c.self_test_map("st-nc", queries=4, encoders=["bev"])
        assert err.value.status == 422 and err.value.field == "encoders"
        assert "keep_clouds" in str(err.value)
        c.delete_map("st-nc")
        c.delete_map("st-enc")


def test_scans_the_encoder_cannot_describe_are_skipped(
    service_url: str, balm_mini_dir: Path, tmp_path: Path
) -> None:
    """A scan in which the map's encoder finds nothing (flat ground only: no BEV column
    holds two voxels) is a 422 ``empty_scan`` naming it; build-map leaves it out, and a
    scan file with no point, says which, and inserts the rest, into a service and into a
    data directory alike."""
    import shutil

    data = tmp_path / "seq"
    shutil.copytree(balm_mini_dir, data)
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-10, 10, (300, 2)), np.full(300, -1.5), np.ones(300)]
    for i in (1, 4):
        ground.astype(np.float32).tofile(data / "velodyne" / f"{i:06d}.bin")
    (data / "velodyne" / "000003.bin").write_bytes(b"")  # a scan file with no point
    r = httpx.post(f"{service_url}/v1/maps", json={"name": "sparse"})
    assert r.status_code == 201, r.text
    r = httpx.post(
        f"{service_url}/v1/maps/sparse/localize", json={"points": ground.tolist()}, timeout=60
    )
    assert r.status_code == 422, r.text
    assert r.json()["error"]["code"] == "empty_scan"
    assert r.json()["error"]["field"] == "points"

    args = ["build-map", str(data), "--map", "sparse", "--limit", "6", "--batch-size", "4"]
    for target in (["--url", service_url], ["--data-dir", str(tmp_path / "dd")]):
        out = CliRunner().invoke(app, [*args, *target, "--no-progress"])
        assert out.exit_code == 0, out.output
        assert "6 scans sent, 3 new keyframes" in out.output
        assert "3 scans skipped" in out.output, out.output
        assert "seq/000001, seq/000003, seq/000004" in out.output, out.output
    with Client(service_url) as c:
        keys = [kf.key for kf in c.list_keyframes("sparse").keyframes]
        assert sorted(keys) == [f"seq/{i:06d}" for i in (0, 2, 5)]
        c.delete_map("sparse")


def test_another_sequence_in_a_folder_of_the_same_name_is_refused(
    tmp_path: Path, balm_mini_dir: Path
) -> None:
    """Keys name a sequence by its folder: a second drive in a folder of the same name
    must not be skipped scan by scan as "already present"."""
    import shutil

    data_dir = tmp_path / "data"
    build_map(balm_mini_dir, data_dir, "m", limit=2, progress=False)
    other = tmp_path / "elsewhere" / balm_mini_dir.name
    shutil.copytree(balm_mini_dir, other)
    poses = np.loadtxt(other / "poses.txt").reshape(-1, 3, 4)
    poses[:, :, 3] += [100.0, 0.0, 0.0]  # the same scans, 100 m away
    np.savetxt(other / "poses.txt", poses.reshape(-1, 12))
    with pytest.raises(ConflictError, match="100.00 m from this sequence's pose"):
        build_map(other, data_dir, "m", limit=3, progress=False)
    # the same sequence again resumes
    rest = build_map(balm_mini_dir, data_dir, "m", limit=3, progress=False)
    assert (rest.created, rest.existing) == (1, 2)


def test_a_renamed_folder_resumes_under_its_key_prefix(
    tmp_path: Path, balm_mini_dir: Path, service_url: str
) -> None:
    """Keys default to FOLDER/SCAN: after a rename the build would store every scan again
    under the new name, so it is refused, naming the earlier prefix; --key-prefix with
    that name resumes it instead (into a data directory and through the service)."""
    import shutil

    data_dir = tmp_path / "data"
    build_map(balm_mini_dir, data_dir, "m", limit=2, progress=False)
    moved = tmp_path / "renamed"
    shutil.copytree(balm_mini_dir, moved)
    runner = CliRunner()
    args = ["build-map", "--data", str(moved), "--map", "m", "--data-dir", str(data_dir)]
    args += ["--limit", "3", "--no-progress"]
    out = runner.invoke(app, [*args, "--key-prefix", balm_mini_dir.name])
    assert out.exit_code == 0, out.output
    assert "1 new keyframes, 2 already present; 3 keyframes" in out.output, out.output
    out = runner.invoke(app, args)  # the new name as prefix: the same scans again
    assert out.exit_code == 1, out.output
    assert f"--key-prefix {balm_mini_dir.name} to resume" in out.output, out.output
    with pytest.raises(ConflictError, match="was the folder renamed or moved"):
        build_map(moved, data_dir, "m", limit=3, progress=False)
    other = build_map(moved, data_dir, "m2", limit=3, progress=False)  # another map: fine
    assert other.created == 3
    again = build_map(moved, data_dir, "m", limit=1, progress=False, key_prefix="twice")
    assert again.created == 1  # a prefix given on purpose: no check
    none = build_map(moved, data_dir, "m", limit=0, progress=False)  # no scan selected
    assert (none.created, none.existing) == (0, 0)
    build_map(balm_mini_dir, service_url, "renamed", limit=2, progress=False)
    with pytest.raises(ConflictError, match=f"under the key prefix '{balm_mini_dir.name}'"):
        build_map(moved, service_url, "renamed", limit=3, progress=False)
    resumed = build_map(
        moved, service_url, "renamed", limit=3, progress=False, key_prefix=balm_mini_dir.name
    )
    assert (resumed.created, resumed.existing) == (1, 2)

    for bad in ("/", "  ", "a\tb"):
        out = runner.invoke(app, [*args, "--key-prefix", bad])
        assert out.exit_code == 2, out.output  # a usage error, before anything is written
        assert "key_prefix" in out.output, out.output
    with pytest.raises(InputError, match="key_prefix"):
        build_map(moved, data_dir, "m", key_prefix="", progress=False)


def test_two_drives_that_both_start_at_the_origin_go_into_one_map(
    tmp_path: Path, balm_mini_dir: Path
) -> None:
    """KITTI poses start every sequence at the identity, as scan 000000: that scan is no
    sign of a renamed folder, so a second drive is added under its own name."""
    import shutil

    drives = []
    for name, shift in (("drive-a", 0.0), ("drive-b", 100.0)):
        folder = tmp_path / name
        shutil.copytree(balm_mini_dir, folder)
        poses = np.loadtxt(folder / "poses.txt").reshape(-1, 3, 4)
        poses[:, :, 3] += [shift, 0.0, 0.0]
        poses[0] = np.eye(4)[:3]
        np.savetxt(folder / "poses.txt", poses.reshape(-1, 12))
        drives.append(folder)
    data_dir = tmp_path / "data"
    assert build_map(drives[0], data_dir, "city", limit=3, progress=False).created == 3
    both = build_map(drives[1], data_dir, "city", limit=3, progress=False)
    assert (both.created, both.keyframes) == (3, 6)


def test_a_build_that_inserts_nothing_leaves_no_map(
    tmp_path: Path, balm_mini_dir: Path, service_url: str
) -> None:
    """A build that fails before its first keyframe went in (here: the first scan is
    not a scan) deletes the map it made, so that it can simply be run again; a map it
    did not make is left alone."""
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(balm_mini_dir, broken)
    first = sorted((broken / "velodyne").iterdir())[0]
    first.write_bytes(b"\x00" * 5)  # not a whole point
    data_dir = tmp_path / "data"
    with pytest.raises(InputError):
        build_map(broken, data_dir, "m", limit=2, progress=False)
    with Client(service_url) as client:
        with pytest.raises(InputError):
            build_map(broken, client, "broken-build", limit=2, progress=False)
        assert "broken-build" not in [m.name for m in client.list_maps()]
    build_map(balm_mini_dir, data_dir, "other", limit=1, progress=False)
    with pytest.raises(InputError):  # a prefix given: the same poses may go in again
        build_map(broken, data_dir, "other", limit=2, progress=False, key_prefix="broken")
    from sgvloc.server.maps import MapManager

    m = MapManager(data_dir / "maps")
    m.load_all()
    try:
        assert [h.name for h in m.list()] == ["other"] and m.get("other").num_keyframes == 1
    finally:
        m.close()
