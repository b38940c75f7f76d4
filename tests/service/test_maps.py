"""Maps: create, list, describe, delete."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from svc_helpers import PRECOMPUTED, error_of, post_msgpack, random_features


def test_create_describe_list(client: httpx.Client) -> None:
    body = {
        "name": "m-create",
        "retrieval": {"index": "hnsw"},
        "localizer": {"top_k": 7, "rerank": "none"},
    }
    r = client.post("/v1/maps", json=body)
    assert r.status_code == 201, r.text
    info = r.json()
    assert info["name"] == "m-create" and info["version"] == 0 and info["keyframes"] == 0
    # the default encoder: the learned BEV encoder with the shipped weights
    assert info["encoder"]["kind"] == "learned"
    assert info["encoder"]["name"] == "bevnet"
    assert len(info["encoder"]["fingerprint"]) == 16
    assert info["encoder"]["global_dim"] == 876 and info["encoder"]["local_dim"] == 64
    assert info["retrieval"]["index"] == "hnsw" and info["index_kind"] == "hnsw"
    assert info["localizer"]["top_k"] == 7 and info["localizer"]["rerank"] == "none"
    assert info["created_at"].endswith("Z")
    assert client.get("/v1/maps/m-create").json() == info
    names = [m["name"] for m in client.get("/v1/maps").json()["maps"]]
    assert "m-create" in names and names == sorted(names)


def test_list_maps_pages_by_name(client: httpx.Client) -> None:
    """GET /v1/maps: ``limit`` maps per page by name, ``next_cursor`` to the next page
    (null on the last), ``prefix`` to filter; bad paging parameters are 422s naming them."""
    for name in ("pg-c", "pg-a", "pg-e", "pg-b", "pg-d"):
        assert (
            client.post("/v1/maps", json={"name": name, "encoder": PRECOMPUTED}).status_code == 201
        )
    pages, cursor = [], None
    while True:
        params = {"prefix": "pg-", "limit": 2} | ({"cursor": cursor} if cursor else {})
        body = client.get("/v1/maps", params=params).json()
        pages.append([m["name"] for m in body["maps"]])
        assert body["total"] == 5  # on every page
        cursor = body["next_cursor"]
        if cursor is None:
            break
        assert cursor == pages[-1][-1]
    assert pages == [["pg-a", "pg-b"], ["pg-c", "pg-d"], ["pg-e"]]
    # a cursor is a name: any name resumes after it, whether or not such a map exists
    after = client.get("/v1/maps", params={"prefix": "pg-", "cursor": "pg-bb"}).json()
    assert [m["name"] for m in after["maps"]] == ["pg-c", "pg-d", "pg-e"]
    assert after["next_cursor"] is None
    assert client.get("/v1/maps", params={"prefix": "pg-z"}).json() == {
        "maps": [],
        "next_cursor": None,
        "total": 0,
    }
    everything = client.get("/v1/maps").json()  # no limit: every map, as before paging
    assert {"pg-a", "pg-e"} <= {m["name"] for m in everything["maps"]}
    assert everything["next_cursor"] is None
    for params, field in (
        ({"limit": 0}, "limit"),
        ({"limit": 1001}, "limit"),
        ({"limit": "ten"}, "limit"),
        ({"cursor": "x" * 65}, "cursor"),
        ({"prefix": "x" * 65}, "prefix"),
    ):
        r = client.get("/v1/maps", params=params)
        assert r.status_code == 422 and error_of(r)["field"] == field, (params, r.text)


def test_retrieval_given_twice_is_refused(client: httpx.Client) -> None:
    body = {"name": "m-twice", "retrieval": {"index": "flat"}, "localizer": {"retrieval": {}}}
    r = client.post("/v1/maps", json=body)
    assert r.status_code == 422
    assert error_of(r)["code"] == "invalid_input"


def test_delete_map(client: httpx.Client, server) -> None:
    r = client.post("/v1/maps", json={"name": "m-del", "encoder": PRECOMPUTED})
    assert r.status_code == 201
    feats = random_features(np.random.default_rng(0))
    r = post_msgpack(
        client,
        "/v1/maps/m-del/keyframes",
        {"keyframes": [{"T_map_sensor": np.eye(4), "features": feats}]},
    )
    assert r.status_code == 201
    folder = server.data_dir / "maps" / "m-del"
    assert (folder / "map.sqlite").is_file()

    r = client.delete("/v1/maps/m-del")
    assert r.status_code == 204 and r.content == b""
    assert not folder.exists()
    assert client.get("/v1/maps/m-del").status_code == 404
    assert "m-del" not in [m["name"] for m in client.get("/v1/maps").json()["maps"]]
    assert client.delete("/v1/maps/m-del").status_code == 404

    # the name can be used again, for a fresh empty map
    r = client.post("/v1/maps", json={"name": "m-del", "encoder": PRECOMPUTED})
    assert r.status_code == 201 and r.json()["keyframes"] == 0


def test_only_input_errors_are_laid_on_the_field() -> None:
    """A localize's deadline (or a store's error) is no fault of its points: at_field
    names the field for input errors only."""
    from sgvloc.core.errors import DeadlineExceeded, InputError
    from sgvloc.server.maps import at_field

    with pytest.raises(InputError, match="^points: bad") as bad:
        with at_field("points"):
            raise InputError("bad")
    assert getattr(bad.value, "field", None) == "points"
    with pytest.raises(DeadlineExceeded, match="^stopped at retrieval$") as late:
        with at_field("points"):
            raise DeadlineExceeded("stopped at retrieval")
    assert getattr(late.value, "field", None) is None
