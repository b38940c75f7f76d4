"""Static checks of the deployment files (no Docker engine here), plus the container's
commands run natively: the Dockerfile's CMD must be a valid ``sgvloc serve`` call, its
HEALTHCHECK must succeed against that server, and compose/Prometheus must point at it.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
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
    # keys come from SGVLOC_KEYS_FILE (compose sets it), so SGVLOC_DEV=1 can work too
    assert "--keys-file" not in cmd and "--dev" not in cmd
    assert not any("SGVLOC_DEV" in e or "SGVLOC_KEYS_FILE" in e for e in docker.get("ENV", []))
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


def test_dockerfile_healthcheck_probes_readyz(docker, port) -> None:
    """Healthy means ready (every map loaded), not merely up."""
    (hc,) = docker["HEALTHCHECK"]
    probe = exec_form(hc)
    assert probe[:2] == ["python", "-c"]
    assert f"127.0.0.1:{port}/readyz" in probe[2]


REPLICAS = ("sgvloc-1", "sgvloc-2")
PG_SECRET = "/run/secrets/sgvloc-pg-password"


def test_compose_services(compose, port) -> None:
    services = compose["services"]
    assert set(services) >= {"postgres", *REPLICAS, "lb", "prometheus"}
    for name, svc in services.items():
        build = svc.get("build")
        if build is None:
            assert "image" in svc, f"service {name} has neither build nor image"
            continue
        context = ROOT / (build if isinstance(build, str) else build.get("context", "."))
        dockerfile = "Dockerfile" if isinstance(build, str) else build.get("dockerfile")
        assert context.is_dir(), f"{name}: build context {context} missing"
        assert (context / dockerfile).is_file(), f"{name}: {dockerfile} missing"

    secrets = compose["secrets"]
    volumes = compose.get("volumes") or {}
    data_volumes = set()
    for name in REPLICAS:
        sgv = services[name]
        assert sgv["build"] == {"context": ".", "dockerfile": "docker/Dockerfile"}
        assert "ports" not in sgv, "replicas are reached through the load balancer only"
        mounts = [str(v).split(":") for v in sgv["volumes"]]
        data = [m for m in mounts if m[1] == "/data"]
        assert data and data[0][0] in volumes, "a named volume for /data"
        data_volumes.add(data[0][0])
        test = sgv["healthcheck"]["test"]
        probe = " ".join(test if isinstance(test, list) else [test])
        assert f"127.0.0.1:{port}/readyz" in probe
        assert test[0] in ("CMD", "CMD-SHELL") and "curl" not in probe
        # keys and the store's password are secrets at the paths the settings name
        env = sgv.get("environment") or {}
        assert env["SGVLOC_KEYS_FILE"] == KEYS_SECRET and "SGVLOC_DEV" not in env
        assert env["SGVLOC_STORE_URL"].startswith("postgresql://sgvloc@postgres:5432/")
        assert ":" not in env["SGVLOC_STORE_URL"].split("//")[1].split("@")[0], "no password"
        assert env["SGVLOC_STORE_PASSWORD_FILE"] == PG_SECRET
        targets = {s["target"]: s["source"] for s in sgv["secrets"]}
        assert targets[KEYS_SECRET] in secrets and targets[PG_SECRET] in secrets
        assert sgv["depends_on"]["postgres"]["condition"] == "service_healthy"
    assert len(data_volumes) == len(REPLICAS), "each replica its own /data"

    pg = services["postgres"]
    assert pg["image"].startswith("postgres:15")
    assert pg["environment"]["POSTGRES_PASSWORD_FILE"] == PG_SECRET
    assert [s["target"] for s in pg["secrets"]] == [PG_SECRET]
    (pg_data,) = [str(v).split(":") for v in pg["volumes"]]
    assert pg_data[1] == "/var/lib/postgresql/data" and pg_data[0] in volumes
    assert "pg_isready" in pg["healthcheck"]["test"]

    lb = services["lb"]
    assert lb["image"].startswith("nginx:")
    # plain HTTP is published on the host's loopback only, by the load balancer
    assert [str(p) for p in lb["ports"]] == [f"127.0.0.1:{port}:{port}"]
    assert all(str(p).startswith("127.0.0.1:") for p in services["prometheus"]["ports"])
    assert {n: d["condition"] for n, d in lb["depends_on"].items()} == {
        n: "service_healthy" for n in REPLICAS
    }
    conf = [str(v).split(":") for v in lb["volumes"]]
    assert conf[0][:2] == ["./docker/nginx/nginx.conf", "/etc/nginx/nginx.conf"]
    upstream = re.findall(r"^\s*server (\S+?):(\d+)", (ROOT / conf[0][0]).read_text(), re.M)
    assert upstream == [(n, str(port)) for n in REPLICAS]

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
    assert targets == [f"{n}:{port}" for n in REPLICAS]  # every replica, its container port
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


def documented_key_commands() -> list[list[str]]:
    """The commands of docker-compose.yml's header that make its secrets."""
    lines = [ln.lstrip("#").strip() for ln in COMPOSE.read_text().splitlines()]
    starts = ("sgvloc new-key", "chmod ", "python3 -c")
    cmds = [shlex.split(ln) for ln in lines if ln.startswith(starts)]
    assert [c[0] for c in cmds] == ["sgvloc", "sgvloc", "chmod", "python3"], cmds
    return cmds


