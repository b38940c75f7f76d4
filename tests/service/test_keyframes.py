"""Keyframes: idempotent keys, read back, delete."""

from __future__ import annotations

import threading

import httpx
import numpy as np
from svc_helpers import PRECOMPUTED, error_of, map_state, post_msgpack, random_features


def _pose(x: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, 0.0, 0.0]
    return T


def _new_map(c: httpx.Client, name: str) -> None:
    r = c.post("/v1/maps", json={"name": name, "encoder": PRECOMPUTED})
    assert r.status_code == 201, r.text


def test_idempotent_keys(client: httpx.Client) -> None:
    _new_map(client, "kf-keys")
    rng = np.random.default_rng(0)
    a, b, c = (random_features(rng) for _ in range(3))
    path = "/v1/maps/kf-keys/keyframes"

    r = post_msgpack(
        client,
        path,
        {
            "keyframes": [
                {"key": "a", "T_map_sensor": _pose(1), "features": a},
                {"key": "b", "T_map_sensor": _pose(2), "features": b},
            ]
        },
    )
    assert r.status_code == 201, r.text
    first = r.json()
    assert first["created"] == [True, True] and first["map_version"] == 1
    id_a, id_b = first["ids"]

    # a retried batch with one known and one new key: only the new one is stored
    r = post_msgpack(
        client,
        path,
        {
            "keyframes": [
                {"key": "a", "T_map_sensor": _pose(1), "features": a},
                {"key": "c", "T_map_sensor": _pose(3), "features": c},
            ]
        },
    )
    assert r.status_code == 201, r.text
    second = r.json()
    assert second["ids"][0] == id_a and second["created"] == [False, True]
    assert second["ids"][1] not in (id_a, id_b)
    assert second["map_version"] == 2
    assert map_state(client, "kf-keys") == (3, 2)

    # all keys known: nothing changes, not even the version
    r = post_msgpack(
        client, path, {"keyframes": [{"key": "b", "T_map_sensor": _pose(2), "features": b}]}
    )
    assert r.status_code == 201
    assert r.json() == {"ids": [id_b], "created": [False], "map_version": 2}
    assert map_state(client, "kf-keys") == (3, 2)

    # the same key twice in one batch is refused
    r = post_msgpack(
        client,
        path,
        {
            "keyframes": [
                {"key": "d", "T_map_sensor": _pose(4), "features": a},
                {"key": "d", "T_map_sensor": _pose(4), "features": a},
            ]
        },
    )
    assert r.status_code == 422
    assert error_of(r)["field"] == "keyframes[1].key"
    assert map_state(client, "kf-keys") == (3, 2)


def test_get_and_delete_keyframe(client: httpx.Client) -> None:
    _new_map(client, "kf-del")
    rng = np.random.default_rng(1)
    feats = [random_features(rng) for _ in range(3)]
    body = {
        "keyframes": [
            {
                "T_map_sensor": _pose(i),
                "features": f,
                "key": f"k{i}",
                "metadata": {"timestamp": 10.5 + i, "sequence": "s1", "tags": {"lap": "1"}},
            }
            for i, f in enumerate(feats)
        ]
    }
    # JSON body this time (arrays as nested lists)
    from sgvloc_client import wire

    r = client.post("/v1/maps/kf-del/keyframes", json=wire.to_jsonable(body))
    assert r.status_code == 201, r.text
    ids = r.json()["ids"]

    r = client.get(f"/v1/maps/kf-del/keyframes/{ids[1]}")
    assert r.status_code == 200
    kf = r.json()
    assert kf["id"] == ids[1] and kf["key"] == "k1" and kf["num_keypoints"] == 64
    np.testing.assert_allclose(kf["T_map_sensor"], _pose(1))
    assert kf["metadata"] == {"timestamp": 11.5, "sequence": "s1", "tags": {"lap": "1"}}
    assert kf["created_at"].endswith("Z")

    r = client.delete(f"/v1/maps/kf-del/keyframes/{ids[1]}")
    assert r.status_code == 200
    assert r.json() == {"deleted": ids[1], "map_version": 2}
    assert map_state(client, "kf-del") == (2, 2)
    assert client.get(f"/v1/maps/kf-del/keyframes/{ids[1]}").status_code == 404
    assert client.delete(f"/v1/maps/kf-del/keyframes/{ids[1]}").status_code == 404

    # the deleted keyframe is never a candidate again
    r = post_msgpack(client, "/v1/maps/kf-del/localize", {"features": feats[1], "top_k": 5})
    assert r.status_code == 200
    out = r.json()
    assert ids[1] not in [c["keyframe_id"] for c in out["retrieved"]]
    assert out["map_version"] == 2

    # its key is free again; a new insert gets a fresh id (ids are never reused)
    r = post_msgpack(
        client,
        "/v1/maps/kf-del/keyframes",
        {"keyframes": [{"key": "k1", "T_map_sensor": _pose(1), "features": feats[1]}]},
    )
    assert r.status_code == 201
    assert r.json()["created"] == [True] and r.json()["ids"][0] > max(ids)


