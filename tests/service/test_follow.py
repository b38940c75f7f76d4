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
from sgvloc.core.errors import ConflictError, NotFoundError
from sgvloc.server.maps import MapManager, MapUnavailableError
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


def test_start_up_waits_for_the_store(postgres, tmp_path: Path, caplog) -> None:
    """A replica started while PostgreSQL is down is not ready until it can load; one
    stopped while it waits says it stops unready (it logged "ready" then)."""
    from sgvloc.server.api.main import _load_maps

    if postgres.cluster is None:
        pytest.skip("needs the throwaway cluster (SGVLOC_TEST_PG_URL names an outside server)")
    url = postgres.new_database()
    seed = MapManager(tmp_path / "seed", backend=open_backend(url))
    seed.load_all()
    seed.create("m", SPEC)
    seed.close()
    postgres.cluster.stop()
    m = MapManager(tmp_path / "late", backend=open_backend(url))
    stopped = MapManager(tmp_path / "stopped", backend=open_backend(url))
    try:
        loader = threading.Thread(target=m.load_all)
        loader.start()
        quitter = threading.Thread(target=_load_maps, args=(stopped,))
        quitter.start()
        time.sleep(2.0)
        assert not m.loaded.is_set()
        with pytest.raises(StoreUnavailableError):
            m.create("n", SPEC)  # a write meanwhile fails fast, naming the store
        with caplog.at_level("INFO", logger="sgvloc"):
            stopped.stop_loading()
            quitter.join(timeout=30)
        assert not quitter.is_alive() and not stopped.loaded.is_set()
        assert "stopping: not ready (0 map(s) loaded)" in caplog.text
        assert "ready: " not in caplog.text.replace("not ready", "")
    finally:
        stopped.close()
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


def test_one_map_that_cannot_catch_up_holds_back_no_other(
    pair: tuple[MapManager, MapManager], url: str, rng: np.random.Generator
) -> None:
    """Settings this replica cannot read (written by a newer version, say) fail that map's
    catch-up and the round, but every other map is followed all the same."""
    import json

    a, b = pair
    a.create("one", SPEC)
    a.create("two", SPEC)
    b.sync()
    with psycopg.connect(url) as conn:
        meta = conn.execute("SELECT meta FROM sgvloc_maps WHERE name = 'one'").fetchone()[0]
        cfg = json.loads(meta["localizer_config"])
        cfg["pose"]["a_newer_setting"] = 1
        conn.execute(
            "UPDATE sgvloc_maps SET meta = meta || %s::jsonb, "
            "settings_version = settings_version + 1 WHERE name = 'one'",
            (json.dumps({"localizer_config": json.dumps(cfg)}),),
        )
    a.create("three", SPEC)
    version = a.insert("two", feature_keyframes(rng, 3, "t")).map_version
    with pytest.raises(StoreError, match="map 'one'"):
        b.sync()
    assert sorted(h.name for h in b.list()) == ["one", "three", "two"]
    assert b.get("two").version == version


def test_a_write_waits_for_a_lock_held_elsewhere_only_so_long(
    url: str, tmp_path: Path, rng: np.random.Generator
) -> None:
    """Another session holding the map's row lock (a replica stuck mid-write) fails the
    write with StoreUnavailableError (503) after the lock timeout instead of hanging it,
    and the write lock it held is free again."""
    from sgvloc.server.store.postgres import PgBackend

    m = MapManager(tmp_path / "m", backend=PgBackend(url, lock_timeout_s=0.5))
    m.load_all()
    try:
        m.create("m", SPEC)
        with psycopg.connect(url) as stuck:
            stuck.execute("SELECT version FROM sgvloc_maps WHERE name = 'm' FOR UPDATE")
            with pytest.raises(StoreUnavailableError):
                m.insert("m", feature_keyframes(rng, 1, "a"))
        assert m.insert("m", feature_keyframes(rng, 1, "b")).map_version == 1
    finally:
        m.close()


def test_a_replica_removes_only_uploads_a_crash_left(url: str, tmp_path: Path) -> None:
    """With a shared store the maps folder holds uploads being spooled: an old one is a
    crash's leftover, a fresh one may be another request's."""
    import os

    folder = tmp_path / "r" / "maps"
    folder.mkdir(parents=True)
    old, fresh = folder / ".tmp-import-aaaa-1", folder / ".tmp-import-bbbb-2"
    old.write_bytes(b"x")
    fresh.write_bytes(b"y")
    os.utime(old, (time.time() - 7200, time.time() - 7200))
    m = MapManager(folder, backend=open_backend(url))
    m.load_all()
    m.close()
    assert not old.exists() and fresh.exists()


