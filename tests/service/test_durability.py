"""Durability under faults, done for real on a ``sgvloc serve`` process:

- SIGKILL in the middle of a stream of bulk inserts: after a restart every acknowledged
  keyframe is there, every request's batch is there whole or not at all, and the FAISS
  index holds exactly the store's ids;
- a corrupt, truncated or deleted FAISS snapshot is rebuilt from the store at start-up,
  and the log says so;
- concurrent inserts and localizes on one map: no errors, and every localize answer shows
  exactly the keyframes of one committed version (no torn reads).
"""

from __future__ import annotations

import sqlite3
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from conftest import Server
from svc_helpers import PRECOMPUTED, post_msgpack, random_features

from sgvloc.core.retrieval import FaissIndex

BATCH = 5
EYE = np.eye(4)


@pytest.fixture
def server_at(tmp_path: Path) -> Iterator[Server]:
    """A server of the test's own on a fresh data directory (not started yet)."""
    srv = Server(
        data_dir=tmp_path / "data",
        log_path=tmp_path / "server.log",
        env={
            "SGVLOC_SNAPSHOT_EVERY": "7",
            "SGVLOC_SNAPSHOT_DELAY_S": "0.5",
            "SGVLOC_MAX_TOP_K": "100",
        },
    )
    try:
        yield srv
    finally:
        srv.stop()


def _batch(n: int, rng: np.random.Generator) -> dict:
    return {
        "keyframes": [
            {"key": f"b{n}-{j}", "T_map_sensor": EYE, "features": random_features(rng)}
            for j in range(BATCH)
        ]
    }


def _stored(srv: Server, name: str) -> dict[str, int]:
    """``{key: id}`` read from the map's SQLite store itself (read-only)."""
    db = srv.data_dir / "maps" / name / "map.sqlite"
    with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as conn:
        return dict(conn.execute("SELECT key, id FROM keyframes"))


def _snapshot_ids(srv: Server, name: str) -> list[int]:
    return FaissIndex.load(srv.data_dir / "maps" / name / "index.faiss").ids().tolist()


def _create(c: httpx.Client, name: str) -> None:
    r = c.post("/v1/maps", json={"name": name, "encoder": PRECOMPUTED})
    assert r.status_code == 201, r.text


def test_sigkill_during_bulk_inserts(server_at: Server) -> None:
    srv = server_at
    srv.start()
    with httpx.Client(base_url=srv.url, timeout=60) as c:
        _create(c, "crash")
    acked: list[int] = []  # batches whose insert was answered 201
    sent: list[int] = []
    stop = threading.Event()

    def stream() -> None:
        rng = np.random.default_rng(0)
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            for n in range(10_000):
                if stop.is_set():
                    return
                sent.append(n)
                try:
                    r = post_msgpack(c, "/v1/maps/crash/keyframes", _batch(n, rng))
                except httpx.TransportError:
                    return  # the server is gone
                assert r.status_code == 201, r.text
                acked.append(n)

    thread = threading.Thread(target=stream)
    thread.start()
    deadline = time.monotonic() + 120
    while len(acked) < 12 and thread.is_alive() and time.monotonic() < deadline:
        time.sleep(0.02)
    srv.kill()  # SIGKILL while the stream goes on: no shutdown code runs
    stop.set()
    thread.join(60)
    assert len(acked) >= 12, srv.log()[-3000:]

    srv.start()
    stored = _stored(srv, "crash")
    for n in sent:  # all or nothing per request
        present = [f"b{n}-{j}" in stored for j in range(BATCH)]
        assert all(present) or not any(present), (n, present)
    for n in acked:  # every acknowledged keyframe survived
        assert all(f"b{n}-{j}" in stored for j in range(BATCH)), n
    assert len(stored) % BATCH == 0
    with httpx.Client(base_url=srv.url, timeout=60) as c:
        info = c.get("/v1/maps/crash").json()
        assert info["keyframes"] == len(stored)
        # the index serves exactly the stored ids: a top_k over everything finds them all
        feats = random_features(np.random.default_rng(1))
        r = post_msgpack(
            c,
            "/v1/maps/crash/localize",
            {"features": feats, "top_k": 100, "rerank": "none", "refine": "none"},
        )
        assert r.status_code == 200, r.text
        got = {cand["keyframe_id"] for cand in r.json()["retrieved"]}
        assert got <= set(stored.values()) and len(got) == min(100, len(stored))
    log = srv.log()
    assert "map 'crash': using index snapshot" in log or "rebuilding" in log
    srv.stop()  # graceful: the snapshot is saved; it holds the store's ids exactly
    assert _snapshot_ids(srv, "crash") == sorted(stored.values())


