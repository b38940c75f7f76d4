"""GET /v1/maps/{map}/localizations: a map's most recent localize answers, newest first,
from a bounded in-memory ring that a deleted map loses."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from svc_helpers import PRECOMPUTED, decode, error_of, post_msgpack, random_features

from sgvloc.core.localizer import LocalizationResult
from sgvloc.server.recent import RecentLocalizations
from sgvloc_client import wire


def _result(version: int, localized: bool = True, x: float | None = 1.0) -> LocalizationResult:
    T = None
    if x is not None:
        T = np.eye(4)
        T[:3, 3] = [x, 2.0, 3.0]
    return LocalizationResult(
        localized=localized,
        reason="",
        keyframe_id=7 if x is not None else None,
        pose=None,
        retrieved=[],
        reranked=[],
        rerank_method="sgv",
        timings_ms={},
        map_version=version,
        verdict="localized" if localized else "no_estimate",
        confidence=0.9 if localized else 0.0,
        T_map_sensor_estimate=T,
    )


def test_the_ring_keeps_the_newest_per_map() -> None:
    ring = RecentLocalizations(size=3)
    for v in range(5):
        ring.record("a", _result(v))
    ring.record("b", _result(9, localized=False, x=None))
    assert [e.map_version for e in ring.newest("a")] == [4, 3, 2]
    assert [e.map_version for e in ring.newest("a", 2)] == [4, 3]
    (b,) = ring.newest("b")
    assert b.to_dict() | {"time": None} == {
        "time": None,
        "translation": None,
        "localized": False,
        "verdict": "no_estimate",
        "confidence": 0.0,
        "keyframe_id": None,
        "map_version": 9,
    }
    assert b.time.endswith("Z") and "T" in b.time
    assert ring.newest("a")[0].translation == [1.0, 2.0, 3.0]
    ring.on_change("a", 12)  # a change that is not a deletion keeps the ring
    assert len(ring.newest("a")) == 3
    ring.on_change("a", None)
    assert ring.newest("a") == [] and len(ring.newest("b")) == 1
    with pytest.raises(ValueError):
        RecentLocalizations(size=0)


def test_an_answer_of_a_deleted_map_is_not_recorded() -> None:
    """A localize that ends after its map was deleted must not seed the ring of a map
    made since under the same name."""
    ring = RecentLocalizations(size=3)
    ring.record("a", _result(1), alive=lambda: True)
    ring.on_change("a", None)  # deleted
    ring.record("a", _result(2), alive=lambda: False)  # the old map's late answer
    assert ring.newest("a") == []


def _map_with_keyframes(c: httpx.Client, name: str, rng: np.random.Generator) -> list[dict]:
    r = c.post("/v1/maps", json={"name": name, "encoder": PRECOMPUTED})
    assert r.status_code == 201, r.text
    feats = [random_features(rng) for _ in range(4)]
    kfs = []
    for i, f in enumerate(feats):
        T = np.eye(4)
        T[:3, 3] = [10.0 * i, -5.0 * i, 0.0]
        kfs.append({"T_map_sensor": T, "features": f})
    r = post_msgpack(c, f"/v1/maps/{name}/keyframes", {"keyframes": kfs})
    assert r.status_code == 201, r.text
    return feats


def test_recent_localizations_newest_first(client: httpx.Client) -> None:
    rng = np.random.default_rng(11)
    feats = _map_with_keyframes(client, "recent-a", rng)
    r = client.get("/v1/maps/recent-a/localizations")
    assert r.status_code == 200, r.text
    assert r.json() == {"map": "recent-a", "localizations": []}

    answers = []
    for q in (feats[1], random_features(rng), feats[3]):
        r = post_msgpack(client, "/v1/maps/recent-a/localize", {"features": q})
        assert r.status_code == 200, r.text
        answers.append(r.json())

    r = client.get("/v1/maps/recent-a/localizations")
    assert r.status_code == 200, r.text
    got = r.json()["localizations"]
    assert len(got) == 3
    for entry, answer in zip(got, reversed(answers), strict=True):
        assert set(entry) == {
            "time",
            "translation",
            "localized",
            "verdict",
            "confidence",
            "keyframe_id",
            "map_version",
        }
        for field in ("localized", "verdict", "keyframe_id", "map_version"):
            assert entry[field] == answer[field], field
        assert entry["confidence"] == pytest.approx(answer["confidence"])
        estimate = answer["estimate"]
        if estimate is None:
            assert entry["translation"] is None
        else:
            assert entry["translation"] == pytest.approx(estimate["translation"])
    times = [e["time"] for e in got]
    assert times == sorted(times, reverse=True) and all(t.endswith("Z") for t in times)
    assert got[0]["localized"] and got[0]["translation"] == pytest.approx([30.0, -15.0, 0.0])

    r = client.get("/v1/maps/recent-a/localizations", params={"limit": 1})
    assert r.json()["localizations"] == got[:1]
    # MessagePack: the translation is a float64 array, as in the localize answer
    r = client.get("/v1/maps/recent-a/localizations", headers={"Accept": wire.MSGPACK})
    body = decode(r)
    assert body["localizations"][0]["translation"].dtype == np.float64


@pytest.mark.parametrize("limit", [0, 501, "x"])
def test_limit_is_bounded(client: httpx.Client, limit: object) -> None:
    r = client.get("/v1/maps/recent-a/localizations", params={"limit": limit})
    assert r.status_code == 422 and error_of(r)["field"] == "limit"


def test_unknown_map_is_404(client: httpx.Client) -> None:
    r = client.get("/v1/maps/no-such-map/localizations")
    assert r.status_code == 404 and error_of(r)["code"] == "not_found"


def test_a_deleted_map_forgets_its_localizations(client: httpx.Client) -> None:
    rng = np.random.default_rng(12)
    feats = _map_with_keyframes(client, "recent-del", rng)
    r = post_msgpack(client, "/v1/maps/recent-del/localize", {"features": feats[0]})
    assert r.status_code == 200, r.text
    assert len(client.get("/v1/maps/recent-del/localizations").json()["localizations"]) == 1
    assert client.delete("/v1/maps/recent-del").status_code == 204
    assert client.get("/v1/maps/recent-del/localizations").status_code == 404
    _map_with_keyframes(client, "recent-del", rng)  # the same name again: a new map
    assert client.get("/v1/maps/recent-del/localizations").json()["localizations"] == []
