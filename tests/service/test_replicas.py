"""Replicas over one PostgreSQL store: real ``sgvloc serve`` processes on loopback and a
real PostgreSQL server (see the ``postgres`` fixture).

What an operator scaling out relies on: a write on one replica is served by every other,
maps made or deleted anywhere appear or vanish everywhere, a killed replica loses
nothing and a new one catches up, the store going away makes writes fail fast (503) while
localizations go on from memory, and concurrent writers never lose or double keyframes.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from conftest import Server
from svc_helpers import decode, error_of, post_msgpack

from sgvloc.core.sequence import KittiSequence
from sgvloc.tools.service_process import start_side_by_side
from sgvloc_client import Client

POLL_S = "0.5"


@pytest.fixture(scope="module")
def replicas(postgres, tmp_path_factory: pytest.TempPathFactory) -> Iterator[list[Server]]:
    """Three replicas sharing one fresh database, for the whole module (each test uses
    maps of its own; the test that kills a replica runs last)."""
    root = tmp_path_factory.mktemp("replicas")
    url = postgres.new_database()
    servers = [_replica(root, name, url) for name in "abc"]
    try:
        start_side_by_side(servers)
        yield servers
    finally:
        for s in servers:
            s.stop()


def _replica(root: Path, name: str, url: str) -> Server:
    return Server(
        data_dir=root / name,
        log_path=root / f"{name}.log",
        env={"SGVLOC_STORE_URL": url, "SGVLOC_FOLLOW_POLL_S": POLL_S},
        workers=1,
    )


def _until(check, timeout: float = 10.0, what: str = "") -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if check():
            return
        time.sleep(0.05)
    raise AssertionError(f"not within {timeout} s: {what}")


def _scans(balm_mini_dir: Path, roles: list) -> tuple[KittiSequence, list[int], list[int]]:
    seq = KittiSequence(balm_mini_dir)
    db = [i for i, (_, role) in enumerate(roles) if role == "database"]
    queries = [i for i, (_, role) in enumerate(roles) if role == "query"]
    return seq, db, queries


def _keyframes(seq: KittiSequence, idx: list[int], prefix: str = "kf") -> list[dict]:
    return [
        {
            "key": f"{prefix}/{i}",
            "T_map_sensor": seq[i].T_world_sensor,
            "points": seq[i].scan().xyzi(),
            "metadata": {"timestamp": seq[i].time},
        }
        for i in idx
    ]


def _keyframes_on(c: httpx.Client, name: str) -> int | None:
    r = c.get(f"/v1/maps/{name}")
    return r.json()["keyframes"] if r.status_code == 200 else None


def _localize(c: httpx.Client, name: str, points: np.ndarray, **params) -> httpx.Response:
    return post_msgpack(
        c,
        f"/v1/maps/{name}/localize?" + "&".join(f"{k}={v}" for k, v in params.items()),
        {"points": points},
    )


def _answer(r: httpx.Response) -> tuple[bool, int | None, int, np.ndarray | None]:
    assert r.status_code == 200, r.text
    body = decode(r)
    T = body["T_map_sensor"]
    return (
        body["localized"],
        body["keyframe_id"],
        body["map_version"],
        (None if T is None else np.asarray(T)),
    )


def test_writes_on_one_replica_are_served_by_all(
    replicas: list[Server], balm_mini_dir: Path, balm_mini_roles: list
) -> None:
    a, b, c = (httpx.Client(base_url=s.url, timeout=120.0) for s in replicas)
    seq, db, queries = _scans(balm_mini_dir, balm_mini_roles)
    # a map created on B appears on A and C
    assert b.post("/v1/maps", json={"name": "shared"}).status_code == 201
    for other in (a, c):
        _until(lambda o=other: o.get("/v1/maps/shared").status_code == 200, what="map on peer")
    # keyframes inserted on A are localizable on B and C (read-your-writes by version)
    r = post_msgpack(a, "/v1/maps/shared/keyframes", {"keyframes": _keyframes(seq, db)})
    assert r.status_code == 201, r.text
    version, ids = r.json()["map_version"], r.json()["ids"]
    points = seq[queries[0]].scan().xyzi()
    answers = []
    for peer in (b, c, a):
        localized, kf, v, T = _answer(_localize(peer, "shared", points, min_map_version=version))
        assert v >= version and localized and kf in ids
        answers.append((kf, T))
    assert answers[0][0] == answers[1][0] == answers[2][0]
    np.testing.assert_allclose(answers[0][1], answers[2][1], atol=1e-6)
    # the same key sent to C is known there: same id, not created again
    r = post_msgpack(c, "/v1/maps/shared/keyframes", {"keyframes": _keyframes(seq, db[:1])})
    assert r.status_code == 201 and r.json()["ids"] == ids[:1] and r.json()["created"] == [False]
    # a keyframe deleted on C is gone on A; the map deleted on C is gone everywhere
    assert c.delete(f"/v1/maps/shared/keyframes/{ids[0]}").status_code == 200
    _until(lambda: a.get("/v1/maps/shared").json()["keyframes"] == len(ids) - 1, what="delete")
    assert c.delete("/v1/maps/shared").status_code == 204
    for peer in (a, b):
        _until(lambda p=peer: p.get("/v1/maps/shared").status_code == 404, what="map gone")
    # a version nobody has reached: 503 stale with Retry-After, after the bounded wait
    assert b.post("/v1/maps", json={"name": "other"}).status_code == 201
    t0 = time.monotonic()
    r = _localize(b, "other", points, min_map_version=99)
    assert r.status_code == 503 and error_of(r)["code"] == "stale"
    assert r.headers["Retry-After"] and time.monotonic() - t0 < 10


def _two_replicas_with_a_map(postgres, replicas, balm_mini_dir, roles, name: str):
    """Clients of replicas a and b, the fixture's scans, and map ``name`` with three
    keyframes that b holds too (for the outage tests: needs the throwaway cluster)."""
    if postgres.cluster is None:
        pytest.skip("needs the throwaway cluster (SGVLOC_TEST_PG_URL names an outside server)")
    a, b, _ = replicas
    seq, db, queries = _scans(balm_mini_dir, roles)
    ca, cb = (httpx.Client(base_url=s.url, timeout=120.0) for s in (a, b))
    assert ca.post("/v1/maps", json={"name": name}).status_code == 201
    r = post_msgpack(ca, f"/v1/maps/{name}/keyframes", {"keyframes": _keyframes(seq, db[:3])})
    assert r.status_code == 201
    _until(lambda: _keyframes_on(cb, name) == 3, what="map on b, caught up")
    return ca, cb, seq, db, queries


def test_store_outage_fails_writes_fast_and_localizations_go_on(
    postgres, replicas: list[Server], balm_mini_dir: Path, balm_mini_roles: list
) -> None:
    ca, cb, seq, db, queries = _two_replicas_with_a_map(
        postgres, replicas, balm_mini_dir, balm_mini_roles, "outage"
    )
    acked = [f"kf/{i}" for i in db[:3]]
    points = seq[queries[0]].scan().xyzi()

    postgres.cluster.stop()
    try:
        # a delete that waits on the store and fails: the map is served meanwhile (it
        # was hidden, 404 and left out of the list, for those seconds) and after
        answers: list[httpx.Response] = []
        deleting = threading.Thread(target=lambda: answers.append(ca.delete("/v1/maps/outage")))
        deleting.start()
        time.sleep(0.5)
        assert deleting.is_alive()  # still waiting on the store
        assert "outage" in {m["name"] for m in ca.get("/v1/maps").json()["maps"]}
        assert ca.get("/v1/maps/outage").status_code == 200
        deleting.join(30)
        assert answers[0].status_code == 503, answers[0].text
        assert ca.get("/v1/maps/outage").status_code == 200
        t0 = time.monotonic()
        r = post_msgpack(ca, "/v1/maps/outage/keyframes", {"keyframes": _keyframes(seq, db[3:5])})
        took = time.monotonic() - t0
        assert r.status_code == 503, r.text
        assert error_of(r)["code"] == "store_unavailable" and r.headers["Retry-After"]
        assert took < 15, took
        assert cb.post("/v1/maps", json={"name": "n"}).status_code == 503
        for c in (ca, cb):  # served from memory, naming the version used
            localized, _, version, _ = _answer(_localize(c, "outage", points))
            assert version == 1
        assert cb.get("/v1/maps/outage").status_code == 200
    finally:
        postgres.cluster.start()

    # the replicas reconnect by themselves: writes succeed again
    def write_ok() -> bool:
        r = post_msgpack(ca, "/v1/maps/outage/keyframes", {"keyframes": _keyframes(seq, db[3:5])})
        return r.status_code == 201

    _until(write_ok, timeout=30, what="writes after the store came back")
    _until(lambda: cb.get("/readyz").json()["store_reachable"] is True, what="b reaches it")
    assert "sgvloc_store_up 1.0" in cb.get("/metrics").text
    acked += [f"kf/{i}" for i in db[3:5]]
    _until(lambda: cb.get("/v1/maps/outage").json()["keyframes"] == len(acked), what="b caught up")
    keys = {k["key"] for k in cb.get("/v1/maps/outage/keyframes").json()["keyframes"]}
    assert keys == set(acked)


def test_a_frozen_store_fails_writes_and_localizations_go_on(
    postgres, replicas: list[Server], balm_mini_dir: Path, balm_mini_roles: list
) -> None:
    """PostgreSQL stopped (SIGSTOP) keeps its connections open and answers nothing: a
    write fails with 503 instead of waiting for it, the replica's worker is free again,
    and once the store is back a keyed retry stores each keyframe once."""
    ca, cb, seq, db, queries = _two_replicas_with_a_map(
        postgres, replicas, balm_mini_dir, balm_mini_roles, "frozen"
    )
    points = seq[queries[0]].scan().xyzi()
    later = _keyframes(seq, db[3:5])

    postgres.cluster.pause()
    try:
        r = post_msgpack(ca, "/v1/maps/frozen/keyframes", {"keyframes": later})
        assert r.status_code == 503, r.text
        assert error_of(r)["code"] == "store_unavailable" and r.headers["Retry-After"]
        for c in (ca, cb):  # served from memory by the replicas' only worker
            localized, _, version, _ = _answer(_localize(c, "frozen", points))
            assert version == 1

        def store_down(c: httpx.Client) -> bool:  # once a catch-up has failed
            ready = c.get("/readyz")
            return ready.status_code == 200 and ready.json()["store_reachable"] is False

        for c in (ca, cb):
            _until(lambda c=c: store_down(c), timeout=30, what="store_reachable false")
            assert "sgvloc_store_up 0.0" in c.get("/metrics").text
    finally:
        postgres.cluster.resume()

    def write_ok() -> bool:
        r = post_msgpack(ca, "/v1/maps/frozen/keyframes", {"keyframes": later})
        return r.status_code in (200, 201)

    _until(write_ok, timeout=30, what="writes after the store came back")
    _until(lambda: cb.get("/v1/maps/frozen").json()["keyframes"] == 5, what="b caught up")
    keys = [k["key"] for k in cb.get("/v1/maps/frozen/keyframes").json()["keyframes"]]
    assert sorted(keys) == sorted(f"kf/{i}" for i in db[:5])


def test_concurrent_writers_on_two_replicas(replicas: list[Server]) -> None:
    """Two replicas inserting into one map at once, with overlapping keys: every key
    stored exactly once, ids distinct, both replicas end with the same content."""
    servers = replicas[:2]
    clients = [httpx.Client(base_url=s.url, timeout=120.0) for s in servers]
    spec = {"kind": "precomputed", "name": "egonn", "global_dim": 16, "local_dim": 8}
    assert (
        clients[0].post("/v1/maps", json={"name": "concurrent", "encoder": spec}).status_code == 201
    )
    _until(lambda: clients[1].get("/v1/maps/concurrent").status_code == 200, what="map on b")
    rng = np.random.default_rng(0)

    def batch(keys: list[str]) -> dict:
        kfs = []
        for k in keys:
            kfs.append(
                {
                    "key": k,
                    "T_map_sensor": np.eye(4),
                    "features": {
                        "global_descriptor": rng.normal(size=16).astype(np.float32),
                        "keypoints": rng.uniform(-20, 20, (32, 3)).astype(np.float32),
                        "local_features": rng.normal(size=(32, 8)).astype(np.float32),
                    },
                }
            )
        return {"keyframes": kfs}

    bodies = [[batch([f"k{j}-{i}" for i in range(5)]) for j in range(12)] for _ in range(2)]
    results: list[list[int]] = [[], []]
    errors: list[str] = []

    def writer(n: int) -> None:
        for body in bodies[n]:  # both replicas send the same 12 batches of keys
            r = post_msgpack(clients[n], "/v1/maps/concurrent/keyframes", body)
            if r.status_code != 201:
                errors.append(r.text)
            else:
                results[n] += r.json()["ids"]

    threads = [threading.Thread(target=writer, args=(n,)) for n in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=300)
    assert not errors
    assert results[0] == results[1]  # the same key got the same id on both
    assert len(set(results[0])) == 60
    _until(
        lambda: (
            [c.get("/v1/maps/concurrent").json()["version"] for c in clients][0]
            == clients[1].get("/v1/maps/concurrent").json()["version"]
        ),
        what="same version",
    )
    infos = [c.get("/v1/maps/concurrent").json() for c in clients]
    assert infos[0]["keyframes"] == infos[1]["keyframes"] == 60
    listed = clients[1].get("/v1/maps/concurrent/keyframes?limit=1000").json()["keyframes"]
    assert sorted(k["id"] for k in listed) == sorted(set(results[0]))


def test_sdk_spreads_calls_over_replicas(replicas: list[Server]) -> None:
    """Client([a, b, c]) takes turns: each replica answers a share of the calls."""

    def served(s: Server) -> float:
        text = httpx.get(f"{s.url}/metrics").text
        return sum(
            float(line.rsplit(" ", 1)[1])
            for line in text.splitlines()
            if line.startswith("sgvloc_http_requests_total{")
            and 'route="/v1/maps/{map}"' in line
            and 'method="GET"' in line
        )

    with Client([s.url for s in replicas]) as sdk:
        sdk.create_map("spread", encoder={"kind": "handcrafted"})
        for s in replicas:
            _until(lambda s=s: httpx.get(f"{s.url}/v1/maps/spread").status_code == 200)
        before = [served(s) for s in replicas]
        for _ in range(9):
            assert sdk.get_map("spread").name == "spread"
    after = [served(s) for s in replicas]
    # 9 GETs through the SDK: three on each replica
    assert [x - y for x, y in zip(after, before, strict=True)] == [3, 3, 3], (before, after)


def test_build_map_over_replicas_reports_what_it_wrote(
    replicas: list[Server], balm_mini_dir: Path
) -> None:
    """build-map through several replicas (as through a load balancer) ends with the map's
    state: read from a replica that has caught up with the build's last insert, not from
    one still behind it (which gave "12 new keyframes; 0 keyframes, version 0")."""
    from sgvloc.tools.build_map import build_map

    for i in range(3):
        with Client([s.url for s in replicas]) as sdk:
            name = f"built-{i}"
            out = build_map(balm_mini_dir, sdk, name, batch_size=1, limit=4, progress=False)
            assert (out.created, out.keyframes) == (4, 4), out
            for s in replicas:
                _until(lambda u=f"{s.url}/v1/maps/{name}": httpx.get(u).json()["keyframes"] == 4)
            info = httpx.get(f"{replicas[0].url}/v1/maps/{name}").json()
            assert out.map_version == info["version"]


def test_a_map_is_served_by_every_replica_right_after_it_is_made(
    replicas: list[Server],
) -> None:
    """The SDK takes turns over replicas, so the call after a create lands on another
    one: it was a 404 there (get, stats, and a DELETE answered "does not exist" for a map
    that stayed) until that replica had followed the create, tens of ms later. And the
    same PATCH on two replicas: the second found nothing to change and answered its own
    settings from before the first."""
    body = {"encoder": {"kind": "handcrafted"}}
    a, b, c = (httpx.Client(base_url=s.url, timeout=30) for s in replicas)  # kept alive
    with a, b, c:
        for x in (a, b, c):  # connections open before the timed part
            assert x.get("/healthz").status_code == 200
        for i in range(4):
            name = f"fresh-{i}"
            patch = {"localizer": {"top_k": 30 + i}}
            assert a.post("/v1/maps", json={"name": name, **body}).status_code == 201
            first = b.patch(f"/v1/maps/{name}", json=patch)
            assert first.status_code == 200, first.text
            assert c.get(f"/v1/maps/{name}/stats").status_code == 200
            second = a.patch(f"/v1/maps/{name}", json=patch).json()
            assert second["localizer"]["top_k"] == first.json()["localizer"]["top_k"] == 30 + i
            assert second["settings_version"] == first.json()["settings_version"] == 1, second
            assert b.get(f"/v1/maps/{name}").status_code == 200
            name = f"gone-{i}"
            assert a.post("/v1/maps", json={"name": name, **body}).status_code == 201
            assert b.delete(f"/v1/maps/{name}").status_code == 204
            for x in (a, b, c):
                _until(lambda x=x, n=name: x.get(f"/v1/maps/{n}").status_code == 404)


def test_killed_replica_loses_nothing_and_a_new_one_catches_up(
    replicas: list[Server], balm_mini_dir: Path, balm_mini_roles: list, tmp_path: Path
) -> None:
    a, b, c = replicas
    seq, db, queries = _scans(balm_mini_dir, balm_mini_roles)
    ca, cb, cc = (httpx.Client(base_url=s.url, timeout=120.0) for s in replicas)
    assert ca.post("/v1/maps", json={"name": "killed"}).status_code == 201
    r = post_msgpack(ca, "/v1/maps/killed/keyframes", {"keyframes": _keyframes(seq, db[:4])})
    assert r.status_code == 201
    _until(lambda: cb.get("/v1/maps/killed").status_code == 200, what="map on b")
    points = seq[queries[0]].scan().xyzi()

    failures: list[str] = []
    served = [0, 0]
    stop = threading.Event()

    def load() -> None:  # localizations against B and C the whole time
        with httpx.Client(timeout=60.0) as h:
            while not stop.is_set():
                for s in (b, c):
                    r = post_msgpack(h, f"{s.url}/v1/maps/killed/localize", {"points": points})
                    if r.status_code != 200:
                        failures.append(f"{s.url}: {r.status_code} {r.text[:200]}")
                    served[0] += 1

    def sdk_load() -> None:  # the SDK over all three, A among them: it fails over
        with Client([a.url, b.url, c.url], timeout=60.0) as sdk:
            while not stop.is_set():
                try:
                    sdk.localize("killed", points)
                    served[1] += 1
                except Exception as exc:  # noqa: BLE001 - every failure is the finding
                    failures.append(f"sdk: {exc!r}")

    threads = [threading.Thread(target=load), threading.Thread(target=sdk_load)]
    for t in threads:
        t.start()
    try:
        # A acknowledges a batch, then dies without any shutdown code
        r = post_msgpack(ca, "/v1/maps/killed/keyframes", {"keyframes": _keyframes(seq, db[4:])})
        assert r.status_code == 201
        acked = r.json()["map_version"]
        a.kill()
        time.sleep(2.0)
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=120)
    assert not failures and served[0] > 0 and served[1] > 0
    # a new replica catches up to the same version and gives the same answers
    d = _replica(tmp_path, "d", b.env["SGVLOC_STORE_URL"])
    d.start()
    try:
        cd = httpx.Client(base_url=d.url, timeout=120.0)
        _until(lambda: cb.get("/v1/maps/killed").json()["version"] == acked, what="b caught up")
        info_b, info_d = cb.get("/v1/maps/killed").json(), cd.get("/v1/maps/killed").json()
        assert info_d["version"] == info_b["version"] == acked
        assert info_d["keyframes"] == info_b["keyframes"] == len(db)
        for q in queries:
            qp = seq[q].scan().xyzi()
            want = _answer(post_msgpack(cb, "/v1/maps/killed/localize", {"points": qp}))
            got = _answer(post_msgpack(cd, "/v1/maps/killed/localize", {"points": qp}))
            assert got[:3] == want[:3]
            if want[3] is not None:
                np.testing.assert_allclose(got[3], want[3], atol=1e-6)
    finally:
        d.stop()
