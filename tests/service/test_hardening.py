"""Hardening against a real server: bounded settings and keypoints, finite metadata,
model files confined to a models directory, and a bad map folder that blocks nothing
and leaks no server path."""

from __future__ import annotations

import shutil
from pathlib import Path

import httpx
import numpy as np
import pytest
from conftest import Server
from svc_helpers import PRECOMPUTED, error_of, post_msgpack

from sgvloc.core.encoders.learned import shipped_weights_path

EYE = np.eye(4).tolist()


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"localizer": {"pose": {"max_iterations": 10**12}}}, "max_iterations"),
        ({"retrieval": {"index": "hnsw", "hnsw_m": 10**6}}, "hnsw_m"),
        ({"retrieval": {"index": "ivf", "nlist": 10**9}}, "nlist"),
        ({"encoder": {"kind": "bev", "bev": {"raster": {"extent": 1e6}}}}, "extent"),
        ({"encoder": {"kind": "handcrafted", "handcrafted": {"rings": 10**6}}}, "rings"),
        ({"encoder": {"kind": "handcrafted", "handcrafted": {"sectors": 10**6}}}, "sectors"),
        ({"localizer": {"pose": {"seed": -1}}}, "seed"),
        ({"encoder": {**PRECOMPUTED, "global_dim": 10**9}}, "global_dim"),
    ],
)
def test_map_settings_have_upper_bounds(client: httpx.Client, body: dict, field: str) -> None:
    r = client.post("/v1/maps", json={"name": "bounded", **body})
    assert r.status_code == 422, r.text
    err = error_of(r)
    assert err["code"] == "invalid_input" and field in (err["field"] or ""), err
    assert client.get("/v1/maps/bounded").status_code == 404


def test_keypoints_per_feature_set_are_limited(client: httpx.Client) -> None:
    """Precomputed features beyond max_keypoints (4096 by default) are refused before
    any work; a new map's encoder may not make more either."""
    assert client.get("/v1/config").json()["limits"]["max_keypoints"] == 4096
    assert client.post("/v1/maps", json={"name": "kp", "encoder": PRECOMPUTED}).status_code == 201
    rng = np.random.default_rng(0)
    n = 5000
    feats = {
        "global_descriptor": rng.normal(size=16).astype(np.float32),
        "keypoints": rng.normal(size=(n, 3)).astype(np.float32),
        "local_features": rng.normal(size=(n, 8)).astype(np.float32),
    }
    r = post_msgpack(client, "/v1/maps/kp/localize", {"features": feats})
    assert r.status_code == 422 and "max_keypoints" in error_of(r)["message"], r.text
    assert error_of(r)["field"].startswith("features.")
    r = post_msgpack(client, "/v1/maps/kp/keyframes", {"keyframes": [
        {"T_map_sensor": np.eye(4), "features": feats}]})  # fmt: skip
    assert r.status_code == 422, r.text
    assert client.get("/v1/maps/kp").json()["keyframes"] == 0
    spec = {"kind": "handcrafted", "handcrafted": {"num_keypoints": 10_000}}
    r = client.post("/v1/maps", json={"name": "kp2", "encoder": spec})
    assert r.status_code == 422, r.text
    assert error_of(r)["field"] == "encoder.handcrafted.num_keypoints"
    client.delete("/v1/maps/kp")


@pytest.mark.parametrize("value", ["NaN", "Infinity", "-Infinity"])
def test_metadata_timestamps_are_finite(client: httpx.Client, value: str) -> None:
    assert client.post("/v1/maps", json={"name": "ts", "encoder": PRECOMPUTED}).status_code in (
        201,
        409,
    )
    feats = ('{"global_descriptor": [1,0,0,0,0,0,0,0,0,0,0,0,0,0,0,0], "keypoints": [[0,0,0]],'
             ' "local_features": [[1,0,0,0,0,0,0,0]]}')  # fmt: skip
    body = (
        f'{{"keyframes": [{{"T_map_sensor": {EYE}, "features": {feats}, '
        f'"metadata": {{"timestamp": {value}}}}}]}}'
    )
    r = client.post(
        "/v1/maps/ts/keyframes", content=body, headers={"Content-Type": "application/json"}
    )
    assert r.status_code == 422, r.text
    assert error_of(r)["field"] == "keyframes[0].metadata.timestamp"


def test_model_files_only_from_the_models_directory(tmp_path: Path) -> None:
    """Without SGVLOC_MODELS_DIR no path is accepted; with it, only files inside it, and
    every refusal reads the same (no probing the server's files)."""
    models = tmp_path / "models"
    models.mkdir()
    shutil.copy(shipped_weights_path(), models / "bevnet.pt")
    srv = Server(tmp_path / "data", tmp_path / "server.log", env={})
    srv.start()
    try:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            spec = {"kind": "learned", "model_path": "/etc/passwd"}
            r = c.post("/v1/maps", json={"name": "m", "encoder": spec})
            assert r.status_code == 422 and error_of(r)["field"] == "encoder.model_path"
    finally:
        srv.stop()
    srv = Server(tmp_path / "data", tmp_path / "server.log", env={"SGVLOC_MODELS_DIR": str(models)})
    srv.start()
    try:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            messages = set()
            for path in ("/etc/passwd", "/etc/nonexistent", "../../etc/passwd", "nope.pt",
                         str(tmp_path / "server.log")):  # fmt: skip
                spec = {"kind": "torchscript", "model_path": path}
                r = c.post("/v1/maps", json={"name": "m", "encoder": spec})
                assert r.status_code == 422, r.text
                assert error_of(r)["field"] == "encoder.model_path"
                messages.add(error_of(r)["message"])
            assert len(messages) == 1 and "/etc" not in messages.pop()
            spec = {"kind": "learned", "model_path": "bevnet.pt"}
            r = c.post("/v1/maps", json={"name": "m", "encoder": spec})
            assert r.status_code == 201, r.text
            assert c.get("/v1/maps").json()["maps"][0]["name"] == "m"
    finally:
        srv.stop()


def test_a_bad_map_folder_blocks_no_other_map_and_leaks_no_path(tmp_path: Path) -> None:
    srv = Server(tmp_path / "data", tmp_path / "server.log")
    srv.start()
    try:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            assert (
                c.post("/v1/maps", json={"name": "good", "encoder": PRECOMPUTED}).status_code == 201
            )
    finally:
        srv.stop()
    for name, content in (("broken", b"not a database"), ("empty", None)):
        folder = tmp_path / "data" / "maps" / name
        folder.mkdir()
        if content is not None:
            (folder / "map.sqlite").write_bytes(content)
    srv.start()
    try:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            assert c.get("/v1/maps/good").status_code == 200
            ready = c.get("/readyz").json()
            assert set(ready["failed"]) == {"broken", "empty"}, ready
            text = str(ready) + c.post("/v1/maps", json={"name": "broken"}).text
            assert str(tmp_path) not in text, text
    finally:
        srv.stop()
