"""The map manager and its SQLite store, in process: snapshots, rebuilds, rollback."""

from __future__ import annotations

import json
import logging
import shutil
import sqlite3
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from svc_helpers import feature_keyframes

from sgvloc.core.config import LocalizerConfig
from sgvloc.core.encoders import EncoderSpec
from sgvloc.core.errors import ConflictError, InputError, NotFoundError
from sgvloc.core.retrieval import FaissIndex
from sgvloc.server.maps import FeaturesIn, KeyframeIn, MapManager
from sgvloc.server.store import KeyframeFilter, SqliteMapStore

SPEC = EncoderSpec(kind="precomputed", name="egonn", global_dim=16, local_dim=8)


def _items(rng: np.random.Generator, n: int, key_prefix: str | None = None) -> list[KeyframeIn]:
    return feature_keyframes(rng, n, key_prefix, {"sequence": "s"})


def _manager(root: Path, **kwargs) -> MapManager:
    m = MapManager(root / "maps", **kwargs)
    m.load_all()
    return m


def _top_ids(m: MapManager, name: str, query: FeaturesIn) -> list[int]:
    res = m.localize(name, features=query, top_k=10, rerank="none")
    return [c.keyframe_id for c in res.retrieved]


def test_restore_uses_agreeing_snapshot(tmp_path: Path, caplog) -> None:
    rng = np.random.default_rng(0)
    m = _manager(tmp_path)
    m.create("a", SPEC)
    items = _items(rng, 6)
    ids = m.insert("a", items).ids
    m.delete_keyframe("a", ids[2])
    answer = _top_ids(m, "a", items[0].features)
    m.close()

    with caplog.at_level(logging.INFO, logger="sgvloc.server.maps"):
        m2 = _manager(tmp_path)
    assert "map 'a': using index snapshot (5 ids)" in caplog.text
    h = m2.get("a")
    assert h.localizer.keyframe_ids() == [i for i in ids if i != ids[2]]
    assert h.version == 2 and _top_ids(m2, "a", items[0].features) == answer
    m2.close()


def test_missing_stale_or_damaged_snapshot_is_rebuilt(tmp_path: Path, caplog) -> None:
    rng = np.random.default_rng(1)
    m = _manager(tmp_path)
    m.create("a", SPEC)
    items = _items(rng, 4)
    m.insert("a", items[:2])
    index_path = tmp_path / "maps" / "a" / "index.faiss"
    m.snapshot("a")
    shutil.copy(index_path, tmp_path / "stale.faiss")
    m.insert("a", items[2:])
    answer = _top_ids(m, "a", items[3].features)
    m.close()

    cases = {
        "stale": lambda: shutil.copy(tmp_path / "stale.faiss", index_path),
        "missing": lambda: index_path.unlink(),
        "damaged": lambda: index_path.write_bytes(b"not an index"),
    }
    expected = {
        "stale": "disagrees with the store",
        "missing": "no index snapshot",
        "damaged": "unreadable",
    }
    for case, damage in cases.items():
        damage()
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="sgvloc.server.maps"):
            m2 = _manager(tmp_path)
        assert expected[case] in caplog.text, case
        assert _top_ids(m2, "a", items[3].features) == answer
        m2.close()
        # the rebuilt index was saved again and agrees with the store now
        assert FaissIndex.load(index_path).ids().tolist() == [1, 2, 3, 4]


def test_failed_in_memory_insert_leaves_nothing(tmp_path: Path, monkeypatch) -> None:
    rng = np.random.default_rng(2)
    m = _manager(tmp_path)
    h = m.create("a", SPEC)
    m.insert("a", _items(rng, 2, "k"))

    def broken(kfs):
        raise RuntimeError("simulated FAISS failure")

    monkeypatch.setattr(h.localizer, "add_keyframes", broken)
    with pytest.raises(RuntimeError):
        m.insert("a", _items(rng, 3, "new"))
    monkeypatch.undo()
    with h.store.snapshot() as (version, count, _):
        assert count == 2 and version == 1 and h.version == 1
    assert h.store.find_keys(["new0", "new1", "new2"]) == {}
    # the map keeps working and both version counters stay equal
    res = m.insert("a", _items(rng, 3, "new"))
    with h.store.snapshot() as (version, count, _):
        assert res.created == [True] * 3 and res.map_version == 2 == version
        assert len(h.localizer) == count == 5
    m.close()


