"""The verdict over HTTP: confidence, estimates of rejected answers, priors, and map
settings changed after creation (PATCH) that survive a restart."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import numpy as np
import pytest
from conftest import Server
from svc_helpers import PRECOMPUTED, BalmMap, decode, error_of, post_msgpack, random_features

from sgvloc.core.confidence import shipped_calibration


def _localize(c: httpx.Client, name: str, body: dict) -> dict:
    r = post_msgpack(c, f"/v1/maps/{name}/localize", body)
    assert r.status_code == 200, r.text
    return decode(r)


def test_answers_carry_confidence_and_estimate(client: httpx.Client, balm_map: BalmMap) -> None:
    q = balm_map.queries[0]
    scan = balm_map.seq[q].scan().xyzi()
    out = _localize(client, "balm", {"points": scan})
    assert out["localized"] and out["verdict"] == "localized", out["reason"]
    assert out["min_confidence"] <= out["confidence"] <= 1.0
    assert out["estimate"]["T_map_sensor"] == out["T_map_sensor"]
    assert out["estimate"]["translation"] == out["translation"]
    assert {"sgv", "sgv_margin", "inliers", "icp_fitness", "agreement"} <= set(out["evidence"])
    assert out["prior"] is None

    # the same scan with a stricter threshold: rejected, and nothing else changes
    strict = _localize(client, "balm", {"points": scan, "min_confidence": 1.0})
    assert not strict["localized"] and strict["verdict"] == "low_confidence"
    assert strict["T_map_sensor"] is None and strict["translation"] is None
    np.testing.assert_allclose(
        strict["estimate"]["T_map_sensor"], out["estimate"]["T_map_sensor"], atol=1e-9
    )
    assert strict["confidence"] == pytest.approx(out["confidence"], rel=1e-9)
    assert strict["keyframe_id"] == out["keyframe_id"]


def test_a_prior_restricts_the_search(client: httpx.Client, balm_map: BalmMap) -> None:
    q = balm_map.queries[0]
    frame = balm_map.seq[q]
    xy = frame.T_world_sensor[:2, 3].tolist()
    near = _localize(
        client, "balm", {"points": frame.scan().xyzi(), "prior": {"position": xy, "radius_m": 15}}
    )
    assert near["localized"] and near["prior"]["used"]
    assert 0 < near["prior"]["keyframes_in_radius"] <= len(balm_map.ids)
    far = _localize(
        client,
        "balm",
        {"points": frame.scan().xyzi(), "prior": {"position": [9e3, 9e3, 0], "radius_m": 20}},
    )
    assert not far["localized"] and far["verdict"] == "no_keyframe_in_prior"
    assert far["prior"] == {"used": True, "keyframes_in_radius": 0}
    assert far["estimate"] is None and far["keyframe_id"] is None


@pytest.mark.parametrize(
    "prior, field",
    [
        ({"position": [1.0], "radius_m": 5}, "prior.position"),
        ({"position": [1, 2, 3, 4], "radius_m": 5}, "prior.position"),
        ({"position": [1, "2"], "radius_m": 5}, "prior.position[1]"),
        ({"position": [1, 2], "radius_m": 0}, "prior.radius_m"),
        ({"position": [1, 2], "radius_m": True}, "prior.radius_m"),
        ({"position": [1, 2]}, "prior.radius_m"),
        ({"position": [1, 2], "radius_m": 5, "yaw_tolerance_deg": 200}, "prior.yaw_tolerance_deg"),
        ({"position": [1, 2], "radius_m": 5, "extra": 1}, "prior.extra"),
    ],
)
def test_bad_priors_are_422_naming_the_field(client: httpx.Client, prior: dict, field: str) -> None:
    r = client.post("/v1/maps/balm/localize", json={"points": [[1, 2, 3]] * 10, "prior": prior})
    assert r.status_code == 422, r.text
    assert error_of(r)["field"] == field


def test_non_finite_prior_and_min_confidence_over_msgpack(
    client: httpx.Client, balm_map: BalmMap
) -> None:
    pts = np.ones((10, 3), np.float32)
    r = post_msgpack(
        client,
        "/v1/maps/balm/localize",
        {"points": pts, "prior": {"position": [float("nan"), 0.0], "radius_m": 5.0}},
    )
    assert r.status_code == 422 and error_of(r)["field"] == "prior.position[0]"
    for bad in (float("inf"), 1.5, -0.1, "0.5", True):
        r = post_msgpack(client, "/v1/maps/balm/localize", {"points": pts, "min_confidence": bad})
        assert r.status_code == 422, (bad, r.text)
        assert error_of(r)["field"] == "min_confidence"


def _info(c: httpx.Client, name: str) -> dict:
    r = c.get(f"/v1/maps/{name}")
    assert r.status_code == 200, r.text
    return r.json()


def test_patch_changes_settings_and_survives_a_restart(tmp_path: Path) -> None:
    srv = Server(data_dir=tmp_path / "data", log_path=tmp_path / "server.log")
    srv.start()
    try:
        rng = np.random.default_rng(4)
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            assert c.post("/v1/maps", json={"name": "p", "encoder": PRECOMPUTED}).status_code == 201
            body = {"keyframes": [{"T_map_sensor": np.eye(4), "features": random_features(rng)}]}
            assert post_msgpack(c, "/v1/maps/p/keyframes", body).status_code == 201
            before = _info(c, "p")
            assert before["settings_version"] == 0 and before["settings_updated_at"] is None
            assert (
                before["calibration"]["fingerprint"]
                == shipped_calibration("precomputed").fingerprint
            )

            patch = {"localizer": {"verdict": {"min_confidence": 0.8}, "top_k": 7}}
            r = c.patch("/v1/maps/p", json=patch)
            assert r.status_code == 200, r.text
            after = r.json()
            assert after["localizer"]["verdict"]["min_confidence"] == 0.8
            assert after["localizer"]["top_k"] == 7
            # other settings are kept; the keyframe version does not move
            assert after["localizer"]["sgv"] == before["localizer"]["sgv"]
            assert (after["version"], after["keyframes"]) == (before["version"], 1)
            assert after["settings_version"] == 1 and after["settings_updated_at"]
            out = _localize(c, "p", {"features": random_features(rng)})
            assert out["min_confidence"] == 0.8 and len(out["retrieved"]) == 1
            # the same values again, or nothing: no change, so no new settings version
            for same in (patch, {"localizer": {}}, {"localizer": {"top_k": 7}}):
                r = c.patch("/v1/maps/p", json=same)
                assert r.status_code == 200, r.text
                assert r.json() == after, same

            # a calibration of one's own, then back to the shipped one
            own = shipped_calibration("learned").to_dict()
            own["name"] = "mine"
            own["models"]["none"]["bias"] -= 1.0
            r = c.patch("/v1/maps/p", json={"calibration": own})
            assert r.status_code == 200, r.text
            assert r.json()["calibration"]["name"] == "mine"
            mine = r.json()["calibration"]["fingerprint"]
        srv.restart()
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            info = _info(c, "p")
            assert info["localizer"]["verdict"]["min_confidence"] == 0.8
            assert info["settings_version"] == 2 and info["calibration"]["fingerprint"] == mine
            assert info["version"] == before["version"]
            r = c.patch("/v1/maps/p", json={"calibration": "shipped"})
            assert r.json()["calibration"]["name"] == shipped_calibration("precomputed").name
    finally:
        srv.stop()


def _with_bias(value: object) -> dict:
    d = shipped_calibration("learned").to_dict()
    for model in d["models"].values():
        model["bias"] = value
    return d


@pytest.mark.parametrize(
    "body, status, field",
    [
        ({}, 422, None),
        (
            {"localizer": {"verdict": {"min_confidence": 2}}},
            422,
            "localizer.verdict.min_confidence",
        ),
        ({"localizer": {"retrieval": {"index": "hnsw"}}}, 422, "localizer.retrieval"),
        ({"localizer": {"nonsense": 1}}, 422, "localizer.nonsense"),
        ({"localizer": {"top_k": 0}}, 422, "localizer.top_k"),
        ({"localizer": {"top_k": 101}}, 422, "localizer.top_k"),  # above the service's max_top_k
        ({"calibration": {"format": "x"}}, 422, "calibration"),
        ({"calibration": "latest"}, 422, "calibration"),
        # stored, a bias that is not a finite number failed every later localize (500)
        ({"calibration": _with_bias("x")}, 422, "calibration"),
        ({"calibration": _with_bias(float("nan"))}, 422, "calibration"),
        ({"encoder": {"kind": "bev"}}, 422, "encoder"),
    ],
)
def test_bad_patches(
    client: httpx.Client, balm_map: BalmMap, body: dict, status: int, field: str | None
) -> None:
    before = _info(client, "balm")
    # json.dumps writes NaN as JSON's parsers read it (httpx's json= refuses it)
    r = client.patch(
        "/v1/maps/balm", content=json.dumps(body), headers={"Content-Type": "application/json"}
    )
    assert r.status_code == status, r.text
    if field is not None:
        assert error_of(r)["field"] == field
    if field == "encoder":  # why, not "Extra inputs are not permitted"
        assert "cannot be changed" in error_of(r)["message"], r.text
    after = _info(client, "balm")
    assert after == before


def test_patch_of_a_missing_map_is_404(client: httpx.Client) -> None:
    r = client.patch("/v1/maps/nothing-here", json={"localizer": {"top_k": 3}})
    assert r.status_code == 404


def test_a_map_on_small_gicps_icp_moves_to_the_default_by_patch(
    client: httpx.Client, balm_mini_dir: Path, balm_mini_roles: list
) -> None:
    """Maps keep the ICP backend they were made with; new maps get the numba one, and a
    PATCH moves an older map over: the same place, the pose within a few centimetres."""
    from sgvloc.core.sequence import KittiSequence

    seq = KittiSequence(balm_mini_dir)
    db = [i for i, (_, role) in enumerate(balm_mini_roles) if role == "database"]
    query = next(i for i, (_, role) in enumerate(balm_mini_roles) if role == "query")
    old = {"pose": {"icp_backend": "small_gicp"}}
    r = client.post("/v1/maps", json={"name": "icp-move", "localizer": old})
    assert r.status_code == 201, r.text
    assert r.json()["localizer"]["pose"]["icp_backend"] == "small_gicp"
    kfs = [{"T_map_sensor": seq[i].T_world_sensor, "points": seq[i].scan().xyzi()} for i in db]
    r = post_msgpack(client, "/v1/maps/icp-move/keyframes", {"keyframes": kfs})
    assert r.status_code == 201, r.text
    body = {"points": seq[query].scan().xyzi()}
    before = _localize(client, "icp-move", body)

    r = client.patch("/v1/maps/icp-move", json={"localizer": {"pose": {"icp_backend": "numba"}}})
    assert r.status_code == 200, r.text
    assert r.json()["localizer"]["pose"]["icp_backend"] == "numba"
    after = _localize(client, "icp-move", body)
    assert before["localized"] and after["localized"], (before["reason"], after["reason"])
    assert after["keyframe_id"] == before["keyframe_id"]
    moved = np.subtract(after["translation"], before["translation"])
    assert np.linalg.norm(moved) < 0.05
    assert after["evidence"]["icp_fitness"] == pytest.approx(
        before["evidence"]["icp_fitness"], abs=0.02
    )

    r = client.patch("/v1/maps/icp-move", json={"localizer": {"pose": {"icp_backend": "gicp"}}})
    assert r.status_code == 422 and error_of(r)["field"] == "localizer.pose.icp_backend"
    r = client.post("/v1/maps", json={"name": "icp-new"})
    assert r.status_code == 201 and r.json()["localizer"]["pose"]["icp_backend"] == "numba"
    # the re-ranking's tie tolerance: changeable, bounded, and on for new maps
    assert r.json()["localizer"]["sgv"]["tie_tolerance"] == pytest.approx(0.1)
    for bad in (-0.1, 1.0, "x"):
        r = client.patch("/v1/maps/icp-move", json={"localizer": {"sgv": {"tie_tolerance": bad}}})
        assert r.status_code == 422 and error_of(r)["field"] == "localizer.sgv.tie_tolerance"
    r = client.patch("/v1/maps/icp-move", json={"localizer": {"sgv": {"tie_tolerance": 0.0}}})
    assert r.status_code == 200 and r.json()["localizer"]["sgv"]["tie_tolerance"] == 0.0
    assert _localize(client, "icp-move", body)["keyframe_id"] == after["keyframe_id"]
    # retrieval about displaced centres: the same, 4 m on for new maps
    assert r.json()["localizer"]["retrieval"]["offset_m"] == 4.0
    for field, bad in (("offset_m", -1.0), ("offset_m", 21.0), ("offsets", 0), ("offsets", 33)):
        r = client.patch("/v1/maps/icp-move", json={"localizer": {"retrieval": {field: bad}}})
        assert r.status_code == 422 and error_of(r)["field"] == f"localizer.retrieval.{field}"
    r = client.patch("/v1/maps/icp-move", json={"localizer": {"retrieval": {"offset_m": 0.0}}})
    assert r.status_code == 200, r.text
    assert r.json()["localizer"]["retrieval"]["offset_m"] == 0.0
    assert _localize(client, "icp-move", body)["keyframe_id"] == after["keyframe_id"]
    # the ICP constraint floor: reported, changeable, bounded; above every real fit it
    # rejects the answer as a pose check and nothing else changes
    assert after["evidence"]["icp_constraint"] > 0.1
    r = client.post("/v1/maps", json={"name": "icp-floor"})
    assert r.json()["localizer"]["pose"]["min_icp_constraint"] == pytest.approx(0.035)
    for bad in (-0.1, 0.34, "x"):
        r = client.patch(
            "/v1/maps/icp-move", json={"localizer": {"pose": {"min_icp_constraint": bad}}}
        )
        assert r.status_code == 422 and error_of(r)["field"] == "localizer.pose.min_icp_constraint"
    r = client.patch(
        "/v1/maps/icp-move", json={"localizer": {"pose": {"min_icp_constraint": 0.33}}}
    )
    assert r.status_code == 200, r.text
    strict = _localize(client, "icp-move", body)
    assert not strict["localized"] and strict["verdict"] == "pose_check"
    assert "min_icp_constraint" in strict["reason"]
    assert strict["estimate"] is not None and strict["keyframe_id"] == after["keyframe_id"]
    assert strict["confidence"] == pytest.approx(after["confidence"])
    for name in ("icp-move", "icp-new", "icp-floor"):
        assert client.delete(f"/v1/maps/{name}").status_code in (200, 204)
