"""The SDK reads a map's recent localizations (sync and async, MessagePack and JSON)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from sgvloc_client import AsyncClient, Client, NotFound, RecentLocalization

PRECOMPUTED = {"kind": "precomputed", "name": "egonn", "global_dim": 16, "local_dim": 8}


def _features(rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {
        "global_descriptor": rng.normal(size=16).astype(np.float32),
        "keypoints": rng.uniform(-20, 20, size=(64, 3)).astype(np.float32),
        "local_features": rng.normal(size=(64, 8)).astype(np.float32),
    }


@pytest.mark.parametrize("wire_format", ["msgpack", "json"])
def test_recent_localizations(service_url: str, wire_format: str) -> None:
    rng = np.random.default_rng(5)
    name = f"recent-sdk-{wire_format}"
    feats = [_features(rng) for _ in range(3)]
    with Client(service_url, wire_format=wire_format) as c:
        c.create_map(name, encoder=PRECOMPUTED)
        poses = [np.eye(4) for _ in feats]
        for i, T in enumerate(poses):
            T[:3, 3] = [5.0 * i, 1.0, 0.0]
        ids = c.insert_keyframes(
            name, [{"T_map_sensor": T, "features": f} for T, f in zip(poses, feats, strict=True)]
        ).ids
        assert c.recent_localizations(name) == []
        answers = [c.localize(name, features=f) for f in (feats[0], feats[2])]
        recent = c.recent_localizations(name)
        assert [type(r) for r in recent] == [RecentLocalization] * 2
        newest = recent[0]
        assert newest.keyframe_id == ids[2] == answers[1].keyframe_id
        assert newest.localized == answers[1].localized
        assert newest.verdict == answers[1].verdict
        assert newest.confidence == pytest.approx(answers[1].confidence)
        assert newest.map_version == answers[1].map_version
        assert newest.time.endswith("Z") and newest.time >= recent[1].time
        assert isinstance(newest.translation, np.ndarray)
        np.testing.assert_allclose(newest.translation, answers[1].estimate.translation)
        assert [r.keyframe_id for r in c.recent_localizations(name, limit=1)] == [ids[2]]
        with pytest.raises(ValueError):
            c.recent_localizations(name, limit=0)
        with pytest.raises(NotFound):
            c.recent_localizations("no-such-map")

        async def read() -> list[RecentLocalization]:
            async with AsyncClient(service_url, wire_format=wire_format) as ac:
                return await ac.recent_localizations(name, limit=5)

        assert [r.keyframe_id for r in asyncio.run(read())] == [ids[2], ids[0]]
        c.delete_map(name)
