"""The embedded store backend: one SQLite database per map (the default of ``sgvloc serve``).

Layout under the data directory::

    <data_dir>/maps/<name>/map.sqlite       map settings + keyframes (this module)
    <data_dir>/maps/<name>/index.faiss      FAISS snapshot (+ index.faiss.json), a cache

The database runs in WAL mode with ``synchronous=FULL``: a keyframe insert is
acknowledged only after its transaction commits, and FULL makes that commit durable
against power loss too (NORMAL in WAL mode may lose the last commits on an OS crash,
which would silently break the promise made to a map-building job that was told "201").
The cost is one WAL fsync per transaction; inserts are batched into one transaction per
request, so it is paid once per batch, not per keyframe.

Arrays are stored as ``.npy`` blobs (dtype and shape in the header, no pickle). Keyframe
ids are ``INTEGER PRIMARY KEY AUTOINCREMENT``: an id is never reused after a delete, so a
client holding an old id can never address a different keyframe. The position (x, y, z of
the pose) is kept in columns too, for bounding-box filters and the map's extent.

Schema versions: 1 (no position columns) is migrated to 2 when the map is opened.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import resource
import sqlite3
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sgvloc.core.confidence import Calibration
from sgvloc.core.config import LocalizerConfig
from sgvloc.core.errors import NotFoundError

from .base import (
    ROW_COLUMNS,
    SLIM_COLUMNS,
    KeyframeFilter,
    KeyframeRow,
    KeyframeSummary,
    MapRecord,
    MapStore,
    SettingsChangedError,
    StoreBackend,
    StoreClosedError,
    StoreError,
    StoreUnavailableError,
    blob_to_array,
    keyframe_row,
    position,
    raise_if_full,
    record_from_meta,
    record_to_meta,
    row_values,
    utc_now,
)

log = logging.getLogger(__name__)


def _no_file_left(exc: sqlite3.Error) -> None:
    """Raise :class:`StoreUnavailableError` when ``exc`` came from the process's open-file
    limit (each open map holds its database and WAL files): retryable once a map is
    unloaded or the limit raised, not a fault of the request."""
    try:
        os.close(os.open(os.devnull, os.O_RDONLY))
    except OSError as probe:
        if probe.errno == errno.EMFILE:
            limit = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
            raise StoreUnavailableError(
                f"cannot open another map database: this process has every file it may "
                f"open in use (limit {limit}, about 3 per map; raise it with ulimit -n)"
            ) from exc


DB_NAME = "map.sqlite"
SCHEMA_VERSION = 2
#: a delete that leaves at least this much free space in the file gives it back to the
#: file system (maps made with incremental auto-vacuum: every map made since it came)
GIVE_BACK_MIN_BYTES = 8 << 20
#: pages moved per step of giving space back; the connection is free between steps
_VACUUM_STEP_PAGES = 2048
#: the write-ahead log is cut back to this size after a checkpoint (it may grow while a
#: large batch is written)
_WAL_LIMIT_BYTES = 64 << 20

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (
    key   TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS keyframes (
    id                INTEGER PRIMARY KEY AUTOINCREMENT,
    key               TEXT UNIQUE,
    T_map_sensor      BLOB NOT NULL,
    global_descriptor BLOB NOT NULL,
    keypoints         BLOB NOT NULL,
    local_features    BLOB NOT NULL,
    cloud             BLOB,
    metadata          TEXT NOT NULL,
    created_at        TEXT NOT NULL,
    x                 REAL,
    y                 REAL,
    z                 REAL
);
"""


def _migrate_1_to_2(conn: sqlite3.Connection) -> None:
    """Schema 1 -> 2: position columns, filled from the stored poses (one transaction)."""
    conn.execute("BEGIN IMMEDIATE")
    try:
        for column in ("x", "y", "z"):
            conn.execute(f"ALTER TABLE keyframes ADD COLUMN {column} REAL")
        rows = conn.execute("SELECT id, T_map_sensor FROM keyframes").fetchall()
        conn.executemany(
            "UPDATE keyframes SET x = ?, y = ?, z = ? WHERE id = ?",
            [(*position(blob_to_array(blob)), i) for i, blob in rows],
        )
        conn.execute("UPDATE meta SET value = '2' WHERE key = 'schema_version'")
        conn.execute("COMMIT")
    except BaseException:
        if conn.in_transaction:
            conn.execute("ROLLBACK")
        raise


_MIGRATIONS = {1: _migrate_1_to_2}  # from version -> the step to the next


