"""Observability of a real service: per-map and per-key series, gauges, a deleted map's
series gone, request ids, JSON log lines, and the Grafana dashboard and alert rules
checked against the series the service really exports (then drawn from a real run)."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
import yaml
from conftest import Server
from svc_helpers import PRECOMPUTED, BalmMap, map_state, post_msgpack, random_features

from sgvloc.about import __version__
from sgvloc.core.confidence import VERDICT_CODES
from sgvloc.tools.dashboard import (
    dashboard_queries,
    exported_names,
    load_dashboard,
    metric_names,
    record_dashboard,
)

ROOT = Path(__file__).resolve().parents[2]
STAGES = ("encode", "retrieve", "rerank", "pose", "verify")
EYE = np.eye(4)


def samples(text: str) -> dict[str, float]:
    """``name{labels}`` -> value of every sample of a ``/metrics`` text."""
    out = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            series, value = line.rsplit(" ", 1)
            out[series] = float(value)
    return out


def test_localize_series_per_map_and_key(client: httpx.Client, balm_map: BalmMap) -> None:
    before = samples(client.get("/metrics").text)
    points = balm_map.seq[balm_map.queries[0]].scan().xyzi()
    r = post_msgpack(client, "/v1/maps/balm/localize", {"points": points})
    assert r.status_code == 200, r.text
    verdict = "localized" if r.json()["localized"] else "not_localized"
    after = samples(client.get("/metrics").text)

    def grew(series: str) -> float:
        return after[series] - before.get(series, 0.0)

    for stage in STAGES:
        assert grew(f'sgvloc_stage_duration_seconds_count{{map="balm",stage="{stage}"}}') == 1
    assert grew(f'sgvloc_localize_total{{map="balm",verdict="{verdict}"}}') == 1
    reason = r.json()["verdict"]
    assert grew(f'sgvloc_localize_reason_total{{map="balm",reason="{reason}"}}') == 1
    # development mode: every caller is the principal "development"
    assert grew(f'sgvloc_localize_by_key_total{{key_name="development",verdict="{verdict}"}}') == 1
    # both verdicts and every verdict code exist per loaded map from the start
    for v in ("localized", "not_localized"):
        assert f'sgvloc_localize_total{{map="balm",verdict="{v}"}}' in after
    for code in VERDICT_CODES:
        assert f'sgvloc_localize_reason_total{{map="balm",reason="{code}"}}' in after
    # the localize waited for a worker thread (and the /metrics scrape did not)
    assert grew("sgvloc_queue_wait_seconds_count") >= 1
    # nothing in flight or queued between requests
    assert after["sgvloc_localize_inflight"] == 0
    assert after["sgvloc_queue_waiting"] == 0
    keyframes, version = map_state(client, "balm")
    assert after['sgvloc_map_keyframes{map="balm"}'] == keyframes
    assert after['sgvloc_map_version{map="balm"}'] == version


def test_a_deleted_map_loses_its_series(client: httpx.Client) -> None:
    name = "obs-gone"
    assert client.post("/v1/maps", json={"name": name, "encoder": PRECOMPUTED}).status_code == 201
    feats = random_features(np.random.default_rng(7))
    kf = {"keyframes": [{"T_map_sensor": EYE, "features": feats}]}
    assert post_msgpack(client, f"/v1/maps/{name}/keyframes", kf).status_code == 201
    body = {"features": feats, "rerank": "none"}
    assert post_msgpack(client, f"/v1/maps/{name}/localize", body).status_code == 200
    text = client.get("/metrics").text
    per_map = [ln for ln in text.splitlines() if f'map="{name}"' in ln]
    assert any(ln.startswith("sgvloc_stage_duration_seconds_count") for ln in per_map)
    assert samples(text)[f'sgvloc_map_version{{map="{name}"}}'] == 1
    assert samples(text)[f'sgvloc_map_keyframes{{map="{name}"}}'] == 1

    assert client.delete(f"/v1/maps/{name}").status_code == 204
    text = client.get("/metrics").text
    assert f'map="{name}"' not in text


def test_made_up_methods_do_not_grow_the_metrics(client: httpx.Client) -> None:
    """Any token is a method to HTTP: unknown ones share the label "other", so no request,
    authenticated or not, adds series at will."""
    for i in range(5):
        assert client.request(f"XMETH{i}", "/healthz").status_code in (404, 405)
    text = client.get("/metrics").text
    assert "XMETH" not in text and 'method="other"' in text


def test_request_ids(client: httpx.Client) -> None:
    r = client.get("/healthz", headers={"X-Request-ID": "edge-7f3a:42"})
    assert r.headers["X-Request-ID"] == "edge-7f3a:42"
    r = client.get("/v1/maps/no-such-map", headers={"X-Request-ID": "trace.1"})
    assert r.status_code == 404 and r.headers["X-Request-ID"] == "trace.1"
    # missing, too long, or with characters that do not belong in a log line: a new one
    generated = set()
    for header in ({}, {"X-Request-ID": "x" * 129}, {"X-Request-ID": "a b"}, {"X-Request-ID": ""}):
        rid = client.get("/healthz", headers=header).headers["X-Request-ID"]
        assert re.fullmatch(r"[0-9a-f]{32}", rid), rid
        generated.add(rid)
    assert len(generated) == 4
    assert len(r.headers.get_list("X-Request-ID")) == 1


def test_text_log_lines_name_their_request(server: Server, balm_map: BalmMap) -> None:
    """The shared server logs text; a record made while handling a request (here the
    map's creation, logged in a worker thread) ends with the request's id."""
    lines = [ln for ln in server.log().splitlines() if "created map 'balm'" in ln]
    assert lines and re.search(r" \[request [0-9a-f]{32}\]$", lines[0]), lines


def test_dashboard_and_alerts_use_only_exported_series(
    client: httpx.Client, balm_map: BalmMap
) -> None:
    """Every metric name in every panel, template variable and alert rule is a name the
    service exports (after a localize, so that every series exists)."""
    points = balm_map.seq[balm_map.queries[0]].scan().xyzi()
    assert post_msgpack(client, "/v1/maps/balm/localize", {"points": points}).status_code == 200
    exported = exported_names(client.get("/metrics").text)
    queries = dashboard_queries(load_dashboard(ROOT / "docker/grafana/dashboards/sgvloc.json"))
    groups = yaml.safe_load((ROOT / "docker/prometheus/alerts.yml").read_text())["groups"]
    queries += [rule["expr"] for g in groups for rule in g["rules"]]
    used = set()
    for q in queries:
        names = metric_names(q)
        assert names <= exported, f"not exported: {sorted(names - exported)} in {q}"
        used |= names
    # the dashboard covers the new series, and no name is a histogram's bare base name
    for name in (
        "sgvloc_localize_total",
        "sgvloc_stage_duration_seconds_bucket",
        "sgvloc_http_request_duration_seconds_bucket",
        "sgvloc_http_requests_total",
        "sgvloc_localize_inflight",
        "sgvloc_queue_waiting",
        "sgvloc_queue_wait_seconds_bucket",
        "sgvloc_map_keyframes",
        "sgvloc_map_version",
        "sgvloc_localize_by_key_total",
    ):
        assert name in used, f"{name} is on no panel or alert"


# -- JSON log lines, with API keys -------------------------------------------------------

KEYS = {
    "truck-17": ("vehicle", "obs-vehicle-key-0123456789abcdef"),
    "builder": ("mapper", "obs-mapper-key-0123456789abcdef"),
    "prometheus": ("viewer", "obs-viewer-key-0123456789abcdef"),
}


@pytest.fixture(scope="module")
def json_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    root = tmp_path_factory.mktemp("jsonlogs")
    lines = []
    for name, (role, key) in KEYS.items():
        lines += ["[[keys]]", f'name = "{name}"', f'role = "{role}"', f'key = "{key}"']
    (root / "keys.toml").write_text("\n".join(lines) + "\n")
    broken = root / "data" / "maps" / "broken"  # a map that cannot be loaded: 503s
    broken.mkdir(parents=True)
    (broken / "map.sqlite").write_bytes(b"not a database")
    srv = Server(
        data_dir=root / "data",
        log_path=root / "server.log",
        env={"SGVLOC_KEYS_FILE": str(root / "keys.toml"), "SGVLOC_LOG_FORMAT": "json"},
    )
    srv.start()
    try:
        yield srv
    finally:
        srv.stop()


def _as(name: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {KEYS[name][1]}"}


def test_json_log_lines_with_request_ids_and_access_lines(json_server: Server) -> None:
    feats = random_features(np.random.default_rng(11))
    with httpx.Client(base_url=json_server.url, timeout=60) as c:
        r = c.post(
            "/v1/maps",
            json={"name": "jl", "encoder": PRECOMPUTED},
            headers={**_as("builder"), "X-Request-ID": "create-jl-1"},
        )
        assert r.status_code == 201, r.text
        kf = {"keyframes": [{"T_map_sensor": EYE, "features": feats}]}
        r = post_msgpack(c, "/v1/maps/jl/keyframes", kf, headers=_as("builder"))
        assert r.status_code == 201, r.text
        body = {"features": feats, "rerank": "none"}
        r = post_msgpack(c, "/v1/maps/jl/localize", body, headers=_as("truck-17"))
        assert r.status_code == 200, r.text
        localize_id = r.headers["X-Request-ID"]
        verdict = "localized" if r.json()["localized"] else "not_localized"
        r = c.get("/v1/maps", headers={"X-Request-ID": "no-key-1"})
        assert r.status_code == 401
        r = c.get("/v1/maps/broken", headers={**_as("prometheus"), "X-Request-ID": "unavailable-1"})
        assert r.status_code == 503, r.text
        r = c.post(
            "/v1/maps", json={"name": "x"}, headers={**_as("truck-17"), "X-Request-ID": "f-1"}
        )
        assert r.status_code == 403, r.text
        assert c.get("/ui", headers={"X-Request-ID": "ui-1"}).status_code == 200
        assert c.get("/readyz", headers={"X-Request-ID": "ready-1"}).status_code == 503  # broken
        text = c.get("/metrics", headers=_as("prometheus")).text
    json_server.stop()  # every line written

    by_key = samples(text)
    assert by_key[f'sgvloc_localize_by_key_total{{key_name="truck-17",verdict="{verdict}"}}'] == 1
    assert by_key["sgvloc_maps_failed"] == 1  # the broken folder
    # what each error answer was, by route and code
    assert by_key['sgvloc_errors_total{code="map_unavailable",route="/v1/maps/{map}"}'] == 1
    assert by_key['sgvloc_errors_total{code="unauthorized",route="/v1/maps"}'] == 1
    assert by_key[f'sgvloc_build_info{{version="{__version__}"}}'] == 1
    assert by_key["process_resident_memory_bytes"] > 0
    assert by_key["sgvloc_store_up"] == 1  # SQLite: always
    assert not any("key_name" in s and "builder" in s for s in by_key)

    records = []
    for line in json_server.log().splitlines():
        if line.strip():
            records.append(json.loads(line))  # every line is one JSON object
    for rec in records:
        assert {"time", "level", "logger", "message", "request_id"} <= set(rec), rec
        assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}\+00:00", rec["time"])
    # a record logged in a worker thread while creating the map carries its request id
    (created,) = [r for r in records if r["message"].startswith("created map 'jl'")]
    assert created["request_id"] == "create-jl-1" and created["logger"] == "sgvloc.server.maps"
    # start-up records belong to no request
    assert any(r["request_id"] is None and r["logger"].startswith("uvicorn") for r in records)

    access = [r for r in records if r["logger"] == "sgvloc.access"]
    (loc,) = [r for r in access if r["request_id"] == localize_id]
    assert loc["level"] == "INFO"
    assert (loc["method"], loc["route"], loc["status"]) == ("POST", "/v1/maps/{map}/localize", 200)
    assert loc["key_name"] == "truck-17" and loc["duration_ms"] > 0
    (create,) = [r for r in access if r["request_id"] == "create-jl-1"]
    assert (create["route"], create["status"], create["key_name"]) == ("/v1/maps", 201, "builder")
    (refused,) = [r for r in access if r["request_id"] == "no-key-1"]
    assert refused["status"] == 401 and refused["key_name"] is None
    assert refused["code"] == "unauthorized" and refused["client"] == "127.0.0.1"
    assert loc["code"] is None and refused["level"] == "INFO"
    (failed,) = [r for r in access if r["request_id"] == "unavailable-1"]
    assert (failed["status"], failed["code"], failed["level"]) == (
        503,
        "map_unavailable",
        "WARNING",
    )
    # a known key refused for its role is named; open routes answer "anonymous"; the
    # readiness probe's 503 says why
    (forbidden,) = [r for r in access if r["request_id"] == "f-1"]
    assert (forbidden["status"], forbidden["code"], forbidden["key_name"]) == (
        403,
        "forbidden",
        "truck-17",
    )
    (ui,) = [r for r in access if r["request_id"] == "ui-1"]
    assert (ui["route"], ui["status"], ui["key_name"]) == ("/ui", 200, "anonymous")
    (ready,) = [r for r in access if r["request_id"] == "ready-1"]
    assert (ready["status"], ready["code"], ready["key_name"]) == (503, "degraded", "anonymous")
    # keys are never logged
    log_text = json_server.log()
    assert not any(key in log_text for _, key in KEYS.values())


# -- the dashboard drawn from a real run -------------------------------------------------


def test_dashboard_png_from_a_real_run(tmp_path: Path, balm_mini_dir: Path) -> None:
    """The tool behind docs/dashboard.png: a service, traffic, a local Prometheus with the
    alert rules, every panel's query evaluated and drawn (a short run here)."""
    run = record_dashboard(
        tmp_path / "dashboard.png",
        data=balm_mini_dir,
        dashboard=ROOT / "docker/grafana/dashboards/sgvloc.json",
        alerts=ROOT / "docker/prometheus/alerts.yml",
        seconds=15,
        work_dir=tmp_path,
    )
    assert run.out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert run.traffic.get(200, 0) > 0 and run.traffic.get(201, 0) > 0
    empty = [title for title, n in run.drawn.items() if n == 0]
    assert not empty, f"panels without data: {empty}"
    # Prometheus loaded every alert rule and evaluates it without error
    assert {r["name"] for r in run.rules} >= {
        "SgvlocHighErrorRate",
        "SgvlocLocalizeLatencyHigh",
        "SgvlocNotLocalizedRising",
    }
    assert all(r["health"] == "ok" for r in run.rules), run.rules
