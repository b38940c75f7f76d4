"""``sgvloc calibrate`` end to end on a tiny generated sequence."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from sgvloc.cli import app
from sgvloc.core.confidence import PROFILE_FEATURES, Calibration, Evidence, shipped_calibration
from sgvloc.tools.synth import SynthConfig, generate


def test_calibrate_writes_a_calibration_that_loads(tmp_path):
    seq = tmp_path / "town"
    generate(seq, SynthConfig(scans=40, seed=3))
    out = tmp_path / "cal.json"
    args = ["calibrate", "--data", str(seq), "--db-until", "2", "--name", "tiny"]
    args += ["--cache-dir", str(tmp_path / "cache"), "--no-progress", "--out", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    cal = Calibration.load(out)
    assert cal.name == "tiny" and cal.encoder_kind == "learned"
    assert set(cal.models) == {"icp", "none"}  # a 3-D sequence runs with and without ICP
    for profile, model in cal.models.items():
        assert model.features == list(PROFILE_FEATURES[profile])
        assert all(w >= 0 for w in model.weights)
        fit = cal.fitted_on["fit"][profile]
        assert fit["answers"] > fit["correct"] > 0
    assert [r["refine"] for r in cal.fitted_on["runs"]] == ["icp", "none"]
    assert f"fingerprint {cal.fingerprint}" in res.output
    # a tiny town gives few answers of one kind: the fit is written, with a warning
    fewest = min(
        min(f["correct"], f["answers"] - f["correct"]) for f in cal.fitted_on["fit"].values()
    )
    assert (fewest < 20) == ("warning: profile" in res.output), res.output
    assert 0.0 < cal.confidence(Evidence(sgv=0.2, inliers=20, inlier_ratio=0.3)) < 1.0
    assert json.loads(out.read_text())["format"] == "sgvloc-calibration/1"

    # the same from an eval report: answers without ICP give the "none" profile only
    report = tmp_path / "eval"
    args = ["eval", "--data", str(seq), "--db-until", "2", "--methods", "sgv", "--topk", "20"]
    args += ["--sweep", "20", "--refine", "none", "--no-progress", "--out", str(report)]
    args += ["--cache-dir", str(tmp_path / "cache")]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    args = ["calibrate", "--from", str(report / "eval.json"), "--out", str(tmp_path / "b.json")]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    cal = Calibration.load(tmp_path / "b.json")
    assert set(cal.models) == {"none"} and cal.fitted_on["runs"][0]["refine"] == "none"
    # with a base, the profiles these answers do not cover are kept from it, and said so
    args = ["calibrate", "--from", str(report / "eval.json"), "--base", "shipped"]
    res = CliRunner().invoke(app, [*args, "--name", "partial", "--out", str(tmp_path / "p.json")])
    assert res.exit_code == 0, res.output
    partial = Calibration.load(tmp_path / "p.json")
    shipped = shipped_calibration("learned")
    assert partial.models["none"] == cal.models["none"]  # refitted on these answers
    for profile in set(shipped.models) - {"none"}:
        assert partial.models[profile] == shipped.models[profile]
        kept = partial.fitted_on["kept"][profile]
        assert (kept["from"], kept["fingerprint"]) == (shipped.name, shipped.fingerprint)
        # the runs it was fitted on, also when the shipped one kept it from an earlier one
        assert kept["fit"]["answers"] > 0 and kept["runs"], kept
        assert all(profile in r["answers"] for r in kept["runs"])
    assert "kept from" in res.output
    # a report without sgv at the map's top-k is refused with what to run
    args = ["calibrate", "--from", str(report / "eval.json"), "--config", str(tmp_path / "k.json")]
    (tmp_path / "k.json").write_text('{"top_k": 5}')
    res = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "c.json")])
    assert res.exit_code == 2 and "--methods sgv --topk 5" in res.output


def test_calibrate_refuses_bad_options(tmp_path):
    res = CliRunner().invoke(
        app,
        [
            "calibrate",
            "--data",
            str(tmp_path),
            "--min-gap",
            "30",
            "--refine",
            "magic",
            "--out",
            str(tmp_path / "c.json"),
        ],
    )
    assert res.exit_code == 2 and "icp and/or none" in res.output
    res = CliRunner().invoke(
        app,
        [
            "calibrate",
            "--data",
            str(tmp_path / "missing"),
            "--min-gap",
            "30",
            "--out",
            str(tmp_path / "c.json"),
        ],
    )
    assert res.exit_code != 0 and "not found" in res.output
    assert not (tmp_path / "c.json").exists()
