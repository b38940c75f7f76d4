"""Localize against the real balm_mini map, and with precomputed features."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from svc_helpers import PRECOMPUTED, BalmMap, decode, pose_error, post_msgpack, random_features

from sgvloc_client import wire


def _localize(c: httpx.Client, name: str, body: dict, **headers: str) -> dict:
    r = post_msgpack(c, f"/v1/maps/{name}/localize", body, headers=headers or None)
    assert r.status_code == 200, r.text
    return decode(r)


def test_insert_answer(balm_map: BalmMap) -> None:
    assert sorted(balm_map.ids.values()) == list(range(1, len(balm_map.ids) + 1))
    assert balm_map.version == 1  # one batch, one version step


def test_response_names_frames_and_map(client: httpx.Client, balm_map: BalmMap) -> None:
    """A database scan localizes onto its own keyframe; the response is complete."""
    i = 5
    frame = balm_map.seq[i]
    out = _localize(client, "balm", {"points": frame.scan().xyzi()})
    assert out["map"] == "balm" and out["map_version"] == balm_map.version
    assert out["localized"], out["reason"]
    assert out["keyframe_id"] == balm_map.ids[i]
    T = np.asarray(out["T_map_sensor"])
    t_err, r_err = pose_error(T, frame.T_world_sensor)
    assert t_err < 0.1 and r_err < 0.5, (t_err, r_err)
    # translation and the scalar-last quaternion describe the same transform
    np.testing.assert_allclose(out["translation"], T[:3, 3], atol=1e-9)
    R = Rotation.from_quat(out["quaternion_xyzw"]).as_matrix()
    np.testing.assert_allclose(R, T[:3, :3], atol=1e-6)
    np.testing.assert_allclose(
        np.asarray(out["T_keyframe_sensor"]),
        np.linalg.inv(frame.T_world_sensor) @ T,
        atol=1e-6,
    )
    assert set(out["pose"]) == {
        "inliers",
        "num_correspondences",
        "fitness",
        "inlier_rmse",
        "refined",
        "icp",
    }
    assert out["pose"]["inliers"] >= 10
    # maps keep keyframe clouds by default, so the default ICP refinement ran
    assert out["pose"]["refined"] and out["pose"]["icp"]["used"]
    assert out["pose"]["icp"]["fitness"] > 0.5
    assert set(out["timings_ms"]) == {
        "encode",
        "retrieve",
        "rerank",
        "pose",
        "verify",
        "track",
        "total",
    }
    assert out["timings_ms"]["track"] == 0 and out["mode"] == "global"
    assert out["tracking"] is None
    assert out["rerank_method"] == "sgv"
    assert len(out["retrieved"]) == len(balm_map.ids)  # map default top_k 20 > map size
    assert out["reranked"][0]["keyframe_id"] == out["keyframe_id"]
    assert out["top1_changed"] == (
        out["retrieved"][0]["keyframe_id"] != out["reranked"][0]["keyframe_id"]
    )


def test_msgpack_response_carries_float64_arrays(client: httpx.Client, balm_map: BalmMap) -> None:
    frame = balm_map.seq[3]
    r = post_msgpack(
        client,
        "/v1/maps/balm/localize",
        {"points": frame.scan().xyzi(), "rerank": "none", "top_k": 3},
        headers={"Accept": wire.MSGPACK},
    )
    assert r.status_code == 200
    assert r.headers["content-type"].startswith(wire.MSGPACK)
    out = wire.unpackb(r.content)
    assert isinstance(out["T_map_sensor"], np.ndarray)
    assert out["T_map_sensor"].dtype == np.float64 and out["T_map_sensor"].shape == (4, 4)
    assert out["quaternion_xyzw"].shape == (4,)
    assert len(out["retrieved"]) == 3 and out["rerank_method"] == "none"


@pytest.mark.parametrize(
    "options",
    [{}, {"rerank": "ransac-rir", "top_k": 12}],
    ids=["map-defaults", "ransac-rir"],
)
def test_revisit_queries_within_2m_5deg(
    client: httpx.Client, balm_map: BalmMap, options: dict
) -> None:
    """Every revisit query of the fixture (never inserted) localizes within 2 m / 5 degrees
    of its ground truth T_world_query (poses.txt), with the map's default settings (SGV,
    top_k 20, ICP) and with RANSAC-RIR over the whole map."""
    results = []
    for q in balm_map.queries:
        frame = balm_map.seq[q]
        out = _localize(client, "balm", {"points": frame.scan().xyzi(), **options})
        err = None
        if out["localized"]:
            err = pose_error(np.asarray(out["T_map_sensor"]), frame.T_world_sensor)
        results.append((q, out["localized"], out["reason"], out["keyframe_id"], err))
    bad = [r for r in results if r[4] is None or r[4][0] >= 2.0 or r[4][1] >= 5.0]
    assert not bad, f"revisit queries not within 2 m / 5 deg: {bad} (all: {results})"


def test_precomputed_features_localize(client: httpx.Client) -> None:
    """A precomputed-feature map: the features of a keyframe localize onto it."""
    rng = np.random.default_rng(7)
    r = client.post("/v1/maps", json={"name": "pre-loc", "encoder": PRECOMPUTED})
    assert r.status_code == 201, r.text
    feats = [random_features(rng) for _ in range(4)]
    poses = []
    for k in range(4):
        T = np.eye(4)
        T[:3, 3] = [10.0 * k, 2.0, 0.0]
        poses.append(T)
    body = {
        "keyframes": [{"T_map_sensor": T, "features": f} for T, f in zip(poses, feats, strict=True)]
    }
    r = post_msgpack(client, "/v1/maps/pre-loc/keyframes", body)
    assert r.status_code == 201, r.text
    ids = r.json()["ids"]
    out = _localize(
        client, "pre-loc", {"features": {**feats[2], "encoder": "egonn"}, "rerank": "none"}
    )
    assert out["localized"], out["reason"]
    assert out["keyframe_id"] == ids[2]
    np.testing.assert_allclose(np.asarray(out["T_map_sensor"]), poses[2], atol=1e-3)


def test_empty_map_is_not_localized(client: httpx.Client) -> None:
    r = client.post("/v1/maps", json={"name": "pre-empty", "encoder": PRECOMPUTED})
    assert r.status_code == 201
    out = _localize(client, "pre-empty", {"features": random_features(np.random.default_rng(1))})
    assert out["localized"] is False and out["keyframe_id"] is None
    assert out["T_map_sensor"] is None and out["retrieved"] == []
    assert "no keyframes" in out["reason"]
