"""Every kind of bad input gets its 4xx with the documented error body, and leaves the
map unchanged (keyframe count and version)."""

from __future__ import annotations

import json
from collections.abc import Iterator

import httpx
import msgpack
import numpy as np
import pytest
import torch
from svc_helpers import (
    MAX_BATCH,
    MAX_BODY_BYTES,
    MAX_POINTS,
    MAX_TOP_K,
    PRECOMPUTED,
    BalmMap,
    error_of,
    map_state,
    post_msgpack,
    random_features,
)

from sgvloc_client import wire

EYE = np.eye(4)


@pytest.fixture(scope="module")
def pre_map(server) -> str:
    """A precomputed-feature map (``egonn``, G=16, D=8) holding two keyframes."""
    rng = np.random.default_rng(3)
    with httpx.Client(base_url=server.url, timeout=60) as c:
        assert c.post("/v1/maps", json={"name": "pre", "encoder": PRECOMPUTED}).status_code == 201
        kfs = [{"T_map_sensor": EYE, "features": random_features(rng)} for _ in range(2)]
        r = post_msgpack(c, "/v1/maps/pre/keyframes", {"keyframes": kfs})
        assert r.status_code == 201, r.text
    return "pre"


@pytest.fixture
def unchanged(client: httpx.Client, pre_map: str, balm_map: BalmMap) -> Iterator[None]:
    """Asserts that neither test map changed during the test."""
    before = {name: map_state(client, name) for name in (pre_map, balm_map.name)}
    yield
    after = {name: map_state(client, name) for name in (pre_map, balm_map.name)}
    assert after == before


