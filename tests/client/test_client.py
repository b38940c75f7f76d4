"""The SDK against a real service (``sgvloc serve`` in a subprocess, see conftest.py).

Scans come from the committed balm_mini fixture; each test works in its own maps.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import httpx
import numpy as np
import pytest

from sgvloc_client import (
    AsyncClient,
    BadRequest,
    Client,
    Conflict,
    InsertResult,
    KeyframeIn,
    Localization,
    MapInfo,
    NotFound,
    Prior,
    TransportError,
    read_scan,
    wire,
)


def _poses(balm_mini_dir: Path) -> np.ndarray:
    rows = np.loadtxt(balm_mini_dir / "poses.txt").reshape(-1, 3, 4)
    T = np.tile(np.eye(4), (len(rows), 1, 1))  # [F, 4, 4]
    T[:, :3] = rows
    return T


def _scan(balm_mini_dir: Path, i: int) -> np.ndarray:
    return read_scan(balm_mini_dir / "velodyne" / f"{i:06d}.bin")  # [P, 4]


def _rot_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    R = np.eye(4)
    R[:2, :2] = [[c, -s], [s, c]]
    return R


class RecordingTransport(httpx.HTTPTransport):
    """A real transport that keeps every request and response it carried."""

    def __init__(self) -> None:
        super().__init__()
        self.exchanges: list[tuple[httpx.Request, httpx.Response]] = []

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        response = super().handle_request(request)
        self.exchanges.append((request, response))
        return response


def test_probes(service_url: str) -> None:
    with Client(service_url) as c:
        assert c.health() == {"status": "ok"}
        assert c.ready() is True
        c.wait_until_ready(timeout=5)


def test_map_lifecycle(service_url: str) -> None:
    with Client(service_url) as c:
        info = c.create_map("lifecycle", retrieval="flat")
        assert isinstance(info, MapInfo)
        assert (info.name, info.keyframes) == ("lifecycle", 0)
        assert info.encoder.kind == "learned" and info.encoder.fingerprint  # the default
        assert info.encoder.global_dim > 0 and info.index_kind == "flat"

        assert "lifecycle" in [m.name for m in c.list_maps()]
        assert c.get_map("lifecycle") == info
        c.create_map("lifecycle-2", retrieval="flat")
        first = c.list_maps_page(limit=1, prefix="lifecycle")
        assert [m.name for m in first.maps] == ["lifecycle"]
        assert first.next_cursor == "lifecycle" and first.total == 2
        last = c.list_maps_page(limit=1, prefix="lifecycle", cursor=first.next_cursor)
        assert [m.name for m in last.maps] == ["lifecycle-2"] and last.next_cursor is None
        assert [m.name for m in c.list_maps(prefix="lifecycle")] == ["lifecycle", "lifecycle-2"]
        c.delete_map("lifecycle-2")

        with pytest.raises(Conflict) as dup:
            c.create_map("lifecycle")
        assert (dup.value.status, dup.value.code) == (409, "conflict")

        c.delete_map("lifecycle")
        assert "lifecycle" not in [m.name for m in c.list_maps()]
        with pytest.raises(NotFound) as missing:
            c.get_map("lifecycle")
        assert (missing.value.status, missing.value.code) == (404, "not_found")
        with pytest.raises(NotFound):
            c.delete_map("lifecycle")
        # a map that keeps no keyframe clouds
        assert c.create_map("no-clouds", keep_clouds=False).keep_clouds is False
        c.delete_map("no-clouds")


def test_unknown_map_is_not_found(service_url: str) -> None:
    with Client(service_url) as c:
        with pytest.raises(NotFound):
            c.get_map("no-such-map")
        with pytest.raises(NotFound):
            c.insert_keyframe("no-such-map", np.eye(4), points=np.zeros((10, 3)), key="k")
        with pytest.raises(NotFound):
            c.localize("no-such-map", points=np.zeros((10, 3)))
        with pytest.raises(NotFound):
            c.get_keyframe("no-such-map", 0)


def test_errors_carry_the_request_id_of_the_services_log(service_url: str, closed_url: str) -> None:
    """Each call sends an X-Request-ID; an error answer carries the id the service
    logged it under, and a call that got no answer the id it was sent with."""
    with Client(service_url) as c:
        with pytest.raises(NotFound) as info:
            c.get_map("no-such-map")
    rid = info.value.request_id
    assert rid and len(rid) == 32 and rid in str(info.value)
    with Client(closed_url, retries=1, backoff=0) as c:
        with pytest.raises(TransportError) as lost:
            c.get_map("m")
    assert lost.value.request_id and lost.value.request_id in str(lost.value)
    assert lost.value.request_id != rid

    async def main() -> str | None:
        async with AsyncClient(service_url) as c:
            try:
                await c.get_map("no-such-map")
            except NotFound as exc:
                return exc.request_id
        return None

    assert asyncio.run(main()) not in (None, rid)


def test_bad_shapes_are_bad_request(service_url: str, balm_mini_dir: Path) -> None:
    scan = _scan(balm_mini_dir, 0)
    with Client(service_url) as c:
        c.create_map("shapes")
        good = KeyframeIn(np.eye(4), points=scan, key="good")
        with pytest.raises(BadRequest) as info:
            c.insert_keyframes("shapes", [good, KeyframeIn(np.eye(4), points=scan[:, :2])])
        assert info.value.status == 422 and info.value.code == "invalid_input"
        assert info.value.field == "keyframes[1].points"
        with pytest.raises(BadRequest) as info:
            c.insert_keyframe("shapes", np.eye(3), points=scan)
        assert "T_map_sensor" in (info.value.field or "") + info.value.message
        with pytest.raises(BadRequest) as info:
            c.localize("shapes", points=np.zeros((10, 5, 2)))
        assert info.value.field == "points"
        # all or nothing: the good keyframe of the refused batch was not stored
        assert c.get_map("shapes").keyframes == 0
        c.delete_map("shapes")


def test_insert_msgpack_idempotent_and_keyframes(service_url: str, balm_mini_dir: Path) -> None:
    poses = _poses(balm_mini_dir)
    kfs = [
        KeyframeIn(
            poses[i],
            points=_scan(balm_mini_dir, i),
            key=f"balm_mini/{i:06d}",
            metadata={"timestamp": float(i), "sequence": "balm_mini", "tags": {"role": "db"}},
        )
        for i in range(3)
    ]
    transport = RecordingTransport()
    with Client(service_url, transport=transport) as c:
        c.create_map("inserts")
        v0 = c.get_map("inserts").version
        res = c.insert_keyframes("inserts", kfs)
        assert isinstance(res, InsertResult)
        assert res.created == [True, True, True] and len(set(res.ids)) == 3
        assert res.map_version != v0

        # The request and the answer travelled as MessagePack with raw arrays.
        request, response = transport.exchanges[-1]
        assert request.headers["content-type"] == wire.MSGPACK
        assert response.headers["content-type"].startswith(wire.MSGPACK)
        assert len(request.content) < 1.2 * sum(k.points.nbytes for k in kfs) + 10_000

        # A retried (repeated) insert with the same keys stores nothing new.
        again = c.insert_keyframes("inserts", [kfs[1], kfs[2]])
        assert again.created == [False, False] and again.ids == res.ids[1:]
        info = c.get_map("inserts")
        assert info.keyframes == 3

        kf = c.get_keyframe("inserts", res.ids[1])
        assert kf.id == res.ids[1] and kf.key == "balm_mini/000001"
        np.testing.assert_allclose(kf.T_map_sensor, poses[1], atol=1e-12)
        assert kf.metadata["tags"] == {"role": "db"} and kf.num_keypoints > 0

        deleted = c.delete_keyframe("inserts", res.ids[1])
        assert deleted.id == res.ids[1] and deleted.map_version != info.version
        assert c.get_map("inserts").keyframes == 2
        with pytest.raises(NotFound):
            c.get_keyframe("inserts", res.ids[1])
        c.delete_map("inserts")


def test_localize_returns_typed_pose(service_url: str, balm_mini_dir: Path) -> None:
    poses = _poses(balm_mini_dir)
    with Client(service_url) as c:
        c.create_map("loc")
        res = c.insert_keyframes(
            "loc",
            [KeyframeIn(poses[i], points=_scan(balm_mini_dir, i), key=str(i)) for i in range(4)],
        )
        # Query: keyframe 2's scan seen from a sensor moved by A (q = A p), so the query's
        # pose in the keyframe is inv(A) and in the map poses[2] @ inv(A).
        A = _rot_z(25.0)
        A[:3, 3] = [0.8, -0.5, 0.1]
        scan = _scan(balm_mini_dir, 2)
        query = scan.copy()
        query[:, :3] = scan[:, :3] @ A[:3, :3].T + A[:3, 3]
        loc = c.localize("loc", points=query, rerank="sgv")

    assert isinstance(loc, Localization)
    assert loc.map == "loc" and loc.map_version == res.map_version
    assert loc.localized, loc.reason
    assert loc.keyframe_id == res.ids[2]
    assert loc.T_map_sensor.shape == (4, 4) and loc.T_map_sensor.dtype == np.float64
    expected = poses[2] @ np.linalg.inv(A)
    assert np.linalg.norm(loc.T_map_sensor[:3, 3] - expected[:3, 3]) < 0.2
    R_err = loc.T_map_sensor[:3, :3].T @ expected[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(R_err) - 1) / 2, -1, 1))) < 2.0
    np.testing.assert_allclose(loc.translation, loc.T_map_sensor[:3, 3])
    assert loc.quaternion_xyzw.shape == (4,)
    assert loc.pose is not None and loc.pose.inliers > 0
    assert loc.retrieved and loc.reranked[0].keyframe_id == loc.keyframe_id
    assert loc.rerank_method == "sgv" and loc.timings_ms["total"] > 0
    assert loc.verdict == "localized" and loc.min_confidence <= loc.confidence <= 1.0
    np.testing.assert_array_equal(loc.estimate.T_map_sensor, loc.T_map_sensor)
    assert loc.evidence["inliers"] == loc.pose.inliers and loc.prior is None


def test_verdict_prior_and_settings(service_url: str, balm_mini_dir: Path) -> None:
    poses = _poses(balm_mini_dir)
    with Client(service_url) as c:
        c.create_map("trust")
        c.insert_keyframes(
            "trust", [KeyframeIn(poses[i], points=_scan(balm_mini_dir, i)) for i in range(4)]
        )
        scan = _scan(balm_mini_dir, 1)
        near = Prior(position=poses[1][:2, 3], radius_m=5.0, yaw_deg=None)
        loc = c.localize("trust", points=scan, prior=near)
        assert loc.localized and loc.prior["used"] and loc.prior["keyframes_in_radius"] >= 1
        far = c.localize("trust", points=scan, prior={"position": [500.0, 0.0], "radius_m": 5})
        assert not far.localized and far.verdict == "no_keyframe_in_prior"
        assert far.estimate is None and far.T_map_sensor is None
        strict = c.localize("trust", points=scan, min_confidence=1.0)
        assert not strict.localized and strict.verdict == "low_confidence"
        assert strict.T_map_sensor is None and strict.estimate is not None
        np.testing.assert_allclose(strict.estimate.T_map_sensor, loc.T_map_sensor, atol=1e-6)

        info = c.update_map("trust", localizer={"verdict": {"min_confidence": 0.99}})
        assert info.localizer["verdict"]["min_confidence"] == 0.99
        assert info.settings_version == 1 and info.calibration["fingerprint"]
        assert c.localize("trust", points=scan).min_confidence == 0.99
        with pytest.raises(BadRequest) as err:
            c.update_map("trust", localizer={"retrieval": {"index": "hnsw"}})
        assert err.value.field == "localizer.retrieval"
        with pytest.raises(ValueError):
            c.update_map("trust")
        c.delete_map("trust")


def test_json_wire_format(service_url: str, balm_mini_dir: Path) -> None:
    with Client(service_url, wire_format="json") as c:
        c.create_map("json-wire")
        res = c.insert_keyframe("json-wire", np.eye(4), points=_scan(balm_mini_dir, 0)[::4])
        assert res.created == [True]
        assert c.get_keyframe("json-wire", res.ids[0]).T_map_sensor.shape == (4, 4)
        c.delete_map("json-wire")


def test_async_client(service_url: str, balm_mini_dir: Path) -> None:
    poses = _poses(balm_mini_dir)

    async def main() -> None:
        async with AsyncClient(service_url) as c:
            assert await c.health() == {"status": "ok"}
            assert await c.ready()
            info = await c.create_map("async")
            assert isinstance(info, MapInfo) and info.keyframes == 0
            with pytest.raises(Conflict):
                await c.create_map("async")
            kfs = [
                {"T_map_sensor": poses[i], "points": _scan(balm_mini_dir, i), "key": str(i)}
                for i in range(3)
            ]
            # Concurrent requests on one client.
            first, second = await asyncio.gather(
                c.insert_keyframes("async", kfs[:2]), c.insert_keyframe("async", **kfs[2])
            )
            assert first.created == [True, True] and second.created == [True]
            again = await c.insert_keyframes("async", kfs)
            assert again.created == [False] * 3
            assert (await c.get_map("async")).keyframes == 3
            assert "async" in [m.name for m in await c.list_maps()]
            loc = await c.localize("async", points=_scan(balm_mini_dir, 1))
            assert isinstance(loc, Localization) and loc.localized, loc.reason
            assert loc.keyframe_id == first.ids[1]
            np.testing.assert_allclose(loc.T_map_sensor, poses[1], atol=0.05)
            kf = await c.get_keyframe("async", second.ids[0])
            assert kf.key == "2"
            await c.delete_keyframe("async", second.ids[0])
            with pytest.raises(BadRequest):
                await c.insert_keyframe("async", np.eye(4), points=np.zeros((5, 2)))
            await c.delete_map("async")
            with pytest.raises(NotFound):
                await c.get_map("async")

    asyncio.run(main())