def test_encoder_fingerprint_change_refuses_the_map(tmp_path: Path) -> None:
    m = _manager(tmp_path)
    m.create("a", SPEC)
    m.create("b", SPEC)
    m.close()
    db = tmp_path / "maps" / "a" / "map.sqlite"
    with sqlite3.connect(db) as conn:
        conn.execute("UPDATE meta SET value = 'deadbeef' WHERE key = 'encoder_fingerprint'")
    m2 = _manager(tmp_path)
    assert [h.name for h in m2.list()] == ["b"]
    assert "fingerprint" in m2.failed["a"]
    with pytest.raises(ConflictError):
        m2.create("a", SPEC)
    m2.close()


def test_names_leftovers_and_deletion(tmp_path: Path) -> None:
    m = _manager(tmp_path)
    with pytest.raises(InputError):
        m.create("../evil", SPEC)
    m.create("a", SPEC)
    with pytest.raises(ConflictError):
        m.create("a", SPEC)
    m.close()
    leftover = tmp_path / "maps" / ".tmp-b-1234"
    leftover.mkdir()
    spooled = tmp_path / "maps" / ".tmp-import-1a2b3c4d-xyz"  # an upload a crash left
    spooled.write_bytes(b"part of an archive")
    m2 = _manager(tmp_path)
    assert not leftover.exists() and not spooled.exists()
    m2.delete("a")
    assert not (tmp_path / "maps" / "a").exists()
    with pytest.raises(NotFoundError):
        m2.get("a")
    m2.close()


