"""Following a shared PostgreSQL store, in process: two map managers (two replicas' views)
on one real database, and the cases the HTTP tests do not reach cheaply."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import psycopg
import pytest
from svc_helpers import feature_keyframes

from sgvloc.core.encoders import EncoderSpec
from sgvloc.core.errors import NotFoundError
from sgvloc.server.maps import MapManager
from sgvloc.server.store import StoreError, StoreUnavailableError, open_backend
from sgvloc.server.store.postgres import redact

SPEC = EncoderSpec(kind="precomputed", name="egonn", global_dim=16, local_dim=8)


@pytest.fixture
def url(postgres) -> str:
    return postgres.new_database()


@pytest.fixture
def pair(url: str, tmp_path: Path) -> Iterator[tuple[MapManager, MapManager]]:
    """Two managers on one database; neither runs the follower thread (``sync`` is
    called by the tests, so every step is deterministic)."""
    managers = [MapManager(tmp_path / n, backend=open_backend(url)) for n in "ab"]
    for m in managers:
        m.load_all()
    yield managers[0], managers[1]
    for m in managers:
        m.close()


def test_sync_applies_every_kind_of_change(
    pair: tuple[MapManager, MapManager], rng: np.random.Generator
) -> None:
    a, b = pair
    a.create("m", SPEC)
    b.sync()
    assert b.get("m").version == 0
    ids = a.insert("m", feature_keyframes(rng, 4, "k")).ids
    a.delete_keyframe("m", ids[1])
    a.update_settings("m", {"top_k": 2})
    b.sync()
    hb = b.get("m")
    assert hb.version == 2 and hb.localizer.keyframe_ids() == [ids[0], ids[2], ids[3]]
    assert hb.record.localizer_config.top_k == 2 and hb.localizer.config.top_k == 2
    # deleted and made again under the same name: b drops its copy and loads the new map
    a.delete("m")
    a.create("m", SPEC)
    a.insert("m", feature_keyframes(rng, 1, "z"))
    b.sync()
    assert b.get("m").num_keyframes == 1 and b.get("m").version == 1
    a.delete("m")
    b.sync()
    with pytest.raises(NotFoundError):
        b.get("m")


def test_a_replica_behind_the_pruned_feed_reloads_the_map(
    pair: tuple[MapManager, MapManager], url: str, rng: np.random.Generator
) -> None:
    a, b = pair
    a.create("m", SPEC)
    b.sync()
    for k in range(3):
        a.insert("m", feature_keyframes(rng, 2, f"p{k}-"))
    with psycopg.connect(url, autocommit=True) as conn:
        conn.execute("DELETE FROM sgvloc_changes WHERE version <= 2")  # as pruning does
    b.sync()
    hb = b.get("m")
    assert hb.version == 3 and hb.localizer.keyframe_ids() == a.get("m").localizer.keyframe_ids()


def test_writes_on_both_keep_both_in_step(
    pair: tuple[MapManager, MapManager], rng: np.random.Generator
) -> None:
    """A replica writing after another's unseen write applies that write first."""
    a, b = pair
    a.create("m", SPEC)
    b.sync()
    ra = a.insert("m", feature_keyframes(rng, 2, "a"))
    rb = b.insert("m", feature_keyframes(rng, 2, "b"))  # b has not synced: it catches up first
    assert rb.map_version == ra.map_version + 1
    hb = b.get("m")
    assert hb.version == rb.map_version and hb.localizer.keyframe_ids() == ra.ids + rb.ids
    a.sync()
    assert a.get("m").localizer.keyframe_ids() == ra.ids + rb.ids


def test_start_up_waits_for_the_store(postgres, tmp_path: Path) -> None:
    """A replica started while PostgreSQL is down is not ready until it can load."""
    if postgres.cluster is None:
        pytest.skip("needs the throwaway cluster (SGVLOC_TEST_PG_URL names an outside server)")
    url = postgres.new_database()
    seed = MapManager(tmp_path / "seed", backend=open_backend(url))
    seed.load_all()
    seed.create("m", SPEC)
    seed.close()
    postgres.cluster.stop()
    m = MapManager(tmp_path / "late", backend=open_backend(url))
    try:
        loader = threading.Thread(target=m.load_all)
        loader.start()
        time.sleep(2.0)
        assert not m.loaded.is_set()
        with pytest.raises(StoreUnavailableError):
            m.create("n", SPEC)  # a write meanwhile fails fast, naming the store
    finally:
        postgres.cluster.start()
    loader.join(timeout=60)
    try:
        assert m.loaded.is_set() and m.get("m").version == 0
    finally:
        m.close()


def test_store_urls_and_passwords(tmp_path: Path) -> None:
    assert redact("postgresql://u:secret@h:5/db") == "postgresql://u:***@h:5/db"
    assert redact("postgresql://u@h/db") == "postgresql://u@h/db"
    with pytest.raises(StoreError, match="postgresql://"):
        open_backend("mysql://x")
    with pytest.raises(StoreError, match="password file"):
        open_backend("postgresql://u@h/db", password_file=tmp_path / "missing")
