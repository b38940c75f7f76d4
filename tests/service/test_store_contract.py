"""The store contract, run against both backends: SQLite (one database per map folder)
and PostgreSQL (one shared database, a real server). Every test here must hold for both;
tests of one backend's own behaviour live in test_store.py and test_replicas.py."""

from __future__ import annotations

import io
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from svc_helpers import random_features

from sgvloc.core.encoders import EncoderSpec, make_encoder
from sgvloc.core.errors import ConflictError, InputError, NotFoundError
from sgvloc.server.maps import FeaturesIn, KeyframeIn, MapManager
from sgvloc.server.store import KeyframeFilter, open_backend

SPEC = EncoderSpec(kind="precomputed", name="egonn", global_dim=16, local_dim=8)

Factory = Callable[..., MapManager]


@pytest.fixture(params=["sqlite", "postgresql"])
def managers(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Factory]:
    """``managers()`` opens a map manager on one store (each call: a new process's view
    of the same store, as after a restart); all are closed at the end."""
    url = None
    if request.param == "postgresql":
        url = request.getfixturevalue("postgres").new_database()
    opened: list[MapManager] = []

    def make(**kwargs) -> MapManager:
        m = MapManager(tmp_path / "maps", backend=open_backend(url), **kwargs)
        m.load_all()
        opened.append(m)
        return m

    yield make
    for m in opened:
        m.close()


def _items(rng: np.random.Generator, n: int, key_prefix: str | None = None, x0: float = 0.0):
    out = []
    for i in range(n):
        f = random_features(rng)
        T = np.eye(4)
        T[:3, 3] = [x0 + i, 2.0 * i, 0.5]
        out.append(
            KeyframeIn(
                T_map_sensor=T,
                features=FeaturesIn(f["global_descriptor"], f["keypoints"], f["local_features"]),
                key=None if key_prefix is None else f"{key_prefix}{i}",
                metadata={"timestamp": 100.0 + i, "sequence": "a" if i % 2 else "b"},
            )
        )
    return out


def test_create_insert_read_back(managers: Factory, rng: np.random.Generator) -> None:
    m = managers()
    m.create("a", SPEC)
    with pytest.raises(ConflictError):
        m.create("a", SPEC)
    items = _items(rng, 5, "k")
    r = m.insert("a", items)
    assert r.ids == [1, 2, 3, 4, 5] and r.created == [True] * 5 and r.map_version == 1
    row = m.get_keyframe("a", r.ids[3])
    assert row.key == "k3" and row.metadata == {"timestamp": 103.0, "sequence": "a"}
    np.testing.assert_array_equal(row.T_map_sensor, items[3].T_map_sensor)
    np.testing.assert_array_equal(row.local_features, items[3].features.local_features)
    assert row.created_at.endswith("Z")
    with pytest.raises(NotFoundError):
        m.get_keyframe("a", 99)
    stats = m.stats("a")
    assert stats["keyframes"] == 5 and stats["version"] == 1 and stats["disk_bytes"] > 0
    assert stats["extent"] == {"min": [0.0, 0.0, 0.5], "max": [4.0, 8.0, 0.5]}


def test_keys_are_idempotent_and_ids_never_reused(
    managers: Factory, rng: np.random.Generator
) -> None:
    m = managers()
    m.create("a", SPEC)
    first = m.insert("a", _items(rng, 3, "k"))
    again = m.insert("a", _items(rng, 4, "k"))  # k0..k2 known, k3 new
    assert again.ids[:3] == first.ids and again.created == [False, False, False, True]
    assert again.map_version == first.map_version + 1
    assert m.insert("a", _items(rng, 2, "k")).map_version == again.map_version  # nothing new
    m.delete_keyframe("a", again.ids[3])
    later = m.insert("a", _items(rng, 1))
    assert later.ids[0] > again.ids[3]  # a deleted id is never handed out again