def test_snapshot_after_n_changes_and_after_delay(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    m = _manager(tmp_path, snapshot_every=3, snapshot_delay_s=0.2)
    m.create("a", SPEC)
    index_path = tmp_path / "maps" / "a" / "index.faiss"
    m.insert("a", _items(rng, 3))  # reaches snapshot_every: saved at once
    assert FaissIndex.load(index_path).ids().tolist() == [1, 2, 3]
    for _ in range(7):  # one by one to 10: saved at 6 (3 changes, half the map); at 10,
        m.insert("a", _items(rng, 1))  # 4 changes are fewer than half of 10
    assert m.get("a").unsaved == 4 and len(FaissIndex.load(index_path).ids()) == 6
    m.start_snapshotter()
    m.insert("a", _items(rng, 1))  # saved by the background thread
    deadline = time.monotonic() + 30
    while FaissIndex.load(index_path).ids().tolist() != list(range(1, 12)):
        assert time.monotonic() < deadline, "the snapshot thread never saved the change"
        time.sleep(0.05)
    m.close()


def test_failed_snapshots_back_off(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A snapshot that cannot be written (here its path is a folder) is retried after a
    growing pause, logged as an ERROR once and then as WARNINGs, not on every tick."""
    rng = np.random.default_rng(5)
    m = _manager(tmp_path, snapshot_every=1000, snapshot_delay_s=0.04)
    m.create("a", SPEC)
    index_path = tmp_path / "maps" / "a" / "index.faiss"
    index_path.unlink()
    index_path.mkdir()  # every save fails now
    m.insert("a", _items(rng, 1))
    with caplog.at_level(logging.WARNING, logger="sgvloc.server.maps"):
        m.start_snapshotter()
        time.sleep(1.0)  # 100 ticks of the snapshot thread
        handle = m.get("a")
        assert handle.snapshot_failures == 1 and handle.unsaved == 1
        assert handle.snapshot_retry_at > time.monotonic() + 5  # the next try in ~10 s
        fails = [r for r in caplog.records if "saving the index snapshot failed" in r.message]
        assert [r.levelname for r in fails] == ["ERROR"]
        index_path.rmdir()
        handle.snapshot_retry_at = 0.0  # as if the pause had passed
        deadline = time.monotonic() + 30
        while handle.unsaved:
            assert time.monotonic() < deadline, "the snapshot was never saved again"
            time.sleep(0.05)
    assert handle.snapshot_failures == 0 and FaissIndex.load(index_path).ids().tolist() == [1]
    m.close()


def test_store_round_trip(tmp_path: Path) -> None:
    """Arrays keep dtype and shape; ids are never reused after a delete."""
    rng = np.random.default_rng(4)
    m = _manager(tmp_path)
    h = m.create("a", SPEC)
    items = _items(rng, 3, "k")
    ids = m.insert("a", items).ids
    m.delete_keyframe("a", ids[-1])
    new_id = m.insert("a", _items(rng, 1)).ids[0]
    assert new_id > ids[-1]
    row = h.store.get(ids[0])
    assert row.key == "k0" and row.metadata == {"sequence": "s"}
    assert row.T_map_sensor.dtype == np.float64 and row.T_map_sensor.shape == (4, 4)
    assert row.keypoints.dtype == np.float32 and row.keypoints.shape == (64, 3)
    np.testing.assert_array_equal(row.keypoints, items[0].features.keypoints)
    m.close()
    store = SqliteMapStore.open(tmp_path / "maps" / "a" / "map.sqlite")
    with store.snapshot() as (version, count, rows):
        assert [r.id for r in rows] == [ids[0], ids[1], new_id] and version == count == 3
    with sqlite3.connect(store.path) as conn:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    store.close()


def test_a_closed_store_says_so_and_a_snapshot_reads_only_its_own_map(tmp_path: Path) -> None:
    """Every call on a store closed meanwhile (its map deleted) raises StoreClosedError,
    which the service answers 404; a snapshot of a map whose file was replaced by a new
    map of the same name refuses rather than stream the other map's rows."""
    from sgvloc.server.store import StoreClosedError

    rng = np.random.default_rng(6)
    m = _manager(tmp_path)
    m.create("a", SPEC)
    m.insert("a", _items(rng, 2, "k"))
    store = m.get("a").store
    m.close()
    calls = [
        store.record,
        store.extent,
        store.last_write,
        lambda: store.get(1),
        lambda: store.fetch([1]),
        lambda: store.find_keys(["k0"]),
        lambda: store.select(KeyframeFilter(key_prefix="k")),
        lambda: store.matching_ids(KeyframeFilter(key_prefix="k")),
        lambda: store.delete([1]),
    ]
    for call in calls:
        with pytest.raises(StoreClosedError, match="'a' was deleted or unloaded"):
            call()
    with pytest.raises(StoreClosedError), store.snapshot():
        pass

    path = tmp_path / "maps" / "a" / "map.sqlite"
    old = SqliteMapStore.open(path)
    shutil.rmtree(path.parent)  # the map deleted, and one made again under its name
    m = _manager(tmp_path)
    m.create("a", SPEC)
    m.close()
    with pytest.raises(StoreClosedError), old.snapshot():
        pass
    old.close()


def test_the_snapshot_thread_survives_a_map_deleted_under_it(tmp_path: Path) -> None:
    """A map deleted between the thread's listing and its save ended the thread: no
    other map was saved after its delay any more."""
    rng = np.random.default_rng(8)
    m = _manager(tmp_path, snapshot_delay_s=0.2, snapshot_every=1000)
    m.create("x", SPEC)
    m.create("y", SPEC)
    m.insert("x", _items(rng, 2, "x"))
    real_list = m.list

    def racing_list():
        handles = real_list()
        if any(h.name == "x" and h.unsaved_since is not None for h in handles):
            if time.monotonic() - m.get("x").unsaved_since >= 0.2:
                m.list = real_list
                m.delete("x")  # DELETE /v1/maps/x between the listing and the save
        return handles

    m.list = racing_list
    m.start_snapshotter()
    deadline = time.monotonic() + 10
    while m.list is racing_list and time.monotonic() < deadline:
        time.sleep(0.05)
    m.insert("y", _items(rng, 1, "y"))
    while m.get("y").unsaved and time.monotonic() < deadline:
        time.sleep(0.05)
    assert m.get("y").unsaved == 0 and m._snapshotter.is_alive()
    m.close()


def test_schema_1_is_migrated_on_open(tmp_path: Path) -> None:
    """A map stored before positions had columns (schema 1) is migrated when loaded:
    its extent and bounding-box filters then work, nothing else changes."""
    rng = np.random.default_rng(5)
    m = _manager(tmp_path)
    m.create("old", SPEC)
    ids = m.insert("old", _items(rng, 4, "k")).ids
    m.close()
    db = tmp_path / "maps" / "old" / "map.sqlite"
    with sqlite3.connect(db) as conn:  # back to schema 1, as earlier releases wrote it
        for column in ("x", "y", "z"):
            conn.execute(f"ALTER TABLE keyframes DROP COLUMN {column}")
        conn.execute("UPDATE meta SET value = '1' WHERE key = 'schema_version'")

    m = _manager(tmp_path)
    assert m.failed == {} and m.get("old").version == 1
    store = m.get("old").store
    assert store.extent() == ([0.0, 0.0, 0.0], [3.0, 0.0, 0.0])
    inside = store.select(KeyframeFilter(bbox=(0.5, -1.0, 2.5, 1.0)))
    assert [r.id for r in inside] == ids[1:3]
    m.close()
    with sqlite3.connect(db) as conn:
        assert conn.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone() == (
            "2",
        )

    with sqlite3.connect(db) as conn:  # a schema from the future is refused, not guessed at
        conn.execute("UPDATE meta SET value = '99' WHERE key = 'schema_version'")
    m = _manager(tmp_path)
    assert "schema version 99 is newer than this sgvloc" in m.failed["old"]
    m.close()
    with sqlite3.connect(db) as conn:  # and one that is no version at all is named as such
        conn.execute("UPDATE meta SET value = 'x' WHERE key = 'schema_version'")
    m = _manager(tmp_path)
    assert "unknown schema version 'x'" in m.failed["old"]
    m.close()


def test_a_map_stored_before_a_setting_existed_keeps_its_answers(tmp_path: Path) -> None:
    """A setting added since a map was stored takes the value that keeps the map
    answering as it did, not the default of new maps; the next write stores it."""
    m = _manager(tmp_path)
    m.create("old", SPEC)
    m.create("new", SPEC)
    m.close()
    db = tmp_path / "maps" / "old" / "map.sqlite"
    with sqlite3.connect(db) as conn:  # as a release before these settings wrote it
        (text,) = conn.execute("SELECT value FROM meta WHERE key = 'localizer_config'").fetchone()
        stored = json.loads(text)
        del stored["sgv"]["tie_tolerance"]
        del stored["sgv"]["tie_gain_m"]
        del stored["retrieval"]["offset_m"]
        del stored["pose"]["min_icp_constraint"]
        del stored["pose"]["icp_coarse_m"]
        del stored["tracking"]["min_conditioning"]
        for key in ("ransac_first_batch", "icp_backend", "icp_method", "icp_source_voxel_m"):
            del stored["pose"][key]
        conn.execute(
            "UPDATE meta SET value = ? WHERE key = 'localizer_config'", (json.dumps(stored),)
        )

    m = _manager(tmp_path)
    assert m.failed == {}
    assert m.get("old").record.localizer_config.sgv.tie_tolerance == 0.0
    fresh = LocalizerConfig().sgv.tie_tolerance
    assert m.get("new").record.localizer_config.sgv.tie_tolerance == fresh > 0
    assert m.get("old").record.localizer_config.sgv.tie_gain_m == 1.0
    assert m.get("new").record.localizer_config.sgv.tie_gain_m == 0.0
    assert m.get("old").record.localizer_config.retrieval.offset_m == 0.0
    assert m.get("new").record.localizer_config.retrieval.offset_m == 4.0
    assert m.get("old").record.localizer_config.pose.min_icp_constraint == 0.0
    assert m.get("new").record.localizer_config.pose.min_icp_constraint == 0.035
    assert m.get("old").record.localizer_config.pose.icp_coarse_m == 0.0
    assert m.get("new").record.localizer_config.pose.icp_coarse_m == 3.0
    assert m.get("old").record.localizer_config.tracking.min_conditioning is None
    assert m.get("new").record.localizer_config.tracking.min_conditioning == -1.4
    # the RANSAC batches and ICP of the releases before these settings
    old, new = m.get("old").record.localizer_config.pose, m.get("new").record.localizer_config.pose
    assert (old.ransac_first_batch, new.ransac_first_batch) == (1000, 64)
    assert (old.icp_backend, new.icp_backend) == ("open3d", "numba")
    assert (old.icp_method, new.icp_method) == ("point_to_point", "point_to_plane")
    assert (old.icp_source_voxel_m, new.icp_source_voxel_m) == (0.0, 0.6)
    m.update_settings("old", {"top_k": 7})  # written back whole, the old value with it
    m.close()
    with sqlite3.connect(db) as conn:
        (text,) = conn.execute("SELECT value FROM meta WHERE key = 'localizer_config'").fetchone()
    assert json.loads(text)["sgv"]["tie_tolerance"] == 0.0 and json.loads(text)["top_k"] == 7
    assert json.loads(text)["retrieval"]["offset_m"] == 0.0
    assert json.loads(text)["pose"]["min_icp_constraint"] == 0.0
    assert json.loads(text)["pose"]["icp_coarse_m"] == 0.0


def test_the_documented_patch_gives_a_stored_map_every_current_default(tmp_path: Path) -> None:
    """OPERATIONS.md's "every current default at once" PATCH, on a map stored before
    every added setting, leaves it with the settings of a new map."""
    import re

    from sgvloc.core.config import ADDED_SETTINGS

    doc = (Path(__file__).parents[2] / "docs" / "OPERATIONS.md").read_text()
    after = doc[doc.index("every current default at") :]
    body = json.loads(re.search(r"-d '(\{.*?\})'", after, re.S).group(1))
    m = _manager(tmp_path)
    m.create("old", SPEC)
    m.close()
    db = tmp_path / "maps" / "old" / "map.sqlite"
    with sqlite3.connect(db) as conn:  # none of the added settings stored
        (text,) = conn.execute("SELECT value FROM meta WHERE key = 'localizer_config'").fetchone()
        stored = json.loads(text)
        for section, key in ADDED_SETTINGS:
            del stored[section][key]
        stored["pose"]["min_icp_fitness"] = 0.5  # an earlier default
        conn.execute(
            "UPDATE meta SET value = ? WHERE key = 'localizer_config'", (json.dumps(stored),)
        )
    m = _manager(tmp_path)
    try:
        assert m.get("old").record.localizer_config != LocalizerConfig()
        m.update_settings("old", body["localizer"])
        assert m.get("old").record.localizer_config == LocalizerConfig()
    finally:
        m.close()


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine runs CUDA settings")
def test_a_patch_that_leaves_sgv_alone_is_not_refused_for_it(tmp_path: Path) -> None:
    """A map whose stored settings ask for SGV on CUDA (made on a GPU machine) loads on a
    CPU-only one, and a PATCH of other settings goes through; one that sets SGV to what
    this machine cannot run is refused naming localizer.sgv."""
    m = _manager(tmp_path)
    m.create("gpu", SPEC)
    m.close()
    db = tmp_path / "maps" / "gpu" / "map.sqlite"
    with sqlite3.connect(db) as conn:
        (text,) = conn.execute("SELECT value FROM meta WHERE key = 'localizer_config'").fetchone()
        stored = json.loads(text)
        stored["sgv"]["device"] = "cuda"
        conn.execute(
            "UPDATE meta SET value = ? WHERE key = 'localizer_config'", (json.dumps(stored),)
        )
    m = _manager(tmp_path)
    assert m.failed == {}
    assert m.update_settings("gpu", {"top_k": 7}).record.localizer_config.top_k == 7
    with pytest.raises(InputError, match="CUDA") as err:
        m.update_settings("gpu", {"sgv": {"backend": "numba"}})
    assert err.value.field == "localizer.sgv"
    assert (
        m.update_settings("gpu", {"sgv": {"device": "cpu"}}).record.localizer_config.sgv.device
        == "cpu"
    )
    m.close()


def test_a_reload_while_a_map_is_deleted_does_not_load_it_back(tmp_path: Path) -> None:
    """The delete waits for the map's write lock (an insert or snapshot holds it); a
    reload meanwhile must not load the folder about to be removed, which would serve a
    map whose acknowledged inserts vanish at the next restart."""
    import threading

    rng = np.random.default_rng(0)
    m = _manager(tmp_path)
    m.create("m", SPEC)
    m.insert("m", _items(rng, 3))
    handle = m.get("m")
    handle.write_lock.acquire()  # a write under way
    deleting = threading.Thread(target=m.delete, args=("m",))
    deleting.start()
    deadline = time.monotonic() + 10
    while "m" in [h.name for h in m.list()] and time.monotonic() < deadline:
        time.sleep(0.01)
    with pytest.raises(ConflictError, match="deleted"):
        m.reload("m")
    handle.write_lock.release()
    deleting.join()
    assert m.list() == [] and not (m.maps_dir / "m").exists()
    with pytest.raises(NotFoundError):
        m.insert("m", _items(rng, 1))
    m.close()


def test_a_damaged_row_names_its_keyframe_and_other_maps_load(tmp_path: Path) -> None:
    """A row the store cannot decode, or one whose pose is not a pose, keeps its map
    from loading with a message naming the keyframe and what is wrong with it (not
    numpy's advice to unpickle it); the other maps are served."""
    import sqlite3

    from sgvloc.server.store.base import array_to_blob

    rng = np.random.default_rng(4)
    m = _manager(tmp_path)
    ids = {}
    for name in ("garbled", "nan-pose", "good"):
        m.create(name, SPEC)
        ids[name] = m.insert(name, _items(rng, 4)).ids
    m.close()
    damage = {
        "garbled": ("global_descriptor", b"\x93NUMPY garbage"),
        "nan-pose": ("T_map_sensor", array_to_blob(np.full((4, 4), np.nan))),
    }
    for name, (column, blob) in damage.items():
        with sqlite3.connect(tmp_path / "maps" / name / "map.sqlite") as db:
            db.execute(f"UPDATE keyframes SET {column} = ? WHERE id = ?", (blob, ids[name][2]))
    m = _manager(tmp_path)
    try:
        assert set(m.failed) == {"garbled", "nan-pose"}
        for name, (column, _) in damage.items():
            why = m.failed[name]
            assert f"keyframe {ids[name][2]}" in why and column in why, why
            assert "pickle" not in why
        assert m.get("good").num_keyframes == 4
    finally:
        m.close()


def test_the_open_file_limit_is_raised_and_running_out_is_said(tmp_path: Path) -> None:
    """Each SQLite map keeps files open: serve raises the soft open-file limit to the
    hard one, and a map database that cannot be opened for want of file descriptors is
    a 503-class store error naming the limit, not a 500 "unable to open database file".
    (In a child process: the limits are the process's.)"""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent(
        f"""
        import resource
        from pathlib import Path
        from sgvloc.server.run import raise_open_files_limit
        from sgvloc.server.store import StoreUnavailableError
        from sgvloc.server.store.sqlite import SqliteMapStore

        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        resource.setrlimit(resource.RLIMIT_NOFILE, (64, hard))
        assert raise_open_files_limit() == resource.getrlimit(resource.RLIMIT_NOFILE)[0] > 64
        resource.setrlimit(resource.RLIMIT_NOFILE, (64, hard))
        kept = []
        try:
            for i in range(200):
                kept.append(SqliteMapStore._connect(Path({str(tmp_path)!r}) / f"m{{i}}.sqlite"))
        except StoreUnavailableError as exc:
            assert "limit 64" in str(exc), exc
            print("refused after", len(kept))
        """
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.startswith("refused after"), run.stderr


def test_deletes_give_space_back_to_the_file_system(tmp_path: Path, monkeypatch) -> None:
    """A map's database gives the space of deleted keyframes back once enough is free
    (incremental auto-vacuum), keeping every other keyframe; a database made without it
    (an older release) keeps its size and deletes as before."""
    import sgvloc.server.store.sqlite as sqlite_store

    monkeypatch.setattr(sqlite_store, "GIVE_BACK_MIN_BYTES", 256 << 10)
    monkeypatch.setattr(sqlite_store, "_VACUUM_STEP_PAGES", 64)  # several steps
    rng = np.random.default_rng(11)
    m = _manager(tmp_path)
    m.create("a", SPEC)
    m.insert("a", _items(rng, 1500, key_prefix="k"))
    db = tmp_path / "maps" / "a" / "map.sqlite"

    def pages() -> int:
        with sqlite3.connect(db) as c:
            return int(c.execute("PRAGMA page_count").fetchone()[0])

    full = pages()
    # a small delete leaves its space for the next inserts
    m.delete_keyframes("a", KeyframeFilter(key_prefix="k1499"))
    assert pages() == full
    deleted, _ = m.delete_keyframes("a", KeyframeFilter(key_prefix="k1"))  # k1, k10.., k1xxx
    assert deleted == 610
    assert pages() < 0.7 * full, (pages(), full)
    with sqlite3.connect(db) as c:
        assert c.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        assert c.execute("PRAGMA freelist_count").fetchone()[0] == 0
    kept = sorted(r.key for r in m.list_keyframes("a", KeyframeFilter(), after_id=0, limit=2000))
    assert len(kept) == 889 and "k2" in kept and "k1" not in kept
    m.close()
    m = _manager(tmp_path)  # and it opens again with the same keyframes
    assert m.get("a").localizer.keyframe_ids() == sorted(
        r.id for r in m.list_keyframes("a", KeyframeFilter(), after_id=0, limit=2000)
    )
    assert len(m.get("a").localizer.keyframe_ids()) == 889

    m.create("old", SPEC)
    m.insert("old", _items(rng, 1000, key_prefix="k"))
    m.close()
    old = tmp_path / "maps" / "old" / "map.sqlite"
    with sqlite3.connect(old) as c:  # as a map made before auto-vacuum came
        c.execute("PRAGMA auto_vacuum=NONE")
        c.execute("VACUUM")
        size = int(c.execute("PRAGMA page_count").fetchone()[0])
    m = _manager(tmp_path)
    deleted, _ = m.delete_keyframes("old", KeyframeFilter(key_prefix="k1"))
    assert deleted == 111
    with sqlite3.connect(old) as c:
        assert int(c.execute("PRAGMA page_count").fetchone()[0]) == size
        assert int(c.execute("PRAGMA freelist_count").fetchone()[0]) > 0
    m.close()
