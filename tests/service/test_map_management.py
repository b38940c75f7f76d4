"""Map management over HTTP: keyframe listing with filters and cursors, bulk delete by
the same filters (one transaction, one version step), map statistics."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from svc_helpers import PRECOMPUTED, error_of, map_state, post_msgpack, random_features

N = 24  # keyframes: 2 sequences x 12, on a 6 x 4 grid, 2 m apart


def _fill(c: httpx.Client, name: str) -> dict[str, dict]:
    """A precomputed map with keys ``<seq>/<i>``, a metadata timestamp and sequence;
    returns ``{key: {"id", "position", "timestamp", "sequence"}}``."""
    r = c.post("/v1/maps", json={"name": name, "encoder": PRECOMPUTED})
    assert r.status_code == 201, r.text
    rng = np.random.default_rng(7)
    batch, expect = [], {}
    for i in range(N):
        seq = "north" if i < N // 2 else "south"
        T = np.eye(4)
        T[:3, 3] = [2.0 * (i % 6), 2.0 * (i // 6), 0.5 * i]
        key = f"{seq}/{i:03d}"
        meta = {"sequence": seq, "timestamp": 100.0 + i}
        batch.append(
            {"key": key, "T_map_sensor": T, "features": random_features(rng), "metadata": meta}
        )
        expect[key] = {"position": T[:3, 3].tolist(), "timestamp": 100.0 + i, "sequence": seq}
    for start in range(0, N, 12):
        r = post_msgpack(c, f"/v1/maps/{name}/keyframes", {"keyframes": batch[start : start + 12]})
        assert r.status_code == 201, r.text
        for key, kf_id in zip(list(expect)[start : start + 12], r.json()["ids"], strict=True):
            expect[key]["id"] = kf_id
    return expect


def _all(c: httpx.Client, name: str, **params) -> list[dict]:
    """Every page of a listing, following next_cursor."""
    out, cursor = [], None
    while True:
        q = dict(params, **({"cursor": cursor} if cursor else {}))
        r = c.get(f"/v1/maps/{name}/keyframes", params=q)
        assert r.status_code == 200, r.text
        page = r.json()
        out += page["keyframes"]
        cursor = page["next_cursor"]
        if cursor is None:
            return out


def test_listing_pages_and_filters(client: httpx.Client) -> None:
    expect = _fill(client, "mm-list")
    by_id = {v["id"]: k for k, v in expect.items()}

    page = client.get("/v1/maps/mm-list/keyframes", params={"limit": 5}).json()
    assert len(page["keyframes"]) == 5 and page["next_cursor"] is not None
    first = page["keyframes"][0]
    assert set(first) == {"id", "key", "T_map_sensor", "position", "metadata", "created_at"}
    assert first["position"] == expect[first["key"]]["position"]
    assert np.allclose(np.array(first["T_map_sensor"])[:3, 3], first["position"])
    assert first["metadata"] == {"sequence": "north", "timestamp": 100.0}

    rows = _all(client, "mm-list", limit=7)  # 4 pages, the last one short
    assert [r["id"] for r in rows] == sorted(v["id"] for v in expect.values())
    assert all(by_id[r["id"]] == r["key"] for r in rows)

    def keys(**params) -> set[str]:
        return {r["key"] for r in _all(client, "mm-list", **params)}

    assert keys(key_prefix="south/") == {k for k in expect if k.startswith("south/")}
    assert keys(key_prefix="south/01") == {f"south/01{i}" for i in range(2, 10)}
    assert keys(sequence="north") == {k for k in expect if k.startswith("north/")}
    assert keys(time_min=105, time_max=107.5) == {
        k for k, v in expect.items() if 105 <= v["timestamp"] <= 107.5
    }
    inside = {
        k
        for k, v in expect.items()
        if 1.0 <= v["position"][0] <= 4.0 and 2.0 <= v["position"][1] <= 4.0
    }
    assert len(inside) == 4
    assert keys(bbox="1,2,4,4") == inside
    # filters combine (AND)
    assert keys(bbox="1,2,4,4", sequence="south") == {k for k in inside if k.startswith("south")}
    assert keys(key_prefix="nowhere") == set()


@pytest.mark.parametrize(
    ("params", "field"),
    [
        ({"bbox": "1,2,3"}, "bbox"),
        ({"bbox": "a,b,c,d"}, "bbox"),
        ({"bbox": "4,0,1,1"}, "bbox"),
        ({"bbox": "0,0,inf,1"}, "bbox"),
        ({"cursor": "abc"}, "cursor"),
        ({"cursor": "99999999999999999999"}, "cursor"),
        ({"limit": "0"}, "limit"),
        ({"limit": "1001"}, "limit"),
        ({"time_min": "nan"}, "time_min"),
        ({"time_min": "5", "time_max": "4"}, "time_min"),
        ({"key_prefix": ""}, "key_prefix"),
        ({"key_prefix": "a\x00"}, "key_prefix"),  # PostgreSQL cannot hold NUL in text
        ({"sequence": "s\x00"}, "sequence"),
        ({"cursor": "\u00b2"}, "cursor"),  # a digit to str.isdigit(), not to int()
    ],
)
def test_bad_filters_are_422_naming_the_parameter(client: httpx.Client, params, field) -> None:
    if client.get("/v1/maps/mm-bad").status_code == 404:
        assert (
            client.post("/v1/maps", json={"name": "mm-bad", "encoder": PRECOMPUTED}).status_code
            == 201
        )
    r = client.get("/v1/maps/mm-bad/keyframes", params=params)
    assert r.status_code == 422, r.text
    assert field in error_of(r)["field"]


def test_bulk_delete_is_one_transaction_and_one_version_step(client: httpx.Client) -> None:
    expect = _fill(client, "mm-delete")
    n0, v0 = map_state(client, "mm-delete")
    assert n0 == N

    # no filter: refused, nothing deleted
    r = client.delete("/v1/maps/mm-delete/keyframes")
    assert r.status_code == 422 and error_of(r)["field"] == "all"
    assert map_state(client, "mm-delete") == (N, v0)

    # nothing matches: no version step
    r = client.delete("/v1/maps/mm-delete/keyframes", params={"key_prefix": "nowhere"})
    assert r.status_code == 200 and r.json() == {"deleted": 0, "map_version": v0}

    r = client.delete(
        "/v1/maps/mm-delete/keyframes", params={"sequence": "north", "bbox": "0,0,4,10"}
    )
    gone = {k for k, v in expect.items() if k.startswith("north") and v["position"][0] <= 4}
    assert r.status_code == 200, r.text
    assert r.json() == {"deleted": len(gone), "map_version": v0 + 1}
    assert map_state(client, "mm-delete") == (N - len(gone), v0 + 1)
    left = {row["key"] for row in _all(client, "mm-delete", limit=1000)}
    assert left == set(expect) - gone
    for key in gone:  # gone from the store and from the running map
        assert client.get(f"/v1/maps/mm-delete/keyframes/{expect[key]['id']}").status_code == 404
    rng = np.random.default_rng(1)
    q = random_features(rng)
    r = post_msgpack(
        client, "/v1/maps/mm-delete/localize", {"features": q, "top_k": 20, "rerank": "none"}
    )
    assert r.status_code == 200, r.text
    retrieved = {c["keyframe_id"] for c in r.json()["retrieved"]}
    assert len(retrieved) == N - len(gone)
    assert not retrieved & {expect[k]["id"] for k in gone}

    r = client.delete("/v1/maps/mm-delete/keyframes", params={"all": "true"})
    assert r.json() == {"deleted": N - len(gone), "map_version": v0 + 2}
    assert map_state(client, "mm-delete") == (0, v0 + 2)
    assert client.delete("/v1/maps/nope/keyframes", params={"all": "true"}).status_code == 404


def test_map_statistics(client: httpx.Client) -> None:
    r = client.post("/v1/maps", json={"name": "mm-stats", "encoder": PRECOMPUTED})
    assert r.status_code == 201
    empty = client.get("/v1/maps/mm-stats/stats").json()
    assert empty["keyframes"] == 0 and empty["extent"] is None and empty["last_write"] is None
    assert empty["memory_bytes"] == 0 and empty["disk_bytes"] > 0
    client.delete("/v1/maps/mm-stats")

    _fill(client, "mm-stats")
    s = client.get("/v1/maps/mm-stats/stats").json()
    assert s["map"] == "mm-stats" and s["keyframes"] == N and s["version"] == 2
    assert s["extent"] == {"min": [0.0, 0.0, 0.0], "max": [10.0, 6.0, 0.5 * (N - 1)]}
    # 24 keyframes of 64 keypoints x (3 + 8) float32, a 16-D descriptor and a pose each
    arrays = N * (64 * 11 * 4 + 16 * 4 + 16 * 8)
    assert arrays <= s["memory_bytes"] <= arrays + N * (16 * 4 + 8) + 1
    assert s["disk_bytes"] > arrays  # the store holds every array
    assert s["index_kind"] == "flat"
    assert s["last_write"] >= s["created_at"]
    assert client.get("/v1/maps/nope/stats").status_code == 404