def _damage(index: Path, how: str) -> None:
    if how == "corrupt":  # garbage in the header, and the tail cut off
        data = bytearray(index.read_bytes())
        data[8 : 8 + 64] = np.random.default_rng(3).bytes(64)
        index.write_bytes(bytes(data[: len(data) // 2]))
    elif how == "delete":
        index.unlink()
        index.with_suffix(".faiss.json").unlink()


def test_snapshot_is_rebuilt_from_the_store(server_at: Server) -> None:
    srv = server_at
    # snapshots only when a map is created, at start-up rebuilds and at shutdown
    srv.env.update(SGVLOC_SNAPSHOT_EVERY="100000", SGVLOC_SNAPSHOT_DELAY_S="600")
    srv.start()
    rng = np.random.default_rng(2)
    with httpx.Client(base_url=srv.url, timeout=60) as c:
        _create(c, "snap")
        for n in range(3):
            assert post_msgpack(c, "/v1/maps/snap/keyframes", _batch(n, rng)).status_code == 201
    srv.stop()  # graceful: a good snapshot of 15 keyframes
    index = srv.data_dir / "maps" / "snap" / "index.faiss"
    expected = {
        "corrupt": "index snapshot unreadable",
        "delete": "no index snapshot, rebuilding from the store",
        "stale": "index snapshot disagrees with the store",
    }
    for how, message in expected.items():
        if how == "stale":  # the store moves on, the process dies before any snapshot
            srv.start()
            with httpx.Client(base_url=srv.url, timeout=60) as c:
                r = post_msgpack(c, "/v1/maps/snap/keyframes", _batch(9, rng))
                assert r.status_code == 201
            srv.kill()
        _damage(index, how)
        before = len(srv.log())
        srv.start()
        log = srv.log()[before:]
        assert f"map 'snap': {message}" in log, log
        assert "using index snapshot" not in log, how
        stored = _stored(srv, "snap")
        # rebuilt at start-up and saved again: the file holds the store's ids
        assert index.is_file() and _snapshot_ids(srv, "snap") == sorted(stored.values()), how
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            assert c.get("/v1/maps/snap").json()["keyframes"] == len(stored)
            feats = random_features(np.random.default_rng(1))
            body = {"features": feats, "top_k": 100, "rerank": "none", "refine": "none"}
            r = post_msgpack(c, "/v1/maps/snap/localize", body)
            assert {x["keyframe_id"] for x in r.json()["retrieved"]} == set(stored.values())
        srv.kill()
    assert len(stored) == 20


def test_concurrent_inserts_and_localizes(server_at: Server) -> None:
    """Every localize answer shows exactly the keyframes of the version it reports."""
    srv = server_at
    srv.start()
    with httpx.Client(base_url=srv.url, timeout=60) as c:
        _create(c, "busy")
    inserts: list[tuple[int, list[int]]] = []  # (map_version, ids) per insert answer
    answers: list[tuple[int, set[int]]] = []
    errors: list[str] = []
    done = threading.Event()

    def insert() -> None:
        rng = np.random.default_rng(4)
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            for n in range(16):  # 80 keyframes: fewer than top_k, so a search sees all
                r = post_msgpack(c, "/v1/maps/busy/keyframes", _batch(n, rng))
                if r.status_code != 201:
                    errors.append(f"insert {r.status_code}: {r.text}")
                    break
                out = r.json()
                inserts.append((out["map_version"], out["ids"]))
        done.set()

    def localize(seed: int) -> None:
        rng = np.random.default_rng(seed)
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            while not done.is_set():
                body = {
                    "features": random_features(rng),
                    "top_k": 100,
                    "rerank": "none",
                    "refine": "none",
                }
                r = post_msgpack(c, "/v1/maps/busy/localize", body)
                if r.status_code != 200:
                    errors.append(f"localize {r.status_code}: {r.text}")
                    return
                out = r.json()
                answers.append((out["map_version"], {x["keyframe_id"] for x in out["retrieved"]}))

    threads = [threading.Thread(target=insert)]
    threads += [threading.Thread(target=localize, args=(s,)) for s in (5, 6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(180)
    assert not errors, errors[:3]
    assert len(inserts) == 16 and len(answers) >= 2
    versions = [v for v, _ in inserts]
    assert versions == sorted(versions) and len(set(versions)) == 16
    for version, seen in answers:
        # the keyframes committed at that version, exactly: none missing, none ahead
        committed = {i for v, ids in inserts if v <= version for i in ids}
        assert seen == committed, (version, sorted(seen ^ committed))
