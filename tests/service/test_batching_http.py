"""Dynamic batching in a real service: concurrent localizations of two maps share
network forwards and SGV calls (the metrics count the batches) and get the answers they
get alone; ``GET /v1/config`` reports the setting."""

from __future__ import annotations

import threading
from pathlib import Path

import httpx
import pytest
from conftest import Server
from svc_helpers import post_msgpack

from sgvloc.core.sequence import KittiSequence


@pytest.fixture(scope="module")
def batched(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("batched")
    srv = Server(
        data_dir=root / "data",
        log_path=root / "server.log",
        env={"SGVLOC_BATCH_WAIT_MS": "100", "SGVLOC_BATCH_MAX": "8"},
        workers=4,
    )
    srv.start()
    try:
        yield srv
    finally:
        srv.stop()


def _answer(r: httpx.Response) -> tuple:
    assert r.status_code == 200, r.text
    a = r.json()
    return (
        a["localized"],
        a["keyframe_id"],
        a["confidence"],
        a["T_map_sensor"],
        [(c["keyframe_id"], c["score"]) for c in a["reranked"]],
    )


def _metric(text: str, name: str) -> float:
    return sum(float(ln.split()[-1]) for ln in text.splitlines() if ln.startswith(name))


def _delta(before: str, after: str, stage: str) -> tuple[float, float]:
    """(batches, localizations) of a stage between two /metrics texts."""
    out = []
    for what in ("count", "sum"):
        name = f'sgvloc_batch_size_{what}{{stage="{stage}"}}'
        out.append(_metric(after, name) - _metric(before, name))
    return out[0], out[1]


def test_concurrent_localizations_of_two_maps_share_batches(
    batched: Server, balm_mini_dir: Path, balm_mini_roles: list
) -> None:
    seq = KittiSequence(balm_mini_dir)
    db = [i for i, (_, role) in enumerate(balm_mini_roles) if role == "database"]
    queries = [i for i, (_, role) in enumerate(balm_mini_roles) if role == "query"][:4]
    with httpx.Client(base_url=batched.url, timeout=120.0) as c:
        cfg = c.get("/v1/config").json()["batching"]
        assert cfg == {"enabled": True, "wait_ms": 100.0, "max_size": 8}
        for name in ("a", "b"):
            assert c.post("/v1/maps", json={"name": name}).status_code == 201
            kfs = [
                {"T_map_sensor": seq[i].T_world_sensor, "points": seq[i].scan().xyzi()} for i in db
            ]
            assert (
                post_msgpack(c, f"/v1/maps/{name}/keyframes", {"keyframes": kfs}).status_code == 201
            )
        bodies = {i: {"points": seq[i].scan().xyzi().tolist(), "top_k": 6} for i in queries}
        jobs = [(m, i) for i in queries for m in ("a", "b")]
        # one at a time: nobody to wait for, every batch holds one
        start_text = c.get("/metrics").text
        alone = {(m, i): _answer(c.post(f"/v1/maps/{m}/localize", json=bodies[i])) for m, i in jobs}
        before = c.get("/metrics").text
        for stage in ("forward", "sgv"):
            count, items = _delta(start_text, before, stage)
            assert count == items == len(jobs), (stage, count, items)

    together: dict = {}
    start = threading.Barrier(len(jobs))

    def send(m: str, i: int) -> None:
        with httpx.Client(base_url=batched.url, timeout=120.0) as c:
            start.wait()
            together[(m, i)] = _answer(c.post(f"/v1/maps/{m}/localize", json=bodies[i]))

    threads = [threading.Thread(target=send, args=job) for job in jobs]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert together == alone
    after = httpx.get(f"{batched.url}/metrics").text
    for stage in ("forward", "sgv"):
        count, items = _delta(before, after, stage)
        assert items == len(jobs) and count < items, (stage, count, items)
