"""The monitoring files: Prometheus alert rules (checked and unit-tested by Debian's
``promtool``), the Prometheus configuration, the Grafana provisioning and dashboard, and
how docker-compose.yml wires them. That the dashboard and the rules only use series the
service really exports is checked against a running service in
``tests/service/test_observability.py``.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from sgvloc.tools.dashboard import metric_names, panels

ROOT = Path(__file__).resolve().parents[1]
PROM_DIR = ROOT / "docker" / "prometheus"
GRAFANA_DIR = ROOT / "docker" / "grafana"
DASHBOARD = GRAFANA_DIR / "dashboards" / "sgvloc.json"


def promtool() -> str:
    found = shutil.which("promtool")
    if found is None:
        pytest.fail("Debian's prometheus (promtool) is not installed (README, Install)")
    return found


def compose() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def mounts(service: dict) -> dict[str, Path]:
    """Container path -> host path of a compose service's bind mounts."""
    out = {}
    for vol in service.get("volumes", []):
        src, dst, *_ = str(vol).split(":")
        if src.startswith("."):
            out[dst] = ROOT / src
    return out


def alert_rules() -> list[dict]:
    groups = yaml.safe_load((PROM_DIR / "alerts.yml").read_text())["groups"]
    return [r for g in groups for r in g["rules"] if "alert" in r]


def test_promtool_checks_the_alert_rules() -> None:
    run = subprocess.run(
        [promtool(), "check", "rules", str(PROM_DIR / "alerts.yml")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    assert f"SUCCESS: {len(alert_rules())} rules found" in run.stdout


def test_promtool_unit_tests_of_the_alerts_pass() -> None:
    run = subprocess.run(
        [promtool(), "test", "rules", "alerts.test.yml"],
        cwd=PROM_DIR,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    assert "SUCCESS" in run.stdout


def test_every_alert_is_unit_tested_firing_and_silent() -> None:
    tests = yaml.safe_load((PROM_DIR / "alerts.test.yml").read_text())
    assert tests["rule_files"] == ["alerts.yml"]
    cases = [c for t in tests["tests"] for c in t["alert_rule_test"]]
    for rule in alert_rules():
        mine = [c for c in cases if c["alertname"] == rule["alert"]]
        assert any(c["exp_alerts"] for c in mine), f"{rule['alert']} never expected to fire"
        assert any(not c["exp_alerts"] for c in mine), f"{rule['alert']} never expected silent"
        assert rule["labels"]["severity"] in ("warning", "critical")
        assert rule["annotations"]["summary"] and rule["annotations"]["description"]


def test_promtool_checks_the_prometheus_config(tmp_path: Path) -> None:
    """The compose configuration as Prometheus reads it: its rule file resolves next to it
    (the scrape key is a compose secret, so a stand-in file takes its place here)."""
    cfg = yaml.safe_load((PROM_DIR / "prometheus.yml").read_text())
    (tmp_path / "metrics.key").write_text("stand-in")
    for job in cfg["scrape_configs"]:
        job["authorization"]["credentials_file"] = str(tmp_path / "metrics.key")
    (tmp_path / "prometheus.yml").write_text(yaml.safe_dump(cfg))
    shutil.copy(PROM_DIR / "alerts.yml", tmp_path / "alerts.yml")
    run = subprocess.run(
        [promtool(), "check", "config", str(tmp_path / "prometheus.yml")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    assert f"SUCCESS: {len(alert_rules())} rules found" in run.stdout


def test_compose_prometheus_loads_the_alert_rules() -> None:
    prom = compose()["services"]["prometheus"]
    mounted = mounts(prom)
    cfg_path = mounted["/etc/prometheus/prometheus.yml"]
    assert cfg_path == PROM_DIR / "prometheus.yml"
    cfg = yaml.safe_load(cfg_path.read_text())
    assert cfg["rule_files"], "no rule_files"
    for rule_file in cfg["rule_files"]:
        in_container = rule_file if rule_file.startswith("/") else f"/etc/prometheus/{rule_file}"
        assert mounted.get(in_container) == PROM_DIR / "alerts.yml", in_container


def test_compose_grafana_is_provisioned_with_the_dashboard() -> None:
    services = compose()["services"]
    grafana = services["grafana"]
    image, _, tag = grafana["image"].partition(":")
    assert image == "grafana/grafana" and tag[:1].isdigit(), "a pinned Grafana version"
    assert grafana["ports"] and all(str(p).startswith("127.0.0.1:") for p in grafana["ports"])
    mounted = mounts(grafana)
    provisioning = mounted["/etc/grafana/provisioning"]
    assert provisioning == GRAFANA_DIR / "provisioning"

    # the data source: the compose Prometheus, by the uid the dashboard uses
    (ds_file,) = (provisioning / "datasources").glob("*.yml")
    (ds,) = yaml.safe_load(ds_file.read_text())["datasources"]
    assert ds["type"] == "prometheus" and ds["url"] == "http://prometheus:9090"
    assert "prometheus" in services
    board = json.loads(DASHBOARD.read_text())
    uids = {t["datasource"]["uid"] for p in board["panels"] for t in p["targets"]}
    uids |= {p["datasource"]["uid"] for p in board["panels"]}
    assert uids == {ds["uid"]}

    # the dashboards: a file provider whose folder is where compose mounts the JSON
    (prov_file,) = (provisioning / "dashboards").glob("*.yml")
    (provider,) = yaml.safe_load(prov_file.read_text())["providers"]
    assert provider["type"] == "file"
    folder = provider["options"]["path"]
    assert mounted[folder] == DASHBOARD.parent and DASHBOARD.is_file()
    env = grafana["environment"]
    home = env["GF_DASHBOARDS_DEFAULT_HOME_DASHBOARD_PATH"]
    assert home == f"{folder}/{DASHBOARD.name}"
    # anonymous read-only access, nobody can log in (see docs/OPERATIONS.md, Monitoring)
    assert env["GF_AUTH_ANONYMOUS_ENABLED"] == "true"
    assert env["GF_AUTH_ANONYMOUS_ORG_ROLE"] == "Viewer"
    assert env["GF_AUTH_DISABLE_LOGIN_FORM"] == "true" and env["GF_AUTH_BASIC_ENABLED"] == "false"
    assert "grafana-data" in compose()["volumes"]


def test_dashboard_panels_are_well_formed() -> None:
    board = json.loads(DASHBOARD.read_text())
    assert board["uid"] == "sgvloc" and board["editable"] is False
    ids = [p["id"] for p in board["panels"]]
    assert len(ids) == len(set(ids))
    found = panels(board)
    titles = {p.title for p in found}
    # what the dashboard is for: rate, latency per stage, verdicts, refusals, map sizes
    for needed in (
        "Localize rate",
        "Localize latency (HTTP)",
        "Stage latency p50",
        "Stage latency p99",
        "Localized ratio",
        "429 / 503 answers",
        "Map sizes",
    ):
        assert needed in titles
    cells: set[tuple[int, int]] = set()
    for p in found:
        x, y, w, h = p.grid
        assert 0 <= x and x + w <= 24, p.title
        area = {(r, c) for r in range(y, y + h) for c in range(x, x + w)}
        assert not cells & area, f"{p.title} overlaps another panel"
        cells |= area
        assert p.targets
        for t in p.targets:
            assert metric_names(t.expr), f"{p.title}: {t.expr} uses no sgvloc series"