def make_documented_secrets(compose: dict, where: Path) -> dict[str, Path]:
    """Run the documented commands in ``where``; the compose secrets' files by name."""
    for argv in documented_key_commands():
        out = None
        if argv[0] == "sgvloc":
            argv = [sys.executable, "-c", "from sgvloc.cli import main; main()", *argv[1:]]
        elif argv[0] == "python3":  # python3 -c "..." > file
            assert argv[-2] == ">", argv
            out, argv = where / argv[-1], [sys.executable, *argv[1:-2]]
        run = subprocess.run(argv, cwd=where, capture_output=True, text=True, timeout=60)
        assert run.returncode == 0, (argv, run.stderr)
        if out is not None:
            out.write_text(run.stdout)
    files = {name: where / s["file"] for name, s in compose["secrets"].items()}
    for path in files.values():  # the containers' users (not the host's) read them
        assert path.is_file() and path.stat().st_mode & 0o004, path
    return files


def serve_container_cmd(cmd, argv_env, tmp_path, port, name: str = "serve"):
    """Start the Dockerfile's CMD natively on ``port`` with the given environment."""
    argv = list(cmd[2:])
    argv[argv.index("--port") + 1] = str(port)
    argv[argv.index("--data-dir") + 1] = str(tmp_path / f"{name}-data")
    log = tmp_path / f"{name}.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith("SGVLOC_")}
    with open(log, "wb") as out:
        server = subprocess.Popen(
            [sys.executable, "-c", "from sgvloc.cli import main; main()", "serve", *argv],
            stdout=out,
            stderr=subprocess.STDOUT,
            env={**env, "SGVLOC_LOG_LEVEL": "warning", **argv_env},
        )
    return server, log


def wait_healthy(probe, server, log) -> None:
    deadline = time.monotonic() + 90
    while subprocess.run(probe, capture_output=True, timeout=30).returncode != 0:
        assert server.poll() is None, log.read_text()[-3000:]
        assert time.monotonic() < deadline, "HEALTHCHECK never passed"
        time.sleep(0.3)


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def nginx() -> str:
    found = shutil.which("nginx") or next(
        (p for p in ("/usr/sbin/nginx",) if Path(p).exists()), None
    )
    if found is None:
        pytest.fail("Debian's nginx is not installed (README, Install)")
    return found


