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
client holding an old id can never address a different keyframe.
"""

from __future__ import annotations

import json
import logging
import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from sgvloc.core.confidence import Calibration
from sgvloc.core.config import LocalizerConfig
from sgvloc.core.encoders import EncoderSpec
from sgvloc.core.errors import NotFoundError

from .base import (
    KeyframeRow,
    MapRecord,
    MapStore,
    StoreBackend,
    StoreClosedError,
    StoreError,
    array_to_blob,
    blob_to_array,
    raise_if_full,
    utc_now,
)

log = logging.getLogger(__name__)

DB_NAME = "map.sqlite"
SCHEMA_VERSION = 1

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
    created_at        TEXT NOT NULL
);
"""


class SqliteMapStore(MapStore):
    """One map's SQLite database. Thread-safe: one connection behind a lock.

    Writers are expected to be serialised by the caller (the map manager holds a per-map
    write lock); the lock here only protects the connection object.
    """

    def __init__(self, path: Path, conn: sqlite3.Connection) -> None:
        self.path = path
        self._conn = conn
        self._lock = threading.Lock()

    # -- opening ------------------------------------------------------------------------

    @staticmethod
    def _connect(path: Path) -> sqlite3.Connection:
        conn = sqlite3.connect(path, isolation_level=None, check_same_thread=False, timeout=30.0)
        conn.execute("PRAGMA journal_mode=WAL")
        conn.execute("PRAGMA synchronous=FULL")
        conn.execute("PRAGMA foreign_keys=ON")
        return conn

    @classmethod
    def create(cls, path: Path, record: MapRecord) -> SqliteMapStore:
        """Create a new database at ``path`` holding ``record`` and no keyframes."""
        if path.exists():
            raise StoreError(f"{path} exists already")
        conn = cls._connect(path)
        meta = {
            "schema_version": str(SCHEMA_VERSION),
            "name": record.name,
            "encoder_spec": record.encoder_spec.model_dump_json(),
            "localizer_config": record.localizer_config.model_dump_json(),
            "encoder_fingerprint": record.encoder_fingerprint,
            "keep_clouds": json.dumps(record.keep_clouds),
            "created_at": record.created_at,
            "version": "0",
            "settings_version": "0",
        }
        if record.calibration is not None:
            meta["calibration"] = json.dumps(record.calibration.to_dict())
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
        if schema != str(SCHEMA_VERSION):
            conn.close()
            raise StoreError(f"{path}: unknown schema version {schema!r}")
        return cls(path, conn)

    def close(self) -> None:
        with self._lock:
            self._conn.close()

    # -- map settings -------------------------------------------------------------------

    def _meta(self) -> dict[str, str]:
        with self._lock:
            return dict(self._conn.execute("SELECT key, value FROM meta").fetchall())

    def record(self) -> MapRecord:
        """The map's stored settings."""
        m = self._meta()
        try:
            return MapRecord(
                name=m["name"],
                encoder_spec=EncoderSpec.model_validate_json(m["encoder_spec"]),
                localizer_config=LocalizerConfig.model_validate_json(m["localizer_config"]),
                encoder_fingerprint=m["encoder_fingerprint"],
                keep_clouds=bool(json.loads(m["keep_clouds"])),
                created_at=m["created_at"],
                calibration=Calibration.from_dict(json.loads(m["calibration"]))
                if "calibration" in m
                else None,
                settings_version=int(m.get("settings_version", "0")),
                settings_updated_at=m.get("settings_updated_at"),
            )
        except (KeyError, ValueError) as exc:
            raise StoreError(f"{self.path}: damaged map settings: {exc}") from None

    def update_settings(
        self, localizer_config: LocalizerConfig, calibration: Calibration
    ) -> MapRecord:
        """Replace the localizer settings and calibration (one transaction)."""
        values = {
            "localizer_config": localizer_config.model_dump_json(),
            "calibration": json.dumps(calibration.to_dict()),
            "settings_updated_at": utc_now(),
        }
        with self._lock:
            conn = self._conn
            conn.execute("BEGIN IMMEDIATE")
            try:
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

    def version(self) -> int:
        """The map's version: bumped by every transaction that inserts or deletes."""
        with self._lock:
            row = self._conn.execute("SELECT value FROM meta WHERE key = 'version'").fetchone()
        return int(row[0])

    # -- keyframes: reading -------------------------------------------------------------

    def count(self) -> int:
        with self._lock:
            return int(self._conn.execute("SELECT COUNT(*) FROM keyframes").fetchone()[0])

    def ids(self) -> list[int]:
        """All keyframe ids, ascending."""
        with self._lock:
            return [r[0] for r in self._conn.execute("SELECT id FROM keyframes ORDER BY id")]

    def find_keys(self, keys: list[str]) -> dict[str, int]:
        """The ids of those ``keys`` that exist: ``{key: id}``."""
        found: dict[str, int] = {}
        with self._lock:
            for start in range(0, len(keys), 500):
                chunk = keys[start : start + 500]
                marks = ",".join("?" * len(chunk))
                found.update(
                    self._conn.execute(
                        f"SELECT key, id FROM keyframes WHERE key IN ({marks})", chunk
                    ).fetchall()
                )
        return found

    _COLUMNS = (
        "id, key, T_map_sensor, global_descriptor, keypoints, local_features, cloud, "
        "metadata, created_at"
    )

    @staticmethod
    def _row(r: tuple) -> KeyframeRow:
        return KeyframeRow(
            id=int(r[0]),
            key=r[1],
            T_map_sensor=blob_to_array(r[2]),
            global_descriptor=blob_to_array(r[3]),
            keypoints=blob_to_array(r[4]),
            local_features=blob_to_array(r[5]),
            cloud=None if r[6] is None else blob_to_array(r[6]),
            metadata=json.loads(r[7]),
            created_at=r[8],
        )

    def get(self, keyframe_id: int) -> KeyframeRow:
        try:
            with self._lock:
                r = self._conn.execute(
                    f"SELECT {self._COLUMNS} FROM keyframes WHERE id = ?", (int(keyframe_id),)
                ).fetchone()
        except sqlite3.ProgrammingError:  # closed
            raise StoreClosedError(f"{self.path}: the map store is closed") from None
        if r is None:
            raise NotFoundError(f"keyframe {keyframe_id} does not exist")
        return self._row(r)

    def iter_keyframes(self, chunk: int = 256) -> Iterator[KeyframeRow]:
        """Every keyframe in id order, read in chunks (the lock is not held between them)."""
        last = 0
        while True:
            with self._lock:
                rows = self._conn.execute(
                    f"SELECT {self._COLUMNS} FROM keyframes WHERE id > ? ORDER BY id LIMIT ?",
                    (last, chunk),
                ).fetchall()
            if not rows:
                return
            for r in rows:
                yield self._row(r)
            last = rows[-1][0]

    # -- keyframes: writing -------------------------------------------------------------

    def insert(self, rows: list[KeyframeRow]) -> tuple[list[int], int]:
        """Insert keyframes in one transaction and bump the version.

        Fills ``row.id`` and ``row.created_at``. Returns ``(ids, new_version)``. Nothing
        is stored if any row fails (a duplicate key raises ``sqlite3.IntegrityError``).
        """
        now = utc_now()
        with self._lock:
            conn = self._conn
            conn.execute("BEGIN IMMEDIATE")
            try:
                ids = []
                for row in rows:
                    cur = conn.execute(
                        "INSERT INTO keyframes (key, T_map_sensor, global_descriptor, keypoints,"
                        " local_features, cloud, metadata, created_at)"
                        " VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                        (
                            row.key,
                            array_to_blob(np.asarray(row.T_map_sensor, dtype=np.float64)),
                            array_to_blob(row.global_descriptor),
                            array_to_blob(row.keypoints),
                            array_to_blob(row.local_features),
                            None if row.cloud is None else array_to_blob(row.cloud),
                            json.dumps(row.metadata),
                            now,
                        ),
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
        with self._lock:
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
        return version

    @staticmethod
    def _bump_version(conn: sqlite3.Connection) -> int:
        conn.execute("UPDATE meta SET value = CAST(value AS INTEGER) + 1 WHERE key = 'version'")
        return int(conn.execute("SELECT value FROM meta WHERE key = 'version'").fetchone()[0])


class SqliteBackend(StoreBackend):
    """``<folder>/map.sqlite`` per map."""

    errors = (sqlite3.Error,)

    def create(self, folder: Path, record: MapRecord) -> SqliteMapStore:
        return SqliteMapStore.create(folder / DB_NAME, record)

    def open(self, folder: Path) -> SqliteMapStore:
        return SqliteMapStore.open(folder / DB_NAME)
