"""The Grafana dashboard's panels from a real run, drawn with matplotlib
(``python -m sgvloc.tools.dashboard``, which writes ``docs/dashboard.png``).

Grafana itself does not run here, but Prometheus does (Debian's ``prometheus``): a
local ``sgvloc serve`` gets a map built from a KITTI-layout folder and a few minutes of
localize traffic from several clients and API keys (phases of low and high load, scans
with and without a prior, some that cannot be localized); a local Prometheus scrapes it
every second with the alert rules loaded, and every panel's PromQL, exactly as it stands
in the dashboard JSON (``$__rate_interval`` and the ``$map`` variable filled in), is
evaluated by that Prometheus and plotted in the panel's place.

The module also holds the helpers that the tests use to check the dashboard and the
alert rules against the series the service really exports.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import secrets
import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from sgvloc_client import wire

from .service_process import ServiceProcess, exit_on_sigterm, free_port

log = logging.getLogger(__name__)

DASHBOARD = Path("docker/grafana/dashboards/sgvloc.json")
ALERTS = Path("docker/prometheus/alerts.yml")
#: metric names in PromQL: every series of the service starts with ``sgvloc_``
_METRIC = re.compile(r"\bsgvloc_[A-Za-z0-9_:]+")
_LEGEND = re.compile(r"\{\{\s*([A-Za-z_][A-Za-z0-9_]*)\s*\}\}")


# -- the dashboard -----------------------------------------------------------------------


@dataclass(frozen=True)
class Target:
    expr: str
    legend: str


@dataclass(frozen=True)
class Panel:
    title: str
    unit: str
    targets: tuple[Target, ...]
    grid: tuple[int, int, int, int]  # x, y, w, h (Grafana's 24-column grid)


def load_dashboard(path: Path = DASHBOARD) -> dict[str, Any]:
    return json.loads(Path(path).read_text())


def panels(dashboard: dict[str, Any]) -> list[Panel]:
    """The dashboard's graph panels, top to bottom, left to right (rows flattened)."""
    found: list[Panel] = []

    def walk(items: list[dict[str, Any]]) -> None:
        for p in items:
            if p.get("type") == "row":
                walk(p.get("panels", []))
                continue
            g = p.get("gridPos", {})
            found.append(
                Panel(
                    p["title"],
                    p.get("fieldConfig", {}).get("defaults", {}).get("unit", ""),
                    tuple(Target(t["expr"], t.get("legendFormat", "")) for t in p["targets"]),
                    (g.get("x", 0), g.get("y", 0), g.get("w", 12), g.get("h", 8)),
                )
            )

    walk(dashboard["panels"])
    return sorted(found, key=lambda p: (p.grid[1], p.grid[0]))


def dashboard_queries(dashboard: dict[str, Any]) -> list[str]:
    """Every PromQL text of the dashboard: panel targets and template variable queries."""
    out = [t.expr for p in panels(dashboard) for t in p.targets]
    for var in dashboard.get("templating", {}).get("list", []):
        query = var.get("query")
        out.append(query.get("query", "") if isinstance(query, dict) else str(query or ""))
    return out


def metric_names(promql: str) -> set[str]:
    """The service's metric names that a PromQL text uses."""
    return set(_METRIC.findall(promql))


def exported_names(exposition: str) -> set[str]:
    """Every sample name of a ``/metrics`` text (``_total``, ``_bucket``, ``_count``,
    ``_sum`` included), for comparison with :func:`metric_names`."""
    from prometheus_client.parser import text_string_to_metric_families

    return {s.name for fam in text_string_to_metric_families(exposition) for s in fam.samples}


def concrete(expr: str, rate_interval: str) -> str:
    """A dashboard query as Grafana sends it with every map selected."""
    return (
        expr.replace("$__rate_interval", rate_interval)
        .replace("${map}", ".*")
        .replace("$map", ".*")
    )


# -- a local Prometheus ------------------------------------------------------------------


