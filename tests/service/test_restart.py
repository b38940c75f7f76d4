"""A restart restores every map exactly: names, ids, versions, localize answers."""

from __future__ import annotations

import httpx
import numpy as np
from svc_helpers import PRECOMPUTED, BalmMap, post_msgpack, random_features


def _answer(c: httpx.Client, name: str, body: dict) -> dict:
    r = post_msgpack(c, f"/v1/maps/{name}/localize", body)
    assert r.status_code == 200, r.text
    out = r.json()
    del out["timings_ms"]
    return out


def _assert_same_answer(a: dict, b: dict) -> None:
    """Same verdict, keyframe, candidates and pose; floats equal up to FAISS rounding
    (an HNSW graph rebuilt without tombstones at snapshot time sums in another order)."""
    arrays = ("T_map_sensor", "T_keyframe_sensor", "translation", "quaternion_xyzw")
    for key in arrays:
        if a[key] is None:
            assert b[key] is None
        else:
            np.testing.assert_allclose(b[key], a[key], atol=1e-9)
    np.testing.assert_allclose(b["confidence"], a["confidence"], atol=1e-9)
    assert (a["evidence"] is None) == (b["evidence"] is None)
    assert (b["evidence"] or {}).keys() == (a["evidence"] or {}).keys()
    for key, value in (a["evidence"] or {}).items():
        if value is None or isinstance(value, bool):
            assert b["evidence"][key] == value, key
        else:
            np.testing.assert_allclose(b["evidence"][key], value, atol=1e-9, err_msg=key)
    assert (a["estimate"] is None) == (b["estimate"] is None)
    for key in arrays if a["estimate"] is not None else ():
        np.testing.assert_allclose(b["estimate"][key], a["estimate"][key], atol=1e-9)
    for key in ("retrieved", "reranked"):
        assert [(c["keyframe_id"], c["retrieval_rank"]) for c in b[key]] == [
            (c["keyframe_id"], c["retrieval_rank"]) for c in a[key]
        ]
        for ca, cb in zip(a[key], b[key], strict=True):
            np.testing.assert_allclose(
                [cb["similarity"], cb["score"]], [ca["similarity"], ca["score"]], atol=1e-6
            )
    assert (a["pose"] is None) == (b["pose"] is None)
    if a["pose"] is not None:
        assert b["pose"]["inliers"] == a["pose"]["inliers"]
        np.testing.assert_allclose(b["pose"]["fitness"], a["pose"]["fitness"], atol=1e-9)
    rest = {*arrays, "retrieved", "reranked", "pose", "confidence", "evidence", "estimate"}
    assert {k: v for k, v in b.items() if k not in rest} == {
        k: v for k, v in a.items() if k not in rest
    }


def test_restart_restores_maps(server, balm_map: BalmMap) -> None:
    rng = np.random.default_rng(21)
    feats = [random_features(rng) for _ in range(5)]
    with httpx.Client(base_url=server.url, timeout=120) as c:
        # a second map with a deleted keyframe (so its ids have a gap) and an HNSW index
        r = c.post(
            "/v1/maps",
            json={"name": "restart-pre", "encoder": PRECOMPUTED, "retrieval": {"index": "hnsw"}},
        )
        assert r.status_code == 201
        kfs = [
            {"T_map_sensor": np.eye(4), "features": f, "key": str(i)} for i, f in enumerate(feats)
        ]
        ids = post_msgpack(c, "/v1/maps/restart-pre/keyframes", {"keyframes": kfs}).json()["ids"]
        assert c.delete(f"/v1/maps/restart-pre/keyframes/{ids[1]}").status_code == 200

        maps_before = c.get("/v1/maps").json()["maps"]
        keyframes_before = [
            c.get(f"/v1/maps/balm/keyframes/{i}").json() for i in balm_map.ids.values()
        ]
        queries = [
            ("balm", {"points": balm_map.seq[4].scan().xyzi()}),
            ("balm", {"points": balm_map.seq[balm_map.queries[0]].scan().xyzi(), "top_k": 5}),
            ("restart-pre", {"features": feats[3], "rerank": "none"}),
        ]
        answers_before = [_answer(c, name, body) for name, body in queries]

    server.restart()
    log = server.log()
    assert "map 'balm': using index snapshot" in log

    with httpx.Client(base_url=server.url, timeout=120) as c:
        assert c.get("/v1/maps").json()["maps"] == maps_before
        keyframes_after = [
            c.get(f"/v1/maps/balm/keyframes/{i}").json() for i in balm_map.ids.values()
        ]
        assert keyframes_after == keyframes_before
        assert c.get(f"/v1/maps/restart-pre/keyframes/{ids[1]}").status_code == 404
        for (name, body), before in zip(queries, answers_before, strict=True):
            _assert_same_answer(before, _answer(c, name, body))

        # known keys are still known; new ids continue after the highest ever given
        kfs = [
            {"T_map_sensor": np.eye(4), "features": feats[0], "key": "0"},
            {"T_map_sensor": np.eye(4), "features": feats[1], "key": "1"},
        ]
        r = post_msgpack(c, "/v1/maps/restart-pre/keyframes", {"keyframes": kfs})
        assert r.status_code == 201
        out = r.json()
        assert out["ids"][0] == ids[0] and out["created"] == [False, True]
        assert out["ids"][1] > max(ids)


def test_a_second_process_on_the_same_data_dir_is_refused(server) -> None:
    """Two processes on one embedded store would each serve their own copy of the maps
    and overwrite each other's files (acknowledged keyframes were lost that way): the
    second one does not start, and says why."""
    import subprocess
    import sys

    from conftest import free_port

    cmd = [sys.executable, "-m", "sgvloc.cli", "serve", "--dev", "--host", "127.0.0.1",
           "--port", str(free_port()), "--data-dir", str(server.data_dir)]  # fmt: skip
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert run.returncode == 2, run.stderr[-2000:]
    assert "in use by another sgvloc process" in run.stderr, run.stderr[-2000:]
    with httpx.Client(base_url=server.url, timeout=60) as c:  # the first one is unharmed
        assert c.get("/readyz").status_code == 200
