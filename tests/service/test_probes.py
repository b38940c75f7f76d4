"""Probes and Prometheus metrics."""

from __future__ import annotations

import re

import httpx
import numpy as np
from svc_helpers import BalmMap, post_msgpack


def test_healthz_readyz(client: httpx.Client) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    r = client.get("/readyz")
    assert r.status_code == 200
    body = r.json()
    assert body["status"] == "ready" and body["maps"] == len(client.get("/v1/maps").json()["maps"])


def _value(text: str, series: str) -> float:
    """The value of one exposed sample, ``series`` being its name with labels."""
    for line in text.splitlines():
        if line.startswith(series + " "):
            return float(line.rsplit(" ", 1)[1])
    raise AssertionError(f"{series} not exposed")


def test_metrics_after_traffic(client: httpx.Client, balm_map: BalmMap) -> None:
    before = client.get("/metrics").text
    points = balm_map.seq[2].scan().xyzi()
    r = post_msgpack(client, "/v1/maps/balm/localize", {"points": points})
    assert r.status_code == 200
    localized = r.json()["localized"]
    reason = r.json()["verdict"]
    client.get("/v1/maps/does-not-exist")

    r = client.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    text = r.text
    for name in (
        "sgvloc_http_requests_total",
        "sgvloc_http_request_duration_seconds_bucket",
        "sgvloc_stage_duration_seconds_bucket",
        "sgvloc_localize_total",
        "sgvloc_rerank_top1_changed_total",
        "sgvloc_map_keyframes",
    ):
        assert re.search(rf"^{name}[{{ ]", text, re.M), f"{name} missing"
    route = '{method="POST",route="/v1/maps/{map}/localize",status="200"}'
    assert _value(text, f"sgvloc_http_requests_total{route}") >= 1
    route404 = '{method="GET",route="/v1/maps/{map}",status="404"}'
    assert _value(text, f"sgvloc_http_requests_total{route404}") >= 1
    verdict = "localized" if localized else "not_localized"
    key = f'sgvloc_localize_total{{map="balm",verdict="{verdict}"}}'
    assert _value(text, key) == _value(before, key) + 1
    key = f'sgvloc_localize_reason_total{{map="balm",reason="{reason}"}}'
    assert _value(text, key) == _value(before, key) + 1
    key = "sgvloc_localize_confidence_count"
    assert _value(text, key) == _value(before, key) + 1
    for stage in ("encode", "retrieve", "rerank", "pose", "verify"):
        key = f'sgvloc_stage_duration_seconds_count{{map="balm",stage="{stage}"}}'
        assert _value(text, key) == _value(before, key) + 1
    assert _value(text, 'sgvloc_map_keyframes{map="balm"}') == len(balm_map.ids)
    assert np.isfinite(_value(text, "sgvloc_rerank_top1_changed_total"))
    # no start-time series beside each counter and histogram
    assert not re.search(r"^\w+_created[{ ]", text, re.M)
    assert re.search(r"^process_start_time_seconds ", text, re.M)


def test_openapi_documents_bodies(client: httpx.Client) -> None:
    doc = client.get("/openapi.json").json()
    op = doc["paths"]["/v1/maps/{map}/keyframes"]["post"]
    assert op["operationId"] == "insert_keyframes"
    content = op["requestBody"]["content"]
    assert set(content) == {"application/json", "application/msgpack"}
    assert "KeyframeBatch" in doc["components"]["schemas"]
    ids = [o["operationId"] for p in doc["paths"].values() for o in p.values()]
    assert len(ids) == len(set(ids))