def test_filters_listing_and_bulk_delete(managers: Factory, rng: np.random.Generator) -> None:
    m = managers()
    m.create("a", SPEC)
    ids = m.insert("a", _items(rng, 6, "k")).ids
    page = m.list_keyframes("a", KeyframeFilter(), limit=4)
    assert [s.id for s in page] == ids[:4]
    assert [s.id for s in m.list_keyframes("a", KeyframeFilter(), after_id=ids[3])] == ids[4:]
    assert [s.id for s in m.list_keyframes("a", KeyframeFilter(bbox=(0.5, 1.0, 2.5, 4.0)))] == [
        ids[1],
        ids[2],
    ]
    assert [s.id for s in m.list_keyframes("a", KeyframeFilter(time_min=103.0))] == ids[3:]
    assert [s.id for s in m.list_keyframes("a", KeyframeFilter(time_max=100.5))] == ids[:1]
    assert [s.id for s in m.list_keyframes("a", KeyframeFilter(sequence="a"))] == ids[1::2]
    assert [s.id for s in m.list_keyframes("a", KeyframeFilter(key_prefix="k5"))] == ids[5:]
    deleted, version = m.delete_keyframes("a", KeyframeFilter(sequence="b", time_min=101.0))
    assert deleted == 2 and version == 2  # k2, k4: one transaction, one version
    assert m.delete_keyframes("a", KeyframeFilter(key_prefix="zz")) == (0, 2)
    assert m.get("a").num_keyframes == 4
    top = m.localize("a", features=_items(np.random.default_rng(0), 1)[0].features, top_k=10)
    assert {c.keyframe_id for c in top.retrieved} == {ids[0], ids[1], ids[3], ids[5]}


def test_everything_survives_a_restart(managers: Factory, rng: np.random.Generator) -> None:
    m = managers()
    m.create("a", SPEC)
    items = _items(rng, 5, "k")
    ids = m.insert("a", items).ids
    m.delete_keyframe("a", ids[0])
    m.update_settings("a", {"top_k": 3})
    answer = m.localize("a", features=items[2].features, rerank="none")
    m.close()
    m2 = managers()
    h = m2.get("a")
    assert h.version == 2 and h.num_keyframes == 4
    assert h.record.localizer_config.top_k == 3 and h.record.settings_version == 1
    again = m2.localize("a", features=items[2].features, rerank="none")
    assert [c.keyframe_id for c in again.retrieved] == [c.keyframe_id for c in answer.retrieved]
    assert m2.insert("a", _items(rng, 1)).ids == [6]


def test_a_self_test_runs_on_the_stored_map_and_its_summary_survives_a_restart(
    managers: Factory, rng: np.random.Generator
) -> None:
    m = managers()
    m.create("a", SPEC)
    items = _items(rng, 8)
    for i, it in enumerate(items):  # two passes over four places, a second apart
        it.T_map_sensor[:3, 3] = [10.0 * (i % 4), 0.0, 0.0]
    m.insert("a", items)
    m.update_settings("a", {"top_k": 3})
    version, plan = m.self_test_plan("a", queries=8, gap_s=3.0, gap_keyframes=1, radius_m=1.0)
    assert plan.basis == "timestamp" and len(plan.in_coverage) == 8
    recs = [m.self_test_query("a", version, plan, kf, 1.0) for kf in plan.in_coverage]
    summary = {"format": "test", "figures": {"queries": len(recs)}}
    m.record_self_test("a", summary)
    m.close()
    h = managers().get("a")
    assert h.record.last_self_test == summary
    assert h.record.localizer_config.top_k == 3 and h.record.settings_version == 2
    assert h.version == version  # the keyframes did not change