def _where(f: KeyframeFilter) -> tuple[str, list[object]]:
    """SQL conditions (joined with AND, starting with AND) and their parameters."""
    sql, args = [], []
    if f.key_prefix is not None:
        sql.append("substr(key, 1, ?) = ?")
        args += [len(f.key_prefix), f.key_prefix]
    if f.bbox is not None:
        x0, y0, x1, y1 = f.bbox
        sql.append("x BETWEEN ? AND ? AND y BETWEEN ? AND ?")
        args += [x0, x1, y0, y1]
    if f.time_min is not None:
        sql.append("json_extract(metadata, '$.timestamp') >= ?")
        args.append(f.time_min)
    if f.time_max is not None:
        sql.append("json_extract(metadata, '$.timestamp') <= ?")
        args.append(f.time_max)
    if f.sequence is not None:
        sql.append("CAST(json_extract(metadata, '$.sequence') AS TEXT) = ?")
        args.append(f.sequence)
    return "".join(f" AND {c}" for c in sql), args


class SqliteMapStore(MapStore):
    """One map's SQLite database. Thread-safe: one connection behind a lock.

    Writers are expected to be serialised by the caller (the map manager holds a per-map
    write lock); the lock here only protects the connection object.
    """

    def __init__(self, path: Path, conn: sqlite3.Connection) -> None:
        self.path = path
        self._conn = conn
        self._lock = threading.Lock()
        self._closed = False
        #: the database file this store opened: a snapshot checks that it reads the same
        #: one (not a map deleted and made again under the same name meanwhile)
        self._inode = path.stat().st_ino

    @contextmanager
    def _locked(self) -> Iterator[sqlite3.Connection]:
        """The connection, under the lock; a store closed meanwhile (its map deleted or
        unloaded) raises :class:`StoreClosedError`, as the manager expects of any call."""
        with self._lock:
            if self._closed:
                raise StoreClosedError(f"map {self.path.parent.name!r} was deleted or unloaded")
            yield self._conn

    # -- opening ------------------------------------------------------------------------

    @staticmethod
    def _connect(path: Path, new: bool = False) -> sqlite3.Connection:
        conn = None
        try:
            conn = sqlite3.connect(
                path, isolation_level=None, check_same_thread=False, timeout=30.0
            )
            if new:  # before anything is written: the mode is fixed once the file exists
                conn.execute("PRAGMA auto_vacuum=INCREMENTAL")
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute(f"PRAGMA journal_size_limit={_WAL_LIMIT_BYTES}")
            conn.execute("PRAGMA synchronous=FULL")
            conn.execute("PRAGMA foreign_keys=ON")
        except sqlite3.OperationalError as exc:
            try:
                _no_file_left(exc)  # asked before the connection gives its files back
            finally:
                if conn is not None:
                    conn.close()
            raise
        return conn

    @classmethod
    def create(cls, path: Path, record: MapRecord) -> SqliteMapStore:
        """Create a new database at ``path`` holding ``record`` and no keyframes."""
        if path.exists():
            raise StoreError(f"{path} exists already")
        conn = cls._connect(path, new=True)
        meta = {"schema_version": str(SCHEMA_VERSION), "version": "0", **record_to_meta(record)}
        conn.executescript(_SCHEMA)
        conn.execute("BEGIN IMMEDIATE")
        conn.executemany("INSERT INTO meta (key, value) VALUES (?, ?)", meta.items())
        conn.execute("COMMIT")
        return cls(path, conn)

    @classmethod
    def open(cls, path: Path) -> SqliteMapStore:
        """Open an existing database; raises :class:`StoreError` if it is not one of ours."""
        if not path.is_file():
            raise StoreError(f"{path}: map database not found")
        try:
            conn = cls._connect(path)
            rows = dict(conn.execute("SELECT key, value FROM meta").fetchall())
        except sqlite3.DatabaseError as exc:
            raise StoreError(f"{path}: cannot read map database: {exc}") from None
        schema = rows.get("schema_version")
        try:
            while schema is not None and schema.isdigit() and int(schema) in _MIGRATIONS:
                log.info("%s: migrating the map database from schema %s", path, schema)
                _MIGRATIONS[int(schema)](conn)
                schema = str(int(schema) + 1)
        except sqlite3.Error as exc:
            conn.close()
            raise_if_full(exc)
            raise StoreError(f"{path}: migrating schema {schema} failed: {exc}") from None
        if schema != str(SCHEMA_VERSION):
            conn.close()
            if schema is not None and schema.isdigit() and int(schema) > SCHEMA_VERSION:
                raise StoreError(
                    f"{path}: schema version {schema} is newer than this sgvloc understands "
                    f"({SCHEMA_VERSION}): a newer sgvloc wrote it; upgrade sgvloc"
                )
            raise StoreError(f"{path}: unknown schema version {schema!r}")
        return cls(path, conn)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._conn.close()

    # -- map settings -------------------------------------------------------------------

    def _meta(self) -> dict[str, str]:
        with self._locked():
            return dict(self._conn.execute("SELECT key, value FROM meta").fetchall())

    def record(self) -> MapRecord:
        """The map's stored settings."""
        return record_from_meta(self._meta(), str(self.path))

    def update_settings(
        self,
        localizer_config: LocalizerConfig,
        calibration: Calibration,
        last_self_test: dict[str, Any] | None = None,
        *,
        expect_settings_version: int | None = None,
    ) -> MapRecord:
        """Replace the localizer settings and calibration (one transaction)."""
        values = {
            "localizer_config": localizer_config.model_dump_json(),
            "calibration": json.dumps(calibration.to_dict()),
            "settings_updated_at": utc_now(),
        }
        if last_self_test is not None:
            values["last_self_test"] = json.dumps(last_self_test)
        with self._locked():
            conn = self._conn
            conn.execute("BEGIN IMMEDIATE")
            try:
                if expect_settings_version is not None:
                    row = conn.execute(
                        "SELECT value FROM meta WHERE key = 'settings_version'"
                    ).fetchone()
                    if int(row[0] if row else 0) != expect_settings_version:
                        name = self.path.parent.name
                        raise SettingsChangedError(f"map {name!r}: settings changed")
                conn.executemany(
                    "INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", values.items()
                )
                conn.execute(
                    "INSERT INTO meta (key, value) VALUES ('settings_version', '1') "
                    "ON CONFLICT(key) DO UPDATE SET value = CAST(value AS INTEGER) + 1"
                )
                conn.execute("COMMIT")
            except BaseException as exc:
                if conn.in_transaction:  # a failed COMMIT (disk full) has rolled back already
                    conn.execute("ROLLBACK")
                raise_if_full(exc)
                raise
        return self.record()

    def find_keys(self, keys: list[str]) -> dict[str, int]:
        """The ids of those ``keys`` that exist: ``{key: id}``."""
        found: dict[str, int] = {}
        with self._locked():
            for start in range(0, len(keys), 500):
                chunk = keys[start : start + 500]
                marks = ",".join("?" * len(chunk))
                found.update(
                    self._conn.execute(
                        f"SELECT key, id FROM keyframes WHERE key IN ({marks})", chunk
                    ).fetchall()
                )
        return found

    _COLUMNS = ROW_COLUMNS
    _row = staticmethod(keyframe_row)

    def get(self, keyframe_id: int) -> KeyframeRow:
        with self._locked() as conn:
            r = conn.execute(
                f"SELECT {self._COLUMNS} FROM keyframes WHERE id = ?", (int(keyframe_id),)
            ).fetchone()
        if r is None:
            raise NotFoundError(f"keyframe {keyframe_id} does not exist")
        return self._row(r)

    _PAGE = f"SELECT {_COLUMNS} FROM keyframes WHERE id > ? ORDER BY id LIMIT ?"
    _SLIM_PAGE = f"SELECT {SLIM_COLUMNS} FROM keyframes WHERE id > ? ORDER BY id LIMIT ?"

    def fetch(self, ids: list[int], slim: bool = False) -> list[KeyframeRow]:
        """Those of ``ids`` that exist, in id order (one query per 500 ids)."""
        columns = SLIM_COLUMNS if slim else self._COLUMNS
        want = sorted({int(i) for i in ids})
        rows: list[tuple] = []
        with self._locked():
            for start in range(0, len(want), 500):
                chunk = want[start : start + 500]
                marks = ",".join("?" * len(chunk))
                rows += self._conn.execute(
                    f"SELECT {columns} FROM keyframes WHERE id IN ({marks}) ORDER BY id", chunk
                ).fetchall()
        return [self._row(r) for r in rows]

    def _pages(self, fetch: Callable[[int], list[tuple]]) -> Iterator[KeyframeRow]:
        """Every keyframe in id order, ``fetch(last id)`` giving the next page of rows."""
        last = 0
        while rows := fetch(last):
            yield from (self._row(r) for r in rows)
            last = rows[-1][0]

    def select(
        self, where: KeyframeFilter, *, after_id: int = 0, limit: int = 1000
    ) -> list[KeyframeSummary]:
        """Up to ``limit`` keyframes matching ``where`` with ``id > after_id``, by id."""
        cond, args = _where(where)
        with self._locked():
            rows = self._conn.execute(
                "SELECT id, key, T_map_sensor, metadata, created_at FROM keyframes "
                f"WHERE id > ?{cond} ORDER BY id LIMIT ?",
                [int(after_id), *args, int(limit)],
            ).fetchall()
        return [
            KeyframeSummary(int(r[0]), r[1], blob_to_array(r[2]), json.loads(r[3]), r[4])
            for r in rows
        ]

    def matching_ids(self, where: KeyframeFilter) -> list[int]:
        cond, args = _where(where)
        with self._locked():
            return [
                r[0]
                for r in self._conn.execute(
                    f"SELECT id FROM keyframes WHERE 1{cond} ORDER BY id", args
                )
            ]

    def extent(self) -> tuple[list[float], list[float]] | None:
        with self._locked():
            r = self._conn.execute(
                "SELECT min(x), min(y), min(z), max(x), max(y), max(z) FROM keyframes"
            ).fetchone()
        if r[0] is None:
            return None
        return [float(v) for v in r[:3]], [float(v) for v in r[3:]]

    @contextmanager
    def snapshot(self, slim: bool = False) -> Iterator[tuple[int, int, Iterator[KeyframeRow]]]:
        """A read transaction on a second connection: WAL mode lets it see one state of
        the map while writers go on."""
        with self._locked():
            pass  # closed: the map is gone
        gone = StoreClosedError(f"map {self.path.parent.name!r} was deleted or unloaded")
        try:  # mode=rw: a file deleted meanwhile is not made again, empty
            uri = f"{self.path.resolve().as_uri()}?mode=rw"  # percent-encoded: any folder
            conn = sqlite3.connect(uri, uri=True, isolation_level=None, check_same_thread=False)
        except sqlite3.OperationalError:
            raise gone from None
        try:
            try:
                conn.execute("BEGIN")
                version = int(
                    conn.execute("SELECT value FROM meta WHERE key = 'version'").fetchone()[0]
                )
                count = int(conn.execute("SELECT COUNT(*) FROM keyframes").fetchone()[0])
                same = self.path.stat().st_ino == self._inode
            except (sqlite3.Error, OSError, TypeError):
                raise gone from None
            if not same:  # the map was deleted and made again under this name
                raise gone

            page = self._SLIM_PAGE if slim else self._PAGE
            rows = self._pages(lambda last: conn.execute(page, (last, 256)).fetchall())
            yield version, count, rows
        finally:
            conn.close()

    def last_write(self) -> str | None:
        return self._meta().get("updated_at")

    def disk_bytes(self) -> int:
        """The database with its write-ahead log and shared-memory file."""
        files = [self.path, *(self.path.with_name(self.path.name + s) for s in ("-wal", "-shm"))]
        return sum(p.stat().st_size for p in files if p.exists())

    # -- keyframes: writing -------------------------------------------------------------

    def insert(self, rows: list[KeyframeRow]) -> tuple[list[int], int]:
        """Insert keyframes in one transaction and bump the version.

        Fills ``row.id`` and ``row.created_at``. Returns ``(ids, new_version)``. Nothing
        is stored if any row fails (a duplicate key raises ``sqlite3.IntegrityError``).
        """
        now = utc_now()
        with self._locked():
            conn = self._conn
            conn.execute("BEGIN IMMEDIATE")
            try:
                ids = []
                for row in rows:
                    cur = conn.execute(
                        f"INSERT INTO keyframes ({self._INSERT_COLUMNS}) VALUES ({self._MARKS})",
                        row_values(row, None, now),
                    )
                    ids.append(int(cur.lastrowid))
                version = self._bump_version(conn)
                conn.execute("COMMIT")
            except BaseException as exc:
                if conn.in_transaction:  # a failed COMMIT (disk full) has rolled back already
                    conn.execute("ROLLBACK")
                raise_if_full(exc)
                raise
        for row, i in zip(rows, ids, strict=True):
            row.id, row.created_at = i, now
        return ids, version

    def delete(self, ids: list[int], *, set_version: int | None = None) -> int:
        """Delete keyframes in one transaction; returns the new version.

        The version is bumped, or set to ``set_version`` (used to undo an insert whose
        in-memory half failed). Unknown ids raise :class:`NotFoundError`, deleting nothing.
        """
        with self._locked():
            conn = self._conn
            conn.execute("BEGIN IMMEDIATE")
            try:
                for i in ids:
                    cur = conn.execute("DELETE FROM keyframes WHERE id = ?", (int(i),))
                    if cur.rowcount != 1:
                        raise NotFoundError(f"keyframe {i} does not exist")
                if set_version is None:
                    version = self._bump_version(conn)
                else:
                    version = int(set_version)
                    conn.execute("UPDATE meta SET value = ? WHERE key = 'version'", (str(version),))
                conn.execute("COMMIT")
            except BaseException as exc:
                if conn.in_transaction:  # a failed COMMIT (disk full) has rolled back already
                    conn.execute("ROLLBACK")
                raise_if_full(exc)
                raise
        self._give_back_space()
        return version

    def _give_back_space(self) -> None:
        """Once deletes leave :data:`GIVE_BACK_MIN_BYTES` or more free in the file, hand
        all of it back to the file system (incremental auto-vacuum; a map made before it
        came reuses its free space for new keyframes instead). A step of
        :data:`_VACUUM_STEP_PAGES` pages at a time, so that readers of the connection get
        it in between; a failure only leaves the space free (the delete stands)."""
        before = None  # free pages before the last step
        try:
            while True:
                with self._locked() as conn:
                    if conn.execute("PRAGMA auto_vacuum").fetchone()[0] != 2:
                        return
                    free = int(conn.execute("PRAGMA freelist_count").fetchone()[0])
                    page = int(conn.execute("PRAGMA page_size").fetchone()[0])
                    if before is None and free * page < GIVE_BACK_MIN_BYTES:
                        return
                    if free == 0 or (before is not None and free >= before):
                        return  # all given back (or no step moves on: never loop)
                    before = free
                    # executescript runs the pragma to the end (execute would free one page)
                    conn.executescript(f"PRAGMA incremental_vacuum({_VACUUM_STEP_PAGES});")
        except (sqlite3.Error, StoreClosedError) as exc:
            log.warning("%s: free space not given back after a delete: %s", self.path, exc)

    _INSERT_COLUMNS = (
        "id, key, T_map_sensor, global_descriptor, keypoints, local_features, cloud, metadata, "
        "created_at, x, y, z"
    )
    _MARKS = ",".join("?" * 12)

    def insert_exact(
        self, rows: list[KeyframeRow], version: int, next_id: int | None = None
    ) -> None:
        """Insert rows keeping their ids and ``created_at``, and set the version (one
        transaction). For filling a new store from an archive."""
        with self._locked():
            conn = self._conn
            conn.execute("BEGIN IMMEDIATE")
            try:
                conn.executemany(
                    f"INSERT INTO keyframes ({self._INSERT_COLUMNS}) VALUES ({self._MARKS})",
                    [row_values(row, int(row.id), row.created_at) for row in rows],
                )
                conn.execute("UPDATE meta SET value = ? WHERE key = 'version'", (str(version),))
                self._written_now(conn)
                if next_id is not None:  # AUTOINCREMENT goes on above sqlite_sequence
                    seq = self._sequence(conn)
                    if next_id - 1 > seq:
                        conn.execute("DELETE FROM sqlite_sequence WHERE name = 'keyframes'")
                        conn.execute(
                            "INSERT INTO sqlite_sequence (name, seq) VALUES ('keyframes', ?)",
                            (int(next_id) - 1,),
                        )
                conn.execute("COMMIT")
            except BaseException as exc:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
                raise_if_full(exc)
                raise

    @staticmethod
    def _sequence(conn: sqlite3.Connection) -> int:
        """The highest id AUTOINCREMENT has given (0 before the first insert)."""
        row = conn.execute("SELECT seq FROM sqlite_sequence WHERE name = 'keyframes'").fetchone()
        return 0 if row is None else int(row[0])

    def next_id(self) -> int:
        with self._locked() as conn:
            return self._sequence(conn) + 1

    @staticmethod
    def _written_now(conn: sqlite3.Connection) -> None:
        """Record the time of this write (``last_write``)."""
        conn.execute(
            "INSERT OR REPLACE INTO meta (key, value) VALUES ('updated_at', ?)", (utc_now(),)
        )

    @classmethod
    def _bump_version(cls, conn: sqlite3.Connection) -> int:
        conn.execute("UPDATE meta SET value = CAST(value AS INTEGER) + 1 WHERE key = 'version'")
        cls._written_now(conn)
        return int(conn.execute("SELECT value FROM meta WHERE key = 'version'").fetchone()[0])


class SqliteBackend(StoreBackend):
    """``<folder>/map.sqlite`` per map."""

    errors = (sqlite3.Error,)

    def create(self, folder: Path, record: MapRecord) -> SqliteMapStore:
        return SqliteMapStore.create(folder / DB_NAME, record)

    def open(self, folder: Path) -> SqliteMapStore:
        return SqliteMapStore.open(folder / DB_NAME)