class LocalPrometheus:
    """Debian's ``prometheus`` on 127.0.0.1 scraping one target (a context manager)."""

    def __init__(
        self,
        target: str,
        work_dir: Path,
        *,
        scrape_interval_s: float = 1.0,
        bearer_file: Path | None = None,
        rule_files: tuple[Path, ...] = (),
    ) -> None:
        self.target = target
        self.work_dir = Path(work_dir)
        self.scrape_interval_s = scrape_interval_s
        self.bearer_file = bearer_file
        self.rule_files = rule_files
        self.port = free_port()
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout_s: float = 60.0) -> None:
        binary = shutil.which("prometheus")
        if binary is None:
            raise RuntimeError("Debian's prometheus is not installed (README, Install)")
        self.work_dir.mkdir(parents=True, exist_ok=True)
        job: dict[str, Any] = {
            "job_name": "sgvloc",
            "scrape_interval": f"{self.scrape_interval_s:g}s",
            "static_configs": [{"targets": [self.target]}],
        }
        if self.bearer_file is not None:
            job["authorization"] = {"type": "Bearer", "credentials_file": str(self.bearer_file)}
        config = {
            "global": {"evaluation_interval": f"{self.scrape_interval_s:g}s"},
            "rule_files": [str(Path(p).resolve()) for p in self.rule_files],
            "scrape_configs": [job],
        }
        cfg = self.work_dir / "prometheus.yml"
        cfg.write_text(json.dumps(config))  # JSON is YAML
        cmd = [
            binary,
            f"--config.file={cfg}",
            f"--storage.tsdb.path={self.work_dir / 'tsdb'}",
            f"--web.listen-address=127.0.0.1:{self.port}",
        ]
        with (self.work_dir / "prometheus.log").open("ab") as out:
            self.proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"prometheus exited at start-up:\n{self.log_tail()}")
            try:
                if httpx.get(f"{self.url}/-/ready", timeout=2.0).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        self.stop()
        raise RuntimeError(f"prometheus was not ready within {timeout_s:.0f} s")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)

    def log_tail(self, chars: int = 3000) -> str:
        path = self.work_dir / "prometheus.log"
        return path.read_text(errors="replace")[-chars:] if path.exists() else "(no log)"

    def api(self, path: str, **params: Any) -> Any:
        r = httpx.get(f"{self.url}/api/v1/{path}", params=params, timeout=30.0)
        body = r.json()
        if r.status_code != 200 or body.get("status") != "success":
            raise RuntimeError(f"prometheus {path} {params}: {body.get('error', r.text)}")
        return body["data"]

    def query_range(
        self, expr: str, start: float, end: float, step: float
    ) -> list[tuple[dict[str, str], np.ndarray, np.ndarray]]:
        """``(labels, times, values)`` per series of ``expr`` (NaN where undefined)."""
        data = self.api("query_range", query=expr, start=start, end=end, step=step)
        out = []
        for s in data["result"]:
            pts = np.array([[float(t), float(v)] for t, v in s["values"]], dtype=float)
            out.append((s["metric"], pts[:, 0], pts[:, 1]))
        return out

    def rules(self) -> list[dict[str, Any]]:
        """The loaded rule groups' rules (their health says whether they evaluate)."""
        return [r for g in self.api("rules")["groups"] for r in g["rules"]]

    def __enter__(self) -> LocalPrometheus:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


# -- traffic -----------------------------------------------------------------------------


@dataclass
class Traffic:
    """What the clients sent and got back."""

    statuses: dict[int, int] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def count(self, status: int) -> None:
        with self.lock:
            self.statuses[status] = self.statuses.get(status, 0) + 1


