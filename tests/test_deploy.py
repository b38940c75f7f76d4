"""Static checks of the deployment files (no Docker engine here), plus the container's
commands run natively: the Dockerfile's CMD must be a valid ``sgvloc serve`` call, its
HEALTHCHECK must succeed against that server, and compose/Prometheus must point at it.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "docker" / "Dockerfile"
COMPOSE = ROOT / "docker-compose.yml"
KEYS_SECRET = "/run/secrets/sgvloc-keys"
METRICS_SECRET = "/run/secrets/sgvloc-metrics-key"


def dockerfile_instructions(path: Path) -> list[tuple[str, str]]:
    """``(INSTRUCTION, arguments)`` per instruction, continuation lines joined."""
    out: list[tuple[str, str]] = []
    pending = ""
    for line in path.read_text().splitlines():
        stripped = line.strip()
        if not pending and (not stripped or stripped.startswith("#")):
            continue
        if pending and stripped.startswith("#"):
            continue  # comment inside a continued instruction
        if stripped.endswith("\\"):
            pending += stripped[:-1] + " "
            continue
        full = (pending + stripped).strip()
        pending = ""
        if full:
            word, _, args = full.partition(" ")
            out.append((word.upper(), args.strip()))
    assert not pending, "Dockerfile ends inside a continued line"
    return out


def exec_form(args: str) -> list[str]:
    """The JSON array of an exec-form CMD/HEALTHCHECK (shell form is refused)."""
    start = args.index("[")
    value = json.loads(args[start:])
    assert isinstance(value, list) and all(isinstance(v, str) for v in value)
    return value


def option(argv: list[str], name: str) -> str:
    assert name in argv, f"{name} missing from {argv}"
    return argv[argv.index(name) + 1]


@pytest.fixture(scope="module")
def docker() -> dict[str, list[str]]:
    """Dockerfile instructions by name (each a list of argument strings, in order)."""
    by_name: dict[str, list[str]] = {}
    for word, args in dockerfile_instructions(DOCKERFILE):
        by_name.setdefault(word, []).append(args)
    return by_name


@pytest.fixture(scope="module")
def compose() -> dict:
    data = yaml.safe_load(COMPOSE.read_text())
    assert isinstance(data, dict) and isinstance(data.get("services"), dict)
    return data


@pytest.fixture(scope="module")
def cmd(docker: dict[str, list[str]]) -> list[str]:
    assert len(docker["CMD"]) == 1, "exactly one CMD"
    return exec_form(docker["CMD"][0])


@pytest.fixture(scope="module")
def port(docker: dict[str, list[str]]) -> int:
    (expose,) = docker["EXPOSE"]
    return int(expose.split("/")[0])


def test_dockerfile_base_user_volume_and_cmd(docker, cmd, port) -> None:
    assert docker["FROM"][0].startswith("python:3.11-slim")
    assert cmd[:2] == ["sgvloc", "serve"]
    assert int(option(cmd, "--port")) == port == 8470
    assert option(cmd, "--host") == "0.0.0.0"
    assert docker["VOLUME"] == ["/data"] and option(cmd, "--data-dir") == "/data"
    # authentication on: the keys come from a mounted secret, never development mode
    assert option(cmd, "--keys-file") == KEYS_SECRET and "--dev" not in cmd
    # a non-root user is active when the service starts
    users = [u for u in docker.get("USER", [])]
    assert users and users[-1].split(":")[0] not in ("root", "0")


def test_dockerfile_installs_cpu_torch_then_the_service(docker) -> None:
    # the pin in pyproject.toml (tomllib is 3.11+, the project supports 3.10)
    pins = re.findall(r'"(torch[^"]*)"', (ROOT / "pyproject.toml").read_text())
    assert pins == ["torch==2.13.0"]
    runs = docker["RUN"]
    torch_runs = [r for r in runs if "torch==" in r]
    assert len(torch_runs) == 1
    assert "torch==2.13.0" in torch_runs[0]
    assert "--index-url https://download.pytorch.org/whl/cpu" in torch_runs[0]
    service_runs = [r for r in runs if re.search(r"pip install [\"']?\.\[service\]", r)]
    assert len(service_runs) == 1
    assert runs.index(torch_runs[0]) < runs.index(service_runs[0]), "CPU torch first"
    apt = " ".join(r for r in runs if "apt-get install" in r)
    for lib in ("libusb-1.0-0", "libgomp1"):
        assert lib in apt


def test_dockerfile_copies_existing_files_not_ignored(docker) -> None:
    ignored = {
        ln.strip()
        for ln in (ROOT / ".dockerignore").read_text().splitlines()
        if ln.strip() and not ln.startswith("#")
    }
    sources = []
    for args in docker["COPY"]:
        parts = [p for p in shlex.split(args) if not p.startswith("--")]
        sources += parts[:-1]
    assert {"pyproject.toml", "service", "client"} <= set(sources)
    for src in sources:
        assert (ROOT / src).exists(), f"COPY source {src} does not exist"
        assert src not in ignored and src.split("/")[0] not in ignored, f"{src} is ignored"
    # everything pip needs to build the package is copied
    readme = re.search(r'^readme\s*=\s*"([^"]+)"', (ROOT / "pyproject.toml").read_text(), re.M)
    if readme:
        assert readme.group(1) in sources


def test_installed_package_carries_the_learned_weights(tmp_path: Path) -> None:
    """The image installs the package non-editable (pip install ".[service]"): the wheel
    built from what the Dockerfile copies must hold the shipped weights, byte for byte."""
    import shutil
    import zipfile

    from sgvloc.core.encoders.learned import SHIPPED_WEIGHTS, shipped_weights_path

    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for name in ("service", "client"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
    run = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation"]
        + ["-q", "-w", str(tmp_path / "dist")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr
    (wheel,) = (tmp_path / "dist").glob("sgvloc-*.whl")
    with zipfile.ZipFile(wheel) as z:
        data = z.read(f"sgvloc/weights/{SHIPPED_WEIGHTS}")
    assert data == shipped_weights_path().read_bytes()


def test_dockerfile_healthcheck_probes_healthz(docker, port) -> None:
    (hc,) = docker["HEALTHCHECK"]
    probe = exec_form(hc)
    assert probe[:2] == ["python", "-c"]
    assert f"127.0.0.1:{port}/healthz" in probe[2]


def test_compose_services(compose, port) -> None:
    services = compose["services"]
    assert set(services) >= {"sgvloc", "prometheus"}
    for name, svc in services.items():
        build = svc.get("build")
        if build is None:
            assert "image" in svc, f"service {name} has neither build nor image"
            continue
        context = ROOT / (build if isinstance(build, str) else build.get("context", "."))
        dockerfile = "Dockerfile" if isinstance(build, str) else build.get("dockerfile")
        assert context.is_dir(), f"{name}: build context {context} missing"
        assert (context / dockerfile).is_file(), f"{name}: {dockerfile} missing"

    sgv = services["sgvloc"]
    assert sgv["build"] == {"context": ".", "dockerfile": "docker/Dockerfile"}
    published = [str(p) for p in sgv["ports"]]
    assert f"{port}:{port}" in published
    mounts = [str(v).split(":") for v in sgv["volumes"]]
    data = [m for m in mounts if m[1] == "/data"]
    assert data and data[0][0] in (compose.get("volumes") or {}), "named volume for /data"
    test = sgv["healthcheck"]["test"]
    probe = " ".join(test if isinstance(test, list) else [test])
    assert f"127.0.0.1:{port}/healthz" in probe
    assert test[0] in ("CMD", "CMD-SHELL") and "curl" not in probe
    # the keys file is a secret at the path the CMD reads; no development mode
    secrets = compose["secrets"]
    (keys,) = [s for s in sgv["secrets"] if s["target"] == KEYS_SECRET]
    assert keys["source"] in secrets and "file" in secrets[keys["source"]]
    assert "SGVLOC_DEV" not in (sgv.get("environment") or {})
    ignored = (ROOT / ".dockerignore").read_text().split()
    for secret in secrets.values():  # never baked into the image, never committed
        name = Path(secret["file"]).name
        assert name in ignored and name in (ROOT / ".gitignore").read_text().split()


def test_prometheus_scrapes_the_service(compose, port) -> None:
    prom = compose["services"]["prometheus"]
    assert prom["image"].startswith("prom/prometheus")
    host_cfg = None
    for vol in prom["volumes"]:
        src, dst, *_ = str(vol).split(":")
        if dst == "/etc/prometheus/prometheus.yml":
            host_cfg = ROOT / src
    assert host_cfg is not None and host_cfg.is_file()
    cfg = yaml.safe_load(host_cfg.read_text())
    jobs = {j["job_name"]: j for j in cfg["scrape_configs"]}
    job = jobs["sgvloc"]
    assert job.get("metrics_path", "/metrics") == "/metrics"
    targets = [t for sc in job["static_configs"] for t in sc["targets"]]
    assert targets == [f"sgvloc:{port}"]  # compose service name and container port
    # /metrics needs a viewer key: Prometheus reads it from its own secret
    assert job["authorization"] == {"type": "Bearer", "credentials_file": METRICS_SECRET}
    assert [s["target"] for s in prom["secrets"]] == [METRICS_SECRET]


def test_cli_accepts_the_dockerfile_cmd(cmd) -> None:
    import typer

    from sgvloc.cli import app

    group = typer.main.get_command(app)
    serve = group.commands["serve"]
    known = {opt for p in serve.params for opt in p.opts + p.secondary_opts}
    for arg in cmd[2:]:
        if arg.startswith("-"):
            assert arg in known, f"sgvloc serve has no option {arg}"
    # parse the exact arguments (types included) without running the server
    ctx = serve.make_context("serve", list(cmd[2:]))
    assert ctx.params["port"] == 8470

    help_run = subprocess.run(
        [sys.executable, "-c", "from sgvloc.cli import main; main()", "serve", "--help"],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "COLUMNS": "200", "TERM": "dumb", "NO_COLOR": "1"},
    )
    assert help_run.returncode == 0, help_run.stderr
    for arg in cmd[2:]:
        if arg.startswith("--"):
            assert arg in help_run.stdout


def test_container_commands_run_natively(docker, cmd, port, tmp_path: Path) -> None:
    """The CMD (on a free port and a temporary data dir) serves, the HEALTHCHECK command
    passes against it and fails once it is gone, and /metrics has the service's series."""
    import socket

    import httpx

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        free = s.getsockname()[1]
    argv = list(cmd[2:])
    argv[argv.index("--port") + 1] = str(free)
    argv[argv.index("--data-dir") + 1] = str(tmp_path / "data")
    viewer_key = "deploy-test-viewer-key-0123456789"
    keys = tmp_path / "sgvloc-keys"  # the secret, as mounted: no suffix, so TOML
    keys.write_text(f'[[keys]]\nname = "prometheus"\nrole = "viewer"\nkey = "{viewer_key}"\n')
    argv[argv.index("--keys-file") + 1] = str(keys)
    probe = [a.replace(f":{port}/", f":{free}/") for a in exec_form(docker["HEALTHCHECK"][0])]
    probe[0] = sys.executable  # "python" in the image

    log = tmp_path / "serve.log"
    with open(log, "wb") as out:
        server = subprocess.Popen(
            [sys.executable, "-c", "from sgvloc.cli import main; main()", "serve", *argv],
            stdout=out,
            stderr=subprocess.STDOUT,
            env={
                **{k: v for k, v in os.environ.items() if k not in ("SGVLOC_DEV",)},
                "SGVLOC_LOG_LEVEL": "warning",
            },
        )
    try:
        deadline = time.monotonic() + 90
        while subprocess.run(probe, capture_output=True, timeout=30).returncode != 0:
            assert server.poll() is None, log.read_text()[-3000:]
            assert time.monotonic() < deadline, "HEALTHCHECK never passed"
            time.sleep(0.3)
        url = f"http://127.0.0.1:{free}/metrics"
        assert httpx.get(url, timeout=10).status_code == 401  # metrics need a viewer key
        metrics = httpx.get(url, headers={"Authorization": f"Bearer {viewer_key}"}, timeout=10)
        assert metrics.status_code == 200
        assert "sgvloc_http_requests_total" in metrics.text
    finally:
        server.terminate()
        server.wait(timeout=30)
    assert subprocess.run(probe, capture_output=True, timeout=30).returncode != 0