def test_a_long_import_is_not_taken_for_a_crash_leftover(
    pair: tuple[MapManager, MapManager], url: str, tmp_path: Path, rng, monkeypatch
) -> None:
    """A replica starting up removes staged imports older than an hour; one still being
    filled counts from its latest chunk, not from when it began."""
    import io

    from sgvloc.server import maps as maps_module
    from sgvloc.server.archive import CHUNK

    a, _ = pair
    a.create("src", SPEC)
    a.insert("src", feature_keyframes(rng, CHUNK + 5, "k"))  # two chunks
    with a.export_archive("src") as blocks:
        data = b"".join(blocks)
    checked = {"n": 0}
    real = maps_module.MapManager._check_archived

    def slow_import(encoder, row, max_range) -> None:
        checked["n"] += 1
        if checked["n"] == 1:  # as if the import had begun over an hour ago
            with psycopg.connect(url) as conn:
                conn.execute(
                    "UPDATE sgvloc_maps SET made = now() - interval '2 hours' "
                    "WHERE starts_with(name, '.tmp-')"
                )
        if checked["n"] == CHUNK + 1:  # the first chunk is in; another replica starts
            other = MapManager(tmp_path / "c", backend=open_backend(url))
            other.load_all()
            other.close()
        real(encoder, row, max_range)

    monkeypatch.setattr(maps_module.MapManager, "_check_archived", staticmethod(slow_import))
    handle = a.import_archive(io.BytesIO(data), "copy")
    assert handle.num_keyframes == CHUNK + 5


def test_concurrent_exports_take_one_connection_each(url: str, tmp_path: Path, rng) -> None:
    """An export reads its whole state, next id included, in one transaction: as many
    exports as the pool has connections run at once."""
    m = MapManager(tmp_path / "e", backend=open_backend(url, pool_size=2))
    m.load_all()
    try:
        m.create("m", SPEC)
        m.insert("m", feature_keyframes(rng, 20, "k"))
        go, out = threading.Event(), []

        def export() -> None:
            go.wait()
            try:
                with m.export_archive("m") as blocks:
                    for _ in blocks:
                        time.sleep(0.05)  # a client downloading
                out.append("ok")
            except Exception as exc:
                out.append(type(exc).__name__)

        threads = [threading.Thread(target=export) for _ in range(2)]
        for t in threads:
            t.start()
        go.set()
        for t in threads:
            t.join(60)
        assert out == ["ok", "ok"]
    finally:
        m.close()


def test_a_filtered_delete_survives_a_keyframe_deleted_elsewhere_meanwhile(
    pair: tuple[MapManager, MapManager], rng, monkeypatch
) -> None:
    """The match and the delete are two transactions: a keyframe another replica deletes
    in between is matched again, not a 404 that deletes nothing."""
    from sgvloc.server.store import KeyframeFilter

    a, b = pair
    a.create("m", SPEC)
    a.insert("m", feature_keyframes(rng, 6, "drive/"))
    b.sync()
    store = a.get("m").store
    real = store.matching_ids
    raced = []

    def match_then_race(where):
        out = real(where)
        if not raced:
            raced.append(out[0])
            b.delete_keyframe("m", out[0])  # replica b, between the match and the delete
        return out

    monkeypatch.setattr(store, "matching_ids", match_then_race)
    deleted, version = a.delete_keyframes("m", KeyframeFilter(key_prefix="drive/"))
    assert deleted == 5 and a.get("m").num_keyframes == 0
    assert a.get("m").version == version == 3


def test_a_key_another_replica_stored_is_answered_after_its_write(
    pair: tuple[MapManager, MapManager], rng
) -> None:
    """created: false for a key another replica stored: the answer's version is one that
    holds the key on this replica (read-your-writes with min_map_version)."""
    a, b = pair
    a.create("m", SPEC)
    b.sync()
    items = feature_keyframes(rng, 1, "k")
    first = a.insert("m", items)
    again = b.insert("m", items)  # b has not synced: its copy is at version 0
    assert again.created == [False] and again.ids == first.ids
    assert again.map_version == first.map_version == b.get("m").version
    assert b.get("m").localizer.keyframe_ids() == first.ids