def _scans(folder: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(points, T_world_sensor)`` of every scan of a KITTI-layout folder."""
    from sgvloc.core.sequence import KittiSequence

    seq = KittiSequence(folder)
    return [(seq[i].scan().xyzi(), np.asarray(seq[i].T_world_sensor)) for i in range(len(seq))]


def _client_loop(
    url: str,
    key: str,
    jobs: list[tuple[str, dict[str, Any]]],
    until: float,
    pause_s: float,
    traffic: Traffic,
    seed: int,
) -> None:
    rng = np.random.default_rng(seed)
    headers = {"Authorization": f"Bearer {key}", "Content-Type": wire.MSGPACK}
    with httpx.Client(base_url=url, timeout=60.0, headers=headers) as c:
        while time.monotonic() < until:
            path, body = jobs[int(rng.integers(len(jobs)))]
            try:
                status = c.post(path, content=wire.packb(body)).status_code
            except httpx.TransportError:
                status = 0
            traffic.count(status)
            if pause_s:
                time.sleep(float(rng.uniform(0.5, 1.5)) * pause_s)


def drive(
    url: str,
    keys: dict[str, str],
    scans: list[tuple[np.ndarray, np.ndarray]],
    map_keyframes: int,
    seconds: float,
) -> Traffic:
    """Localize traffic in three phases of ``seconds / 3``: one vehicle at an easy pace
    (global, with a prior, or tracked with a seed);
    three vehicles at once (more than max_inflight_localize: some 429s); then two
    vehicles, one also with priors far from the map (not localized), while a mapper adds
    the keyframes that map ``yard`` (every third scan) lacks, one at a time."""
    traffic = Traffic()
    queries = scans[map_keyframes:] or scans[-1:]
    plain = [("/v1/maps/campus/localize", {"points": p}) for p, _ in queries]
    near = [
        (
            "/v1/maps/campus/localize",
            {"points": p, "prior": {"position": T[:2, 3].tolist(), "radius_m": 10.0}},
        )
        for p, T in queries
    ]
    far = [
        (
            "/v1/maps/campus/localize",
            {"points": p, "prior": {"position": [5000.0, 5000.0], "radius_m": 5.0}},
        )
        for p, _ in queries
    ]
    tracked = [
        (
            "/v1/maps/campus/localize",
            {"points": p, "seed": {"T_map_sensor": T, "sigma_m": 1.0, "sigma_yaw_deg": 5.0}},
        )
        for p, T in queries
    ]
    yard = [("/v1/maps/yard/localize", {"points": p}) for p, _ in queries]
    phase = seconds / 3
    start = time.monotonic()
    plans = [  # (key, jobs, from, to, pause)
        ("truck-17", plain + near + tracked, 0.0, seconds, 0.3),
        ("truck-18", plain + yard, phase, 2 * phase, 0.0),
        ("truck-19", near + yard, phase, 2 * phase, 0.0),
        ("truck-18", far + plain + yard, 2 * phase, seconds, 0.5),
    ]
    missing = [i for i in range(min(map_keyframes, len(scans))) if i % 3]

    def mapper() -> None:
        gap = phase / (len(missing) + 1)
        headers = {"Authorization": f"Bearer {keys['mapper']}", "Content-Type": wire.MSGPACK}
        with httpx.Client(base_url=url, timeout=60.0, headers=headers) as c:
            for n, i in enumerate(missing):
                time.sleep(max(0.0, start + 2 * phase + (n + 1) * gap - time.monotonic()))
                points, T = scans[i]
                body = {"keyframes": [{"T_map_sensor": T, "points": points}]}
                traffic.count(
                    c.post("/v1/maps/yard/keyframes", content=wire.packb(body)).status_code
                )

    threads = [threading.Thread(target=mapper, name="mapper")]
    for i, (name, jobs, t_from, t_to, pause) in enumerate(plans):

        def run(name=name, jobs=jobs, t_from=t_from, t_to=t_to, pause=pause, i=i) -> None:
            time.sleep(max(0.0, start + t_from - time.monotonic()))
            _client_loop(url, keys[name], jobs, start + t_to, pause, traffic, seed=i)

        threads.append(threading.Thread(target=run, name=f"client-{i}"))
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return traffic


# -- drawing -----------------------------------------------------------------------------

_UNITS = {"s": "seconds", "reqps": "per second", "percentunit": "share", "short": ""}


def _legend(fmt: str, labels: dict[str, str]) -> str:
    text = _LEGEND.sub(lambda m: labels.get(m.group(1), ""), fmt).strip()
    return text or json.dumps(labels, sort_keys=True)


def render(
    prom: LocalPrometheus,
    dashboard: dict[str, Any],
    start: float,
    end: float,
    out: Path,
    *,
    step: float = 2.0,
    rate_interval: str = "15s",
    title: str = "",
) -> dict[str, int]:
    """Evaluate every panel's queries over ``[start, end]`` and draw them in the
    dashboard's layout; returns the number of series drawn per panel title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    found = panels(dashboard)
    rows = sorted({p.grid[1] for p in found})
    fig = plt.figure(figsize=(16, 3.4 * len(rows)))
    grid = fig.add_gridspec(len(rows), 24, hspace=0.75, wspace=2.5, top=0.95, bottom=0.04)
    drawn: dict[str, int] = {}
    for panel in found:
        x, y, w, _ = panel.grid
        r = rows.index(y)
        ax = fig.add_subplot(grid[r, x : min(24, x + w)])
        n = 0
        for target in panel.targets:
            for labels, t, v in prom.query_range(
                concrete(target.expr, rate_interval), start, end, step
            ):
                ax.plot(t - start, v, lw=1.2, label=_legend(target.legend, labels))
                n += 1
        drawn[panel.title] = n
        ax.set_title(panel.title, fontsize=10, loc="left")
        ax.set_ylabel(_UNITS.get(panel.unit, panel.unit), fontsize=8)
        ax.set_xlim(0, end - start)
        ax.set_ylim(bottom=0)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        ax.set_xlabel("seconds into the run", fontsize=7)
        if n:
            ax.legend(fontsize=6, loc="upper left", ncol=2 if n > 4 else 1, framealpha=0.6)
        else:
            ax.text(0.5, 0.5, "no data", ha="center", va="center", transform=ax.transAxes)
    if title:
        fig.suptitle(title, fontsize=11, x=0.12, y=0.985, ha="left")
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80, bbox_inches="tight")
    plt.close(fig)
    return drawn


