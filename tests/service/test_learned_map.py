"""A map of the learned BEV encoder (shipped weights) on the real server, and its
features kept apart from the handcrafted map's."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from svc_helpers import BalmMap, decode, error_of, pose_error, post_msgpack

from sgvloc.core.encoders import EncoderSpec, make_encoder


@pytest.fixture(scope="module")
def learned_map(client: httpx.Client, balm_map: BalmMap) -> str:
    """Map ``learned`` with the fixture's database scans, inserted raw."""
    r = client.post("/v1/maps", json={"name": "learned", "encoder": {"kind": "learned"}})
    assert r.status_code == 201, r.text
    assert r.json()["encoder"]["name"] == "bevnet"
    kfs = [
        {"T_map_sensor": balm_map.seq[i].T_world_sensor, "points": balm_map.seq[i].scan().xyzi()}
        for i in balm_map.ids
    ]
    r = post_msgpack(client, "/v1/maps/learned/keyframes", {"keyframes": kfs})
    assert r.status_code == 201, r.text
    return "learned"


@pytest.fixture(scope="module")
def client(server) -> httpx.Client:  # module scope for the map fixture
    with httpx.Client(base_url=server.url, timeout=300.0) as c:
        yield c


def test_revisit_queries_localize_in_the_learned_map(
    client: httpx.Client, learned_map: str, balm_map: BalmMap
) -> None:
    good = 0
    for q in balm_map.queries:
        frame = balm_map.seq[q]
        body = {"points": frame.scan().xyzi()}
        r = post_msgpack(client, f"/v1/maps/{learned_map}/localize", body)
        assert r.status_code == 200, r.text
        out = decode(r)
        if out["localized"]:
            t_err, r_err = pose_error(np.asarray(out["T_map_sensor"]), frame.T_world_sensor)
            assert t_err < 1.0 and r_err < 5.0, (q, t_err, r_err)  # never a wrong "yes"
            good += 1
    assert good == len(balm_map.queries), f"{good} of {len(balm_map.queries)} queries localized"


def test_learned_features_are_refused_by_the_handcrafted_map(
    client: httpx.Client, balm_map: BalmMap
) -> None:
    enc = make_encoder(EncoderSpec(kind="learned"))
    f = enc.encode(balm_map.seq[balm_map.queries[0]].scan().points)
    feats = {
        "global_descriptor": f.global_descriptor,
        "keypoints": f.keypoints,
        "local_features": f.local_features,
    }
    before = client.get("/v1/maps/balm").json()
    for claim, field in (
        ({}, "features"),  # unclaimed: 64-D local features, the map has 33-D (FPFH)
        ({"encoder": enc.identity.name}, "features.encoder"),
        ({"fingerprint": enc.identity.fingerprint}, "features.fingerprint"),
    ):
        body = {"T_map_sensor": np.eye(4), "features": {**feats, **claim}}
        r = post_msgpack(client, "/v1/maps/balm/keyframes", {"keyframes": [body]})
        assert r.status_code == 409, r.text
        err = error_of(r)
        assert err["code"] == "encoder_mismatch" and err["field"] == f"keyframes[0].{field}"
        r = post_msgpack(client, "/v1/maps/balm/localize", {"features": {**feats, **claim}})
        assert r.status_code == 409 and error_of(r)["field"] == field
    after = client.get("/v1/maps/balm").json()
    assert (after["keyframes"], after["version"]) == (before["keyframes"], before["version"])


def test_a_map_of_both_global_descriptors_merges_their_candidates(
    client: httpx.Client, balm_map: BalmMap
) -> None:
    """A map whose learned encoder gives the polar and the network descriptor records
    both blocks, retrieves up to top_k per block (each keyframe once), localizes the
    fixture's revisits, and refuses features of the single-descriptor encoder."""
    spec = {"kind": "learned", "learned": {"global_descriptor": "polar+network"}}  # default
    r = client.post("/v1/maps", json={"name": "both", "encoder": spec})
    assert r.status_code == 201, r.text
    enc = r.json()["encoder"]
    assert enc["global_descriptor"] == "polar+network" and enc["global_blocks"] == [620, 256]
    assert enc["global_dim"] == 876 and r.json()["retrieval"]["combine"] == "merge"
    kfs = [
        {"T_map_sensor": balm_map.seq[i].T_world_sensor, "points": balm_map.seq[i].scan().xyzi()}
        for i in balm_map.ids
    ]
    assert post_msgpack(client, "/v1/maps/both/keyframes", {"keyframes": kfs}).status_code == 201
    for q in balm_map.queries:
        frame = balm_map.seq[q]
        body = {"points": frame.scan().xyzi(), "top_k": 5}
        out = decode(post_msgpack(client, "/v1/maps/both/localize", body))
        ids = [c["keyframe_id"] for c in out["retrieved"]]
        assert 5 <= len(ids) <= 10 and len(set(ids)) == len(ids)
        assert out["localized"], out["reason"]
        t_err, r_err = pose_error(np.asarray(out["T_map_sensor"]), frame.T_world_sensor)
        assert t_err < 1.0 and r_err < 5.0
    polar = make_encoder(
        EncoderSpec.model_validate({**spec, "learned": {"global_descriptor": "polar"}})
    )
    f = polar.encode(balm_map.seq[balm_map.queries[0]].scan().points)
    feats = {
        "global_descriptor": f.global_descriptor,
        "keypoints": f.keypoints,
        "local_features": f.local_features,
    }
    for claim, field in (
        ({}, "features"),
        ({"fingerprint": polar.identity.fingerprint}, "features.fingerprint"),
    ):
        r = post_msgpack(client, "/v1/maps/both/localize", {"features": {**feats, **claim}})
        assert r.status_code == 409, r.text
        assert error_of(r)["code"] == "encoder_mismatch" and error_of(r)["field"] == field


def test_a_recorded_self_test_is_bounded(client: httpx.Client) -> None:
    big = {"encoders": {"x": "y" * 20000}}
    r = client.post("/v1/maps", json={"name": "st", "encoder": {"kind": "bev"}, "self_test": big})
    assert r.status_code == 422 and error_of(r)["field"] == "self_test"
    small = {"chosen": "bev", "encoders": {"bev": {"pose_success_pct": 90.0}}}
    r = client.post("/v1/maps", json={"name": "st", "encoder": {"kind": "bev"}, "self_test": small})
    assert r.status_code == 201 and r.json()["self_test"] == small
    assert client.get("/v1/maps/st").json()["self_test"] == small
    r = client.post("/v1/maps", json={"name": "st-none", "encoder": {"kind": "bev"}})
    assert r.status_code == 201 and client.get("/v1/maps/st-none").json()["self_test"] is None
    client.delete("/v1/maps/st")
    client.delete("/v1/maps/st-none")