def test_a_map_made_elsewhere_is_loaded_by_the_first_write_or_localize(
    pair: tuple[MapManager, MapManager], rng
) -> None:
    """A map another replica made since this one last caught up is loaded when a write
    or a localize asks for it, not answered 404 until the follower gets to it."""
    a, b = pair
    a.create("new", SPEC)
    with pytest.raises(NotFoundError):
        b.get("new")  # plain lookups do not touch the store
    inserted = b.insert("new", feature_keyframes(rng, 2, "k"))  # b never synced
    assert inserted.map_version == 1 and b.get("new").num_keyframes == 2
    with pytest.raises(NotFoundError):
        b.get("nowhere", load=True)


def test_a_map_that_fails_to_load_is_not_loaded_again_by_each_request(
    pair: tuple[MapManager, MapManager], url: str, monkeypatch
) -> None:
    import json

    a, b = pair
    a.create("bad", SPEC)
    with psycopg.connect(url) as conn:  # settings this version cannot read
        meta = conn.execute("SELECT meta FROM sgvloc_maps WHERE name = 'bad'").fetchone()[0]
        cfg = json.loads(meta["localizer_config"])
        cfg["pose"]["a_newer_setting"] = 1
        conn.execute(
            "UPDATE sgvloc_maps SET meta = meta || %s::jsonb WHERE name = 'bad'",
            (json.dumps({"localizer_config": json.dumps(cfg)}),),
        )
    with pytest.raises(MapUnavailableError):
        b.get("bad", load=True)
    loads = []
    monkeypatch.setattr(b, "_load_named", lambda name: loads.append(name))
    with pytest.raises(MapUnavailableError):
        b.get("bad", load=True)
    assert loads == []  # only POST .../reload tries again