# -- the whole run -----------------------------------------------------------------------


@dataclass
class DashboardRun:
    out: Path
    drawn: dict[str, int]
    traffic: dict[int, int]
    rules: list[dict[str, Any]]
    exposition: str


def _keys_file(path: Path) -> dict[str, str]:
    keys = {n: secrets.token_urlsafe(24) for n in ("truck-17", "truck-18", "truck-19")}
    keys |= {"mapper": secrets.token_urlsafe(24), "prometheus": secrets.token_urlsafe(24)}
    roles = {"mapper": "mapper", "prometheus": "viewer"}
    lines = []
    for name, key in keys.items():
        lines += ["[[keys]]", f'name = "{name}"', f'key = "{key}"']
        lines.append(f'role = "{roles.get(name, "vehicle")}"')
    path.write_text("\n".join(lines) + "\n")
    return keys


@contextmanager
def _work_dir(work_dir: Path | None) -> Iterator[Path]:
    root = Path(tempfile.mkdtemp(prefix="sgvloc-dashboard-", dir=work_dir))
    try:
        yield root
    finally:
        shutil.rmtree(root, ignore_errors=True)


def record_dashboard(
    out: Path,
    *,
    data: Path,
    dashboard: Path = DASHBOARD,
    alerts: Path = ALERTS,
    seconds: float = 120.0,
    map_keyframes: int = 12,
    work_dir: Path | None = None,
) -> DashboardRun:
    """Run the service and Prometheus, send traffic for ``seconds``, draw the panels."""
    from .build_map import build_map

    board = load_dashboard(dashboard)
    with ExitStack() as stack:
        root = stack.enter_context(_work_dir(work_dir))
        keys = _keys_file(root / "keys.toml")
        (root / "metrics.key").write_text(keys["prometheus"])
        srv = ServiceProcess(
            root / "data",
            root / "server.log",
            workers=2,
            dev=False,
            env={
                "SGVLOC_KEYS_FILE": str(root / "keys.toml"),
                "SGVLOC_MAX_INFLIGHT_LOCALIZE": "2",
                "SGVLOC_LOG_FORMAT": "json",
            },
        )
        stack.enter_context(srv)
        scans = _scans(data)
        from sgvloc_client import Client

        with Client(srv.url, api_key=keys["mapper"]) as c:
            build_map(data, c, "campus", encoder="handcrafted", limit=map_keyframes, progress=False)
            # a second, smaller map: every third of campus's keyframes (the limit counts
            # the scans taken, after every)
            build_map(
                data,
                c,
                "yard",
                encoder="handcrafted",
                limit=-(-map_keyframes // 3),
                every=3,
                progress=False,
            )
        prom = LocalPrometheus(
            f"127.0.0.1:{srv.port}",
            root / "prometheus",
            bearer_file=root / "metrics.key",
            rule_files=(alerts,),
        )
        stack.enter_context(prom)
        time.sleep(3 * prom.scrape_interval_s)
        start = time.time()
        traffic = drive(srv.url, keys, scans, map_keyframes, seconds)
        time.sleep(3 * prom.scrape_interval_s)
        end = time.time()
        drawn = render(
            prom,
            board,
            start,
            end,
            out,
            title=f"sgvloc dashboard panels: {seconds:.0f} s of traffic, evaluated by Prometheus",
        )
        rules = prom.rules()
        exposition = httpx.get(
            f"{srv.url}/metrics", headers={"Authorization": f"Bearer {keys['prometheus']}"}
        ).text
    return DashboardRun(out, drawn, dict(sorted(traffic.statuses.items())), rules, exposition)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("docs/dashboard.png"))
    parser.add_argument("--data", type=Path, default=Path("tests/fixtures/balm_mini"))
    parser.add_argument("--seconds", type=float, default=120.0)
    args = parser.parse_args(argv)
    exit_on_sigterm()  # the service, Prometheus and folder it starts are removed
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)
    run = record_dashboard(args.out, data=args.data, seconds=args.seconds)
    log.info("wrote %s; answers by status %s; series per panel %s", run.out, run.traffic, run.drawn)


if __name__ == "__main__":
    main()