def _scan(n: int = 2000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(-15, 15, size=(n, 4)).astype(np.float32)


def _insert(c: httpx.Client, name: str, *keyframes: dict) -> httpx.Response:
    return post_msgpack(c, f"/v1/maps/{name}/keyframes", {"keyframes": list(keyframes)})


def _expect(r: httpx.Response, status: int, code: str, field: str | None = "") -> dict:
    assert r.status_code == status, r.text
    err = error_of(r)
    assert err["code"] == code, err
    if field != "":
        assert err["field"] == field, err
    return err


# -- shapes, values, emptiness -----------------------------------------------------------


@pytest.mark.usefixtures("unchanged")
@pytest.mark.parametrize(
    ("points", "fragment"),
    [
        (np.zeros((10, 2), np.float32), "shape [P, 3] or [P, 4]"),
        (np.zeros((10, 5), np.float32), "shape [P, 3] or [P, 4]"),
        (np.zeros((2, 5, 3), np.float32), "shape [P, 3] or [P, 4]"),
        (np.zeros((0, 3), np.float32), "empty"),
    ],
)
def test_wrong_scan_shapes(
    client: httpx.Client, balm_map: BalmMap, points: np.ndarray, fragment: str
) -> None:
    r = _insert(client, "balm", {"T_map_sensor": EYE, "points": points})
    err = _expect(r, 422, "invalid_input", "keyframes[0].points")
    assert fragment in err["message"]
    r = post_msgpack(client, "/v1/maps/balm/localize", {"points": points})
    _expect(r, 422, "invalid_input", "points")


@pytest.mark.usefixtures("unchanged")
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_points(client: httpx.Client, balm_map: BalmMap, bad: float) -> None:
    points = _scan()
    points[17, 1] = bad
    r = _insert(client, "balm", {"T_map_sensor": EYE, "points": points})
    err = _expect(r, 422, "invalid_input", "keyframes[0].points")
    assert "non-finite" in err["message"]
    r = post_msgpack(client, "/v1/maps/balm/localize", {"points": points})
    _expect(r, 422, "invalid_input", "points")


@pytest.mark.usefixtures("unchanged")
def test_non_finite_points_in_json(client: httpx.Client, balm_map: BalmMap) -> None:
    # Python's json writes NaN literals; the service parses and then refuses them
    body = '{"points": [[1.0, 2.0, NaN], [1.0, 2.0, 3.0]]}'
    r = client.post(
        "/v1/maps/balm/localize", content=body, headers={"Content-Type": "application/json"}
    )
    _expect(r, 422, "invalid_input", "points")


@pytest.mark.usefixtures("unchanged")
@pytest.mark.parametrize("where", ["points", "T_map_sensor", "global_descriptor"])
def test_integers_beyond_float64_in_json(client: httpx.Client, pre_map: str, where: str) -> None:
    """A JSON integer of 310 digits is a valid number that no float64 holds: 422, not 500."""
    huge = "1" + "0" * 309
    if where == "points":
        path, body = "/v1/maps/balm/localize", f'{{"points": [[1.0, 2.0, {huge}]]}}'
        field = "points"
    else:
        eye = [[1.0 if i == j else 0.0 for j in range(4)] for i in range(4)]
        feats = {"global_descriptor": [1.0] * 16, "keypoints": [[0.0, 0.0, 0.0]],
                 "local_features": [[1.0] * 8]}  # fmt: skip
        kf = {"T_map_sensor": eye, "features": feats}
        text = json.dumps({"keyframes": [kf]})
        old = "[1.0, 0.0, 0.0, 0.0]" if where == "T_map_sensor" else "[1.0, 1.0"
        text = text.replace(old, old.replace("1.0", huge, 1), 1)
        path, body, field = f"/v1/maps/{pre_map}/keyframes", text, f"keyframes[0].{where}"
        if where == "global_descriptor":
            field = "keyframes[0].features.global_descriptor"
    r = client.post(path, content=body, headers={"Content-Type": "application/json"})
    assert r.status_code == 422, r.text
    assert error_of(r)["code"] == "invalid_input"
    assert error_of(r)["field"] == field, error_of(r)


@pytest.mark.usefixtures("unchanged")
def test_scan_with_nothing_to_describe(client: httpx.Client, balm_map: BalmMap) -> None:
    """Points all beyond the encoder's range: empty after preprocessing."""
    far = _scan() + np.array([500.0, 0, 0, 0], np.float32)
    r = _insert(client, "balm", {"T_map_sensor": EYE, "points": far})
    _expect(r, 422, "empty_scan", "keyframes[0].points")
    r = post_msgpack(client, "/v1/maps/balm/localize", {"points": far})
    _expect(r, 422, "empty_scan", "points")


@pytest.mark.usefixtures("unchanged")
@pytest.mark.parametrize(
    ("points", "words"),
    [
        ("[[null, 1, 2], [1, 2, 3]]", "null where a number belongs"),
        # true among integers beyond int64 was read as 1.0 and stored
        ("[[true, 100000000000000000000, 0], [1, 2, 3]]", "true or false"),
    ],
)
def test_null_and_booleans_among_numbers(
    client: httpx.Client, balm_map: BalmMap, points: str, words: str
) -> None:
    headers = {"Content-Type": "application/json"}
    r = client.post("/v1/maps/balm/localize", content=f'{{"points": {points}}}', headers=headers)
    assert words in _expect(r, 422, "invalid_input", "points")["message"]
    body = f'{{"keyframes": [{{"T_map_sensor": {json.dumps(EYE.tolist())}, "points": {points}}}]}}'
    r = client.post("/v1/maps/balm/keyframes", content=body, headers=headers)
    assert words in _expect(r, 422, "invalid_input", "keyframes[0].points")["message"]


@pytest.mark.usefixtures("unchanged")
def test_nan_in_settings_is_named_as_such(client: httpx.Client, pre_map: str) -> None:
    """NaN in a setting was reported as out of range ("less than or equal to 1")."""
    headers = {"Content-Type": "application/json"}
    body = '{"localizer": {"verdict": {"min_confidence": NaN}}}'
    r = client.patch(f"/v1/maps/{pre_map}", content=body, headers=headers)
    err = _expect(r, 422, "invalid_input", "localizer.verdict.min_confidence")
    assert "finite" in err["message"], err
    body = '{"name": "nan-map", "localizer": {"pose": {"icp_max_distance": Infinity}}}'
    r = client.post("/v1/maps", content=body, headers=headers)
    assert "finite" in _expect(r, 422, "invalid_input")["message"]
    r = client.post(f"/v1/maps/{pre_map}/self-test", content='{"gap_s": NaN}', headers=headers)
    assert "finite" in _expect(r, 422, "invalid_input", "gap_s")["message"]
    # an encoder range that leaves every scan empty
    spec = {"kind": "handcrafted", "preprocess": {"min_range": 70}}
    r = client.post("/v1/maps", json={"name": "nan-map", "encoder": spec})
    assert "below max_range" in _expect(r, 422, "invalid_input")["message"]
    assert client.get("/v1/maps/nan-map").status_code == 404


@pytest.mark.usefixtures("unchanged")
def test_a_map_version_no_map_can_reach_is_refused(client: httpx.Client, balm_map: BalmMap) -> None:
    """It waited catch_up_wait_s and answered 503 stale, inviting retries for ever."""
    r = post_msgpack(
        client, "/v1/maps/balm/localize?min_map_version=" + "9" * 23, {"points": _scan()}
    )
    _expect(r, 422, "invalid_input", "min_map_version")


@pytest.mark.usefixtures("unchanged")
def test_msgpack_array_headers_name_their_field(client: httpx.Client, balm_map: BalmMap) -> None:
    nd = {"__nd__": True, "dtype": "<f4", "shape": [True, 3], "data": b"\0" * 12}
    r = client.post(
        "/v1/maps/balm/localize",
        content=msgpack.packb({"points": nd}, use_bin_type=True),
        headers={"Content-Type": "application/msgpack"},
    )
    err = _expect(r, 400, "bad_body", "points")
    assert "shape" in err["message"], err
    deep = b"\x91" * 100_000 + b"\xc0"  # a list in a list in ... 100 000 deep
    r = client.post(
        "/v1/maps/balm/localize", content=deep, headers={"Content-Type": "application/msgpack"}
    )
    assert "nested too deeply" in _expect(r, 400, "bad_body")["message"]


@pytest.mark.usefixtures("unchanged")
def test_ragged_json_array(client: httpx.Client, balm_map: BalmMap) -> None:
    r = client.post("/v1/maps/balm/localize", json={"points": [[1, 2, 3], [1, 2]]})
    err = _expect(r, 422, "invalid_input", "points")
    assert "rectangular" in err["message"]


@pytest.mark.usefixtures("unchanged")
@pytest.mark.parametrize(
    ("change", "fragment"),
    [
        ({"keypoints": np.zeros((64, 2), np.float32)}, "keypoints"),
        ({"local_features": np.zeros((63, 8), np.float32)}, "one feature row per keypoint"),
        ({"global_descriptor": np.full(16, np.nan, np.float32)}, "non-finite"),
        ({"global_descriptor": np.zeros(16, np.float32)}, "all zeros"),
        ({"keypoints": np.full((64, 3), np.inf, np.float32)}, "non-finite"),
    ],
)
def test_malformed_features(
    client: httpx.Client, pre_map: str, change: dict, fragment: str
) -> None:
    feats = {**random_features(np.random.default_rng(5)), **change}
    r = _insert(client, pre_map, {"T_map_sensor": EYE, "features": feats})
    err = _expect(r, 422, "invalid_input", "keyframes[0].features")
    assert fragment in err["message"]
    r = post_msgpack(client, f"/v1/maps/{pre_map}/localize", {"features": feats})
    _expect(r, 422, "invalid_input", "features")


@pytest.mark.usefixtures("unchanged")
def test_one_bad_keyframe_stores_none(client: httpx.Client, pre_map: str) -> None:
    """All-or-nothing: the third keyframe is bad, the first two are not stored either."""
    rng = np.random.default_rng(11)
    good = [{"T_map_sensor": EYE, "features": random_features(rng)} for _ in range(2)]
    bad = {"T_map_sensor": EYE, "features": random_features(rng, n=64, g=16, d=8)}
    bad["features"]["keypoints"] = bad["features"]["keypoints"][:, :2]
    r = _insert(client, pre_map, *good, bad)
    _expect(r, 422, "invalid_input", "keyframes[2].features")


@pytest.mark.usefixtures("unchanged")
def test_points_and_features_together(client: httpx.Client, pre_map: str) -> None:
    feats = random_features(np.random.default_rng(2))
    r = _insert(client, pre_map, {"T_map_sensor": EYE, "features": feats, "points": _scan()})
    _expect(r, 422, "invalid_input", "keyframes[0]")
    r = _insert(client, pre_map, {"T_map_sensor": EYE})
    _expect(r, 422, "invalid_input", "keyframes[0]")


@pytest.mark.usefixtures("unchanged")
def test_unknown_fields_are_refused(client: httpx.Client, pre_map: str) -> None:
    feats = random_features(np.random.default_rng(2))
    r = _insert(client, pre_map, {"T_map_sensor": EYE, "features": feats, "pose": EYE})
    _expect(r, 422, "invalid_input", "keyframes[0].pose")


@pytest.mark.usefixtures("unchanged")
@pytest.mark.parametrize(
    ("extra", "field"),
    [
        ({"key": "k\x00"}, "keyframes[0].key"),
        ({"metadata": {"sequence": "s\x00"}}, "keyframes[0].metadata.sequence"),
        ({"metadata": {"tags": {"a": "b\x00"}}}, "keyframes[0].metadata.tags.a"),
    ],
)
def test_text_with_nul_is_refused(client: httpx.Client, pre_map: str, extra, field) -> None:
    """PostgreSQL cannot hold NUL in text: refused alike on every store."""
    feats = random_features(np.random.default_rng(2))
    r = _insert(client, pre_map, {"T_map_sensor": EYE, "features": feats, **extra})
    _expect(r, 422, "invalid_input", field)


# -- poses -------------------------------------------------------------------------------


@pytest.mark.usefixtures("unchanged")
@pytest.mark.parametrize(
    "T",
    [
        np.diag([2.0, 1.0, 1.0, 1.0]),  # scaled
        np.diag([1.0, 1.0, -1.0, 1.0]),  # reflection (det -1)
        np.vstack([np.eye(4)[:3], [[0.0, 0.0, 1.0, 1.0]]]),  # bad last row
        np.eye(3),  # not 4x4
        np.full((4, 4), np.nan),
        np.vstack([np.hstack([np.eye(3), [[1e200], [0.0], [0.0]]]), [[0, 0, 0, 1.0]]]),  # far
    ],
)
def test_non_rigid_pose(client: httpx.Client, pre_map: str, T: np.ndarray) -> None:
    feats = random_features(np.random.default_rng(4))
    r = _insert(client, pre_map, {"T_map_sensor": T, "features": feats})
    _expect(r, 422, "invalid_input", "keyframes[0].T_map_sensor")


# -- maps and names ----------------------------------------------------------------------


@pytest.mark.usefixtures("unchanged")
def test_unknown_map(client: httpx.Client) -> None:
    feats = random_features(np.random.default_rng(4))
    for r in (
        client.get("/v1/maps/nowhere"),
        client.delete("/v1/maps/nowhere"),
        _insert(client, "nowhere", {"T_map_sensor": EYE, "features": feats}),
        post_msgpack(client, "/v1/maps/nowhere/localize", {"features": feats}),
        client.get("/v1/maps/nowhere/keyframes/1"),
        client.delete("/v1/maps/nowhere/keyframes/1"),
    ):
        err = _expect(r, 404, "not_found")
        assert "nowhere" in err["message"]


@pytest.mark.usefixtures("unchanged")
def test_unknown_keyframe(client: httpx.Client, pre_map: str) -> None:
    _expect(client.get(f"/v1/maps/{pre_map}/keyframes/999"), 404, "not_found")
    _expect(client.delete(f"/v1/maps/{pre_map}/keyframes/999"), 404, "not_found")
    _expect(client.get(f"/v1/maps/{pre_map}/keyframes/abc"), 422, "invalid_input")
    _expect(client.get(f"/v1/maps/{pre_map}/keyframes/{2**63}"), 422, "invalid_input")


@pytest.mark.usefixtures("unchanged")
def test_duplicate_map_name(client: httpx.Client, pre_map: str) -> None:
    r = client.post("/v1/maps", json={"name": pre_map})
    err = _expect(r, 409, "conflict")
    assert pre_map in err["message"]


@pytest.mark.parametrize("name", ["", "-lead", "has space", "a/b", "x" * 65, "..", "é", "pre\n"])
def test_invalid_map_name(client: httpx.Client, name: str) -> None:
    r = client.post("/v1/maps", json={"name": name})
    _expect(r, 422, "invalid_input", "name")
    assert all(m["name"] != name for m in client.get("/v1/maps").json()["maps"])


@pytest.mark.parametrize(
    "body",
    [
        {"name": "bad-enc", "encoder": {"kind": "precomputed", "name": "x"}},
        {"name": "bad-enc", "encoder": {"kind": "torchscript", "model_path": "/no/such.pt"}},
        {"name": "bad-enc", "encoder": {"kind": "nope"}},
        {"name": "bad-enc", "encoder": {**PRECOMPUTED, "global_dim": 2**63}},
        {"name": "bad-enc", "encoder": {**PRECOMPUTED, "local_dim": 10**9}},
        {"name": "bad-enc", "localizer": {"top_k": 0}},
        # a map's own top_k within max_top_k, as a request's
        {"name": "bad-enc", "encoder": PRECOMPUTED, "localizer": {"top_k": MAX_TOP_K + 1}},
        {"name": "bad-enc", "localizer": {"rerank": "magic"}},
        {"name": "bad-enc", "retrieval": {"index": "lsh"}},
    ],
)
def test_invalid_map_settings(client: httpx.Client, body: dict) -> None:
    r = client.post("/v1/maps", json=body)
    err = _expect(r, 422, "invalid_input")
    if "top_k" in body.get("localizer", {}):  # the field itself, not its section
        assert err["field"] == "localizer.top_k", err
    assert client.get("/v1/maps/bad-enc").status_code == 404


@pytest.mark.usefixtures("unchanged")
@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine runs CUDA settings")
@pytest.mark.parametrize(
    "sgv", [{"device": "cuda"}, {"device": "cuda", "backend": "numba"}, {"backend": "numba"}]
)
def test_settings_this_machine_cannot_run_are_refused_where_given(
    client: httpx.Client, pre_map: str, sgv: dict
) -> None:
    """SGV on CUDA without CUDA was stored, and then every localize of the map was a 500;
    refused at creation and in a PATCH now (and in an import, tests/service/test_archive.py)."""
    if sgv == {"backend": "numba"}:  # runnable on a CPU: the control
        r = client.post("/v1/maps", json={"name": "dev-ok", "localizer": {"sgv": sgv}})
        assert r.status_code == 201, r.text
        assert client.delete("/v1/maps/dev-ok").status_code == 204
        return
    r = client.post("/v1/maps", json={"name": "dev-x", "localizer": {"sgv": sgv}})
    err = _expect(r, 422, "invalid_input", "localizer.sgv")
    assert "CUDA is not available" in err["message"], err
    assert client.get("/v1/maps/dev-x").status_code == 404
    before = client.get(f"/v1/maps/{pre_map}").json()
    r = client.patch(f"/v1/maps/{pre_map}", json={"localizer": {"sgv": sgv}})
    _expect(r, 422, "invalid_input", "localizer.sgv")
    after = client.get(f"/v1/maps/{pre_map}").json()
    assert after["settings_version"] == before["settings_version"]
    assert after["localizer"]["sgv"] == before["localizer"]["sgv"]


# -- encoders ----------------------------------------------------------------------------


@pytest.mark.usefixtures("unchanged")
def test_features_of_another_encoder(client: httpx.Client, pre_map: str, balm_map: BalmMap) -> None:
    rng = np.random.default_rng(6)
    feats = random_features(rng)
    # another network's name, or another fingerprint, on the egonn map
    for claim, field in (
        ({"encoder": "logg3d"}, "encoder"),
        ({"fingerprint": "0" * 16}, "fingerprint"),
    ):
        r = _insert(client, pre_map, {"T_map_sensor": EYE, "features": {**feats, **claim}})
        _expect(r, 409, "encoder_mismatch", f"keyframes[0].features.{field}")
        r = post_msgpack(client, f"/v1/maps/{pre_map}/localize", {"features": {**feats, **claim}})
        _expect(r, 409, "encoder_mismatch", f"features.{field}")
    # other dimensions
    for g, d in ((32, 8), (16, 33)):
        other = random_features(rng, g=g, d=d)
        r = _insert(client, pre_map, {"T_map_sensor": EYE, "features": other})
        err = _expect(r, 409, "encoder_mismatch", "keyframes[0].features")
        assert "global_dim=16" in err["message"]
        r = post_msgpack(client, f"/v1/maps/{pre_map}/localize", {"features": other})
        _expect(r, 409, "encoder_mismatch", "features")
    # egonn features sent to the handcrafted map
    r = _insert(client, "balm", {"T_map_sensor": EYE, "features": {**feats, "encoder": "egonn"}})
    _expect(r, 409, "encoder_mismatch", "keyframes[0].features.encoder")
    r = post_msgpack(client, "/v1/maps/balm/localize", {"features": feats})
    _expect(r, 409, "encoder_mismatch", "features")
    # a raw scan sent to the precomputed map
    r = post_msgpack(client, f"/v1/maps/{pre_map}/localize", {"points": _scan()})
    _expect(r, 409, "encoder_mismatch", "points")
    r = _insert(client, pre_map, {"T_map_sensor": EYE, "points": _scan()})
    _expect(r, 409, "encoder_mismatch", "keyframes[0].points")


# -- bodies ------------------------------------------------------------------------------


@pytest.mark.usefixtures("unchanged")
def test_truncated_msgpack(client: httpx.Client, pre_map: str) -> None:
    feats = random_features(np.random.default_rng(8))
    data = wire.packb({"keyframes": [{"T_map_sensor": EYE, "features": feats}]})
    for cut in (len(data) - 7, len(data) // 2, 3):
        r = client.post(
            f"/v1/maps/{pre_map}/keyframes",
            content=data[:cut],
            headers={"Content-Type": wire.MSGPACK},
        )
        _expect(r, 400, "bad_body")


@pytest.mark.usefixtures("unchanged")
def test_a_body_of_empty_containers_is_refused_before_it_is_built(
    client: httpx.Client, pre_map: str
) -> None:
    """An empty map or list takes a byte or two in a body and tens in memory: a body of
    little else (a 10 MB one took 1.4 GB to parse) is a 400, while a real scan sent as
    nested JSON lists still parses."""
    n, m = 300_000, 60_000  # m: within the longest list a MessagePack body may hold
    bombs = [
        (b"\xdd" + m.to_bytes(4, "big") + b"\x80" * m, wire.MSGPACK),  # array32 of {}
        (b"[" + b"{}," * (n - 1) + b"{}]", "application/json"),
    ]
    for data, ctype in bombs:
        r = client.post(
            f"/v1/maps/{pre_map}/localize", content=data, headers={"Content-Type": ctype}
        )
        err = _expect(r, 400, "bad_body")
        assert "too many to be a request" in err["message"], err
    points = np.zeros((50_000, 3)).tolist()  # [0.0, 0.0, 0.0] per point: 17 bytes each
    r = client.post(f"/v1/maps/{pre_map}/localize", json={"points": points})
    assert r.status_code != 400, r.text  # parsed (the map takes features: 409)


@pytest.mark.usefixtures("unchanged")
def test_an_object_of_many_fields_or_a_body_of_many_lists_is_refused_while_parsed(
    client: httpx.Client, pre_map: str
) -> None:
    """Each unknown field of an object costs a validation error (a map of 10 million
    keys took 13 GB and two minutes), and MessagePack carries arrays as bytes: a body
    with an object of more fields than any request has, or with more maps and lists than
    its items could need, is a 400 while it is parsed."""
    wide = {f"f{i}": 1 for i in range(300)}
    many_lists = [[0.0, 0.0, 0.0]] * 60_000  # points as lists: not how MessagePack sends them
    cases = [
        (json.dumps({"points": [[0.0, 0.0, 0.0]], **wide}).encode(), "application/json"),
        (msgpack.packb({"points": [[0.0, 0.0, 0.0]], **wide}), wire.MSGPACK),
        (msgpack.packb({"points": many_lists}), wire.MSGPACK),
    ]
    for data, ctype in cases:
        r = client.post(
            f"/v1/maps/{pre_map}/localize", content=data, headers={"Content-Type": ctype}
        )
        err = _expect(r, 400, "bad_body")
        assert (
            "fields" in err["message"] or "keys" in err["message"] or "too many" in err["message"]
        ), err
    tags = {f"t{i}": "v" for i in range(65)}  # tags are bounded too: 64 at most
    body = {"keyframes": [{"T_map_sensor": EYE.tolist(), "metadata": {"tags": tags}}]}
    r = client.post(f"/v1/maps/{pre_map}/keyframes", json=body)
    err = _expect(r, 422, "invalid_input")
    assert "tags" in (err["field"] or ""), err


@pytest.mark.usefixtures("unchanged")
def test_array_shorter_than_its_shape(client: httpx.Client, pre_map: str) -> None:
    feats = random_features(np.random.default_rng(8))
    raw = wire._to_wire({"keyframes": [{"T_map_sensor": EYE, "features": feats}]})
    arr = raw["keyframes"][0]["features"]["keypoints"]
    arr["data"] = arr["data"][:-12]  # one keypoint missing
    r = client.post(
        f"/v1/maps/{pre_map}/keyframes",
        content=msgpack.packb(raw, use_bin_type=True),
        headers={"Content-Type": wire.MSGPACK},
    )
    err = _expect(r, 400, "bad_body")
    assert "keypoints" in err["message"]


@pytest.mark.usefixtures("unchanged")
def test_bad_json_and_media_type(client: httpx.Client, pre_map: str) -> None:
    path = f"/v1/maps/{pre_map}/keyframes"
    r = client.post(path, content=b'{"keyframes": [', headers={"Content-Type": "application/json"})
    _expect(r, 400, "bad_body")
    r = client.post(path, content=b"", headers={"Content-Type": "application/json"})
    _expect(r, 400, "bad_body")
    r = client.post(path, content=b"keyframes=1", headers={"Content-Type": "text/plain"})
    _expect(r, 415, "unsupported_media_type")
    r = client.post(path, content=b"{}")  # no Content-Type
    _expect(r, 415, "unsupported_media_type")
    r = client.post(path, json=[1, 2, 3])
    _expect(r, 422, "invalid_input")


@pytest.mark.usefixtures("unchanged")
def test_oversized_body(client: httpx.Client, pre_map: str) -> None:
    blob = np.zeros(MAX_BODY_BYTES // 4 + 1024, np.float32)
    r = post_msgpack(client, f"/v1/maps/{pre_map}/localize", {"points": blob})
    err = _expect(r, 413, "payload_too_large")
    assert str(MAX_BODY_BYTES) in err["message"]

    def chunks() -> Iterator[bytes]:  # no Content-Length: the limit holds while streaming
        for _ in range(MAX_BODY_BYTES // 65536 + 2):
            yield b" " * 65536

    r = client.post(
        f"/v1/maps/{pre_map}/keyframes",
        content=chunks(),
        headers={"Content-Type": "application/json"},
    )
    _expect(r, 413, "payload_too_large")


# -- limits ------------------------------------------------------------------------------


@pytest.mark.usefixtures("unchanged")
def test_too_many_points(client: httpx.Client, balm_map: BalmMap) -> None:
    points = _scan(MAX_POINTS + 1)
    r = _insert(client, "balm", {"T_map_sensor": EYE, "points": points})
    err = _expect(r, 422, "invalid_input", "keyframes[0].points")
    assert str(MAX_POINTS) in err["message"]
    r = post_msgpack(client, "/v1/maps/balm/localize", {"points": points})
    _expect(r, 422, "invalid_input", "points")


@pytest.mark.usefixtures("unchanged")
def test_batch_too_large(client: httpx.Client, pre_map: str) -> None:
    rng = np.random.default_rng(9)
    kfs = [{"T_map_sensor": EYE, "features": random_features(rng)} for _ in range(MAX_BATCH + 1)]
    err = _expect(_insert(client, pre_map, *kfs), 422, "invalid_input", "keyframes")
    assert str(MAX_BATCH) in err["message"]
    _expect(_insert(client, pre_map), 422, "invalid_input", "keyframes")  # empty batch


@pytest.mark.usefixtures("unchanged")
@pytest.mark.parametrize("top_k", [MAX_TOP_K + 1, 0, -3, "5", True, 5.0])
def test_top_k_out_of_range(client: httpx.Client, pre_map: str, top_k: int) -> None:
    feats = random_features(np.random.default_rng(4))
    r = post_msgpack(client, f"/v1/maps/{pre_map}/localize", {"features": feats, "top_k": top_k})
    _expect(r, 422, "invalid_input", "top_k")


@pytest.mark.usefixtures("unchanged")
def test_unknown_rerank_method(client: httpx.Client, pre_map: str) -> None:
    feats = random_features(np.random.default_rng(4))
    r = post_msgpack(client, f"/v1/maps/{pre_map}/localize", {"features": feats, "rerank": "x"})
    _expect(r, 422, "invalid_input", "rerank")
    r = post_msgpack(client, f"/v1/maps/{pre_map}/localize", {"features": feats, "refine": "x"})
    _expect(r, 422, "invalid_input", "refine")


def test_unknown_route_and_method(client: httpx.Client) -> None:
    _expect(client.get("/v2/maps"), 404, "not_found")
    _expect(client.put("/v1/maps"), 405, "method_not_allowed")


def _json(c: httpx.Client, method: str, path: str, body: dict) -> httpx.Response:
    """``body`` as JSON text: a lone surrogate travels as its escape, as any client's
    JSON may send it (MessagePack cannot carry one)."""
    text = json.dumps(wire.to_jsonable(body))
    return c.request(method, path, content=text, headers={"Content-Type": "application/json"})


@pytest.mark.usefixtures("unchanged")
@pytest.mark.parametrize(
    ("extra", "field"),
    [
        ({"key": "k\ud800"}, "keyframes[0].key"),
        ({"metadata": {"sequence": "s\udfff"}}, "keyframes[0].metadata.sequence"),
        ({"metadata": {"tags": {"a": "b\ud800"}}}, "keyframes[0].metadata.tags.a"),
    ],
)
def test_text_with_a_lone_surrogate_is_refused(
    client: httpx.Client, pre_map: str, extra, field
) -> None:
    """Neither store can write such text nor can an answer carry it: refused up front."""
    feats = random_features(np.random.default_rng(2))
    body = {"keyframes": [{"T_map_sensor": EYE, "features": feats, **extra}]}
    r = _json(client, "POST", f"/v1/maps/{pre_map}/keyframes", body)
    _expect(r, 422, "invalid_input", field)
    assert client.get(f"/v1/maps/{pre_map}/keyframes").status_code == 200


def _deep(levels: int) -> dict:
    out: dict = {"a": 1}
    for _ in range(levels):
        out = {"a": out}
    return out


@pytest.mark.parametrize(
    ("self_test", "fragment"),
    [
        ({"note": "x\ud800"}, "lone surrogate"),
        (_deep(100), "nested deeper than 32 levels"),
        ({"note": "x\x00"}, "NUL"),
    ],
)
def test_a_self_test_a_store_could_not_give_back_is_refused(
    client: httpx.Client, self_test: dict, fragment: str
) -> None:
    """A recorded self-test is answered by every map listing: one that could not be
    written back out would break GET /v1/maps for everyone."""
    body = {"name": "st-bad", "encoder": PRECOMPUTED, "self_test": self_test}
    err = _expect(_json(client, "POST", "/v1/maps", body), 422, "invalid_input", "self_test")
    assert fragment in err["message"]
    assert client.get("/v1/maps/st-bad").status_code == 404
    assert client.get("/v1/maps").status_code == 200


def test_a_calibration_sent_as_msgpack_arrays_is_taken(client: httpx.Client) -> None:
    """MessagePack bodies decode arrays into NumPy; a calibration whose weights arrive
    that way is the same calibration (the SDK's default wire format sends it so)."""
    from sgvloc.core.confidence import shipped_calibration

    cal = shipped_calibration("precomputed").to_dict()
    for model in cal["models"].values():
        for k in ("mean", "scale", "weights"):
            model[k] = np.asarray(model[k], np.float64)
    body = {"name": "cal-np", "encoder": PRECOMPUTED, "calibration": cal}
    r = post_msgpack(client, "/v1/maps", body)
    try:
        assert r.status_code == 201, r.text
        info = client.get("/v1/maps/cal-np").json()
        assert info["calibration"]["fingerprint"] == cal["fingerprint"]
        r = _json(client, "PATCH", "/v1/maps/cal-np", {"calibration": {**cal, "name": "\ud800"}})
        _expect(r, 422, "invalid_input", "calibration")
    finally:
        client.delete("/v1/maps/cal-np")


@pytest.mark.usefixtures("unchanged")
@pytest.mark.parametrize("top_k", ["5000", 5000.0])
def test_a_map_top_k_over_the_limit_is_refused_however_written(
    client: httpx.Client, pre_map: str, top_k
) -> None:
    r = client.request("PATCH", f"/v1/maps/{pre_map}", json={"localizer": {"top_k": top_k}})
    err = _expect(r, 422, "invalid_input", "localizer.top_k")
    assert "max_top_k" in err["message"]


@pytest.mark.usefixtures("unchanged")
def test_numbers_are_numbers(client: httpx.Client, pre_map: str) -> None:
    """Strings and booleans are not coordinates or times, and a keyframe id in a path is
    decimal digits: each was quietly taken for a number before."""
    feats = random_features(np.random.default_rng(5))
    r = client.post(f"/v1/maps/{pre_map}/localize", json={"points": [["1", "2", "3"]] * 10})
    _expect(r, 422, "invalid_input", "points")
    r = client.post(f"/v1/maps/{pre_map}/localize", json={"points": [[True, False, True]] * 10})
    _expect(r, 422, "invalid_input", "points")
    for stamp in ("12", True):
        kf = {"T_map_sensor": EYE, "features": feats, "metadata": {"timestamp": stamp}}
        _expect(
            _insert(client, pre_map, kf), 422, "invalid_input", "keyframes[0].metadata.timestamp"
        )
    for bad in ("+1", "1_0", "1.0", "-1"):
        r = client.get(f"/v1/maps/{pre_map}/keyframes/{bad}")
        assert r.status_code == 422, (bad, r.text)