def test_a_self_test_encodes_the_stored_clouds_again_for_another_encoder(
    managers: Factory, rng: np.random.Generator
) -> None:
    """Comparing encoders, each keyframe's stored cloud is encoded again by the candidate
    (pose and id kept), also when clouds are fetched from the store per use; a map that
    keeps no clouds, one over the keyframe limit, or one that changed is refused."""
    m = managers()
    m.create("b", EncoderSpec(kind="bev"))
    items = []
    for i in range(6):
        T = np.eye(4)
        T[:3, 3] = [3.0 * i, 0.0, 0.0]
        pts = rng.uniform([-20, -20, 0], [20, 20, 3], (3000, 3)).astype(np.float32)
        items.append(KeyframeIn(T_map_sensor=T, points=pts, metadata={"timestamp": float(i)}))
    ids = m.insert("b", items).ids
    spec = {"kind": "handcrafted"}
    want = make_encoder(EncoderSpec(**spec))
    for manager in (m, managers(features_in_memory=False, feature_cache=2)):
        version = manager.get("b").version
        candidate = manager.self_test_candidate("b", version, spec, max_keyframes=6)
        assert manager.self_test_encode("b", version, candidate, ids) == 0
        for i in ids:
            stored = m.get("b").localizer.keyframe(i)
            kf = candidate.keyframe(i)
            np.testing.assert_array_equal(kf.T_map_sensor, stored.T_map_sensor)
            f = want.encode_cloud(want.prepare(stored.cloud))
            np.testing.assert_array_equal(kf.features.global_descriptor, f.global_descriptor)
            np.testing.assert_array_equal(kf.features.local_features, f.local_features)
    with pytest.raises(InputError, match="max_self_test_keyframes") as err:
        m.self_test_candidate("b", version, spec, max_keyframes=5)
    assert err.value.field == "encoders"
    m.insert("b", items[:1])
    with pytest.raises(ConflictError, match="changed during the self-test"):
        m.self_test_encode("b", version, candidate, ids)
    m.create("a", SPEC)
    with pytest.raises(InputError, match="keeps no keyframe clouds") as err:
        m.self_test_candidate("a", m.get("a").version, spec, max_keyframes=6)
    assert err.value.field == "encoders"


def test_replicas_settings_changes_never_undo_each_other(managers: Factory) -> None:
    """Two replicas of one shared store: a PATCH on one that the other has not followed
    yet is kept when the other PATCHes something else, and so is a self-test's record."""
    a = managers()
    if not a.shared:
        pytest.skip("one process per SQLite map folder: there are no replicas to race")
    a.create("m", SPEC)
    b = managers()  # loads the map as it is now; it follows nothing in this test
    a.update_settings("m", {"top_k": 7})
    b.update_settings("m", {"rerank": "none"})
    b.record_self_test("m", {"format": "test"})
    for m in (a, b):
        m.close()
    record = managers().get("m").record
    assert record.localizer_config.top_k == 7 and record.localizer_config.rerank == "none"
    assert record.last_self_test == {"format": "test"} and record.settings_version == 3


