"""Library thread limits of a service process (sgvloc.server.threads), in fresh interpreters."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from sgvloc.server.threads import ENV_VARS

PROBE = """
import json, logging
logging.basicConfig(level="WARNING")
from sgvloc.server.threads import limit_library_threads
env = limit_library_threads(1)
import numba, torch
from sgvloc.core.o3d import open3d
print(json.dumps({"env": env, "torch": torch.get_num_threads(),
                  "numba": numba.config.NUMBA_NUM_THREADS,
                  "open3d": open3d().utility.get_max_threads()}))
"""


def _probe(**preset: str) -> tuple[dict, str]:
    env = {k: v for k, v in os.environ.items() if k not in ENV_VARS}
    env.update(preset)
    run = subprocess.run(
        [sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=120
    )
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout.strip().splitlines()[-1]), run.stderr


def test_limits_reach_the_libraries() -> None:
    out, err = _probe()
    assert out["env"] == {var: "1" for var in ENV_VARS}
    assert out["torch"] == 1 and out["numba"] == 1
    assert out["open3d"] == 1  # its TBB pool reads none of the variables: set by call
    assert "not applied" not in err


def test_the_operators_setting_wins() -> None:
    out, _ = _probe(NUMBA_NUM_THREADS="2")
    assert out["env"]["NUMBA_NUM_THREADS"] == "2" and out["env"]["OMP_NUM_THREADS"] == "1"
    assert out["numba"] == 2


def test_late_call_is_reported_and_changes_nothing() -> None:
    code = (
        "import os, numpy\nfrom sgvloc.server.threads import limit_library_threads as f\n"
        "f(1, force=True)\nprint(os.environ.get('OMP_NUM_THREADS'))"
    )
    env = {k: v for k, v in os.environ.items() if k not in ENV_VARS}
    run = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=env
    )
    assert run.returncode == 0 and "not applied" in run.stderr
    assert run.stdout.strip() == "None"


def test_serve_caps_threads_before_the_libraries_load(tmp_path) -> None:
    """``sgvloc serve`` up to the failing keys file: no library was loaded before the cap."""
    keys = tmp_path / "keys.toml"
    keys.write_text("not = [valid")
    run = subprocess.run(
        [sys.executable, "-m", "sgvloc.cli", "serve", "--keys-file", str(keys)],
        capture_output=True,
        text=True,
        timeout=120,
        env={k: v for k, v in os.environ.items() if k not in ENV_VARS},
        cwd=tmp_path,
    )
    assert run.returncode == 2, run.stderr
    assert "sgvloc serve:" in run.stderr
    assert "not applied" not in run.stderr, run.stderr


def test_offline_commands_cap_threads_before_the_libraries_load(balm_mini_dir, tmp_path) -> None:
    """``sgvloc eval`` in a fresh process: 1 thread by default, --threads wins over the
    environment, and no library was loaded before the cap (eval.json records torch's)."""
    env = {k: v for k, v in os.environ.items() if k not in ENV_VARS and k != "SGVLOC_THREADS"}
    args = [sys.executable, "-m", "sgvloc.cli", "eval", "--data", str(balm_mini_dir)]
    args += ["--min-gap", "30", "--topk", "2", "--sweep", "2", "--methods", "none"]
    args += ["--no-progress", "--cache-dir", str(tmp_path / "cache")]
    for extra, preset, expected in (([], {}, 1), (["--threads", "2"], {"OMP_NUM_THREADS": "3"}, 2)):
        out = tmp_path / f"out{expected}"
        run = subprocess.run(
            [*args, "--out", str(out), *extra],
            env={**env, **preset},
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert run.returncode == 0, run.stderr
        assert "not applied" not in run.stderr, run.stderr
        report = json.loads((out / "eval.json").read_text())
        assert report["timings"]["torch_threads"] == expected


def test_every_command_states_its_thread_policy() -> None:
    from typer.testing import CliRunner

    from sgvloc.cli import app

    for name in ("eval", "calibrate", "build-map", "bench", "synth", "bev-images", "train",
                 "loadtest", "export-weights", "serve"):  # fmt: skip
        res = CliRunner().invoke(app, [name, "--help"], env={"COLUMNS": "200"})
        assert res.exit_code == 0, res.output
        assert "--threads" in res.output and "Threads" in res.output, name