def test_container_commands_run_natively(
    compose, docker, cmd, port, postgres, tmp_path: Path
) -> None:
    """The cluster of docker-compose.yml, run natively: the documented commands make the
    secrets; PostgreSQL gets the sgvloc user with that password; both replicas run the
    CMD with compose's environment (the store's host and port pointed at the test
    server) and pass the HEALTHCHECK; nginx runs docker/nginx/nginx.conf in front of
    them (upstreams pointed at them). Through the load balancer the admin key creates a
    map, both replicas serve it, Prometheus's key reads each replica's /metrics, and with
    one replica gone the load balancer still answers from the other."""
    import httpx
    import psycopg

    secrets = make_documented_secrets(compose, tmp_path)
    password = secrets["sgvloc-pg-password"].read_text().strip()
    assert len(password) >= 24
    admin_url = postgres.new_database()
    with psycopg.connect(admin_url, autocommit=True) as conn:
        conn.execute(f"CREATE ROLE sgvloc LOGIN PASSWORD '{password}'")
        conn.execute("CREATE DATABASE sgvloc_deploy OWNER sgvloc")
    host_port = admin_url.split("@")[1].split("/")[0]
    servers, probes, ports = [], [], []
    for name in REPLICAS:
        env = dict(compose["services"][name]["environment"])
        env["SGVLOC_KEYS_FILE"] = str(secrets["sgvloc-keys"])
        env["SGVLOC_STORE_PASSWORD_FILE"] = str(secrets["sgvloc-pg-password"])
        env["SGVLOC_STORE_URL"] = (
            env["SGVLOC_STORE_URL"].replace("postgres:5432", host_port).rsplit("/", 1)[0]
            + "/sgvloc_deploy"
        )
        free = free_port()
        probe = [a.replace(f":{port}/", f":{free}/") for a in exec_form(docker["HEALTHCHECK"][0])]
        probe[0] = sys.executable  # "python" in the image
        servers.append(serve_container_cmd(cmd, env, tmp_path, free, name))
        probes.append(probe)
        ports.append(free)
    lb_port = free_port()
    conf_text = (ROOT / "docker" / "nginx" / "nginx.conf").read_text()
    for name, free in zip(REPLICAS, ports, strict=True):
        conf_text = conf_text.replace(f"server {name}:{port}", f"server 127.0.0.1:{free}")
    conf_text = conf_text.replace(f"listen {port};", f"listen 127.0.0.1:{lb_port};")
    conf_text = conf_text.replace("/tmp/", f"{tmp_path}/nginx-")
    conf = tmp_path / "nginx.conf"
    conf.write_text(conf_text)
    lb = None
    try:
        for (server, log), probe in zip(servers, probes, strict=True):
            wait_healthy(probe, server, log)
        lb = subprocess.Popen(
            [nginx(), "-c", str(conf), "-p", str(tmp_path), "-g", "daemon off;"],
            stdout=subprocess.DEVNULL,
            stderr=open(tmp_path / "nginx.log", "wb"),  # noqa: SIM115 - closed with the process
        )
        base = f"http://127.0.0.1:{lb_port}"
        deadline = time.monotonic() + 30
        while True:
            try:
                if httpx.get(f"{base}/lb-healthz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, (tmp_path / "nginx.log").read_text()
            time.sleep(0.2)
        admin = {"Authorization": f"Bearer {(tmp_path / 'sgvloc-admin.key').read_text()}"}
        made = httpx.post(
            f"{base}/v1/maps",
            json={"name": "m", "encoder": {"kind": "handcrafted"}},
            headers=admin,
            timeout=60,
        )
        assert made.status_code == 201, made.text
        viewer = secrets["sgvloc-metrics-key"].read_text()
        for free in ports:
            replica = f"http://127.0.0.1:{free}"
            deadline = time.monotonic() + 10
            while httpx.get(f"{replica}/v1/maps/m", headers=admin).status_code != 200:
                assert time.monotonic() < deadline, "the map did not reach every replica"
                time.sleep(0.1)
            assert httpx.get(f"{replica}/metrics", timeout=10).status_code == 401
            metrics = httpx.get(
                f"{replica}/metrics", headers={"Authorization": f"Bearer {viewer}"}, timeout=10
            )
            assert metrics.status_code == 200 and "sgvloc_http_requests_total" in metrics.text
        servers[0][0].kill()
        servers[0][0].wait(timeout=30)
        for _ in range(6):  # every answer from the replica that is left
            r = httpx.get(f"{base}/v1/maps/m", headers=admin, timeout=30)
            assert r.status_code == 200, r.text
    finally:
        if lb is not None:
            lb.terminate()
            lb.wait(timeout=30)
        for server, _ in servers:
            if server.poll() is None:
                server.terminate()
                server.wait(timeout=30)
    for probe in probes:
        assert subprocess.run(probe, capture_output=True, timeout=30).returncode != 0


def test_container_cmd_in_development_mode(cmd, docker, port, tmp_path: Path) -> None:
    """SGVLOC_DEV=1 with the same CMD: no keys needed, the service becomes healthy."""
    import httpx

    free = free_port()
    probe = [a.replace(f":{port}/", f":{free}/") for a in exec_form(docker["HEALTHCHECK"][0])]
    probe[0] = sys.executable
    server, log = serve_container_cmd(cmd, {"SGVLOC_DEV": "1"}, tmp_path, free)
    try:
        wait_healthy(probe, server, log)
        assert httpx.get(f"http://127.0.0.1:{free}/v1/maps", timeout=10).status_code == 200
    finally:
        server.terminate()
        server.wait(timeout=30)


def test_ci_runs_the_readme_install_and_test_commands() -> None:
    """.ci/run installs and tests exactly as the README tells a newcomer to."""
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text()
    blocks = {}
    for title in ("Install", "Test"):
        section = readme.split(f"\n## {title}\n", 1)[1]
        blocks[title] = re.search(r"```bash\n(.*?)```", section, re.S).group(1)
    lines = [ln for b in blocks.values() for ln in b.splitlines() if ln.strip()]
    assert any("torch==2.13.0+cpu" in ln and "whl/cpu" in ln for ln in lines)
    assert any(ln.startswith("python3 -m venv") for ln in lines)
    for line in lines:
        assert line in ci, f".ci/run lacks the README's command: {line}"