def test_a_replica_starts_past_a_deleted_map_and_waits_for_a_silent_store(
    managers: Factory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One map deleted by another replica between the catalog and its load, one the
    store does not answer for a moment: the start-up serves every other map, and is
    ready only once it serves them all (it stayed unready for good before)."""
    from sgvloc.server.store import StoreUnavailableError
    from sgvloc.server.store.postgres import PgBackend

    a = managers()
    if not a.shared:
        pytest.skip("one process per SQLite map folder: no other replica deletes a map")
    for name in ("m1", "m2", "m3"):
        a.create(name, SPEC)
    real_open = PgBackend.open
    silent = ["m1"]

    def racing_open(self, name):
        if name in silent:
            silent.remove(name)
            raise StoreUnavailableError("the store did not answer")
        if name == "m2":
            a.delete("m2")  # another replica, just now
        return real_open(self, name)

    monkeypatch.setattr(PgBackend, "open", racing_open)
    b = managers()
    assert b.loaded.is_set() and {h.name for h in b.list()} == {"m1", "m3"} and not b.failed


def test_a_follower_round_undoes_no_own_create_or_delete(
    managers: Factory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A map this replica makes while its follower reads the catalog is not dropped as
    deleted elsewhere, and one it deletes is not loaded back before the delete
    commits; a map that failed to load and was made again under its name is loaded."""
    from sgvloc.server.store.postgres import PgBackend

    a, b = managers(), managers()
    if not a.shared:
        pytest.skip("one process per SQLite map folder: no follower")
    real_catalog = PgBackend.catalog

    def creating_catalog(self):
        monkeypatch.setattr(PgBackend, "catalog", real_catalog)
        out = real_catalog(self)
        a.create("fresh", SPEC)  # a POST /v1/maps lands on a meanwhile
        return out

    monkeypatch.setattr(PgBackend, "catalog", creating_catalog)
    a.sync()
    assert a.get("fresh").name == "fresh"
    real_drop = PgBackend.drop

    def syncing_drop(self, store):
        a.sync()  # a follower round between delete's own steps
        return real_drop(self, store)

    monkeypatch.setattr(PgBackend, "drop", syncing_drop)
    a.delete("fresh")
    monkeypatch.setattr(PgBackend, "drop", real_drop)
    with pytest.raises(NotFoundError):
        a.get("fresh")
    # b fails to load a map (say its model file is missing there); it is made again
    a.create("m", SPEC)
    real_load = b._load_store

    def failing(store, folder, name):
        b._load_store = real_load
        raise RuntimeError("the encoder's model file is missing on this replica")

    b._load_store = failing
    b.sync()
    assert "m" in b.failed
    a.delete("m")
    a.create("m", SPEC)
    a.insert("m", _items(np.random.default_rng(3), 2))
    b.sync()
    assert b.get("m").num_keyframes == 2 and "m" not in b.failed


def test_delete_map_and_use_the_name_again(managers: Factory, rng: np.random.Generator) -> None:
    m = managers()
    m.create("a", SPEC)
    m.insert("a", _items(rng, 2))
    m.delete("a")
    with pytest.raises(NotFoundError):
        m.get("a")
    with pytest.raises(NotFoundError):
        m.delete("a")
    m.create("a", SPEC)
    assert m.get("a").num_keyframes == 0 and m.get("a").version == 0
    m.close()
    assert managers().get("a").num_keyframes == 0


def test_archive_round_trip(managers: Factory, rng: np.random.Generator) -> None:
    m = managers()
    m.create("a", SPEC)
    items = _items(rng, 5, "k")
    ids = m.insert("a", items).ids
    m.delete_keyframe("a", ids[1])
    m.delete_keyframe("a", ids[-1])  # the highest id: the copy must not give it again
    m.update_settings("a", {"top_k": 5})
    with m.export_archive("a") as blocks:
        data = b"".join(blocks)
    h = m.import_archive(io.BytesIO(data), "b")
    assert h.version == 3 and m.get("b").num_keyframes == 3
    assert h.record.settings_version == 1 and h.record.localizer_config.top_k == 5
    with pytest.raises(ConflictError):
        m.import_archive(io.BytesIO(data), "b")
    assert [s.id for s in m.list_keyframes("b", KeyframeFilter())] == [ids[0], *ids[2:4]]
    assert m.get_keyframe("b", ids[2]).key == "k2"
    assert (
        m.insert("b", _items(rng, 1)).ids[0] == ids[-1] + 1 == m.insert("a", _items(rng, 1)).ids[0]
    )
    # a map whose keyframes were all deleted keeps its version and next id too
    m.create("c", SPEC)
    gone = m.insert("c", _items(rng, 2)).ids
    m.delete_keyframes("c", KeyframeFilter(key_prefix=None, sequence="a"))
    m.delete_keyframes("c", KeyframeFilter(sequence="b"))
    with m.export_archive("c") as blocks:
        empty = m.import_archive(io.BytesIO(b"".join(blocks)), "d")
    assert empty.num_keyframes == 0 and empty.version == 3
    assert m.insert("d", _items(rng, 1)).ids[0] == gone[-1] + 1
    m.close()
    assert {h.name for h in managers().list()} == {"a", "b", "c", "d"}


def test_features_fetched_from_the_store_give_the_same_answers(
    managers: Factory, rng: np.random.Generator
) -> None:
    """A manager that keeps only poses and global descriptors in memory (local features
    and clouds fetched per query through its cache) answers exactly as one that holds
    everything, also for keyframes written after it loaded."""
    m = managers()
    m.create("a", SPEC)
    items = _items(rng, 12)
    m.insert("a", items[:8])
    slim = managers(features_in_memory=False, feature_cache=4)
    assert slim.get("a").localizer.memory_bytes() < m.get("a").localizer.memory_bytes() / 4
    slim.insert("a", items[8:])  # written through the slim manager
    m.close()
    full = managers()
    for item in items[::3]:
        want = full.localize("a", features=item.features, top_k=6, rerank="sgv")
        got = slim.localize("a", features=item.features, top_k=6, rerank="sgv")
        assert got.keyframe_id == want.keyframe_id
        assert [c.keyframe_id for c in got.reranked] == [c.keyframe_id for c in want.reranked]
        assert got.confidence == pytest.approx(want.confidence, abs=1e-12)
        assert "fetch" in got.timings_ms and "fetch" not in want.timings_ms
    source = slim.get("a").localizer.keyframe_source
    assert source is not None and len(source) <= 4 and source.misses > 0