def _returns_within(fn, limit_s: float):
    """Run ``fn`` on a thread; its outcome (value or exception), or AssertionError if it
    has not returned after ``limit_s`` (a hang, not a speed figure: the limit is loose)."""
    out: dict = {}

    def run() -> None:
        try:
            out["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            out["error"] = exc

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(limit_s)
    assert not t.is_alive(), f"still waiting after {limit_s} s"
    return out


def test_a_frozen_server_fails_calls_and_a_slow_statement_goes_on(postgres, url: str) -> None:
    """A server that stops answering but keeps its connections open (a stopped process:
    no TCP timeout fires) fails calls on open connections and on the pool's idle ones
    with StoreUnavailableError instead of hanging them; a statement that simply takes
    longer than the limit on a live server is left alone."""
    if postgres.cluster is None:
        pytest.skip("needs the throwaway cluster (SGVLOC_TEST_PG_URL names an outside server)")
    backend = open_backend(url)
    backend.start()
    try:
        with backend.transaction() as cur:
            cur.execute("SELECT pg_sleep(%s)", (backend.timeout_s * 2,))
            assert cur.fetchone() is not None

        def frozen_mid_transaction() -> None:
            with backend.transaction() as cur:
                cur.execute("SELECT 1")
                postgres.cluster.pause()
                cur.execute("SELECT 1")

        try:
            out = _returns_within(frozen_mid_transaction, 60)
            assert isinstance(out.get("error"), StoreUnavailableError), out
            assert "stopped answering" in str(out["error"])
            out = _returns_within(backend.catalog, 60)  # the pool's idle connections
            assert isinstance(out.get("error"), StoreUnavailableError), out
        finally:
            postgres.cluster.resume()
        assert _returns_within(backend.catalog, 60) == {"value": {}}
    finally:
        backend.close()


def test_a_store_that_refuses_the_replica_ends_its_start(postgres, url: str) -> None:
    """Bad credentials or a missing database are errors to fix, not an outage to wait
    out: the start-up check says so (and `sgvloc serve` exits with it), while a store
    that cannot be reached yet passes (the replica waits for it)."""
    if postgres.cluster is None:
        pytest.skip("needs the throwaway cluster (SGVLOC_TEST_PG_URL names an outside server)")
    head, _, _ = url.rpartition("/")
    for bad in (head + "/no_such_database", url.replace("postgres@", "nobody@")):
        with pytest.raises(StoreError, match="refused the connection"):
            open_backend(bad).check_access()
    open_backend(url).check_access()
    port = postgres.cluster.port
    open_backend(url.replace(f":{port}/", ":1/")).check_access()  # nothing listens there


def test_a_store_of_a_newer_sgvloc_ends_the_start(url: str, tmp_path: Path) -> None:
    """A store whose schema a newer sgvloc wrote is refused by the start-up check (it
    stayed 'loading' for ever, the reason only in a logged traceback)."""
    m = MapManager(tmp_path / "a", backend=open_backend(url))
    m.load_all()  # creates the schema
    m.close()
    with psycopg.connect(url, autocommit=True) as conn:
        conn.execute("UPDATE sgvloc_schema SET version = version + 1")
    with pytest.raises(StoreError, match="newer than this sgvloc understands"):
        open_backend(url).check_access()
    # the same found by the loading thread (the store came back after the start-up
    # check): the process is told to stop, and /readyz says failed meanwhile
    from sgvloc.server.api.main import _load_maps

    late = MapManager(tmp_path / "b", backend=open_backend(url))
    stop = threading.Event()
    try:
        _load_maps(late, on_fatal=stop.set)
        assert stop.is_set() and "newer than this sgvloc" in (late.load_error or "")
    finally:
        late.close()


def test_a_map_no_replica_can_load_is_deleted_with_force(
    pair: tuple[MapManager, MapManager], url: str, tmp_path: Path
) -> None:
    """A map whose stored settings no replica reads (say, from another version) is not
    deleted by a plain delete; with force its rows go, and every replica forgets it."""
    import json

    a, b = pair
    for name in ("bad", "again"):
        a.create(name, SPEC)
        with psycopg.connect(url) as conn:
            conn.execute(
                "UPDATE sgvloc_maps SET meta = meta || %s::jsonb WHERE name = %s",
                (json.dumps({"localizer_config": "{not json"}), name),
            )
    c = MapManager(tmp_path / "c", backend=open_backend(url))
    try:
        c.load_all()
        assert {"bad", "again"} <= set(c.failed)
        # deleted elsewhere and made again, healthy, before c followed: not c's to drop
        a.delete("again")
        a.create("again", SPEC)
        with pytest.raises(ConflictError, match="made again"):
            c.delete("again", force=True)
        assert a.get("again").num_keyframes == 0
        with psycopg.connect(url) as conn:
            assert conn.execute("SELECT 1 FROM sgvloc_maps WHERE name = 'again'").fetchall()
        with pytest.raises(MapUnavailableError, match=r"\?force=true"):
            c.delete("bad")
        c.delete("bad", force=True)
        assert "bad" not in c.failed
        with psycopg.connect(url) as conn:
            assert not conn.execute("SELECT 1 FROM sgvloc_maps WHERE name = 'bad'").fetchall()
        a.sync()
        with pytest.raises(NotFoundError):
            a.get("bad")
        with pytest.raises(NotFoundError):
            c.delete("bad", force=True)
    finally:
        c.close()


def test_build_map_waits_for_a_service_still_loading(
    postgres, url: str, tmp_path: Path, balm_mini_dir: Path
) -> None:
    """A build started with its service (here one whose store is not up yet, so it stays
    'loading') waits for the maps to load instead of failing at once with 503."""
    if postgres.cluster is None:
        pytest.skip("needs the throwaway cluster (SGVLOC_TEST_PG_URL names an outside server)")
    import httpx
    from conftest import Server

    from sgvloc.tools.build_map import build_map

    postgres.cluster.stop()
    down = True
    srv = Server(tmp_path / "d", tmp_path / "log", env={"SGVLOC_STORE_URL": url})
    starting = threading.Thread(target=srv.start)  # returns once ready
    out: dict = {}
    try:
        starting.start()
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:  # up and answering "loading"
            try:
                if httpx.get(f"{srv.url}/readyz", timeout=2).json()["status"] == "loading":
                    break
            except (httpx.TransportError, ValueError):
                pass
            time.sleep(0.1)

        def build() -> None:
            try:
                out["result"] = build_map(balm_mini_dir, srv.url, "m", limit=3, progress=False)
            except Exception as exc:  # noqa: BLE001 - reported below
                out["error"] = exc

        builder = threading.Thread(target=build)
        builder.start()
        time.sleep(2.0)  # the build has met the loading service by now
        assert builder.is_alive(), out
        postgres.cluster.start()
        down = False
        builder.join(timeout=180)
        starting.join(timeout=60)
        assert "error" not in out, out
        assert out["result"].created == 3 and out["result"].keyframes == 3
    finally:
        if down:
            postgres.cluster.start()
        srv.stop()
        starting.join(timeout=60)