def test_a_keyframe_without_keypoints_over_json_and_msgpack(client: httpx.Client) -> None:
    """JSON cannot carry the shape of an empty array ([] for [0, 3]): a keyframe with no
    keypoints is stored over either wire format alike."""
    from sgvloc_client import wire

    _new_map(client, "kf-empty")
    rng = np.random.default_rng(2)
    f = random_features(rng)
    f["keypoints"] = np.zeros((0, 3), np.float32)
    f["local_features"] = np.zeros((0, 8), np.float32)
    body = {"keyframes": [{"T_map_sensor": _pose(0), "features": f}]}
    r = client.post("/v1/maps/kf-empty/keyframes", json=wire.to_jsonable(body))
    assert r.status_code == 201, r.text
    assert post_msgpack(client, "/v1/maps/kf-empty/keyframes", body).status_code == 201
    for i in (*r.json()["ids"], r.json()["ids"][0] + 1):
        kf = client.get(f"/v1/maps/kf-empty/keyframes/{i}").json()
        assert kf["num_keypoints"] == 0, kf


def test_concurrent_inserts_and_localizations(client: httpx.Client, server) -> None:
    """Writers and readers at once: every request succeeds, nothing is lost."""
    _new_map(client, "kf-conc")
    rng = np.random.default_rng(2)
    seed = [random_features(rng) for _ in range(2)]
    r = post_msgpack(
        client,
        "/v1/maps/kf-conc/keyframes",
        {"keyframes": [{"T_map_sensor": _pose(i), "features": f} for i, f in enumerate(seed)]},
    )
    assert r.status_code == 201
    statuses: list[int] = []
    lock = threading.Lock()

    def writer(w: int) -> None:
        local = np.random.default_rng(100 + w)
        with httpx.Client(base_url=server.url, timeout=120) as c:
            for j in range(5):
                kf = {
                    "key": f"w{w}-{j}",
                    "T_map_sensor": _pose(j),
                    "features": random_features(local),
                }
                r = post_msgpack(c, "/v1/maps/kf-conc/keyframes", {"keyframes": [kf]})
                with lock:
                    statuses.append(r.status_code)

    def reader() -> None:
        with httpx.Client(base_url=server.url, timeout=120) as c:
            for _ in range(5):
                r = post_msgpack(
                    c, "/v1/maps/kf-conc/localize", {"features": seed[0], "rerank": "none"}
                )
                with lock:
                    statuses.append(r.status_code)

    threads = [threading.Thread(target=writer, args=(w,)) for w in range(3)]
    threads += [threading.Thread(target=reader) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(set(statuses)) == [200, 201] and len(statuses) == 30
    assert map_state(client, "kf-conc") == (2 + 15, 1 + 15)
