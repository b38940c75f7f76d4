"""The ``sgvloc`` command's own behaviour: --version, one-line errors where the
client-only install lacks the service extra, API keys with that install, a busy port."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sgvloc.about import __version__
from sgvloc.server.api.auth import parse_keys
from sgvloc.server.keys import hash_key

tomllib = pytest.importorskip("tomllib", reason="Python 3.11+ reads TOML")

#: what a client-only install (``pip install -e .``) lacks: importing any of them fails
BLOCKED = ("torch", "faiss", "open3d", "scipy", "numba", "fastapi", "uvicorn",
           "pydantic_settings", "prometheus_client", "matplotlib", "cv2")  # fmt: skip


def sgvloc(
    *args: str,
    client_only: bool = False,
    cwd: Path | None = None,
    timeout=120,
    env: dict[str, str] | None = None,
):
    block = f"[sys.modules.__setitem__(m, None) for m in {BLOCKED!r}]; " if client_only else ""
    code = f"import sys; {block}sys.argv = ['sgvloc', *sys.argv[1:]]; "
    code += "from sgvloc.cli import main; main()"
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=cwd,
        env={**os.environ, "COLUMNS": "200", **(env or {})},
    )


def test_version() -> None:
    run = sgvloc("--version", client_only=True)
    assert run.returncode == 0 and run.stdout.strip() == f"sgvloc {__version__}"


def test_client_only_install_says_what_is_missing(tmp_path: Path) -> None:
    for args in (
        ["serve", "--dev", "--data-dir", str(tmp_path / "d")],
        ["eval", "--data", str(tmp_path)],
        ["train", "--data", str(tmp_path), "--out", str(tmp_path / "t")],
        ["bench", "--only", "rerank"],
    ):
        run = sgvloc(*args, client_only=True)
        assert run.returncode == 2, (args, run.stdout, run.stderr)
        assert "Traceback" not in run.stderr, run.stderr
        (line,) = run.stderr.strip().splitlines()
        assert line.startswith(f"sgvloc {args[0]}: needs the service extra"), line


def test_new_key_with_the_client_only_install(tmp_path: Path) -> None:
    keys, admin, viewer = tmp_path / "keys.toml", tmp_path / "admin.key", tmp_path / "m.key"
    for role, name, key_file in (("admin", "operator", admin), ("viewer", "prom", viewer)):
        run = sgvloc("new-key", "--role", role, "--name", name, "--keys-file", str(keys),
                     "--key-file", str(key_file), client_only=True)  # fmt: skip
        assert run.returncode == 0, run.stderr
        assert run.stdout == ""  # nothing secret or needed on stdout
    assert keys.stat().st_mode & 0o777 == 0o644 and admin.stat().st_mode & 0o777 == 0o600
    parsed = parse_keys(tomllib.loads(keys.read_text()), "keys.toml")
    assert [(k.principal.name, k.principal.role) for k in parsed] == [
        ("operator", "admin"),
        ("prom", "viewer"),
    ]
    text = keys.read_text()
    for key_file in (admin, viewer):
        key = key_file.read_text()
        assert len(key) == 43 and key not in text and hash_key(key) in text
    # a key file is never overwritten; the keys file is left as it was
    run = sgvloc("new-key", "--role", "admin", "--name", "x", "--keys-file", str(keys),
                 "--key-file", str(admin), client_only=True)  # fmt: skip
    assert run.returncode == 2 and "never overwritten" in run.stderr
    assert keys.read_text() == text
    # a name already in the keys file would keep the service from starting: refused,
    # before any key file is written
    taken = tmp_path / "taken.key"
    run = sgvloc("new-key", "--role", "vehicle", "--name", "operator", "--keys-file", str(keys),
                 "--key-file", str(taken), client_only=True)  # fmt: skip
    assert run.returncode == 2 and "named 'operator' already" in run.stderr, run.stderr
    assert keys.read_text() == text and not taken.exists()
    # without files: the key on stderr, the entry on stdout
    run = sgvloc("new-key", "--role", "vehicle", "--name", "t1", "--maps", "a,b")
    assert run.returncode == 0 and run.stderr.startswith("key: ")
    entry = tomllib.loads(run.stdout)["keys"][0]
    assert entry["maps"] == ["a", "b"] and entry["key"] == hash_key(run.stderr[5:].strip())


def test_new_key_adds_to_a_json_keys_file(tmp_path: Path) -> None:
    """A .json keys file stays JSON: each entry joins its "keys" list, and the service
    reads both; a JSON file of another shape is refused before a key is written."""
    import json

    keys = tmp_path / "keys.json"
    keys.write_text('{"keys": [{"name": "a", "role": "viewer", "key": "%s"}]}' % ("a" * 25))
    for name in ("b", "c"):
        run = sgvloc("new-key", "--role", "vehicle", "--name", name, "--maps", "m1",
                     "--keys-file", str(keys), "--key-file", str(tmp_path / name),
                     client_only=True)  # fmt: skip
        assert run.returncode == 0, run.stderr
    parsed = parse_keys(json.loads(keys.read_text()), "keys.json")
    assert [(k.principal.name, k.principal.role) for k in parsed] == [
        ("a", "viewer"),
        ("b", "vehicle"),
        ("c", "vehicle"),
    ]
    assert json.loads(keys.read_text())["keys"][1]["maps"] == ["m1"]
    # a new .json file is made as one document
    fresh = tmp_path / "fresh.json"
    run = sgvloc("new-key", "--role", "admin", "--name", "op", "--keys-file", str(fresh),
                 "--key-file", str(tmp_path / "op"), client_only=True)  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert [k["name"] for k in json.loads(fresh.read_text())["keys"]] == ["op"]
    odd = tmp_path / "odd.json"
    odd.write_text('{"keys": {"name": "a"}}')
    run = sgvloc("new-key", "--role", "admin", "--name", "x", "--keys-file", str(odd),
                 "--key-file", str(tmp_path / "x"), client_only=True)  # fmt: skip
    assert run.returncode == 2 and '"keys" list' in run.stderr, run.stderr
    assert odd.read_text() == '{"keys": {"name": "a"}}' and not (tmp_path / "x").exists()


def test_serve_on_a_busy_port_fails_at_once(tmp_path: Path) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        run = sgvloc("serve", "--dev", "--port", str(port), "--data-dir", str(tmp_path / "d"))
    assert run.returncode == 2
    (line,) = [ln for ln in run.stderr.splitlines() if ln.strip()]
    assert line.startswith(f"sgvloc serve: cannot listen on 127.0.0.1:{port}"), run.stderr
    assert "another process listens there" in line
    # nothing was loaded: no data directory made, no map or kernel work (seconds otherwise)
    assert not (tmp_path / "d").exists()


def test_serve_names_the_option_or_variable_of_a_bad_setting(tmp_path: Path) -> None:
    """A bad setting is named as it was given (option or SGVLOC_ variable), and a
    variable that is no setting (a typo) is warned about instead of silently ignored."""
    run = sgvloc("serve", "--dev", "--workers", "0", "--data-dir", str(tmp_path / "d"),
                 env={"SGVLOC_MAX_POINTS": "-1"})  # fmt: skip
    assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr
    text = " ".join(run.stderr.split())
    assert "--workers: Input should be greater than or equal to 1 (got 0)" in text, text
    assert "SGVLOC_MAX_POINTS: Input should be greater than or equal to 1 (got '-1')" in text
    with socket.socket() as busy:  # the service stops at once after the warning
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = str(busy.getsockname()[1])
        run = sgvloc("serve", "--dev", "--port", port, "--data-dir", str(tmp_path / "d"),
                     env={"SGVLOC_WORKRS": "3", "SGVLOC_URL": "http://x"})  # fmt: skip
    assert run.returncode == 2, run.stderr
    assert "SGVLOC_WORKRS is not a setting (ignored); SGVLOC_WORKERS?" in run.stderr
    assert "SGVLOC_URL" not in run.stderr  # the CLI's own variable
    # a variable in other case is read (so not warned about); a check of two settings
    # says what is wrong without pydantic's prefix
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = str(busy.getsockname()[1])
        run = sgvloc("serve", "--dev", "--port", port, "--data-dir", str(tmp_path / "d"),
                     env={"SGVLOC_Log_Level": "debug"})  # fmt: skip
    assert run.returncode == 2 and "not a setting" not in run.stderr, run.stderr
    run = sgvloc("serve", "--dev", "--workers", "2", "--data-dir", str(tmp_path / "d"),
                 env={"SGVLOC_WRITE_WORKERS": "5"})  # fmt: skip
    text = " ".join(run.stderr.replace("│", " ").split())
    assert run.returncode == 2 and "write_workers (5) may not exceed workers (2)" in text, text
    assert "Value error" not in text, text


def test_serve_on_a_data_directory_it_cannot_use_exits(tmp_path: Path) -> None:
    """A maps folder that cannot be made (here a file is in the way) is a start-up error
    with status 2 and the reason (it was a traceback)."""
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "maps").write_text("not a folder")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = str(s.getsockname()[1])
    run = sgvloc("serve", "--dev", "--port", port, "--data-dir", str(tmp_path / "d"))
    assert run.returncode == 2, run.stderr
    last = [ln for ln in run.stderr.splitlines() if ln.strip()][-1]
    assert last.startswith("sgvloc serve: cannot use "), run.stderr
    assert last.endswith("maps as the maps folder: File exists"), run.stderr


def test_serve_starts_without_library_noise(tmp_path: Path) -> None:
    """Start-up at the default log level: no faiss loader lines, no numba or torch
    warnings (the SGV kernels are compiled before /readyz says ready)."""
    import httpx

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    log = tmp_path / "serve.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SGVLOC_", "NUMBA_"))}
    with log.open("wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "sgvloc.cli", "serve", "--dev", "--port", str(port)]
            + ["--data-dir", str(tmp_path / "d")],
            stdout=out,
            stderr=subprocess.STDOUT,
            env=env,
        )
    try:
        deadline = time.monotonic() + 120
        while True:
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
            try:
                if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            time.sleep(0.3)
    finally:
        proc.terminate()
        proc.wait(timeout=60)
    text = log.read_text()
    assert "sgv numba kernels ready" in text
    for noise in ("faiss.loader", "NumbaWarning", "UserWarning", "Traceback"):
        assert noise not in text, text


def test_package_data_loads_beside_a_folder_named_sgvloc(tmp_path: Path) -> None:
    """Run from a folder holding a ``sgvloc/`` checkout: the package's weights,
    calibrations and version still load (an editable install can see ``sgvloc`` as a
    namespace there)."""
    (tmp_path / "sgvloc" / "service").mkdir(parents=True)
    code = (
        "from sgvloc.about import __version__\n"
        "from sgvloc.core.confidence import shipped_calibration\n"
        "from sgvloc.core.encoders import EncoderSpec, make_encoder\n"
        "make_encoder(EncoderSpec())\n"
        "print(__version__, shipped_calibration('learned').name)\n"
    )
    run = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith(__version__)


def test_bad_arguments_are_one_line_usage_errors(tmp_path: Path) -> None:
    """A URL, timeout, device or file the command cannot use is exit 2 naming the option,
    never a traceback, and nothing is left behind."""
    from typer.testing import CliRunner

    from sgvloc.cli import app

    missing = str(tmp_path / "no" / "such.json")
    out = str(tmp_path / "t")
    cases = [
        (["map", "list", "--url", "http://[::1"], "--url"),
        (["map", "list", "--timeout", "-1"], "--timeout"),
        (["build-map", "--data", str(tmp_path), "--map", "x", "--timeout", "0"], "--timeout"),
        (["train", "--data", str(tmp_path), "--out", out, "--device", "gpu"], "--device"),
        (["eval", "--data", str(tmp_path), "--min-gap", "9", "--config", missing], "--config"),
        (["calibrate", "--out", str(tmp_path / "c.json"), "--config", missing], "--config"),
        (["eval", "--data", str(tmp_path), "--min-gap", "9", "--config",
          '{"pose": {"ransac_n": 1}}'], "ransac_n"),
        (["eval", "--data", str(tmp_path), "--min-gap", "9", "--config", '{"pose": '], "--config"),
        (["calibrate", "--out", str(tmp_path / "c.json"), "--config", '{"top_k": "x"}'], "top_k"),
        (["new-key", "--name", "a", "--role", "viewer", "--keys-file", missing], "--keys-file"),
        (["new-key", "--name", "a", "--role", "viewer", "--key-file", missing], "--key-file"),
    ]  # fmt: skip
    for args, option in cases:
        run = CliRunner().invoke(app, args, env={"COLUMNS": "200"})
        assert run.exit_code == 2, (args, run.output)
        assert option in run.output and "Traceback" not in run.output, (args, run.output)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


#: a calibrate run on a folder of the test (none of its output is written)
CALIBRATE = ["calibrate", "--data", "{tmp}", "--db-until", "5", "--out", "{tmp}/c.json"]


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["calibrate", "--out", "{tmp}", "--from", "x.json"], "is a folder; name a file"),
        (["eval", "--data", "{tmp}", "--min-gap", "9", "--out", "{tmp}/afile"], "name a folder"),
        (["bench", "--only", "rerank", "--out", "{tmp}/afile/b.json"], "is a file, not a folder"),
        (["loadtest", "--json", "{tmp}/afile/x/y.json"], "is a file, not a folder"),
        (["calibrate-track", "--data", "{tmp}", "--out", "{tmp}"], "is a folder"),
        (["calibrate-track", "--data", "{tmp}@30:10", "--out", "{tmp}/m.json"], "0 <= A < B"),
        (["calibrate-track", "--data", "{tmp}@x", "--out", "{tmp}/m.json"], "DIR@N"),
        (["synth", "{tmp}/afile"], "is a file; name a folder"),
        (["train", "--data", "{tmp}", "--out", "{tmp}/afile", "--steps", "1"], "is a file"),
        (
            ["build-map", "--data", "{tmp}", "--map", "m", "--data-dir", "{tmp}/d", "--limit", "0"],
            "--limit",
        ),  # fmt: skip
        (
            ["train", "--data", "{tmp}", "--out", "{tmp}/afile/sub", "--steps", "1"],
            "is a file, not a folder",
        ),
        (
            ["build-map", "--data", "{tmp}", "--map", "m", "--data-dir", "{tmp}/afile/d"],
            "is a file, not a folder",
        ),
        (["calibrate", "--out", "{tmp}/afile/c.json"], "afile is a file, not a folder"),
        (["export-weights", "{tmp}/ck.pt", "{tmp}"], "is a folder; name a file"),
        (["export-weights", "{tmp}/ck.pt", "{tmp}/afile/w.pt"], "is a file, not a folder"),
        (["export-onnx", "{tmp}/w.pt", "--out", "{tmp}"], "is a folder; name a file"),
        ([*CALIBRATE, "--refine", "icp"], "icp,none"),
        ([*CALIBRATE, "--refine", "xyz"], "--refine"),
        (["calibrate", "--data", "{tmp}", "--out", "{tmp}/c.json"], "--min-gap"),
        (["eval", "--data", "{tmp}"], "exactly one split"),
        (["eval", "--data", "{tmp}", "--min-gap", "30", "--fov", "0"], "--fov"),
        (["eval", "--data", "{tmp}", "--min-gap", "30", "--prior-radius", "0"], "--prior-radius"),
        (["eval", "--data", "{tmp}", "--min-gap", "30", "--topk", "0"], "--topk"),
        (["eval", "--data", "{tmp}", "--min-gap", "30", "--sweep", "x"], "--sweep"),
        (
            ["eval-track", "--data", "{tmp}", "--tracking", '{{"nosuch": 1, "stop_m": -1}}'],
            "'--tracking': stop_m: Input should be greater than 0; nosuch: Extra inputs",
        ),  # fmt: skip
        (["eval-track", "--data", "{tmp}", "--tracking", "{{bad"], "not valid JSON"),
        (["eval-track", "--data", "{tmp}", "--encoder", "nosuch"], "'--encoder': kind: Input"),
        (
            [
                "eval",
                "--data",
                "{tmp}",
                "--min-gap",
                "9",
                "--encoder",
                '{{"kind": "bev", "foo": 1}}',
            ],
            "Invalid value for '--encoder': foo: Extra inputs are not permitted",
        ),  # fmt: skip
        (
            ["build-map", "--data", "{tmp}", "--map", "m", "--encoder", '{{"kind": "x"}}'],
            "Invalid value for '--encoder': kind: Input should be",
        ),  # fmt: skip
        (["calibrate-track", "--data", "{balm}@20:30", "--out", "{tmp}/m.json"], "has 15 scans"),
        (
            [
                "calibrate-track",
                "--data",
                "{balm}@5",
                "--out",
                "{tmp}/m.json",
                "--samples",
                "{tmp}/afile",
            ],
            "not a samples file",
        ),  # fmt: skip
        (["synth", "{tmp}/s", "--fov", "0"], "--fov"),
        (["synth", "{tmp}/s", "--pattern", "bogus"], "--pattern"),
        (["synth", "{tmp}/s", "--fov-up", "-30", "--fov-down", "10"], "fov"),
        (["train", "--data", "{tmp}", "--out", "{tmp}/t", "--batch", "500"], "--batch"),
    ],
)
def test_arguments_a_command_cannot_use_are_refused_before_the_work(
    tmp_path: Path, args: list[str], words: str
) -> None:
    """Long commands write their results at the end: an output path they could not write,
    or a scan span they could not read, is a usage error at once, not a traceback after
    the work."""
    (tmp_path / "afile").write_text("")
    balm = Path(__file__).parent / "fixtures" / "balm_mini"
    res = sgvloc(*(a.format(tmp=tmp_path, balm=balm) for a in args))
    assert res.returncode == 2, res.stdout + res.stderr
    text = " ".join((res.stdout + res.stderr).replace("│", " ").split())  # unboxed
    assert words in text and "Traceback" not in text, text
    assert "errors.pydantic.dev" not in text, text


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["bench", "--only", "rerank", "--ks", "0"], "Invalid value for --ks"),
        (["bench", "--only", "http", "--http-clients", "0,2"], "at least 1"),
        (["bench", "--only", "tracking", "--track-data", "{tmp}"], "bench: "),
    ],
)
def test_bench_values_it_cannot_use_are_usage_errors(
    tmp_path: Path, args: list[str], words: str
) -> None:
    res = sgvloc(*(a.format(tmp=tmp_path) for a in args), "--out", str(tmp_path / "b.json"))
    assert res.returncode == 2, res.stdout + res.stderr
    assert words in res.stdout + res.stderr and "Traceback" not in res.stderr


def test_an_interruption_inside_a_compiled_kernel_exits_as_one() -> None:
    """Ctrl-C or SIGTERM arriving while numba calls back into Python comes out as a
    SystemError caused by the interruption: the command exits 130 / 143 as for any
    interruption, not with a traceback."""
    from sgvloc.cli import interruption_exit_code

    def raised(inner: BaseException) -> SystemError:
        try:
            try:
                raise inner
            except BaseException:
                raise SystemError("returned a result with an exception set")  # noqa: B904
        except SystemError as exc:
            try:  # numba wraps once more
                raise SystemError("CPUDispatcher(<function _register>)") from exc
            except SystemError as outer:
                return outer

    assert interruption_exit_code(raised(KeyboardInterrupt())) == 130
    assert interruption_exit_code(raised(SystemExit(143))) == 143
    assert interruption_exit_code(raised(ValueError("bad"))) is None
    assert interruption_exit_code(SystemError("alone")) is None
