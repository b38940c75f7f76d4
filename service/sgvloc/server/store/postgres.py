"""The shared store backend: every map in one PostgreSQL database (``sgvloc serve --store
postgresql://...``), so that any number of replicas serve the same maps.

Tables (created and migrated by the service; ``sgvloc_schema`` holds the version)::

    sgvloc_maps       one row per map: settings, version, next keyframe id
    sgvloc_keyframes  (map_id, id) -> pose, features, cloud, key, metadata, position
    sgvloc_changes    (map_id, version) -> the ids one write inserted or deleted

Every write to a map locks its row in ``sgvloc_maps`` first, so writes to one map are
serialised across replicas and its ``version`` is a gap-free sequence: the change feed
is ``sgvloc_changes`` in version order, written in the same transaction as the keyframes
and announced on commit with ``NOTIFY sgvloc_changes``. A replica applies the changes
after the version it holds (:meth:`PgMapStore.changes_since`); the feed keeps the last
``CHANGES_KEPT`` changes per map, and a replica further behind reloads the map.

Keyframe ids come from the map's ``next_id`` counter (never reused after a delete, as in
SQLite). Keys are unique per map: a key another replica stored first raises
:class:`~sgvloc.server.store.base.DuplicateKeyError` and nothing is stored.

Connections come from a psycopg pool with short connect and acquire timeouts: when the
server cannot be reached a call fails within seconds with
:class:`~sgvloc.server.store.base.StoreUnavailableError`, and the pool reconnects by itself.
A server that keeps its connections open but stops answering (a stopped or frozen
process: the kernel still acknowledges what is sent, so no TCP timeout fires) is caught
by :class:`_Watchdog`: a call that has waited ``timeout_s`` makes the server prove it is
alive over a new connection, and a call on a dead server is cut off.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import psycopg
from psycopg import errors as pg_errors
from psycopg_pool import ConnectionPool, PoolTimeout

from sgvloc.core.confidence import Calibration
from sgvloc.core.config import LocalizerConfig
from sgvloc.core.errors import ConflictError, InputError, NotFoundError

from .base import (
    ROW_COLUMNS,
    SLIM_COLUMNS,
    Change,
    DuplicateKeyError,
    KeyframeFilter,
    KeyframeRow,
    KeyframeSummary,
    MapRecord,
    MapStore,
    SettingsChangedError,
    SharedBackend,
    StoreClosedError,
    StoreError,
    StoreUnavailableError,
    blob_to_array,
    keyframe_row,
    record_from_meta,
    record_to_meta,
    row_values,
    utc_now,
)

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1


def _newer_schema(version: int) -> str:
    return (
        f"the store's schema is version {version}, newer than this sgvloc understands "
        f"({SCHEMA_VERSION}): upgrade sgvloc (every replica of a store runs one version)"
    )


CHANNEL = "sgvloc_changes"
CHANGES_KEPT = 10_000  # changes kept per map; a replica further behind reloads the map
_STAGING = ".tmp-"  # hidden names of maps being imported
_STAGING_MAX_AGE = "1 hour"  # a staged map older than this was abandoned

_SCHEMA = f"""
CREATE TABLE IF NOT EXISTS sgvloc_maps (
    map_id      BIGSERIAL PRIMARY KEY,
    name        TEXT NOT NULL UNIQUE,
    meta        JSONB NOT NULL,
    version     BIGINT NOT NULL DEFAULT 0,
    next_id     BIGINT NOT NULL DEFAULT 1,
    settings_version BIGINT NOT NULL DEFAULT 0,
    updated_at  TEXT,
    made        TIMESTAMPTZ NOT NULL DEFAULT now()
);
CREATE TABLE IF NOT EXISTS sgvloc_keyframes (
    map_id            BIGINT NOT NULL REFERENCES sgvloc_maps ON DELETE CASCADE,
    id                BIGINT NOT NULL,
    key               TEXT,
    T_map_sensor      BYTEA NOT NULL,
    global_descriptor BYTEA NOT NULL,
    keypoints         BYTEA NOT NULL,
    local_features    BYTEA NOT NULL,
    cloud             BYTEA,
    metadata          TEXT NOT NULL,
    created_at        TEXT NOT NULL,
    x DOUBLE PRECISION, y DOUBLE PRECISION, z DOUBLE PRECISION,
    PRIMARY KEY (map_id, id),
    UNIQUE (map_id, key)
);
CREATE TABLE IF NOT EXISTS sgvloc_changes (
    map_id  BIGINT NOT NULL REFERENCES sgvloc_maps ON DELETE CASCADE,
    version BIGINT NOT NULL,
    kind    TEXT NOT NULL CHECK (kind IN ('insert', 'delete')),
    ids     BIGINT[] NOT NULL,
    at      TIMESTAMPTZ NOT NULL DEFAULT now(),
    PRIMARY KEY (map_id, version)
);
INSERT INTO sgvloc_schema (version) SELECT {SCHEMA_VERSION}
    WHERE NOT EXISTS (SELECT 1 FROM sgvloc_schema);
"""

#: schema version -> the SQL that takes it to the next one (none yet)
_MIGRATIONS: dict[int, str] = {}


def redact(url: str) -> str:
    """``url`` without its password."""
    parts = urlsplit(url)
    if parts.password is None:
        return url
    host = parts.hostname or ""
    netloc = f"{parts.username}:***@{host}" + (f":{parts.port}" if parts.port else "")
    return urlunsplit(parts._replace(netloc=netloc))


def _where(f: KeyframeFilter) -> tuple[str, list[Any]]:
    """SQL conditions (each starting with AND) and their parameters; the same meaning as
    the SQLite backend's (a non-numeric ``timestamp`` never matches a time bound)."""
    sql: list[str] = []
    args: list[Any] = []
    if f.key_prefix is not None:
        sql.append("starts_with(key, %s)")
        args.append(f.key_prefix)
    if f.bbox is not None:
        x0, y0, x1, y1 = f.bbox
        sql.append("x BETWEEN %s AND %s AND y BETWEEN %s AND %s")
        args += [x0, x1, y0, y1]
    stamp = (
        "(CASE WHEN jsonb_typeof(metadata::jsonb -> 'timestamp') = 'number' "
        "THEN (metadata::jsonb ->> 'timestamp')::float8 END)"
    )
    if f.time_min is not None:
        sql.append(f"{stamp} >= %s")
        args.append(f.time_min)
    if f.time_max is not None:
        sql.append(f"{stamp} <= %s")
        args.append(f.time_max)
    if f.sequence is not None:
        sql.append("metadata::jsonb ->> 'sequence' = %s")
        args.append(f.sequence)
    return "".join(f" AND {c}" for c in sql), args


_INSERT = (
    "INSERT INTO sgvloc_keyframes (map_id, id, key, T_map_sensor, global_descriptor, "
    "keypoints, local_features, cloud, metadata, created_at, x, y, z) "
    "VALUES (%s, %s, %s, %b, %b, %b, %b, %b, %s, %s, %s, %s, %s)"  # arrays sent as binary
)


#: longest wait for a row lock another session holds (seconds)
LOCK_TIMEOUT_S = 30
#: longest single statement (seconds): far above any insert of max_batch keyframes
STATEMENT_TIMEOUT_S = 120
#: longest a transaction may sit idle (seconds): an export streams inside one, as fast
#: as its client reads
IDLE_IN_TRANSACTION_S = 600


def _shut_down(fd: int) -> None:
    """Shut down the socket of a connection stuck on a silent server (its blocked call
    then fails at once); the caller makes sure ``fd`` is still that connection's."""
    try:
        with socket.socket(fileno=os.dup(fd)) as sock:
            sock.shutdown(socket.SHUT_RDWR)
    except OSError as exc:
        log.debug("could not cut a stalled store connection: %s", exc)


class _Call:
    """One watched call on a connection: the socket to cut and when to look again."""

    def __init__(self, fd: int, due: float, limit_s: float, probe: bool) -> None:
        self.fd = fd
        self.due = due
        self.limit_s = limit_s
        self.probe = probe
        self.cut = False


class _Watchdog:
    """Cuts off calls to a server that stopped answering.

    A call registers its connection's socket for as long as it runs. One daemon thread
    looks at the calls every :data:`TICK_S`: a call past its limit either makes the
    server prove it is alive (``probe``: a new connection answering ``SELECT 1`` within
    ``timeout_s``; then the call may go on, a long statement is no fault) or, if it cannot
    or for calls that must be quick (the pool's check of an idle connection), has its
    socket shut down, so that the blocked call fails at once with an OperationalError
    and the pool drops the connection.
    """

    TICK_S = 0.25

    def __init__(self, alive: Callable[[], bool]) -> None:
        self._alive = alive
        self._calls: dict[int, _Call] = {}
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._next = 0

    @contextmanager
    def watch(self, conn: psycopg.Connection, limit_s: float, probe: bool) -> Iterator[_Call]:
        call = _Call(conn.fileno(), time.monotonic() + limit_s, limit_s, probe)
        with self._lock:
            self._next += 1
            token = self._next
            self._calls[token] = call
            if self._thread is None:
                self._thread = threading.Thread(
                    target=self._run, name="sgvloc-store-watchdog", daemon=True
                )
                self._thread.start()
        try:
            yield call
        finally:
            with self._lock:  # unregistered before the connection can close (fd reuse)
                del self._calls[token]

    def _run(self) -> None:
        while True:
            time.sleep(self.TICK_S)
            now = time.monotonic()
            with self._lock:
                due = [(t, c) for t, c in self._calls.items() if c.due <= now and not c.cut]
            if not due:
                continue
            alive = None
            if any(c.probe for _, c in due):
                alive = self._alive()  # one probe answers for every call due
            with self._lock:
                for token, call in due:
                    if self._calls.get(token) is not call:
                        continue  # ended meanwhile: its socket may be another's now
                    if call.probe and alive:
                        call.due = time.monotonic() + call.limit_s
                        continue
                    call.cut = True
                    _shut_down(call.fd)


class PgBackend(SharedBackend):
    """Every map in one PostgreSQL database, through a connection pool."""

    errors = (psycopg.Error,)

    def __init__(
        self,
        url: str,
        *,
        pool_size: int = 8,
        timeout_s: float = 3.0,
        password: str | None = None,
        lock_timeout_s: float = LOCK_TIMEOUT_S,
    ) -> None:
        self.url = url
        self.timeout_s = timeout_s
        connect = {
            "connect_timeout": max(1, int(round(timeout_s))),
            # a server that stops answering (no RST) fails a call instead of hanging it
            "tcp_user_timeout": int(timeout_s * 1000) * 3,
            "keepalives_idle": 10,
            "application_name": "sgvloc",
            # a lock held elsewhere (another replica's stuck write) or a statement that
            # never ends fails the call (503) instead of holding the map's write lock for
            # good; a transaction left idle (an export whose client went away) is ended
            "options": (
                f"-c lock_timeout={int(lock_timeout_s * 1000)} "
                f"-c statement_timeout={STATEMENT_TIMEOUT_S * 1000} "
                f"-c idle_in_transaction_session_timeout={IDLE_IN_TRANSACTION_S * 1000}"
            ),
        }
        if password is not None:
            connect["password"] = password
        self._watchdog = _Watchdog(self._alive)
        self.pool = ConnectionPool(
            url,
            min_size=1,
            max_size=max(2, pool_size),
            timeout=timeout_s,
            kwargs=connect,
            check=self._check,
            # keep trying to reconnect for as long as a request waits for a connection,
            # then give up until the next request asks: the pool's waits between tries
            # double, so a long timeout leaves it asleep long after the store is back,
            # and 0 leaves the requests already waiting without a try
            reconnect_timeout=timeout_s,
            open=False,
            name="sgvloc-store",
        )
        self._listener: psycopg.Connection | None = None
        self._listen_lock = threading.Lock()
        self._connect_kwargs = connect

    def describe(self) -> str:
        return f"postgresql ({redact(self.url)})"

    # -- connections --------------------------------------------------------------------

    def _check(self, conn: psycopg.Connection) -> None:
        """The pool's check of an idle connection before it is lent: an empty query,
        cut off after ``timeout_s`` (a connection to a frozen server fails it)."""
        with self._watchdog.watch(conn, self.timeout_s, probe=False):
            ConnectionPool.check_connection(conn)

    def _alive(self) -> bool:
        """Whether the server answers ``SELECT 1`` on a new connection within about
        twice ``timeout_s`` (run on a thread of its own, so that the watchdog that asks
        never waits longer; a probe left hanging has its socket shut down)."""
        out: dict[str, Any] = {}
        lock = threading.Lock()

        def probe() -> None:
            try:
                conn = psycopg.connect(self.url, autocommit=True, **self._connect_kwargs)
            except psycopg.Error:
                return
            try:
                with lock:
                    out["fd"] = conn.fileno()
                conn.execute("SELECT 1")
                out["ok"] = True
            except psycopg.Error:
                pass
            finally:
                with lock:  # from here on the socket is not the asker's to shut down
                    out.pop("fd", None)
                conn.close()

        t = threading.Thread(target=probe, name="sgvloc-store-probe", daemon=True)
        t.start()
        t.join(2 * self.timeout_s + 1)
        with lock:
            if t.is_alive() and "fd" in out:  # the probe's query hangs: end it
                _shut_down(out["fd"])
        return bool(out.get("ok"))

    @contextmanager
    def transaction(self, read_snapshot: bool = False) -> Iterator[psycopg.Cursor]:
        """A cursor in one transaction (committed when the block ends without error);
        ``read_snapshot``: a read-only REPEATABLE READ one (every query sees one state).
        Unreachable server -> :class:`StoreUnavailableError`."""
        call: _Call | None = None
        try:
            with self.pool.connection() as conn:
                with self._watchdog.watch(conn, self.timeout_s, probe=True) as call:
                    if read_snapshot:
                        conn.isolation_level = psycopg.IsolationLevel.REPEATABLE_READ
                        conn.read_only = True
                    try:
                        with conn.transaction(), conn.cursor() as cur:
                            yield cur
                    finally:
                        if read_snapshot and not call.cut:
                            conn.isolation_level = None
                            conn.read_only = None
        except PoolTimeout:
            raise StoreUnavailableError(
                f"the map store (PostgreSQL) cannot be reached within {self.timeout_s:g} s; "
                "nothing was changed (retry later)"
            ) from None
        except psycopg.OperationalError as exc:
            if call is not None and call.cut:
                raise StoreUnavailableError(
                    "the map store (PostgreSQL) stopped answering (no reply, and no new "
                    f"connection answered within {self.timeout_s:g} s); a write that was "
                    "committing when it stopped may still be applied once it is back "
                    "(writes with keys are safe to retry); retry later"
                ) from None
            raise StoreUnavailableError(
                f"the map store (PostgreSQL) failed: {str(exc).strip() or type(exc).__name__}; "
                "retry later"
            ) from None
        except psycopg.DataError as exc:  # a value PostgreSQL cannot hold (text with NUL)
            raise InputError(
                f"the map store refused a value: {str(exc).strip() or type(exc).__name__}; "
                "nothing was changed"
            ) from None

    #: SQLSTATE classes of a refusal that waiting does not mend: 28 (authentication,
    #: authorisation) and 3D (no such database); a failed connection often carries no
    #: SQLSTATE, only the server's message
    _REFUSED = ("28", "3D")
    _REFUSED_TEXT = (
        "password",
        "authentication",
        "does not exist",
        "permission denied",
        "no pg_hba.conf entry",
    )

    def check_access(self) -> None:
        try:
            with psycopg.connect(self.url, autocommit=True, **self._connect_kwargs) as conn:
                # a store written by a newer sgvloc: refused now, not after loading starts
                try:
                    row = None
                    if conn.execute("SELECT to_regclass('sgvloc_schema')").fetchone()[0]:
                        row = conn.execute("SELECT max(version) FROM sgvloc_schema").fetchone()
                except psycopg.OperationalError:
                    raise
                except psycopg.Error as exc:  # no right to read it, say
                    raise StoreError(
                        f"the map store (PostgreSQL, {redact(self.url)}) cannot be read: "
                        f"{str(exc).strip() or type(exc).__name__}"
                    ) from None
                if row is not None and row[0] is not None and int(row[0]) > SCHEMA_VERSION:
                    raise StoreError(_newer_schema(int(row[0])))
        except psycopg.OperationalError as exc:
            text = str(exc).strip()
            state = getattr(exc, "sqlstate", None) or ""
            if state[:2] in self._REFUSED or any(t in text for t in self._REFUSED_TEXT):
                raise StoreError(
                    f"the map store (PostgreSQL, {redact(self.url)}) refused the connection: "
                    f"{text}; check the store URL's user and database and the password "
                    "(SGVLOC_STORE_PASSWORD_FILE)"
                ) from None
            log.info("the map store cannot be reached yet (%s): waiting for it", text)

    def start(self) -> None:
        if self.pool.closed:
            self.pool.open(wait=False)
        with self.transaction() as cur:
            # a migration of a large store may take long, and so may waiting for another
            # replica's: no time limits in this one transaction
            cur.execute("SET LOCAL statement_timeout = 0")
            cur.execute("SET LOCAL lock_timeout = 0")
            # one replica at a time creates or migrates the schema
            cur.execute("SELECT pg_advisory_xact_lock(hashtext('sgvloc_schema'))")
            cur.execute("CREATE TABLE IF NOT EXISTS sgvloc_schema (version INT NOT NULL)")
            cur.execute("SELECT version FROM sgvloc_schema")
            row = cur.fetchone()
            version = None if row is None else int(row[0])
            if version is None:
                cur.execute(_SCHEMA)
                log.info("created the store's schema (version %d)", SCHEMA_VERSION)
                version = SCHEMA_VERSION
            while version in _MIGRATIONS:
                log.info("migrating the store's schema from version %d", version)
                cur.execute(_MIGRATIONS[version])
                version += 1
                cur.execute("UPDATE sgvloc_schema SET version = %s", (version,))
            if version != SCHEMA_VERSION:
                raise StoreError(_newer_schema(version))
            cur.execute(
                f"DELETE FROM sgvloc_maps WHERE starts_with(name, '{_STAGING}') "
                f"AND made < now() - interval '{_STAGING_MAX_AGE}'"
            )

    def close(self) -> None:
        with self._listen_lock:
            if self._listener is not None:
                self._listener.close()
                self._listener = None
        self.pool.close()

    # -- maps ---------------------------------------------------------------------------

    def catalog(self) -> dict[str, tuple[int, int, int]]:
        with self.transaction() as cur:
            cur.execute(
                "SELECT name, map_id, version, settings_version FROM sgvloc_maps "
                f"WHERE NOT starts_with(name, '{_STAGING}')"
            )
            return {r[0]: (int(r[1]), int(r[2]), int(r[3])) for r in cur.fetchall()}

    def _insert_map(self, name: str, record: MapRecord) -> PgMapStore:
        try:
            with self.transaction() as cur:
                cur.execute(
                    "INSERT INTO sgvloc_maps (name, meta, settings_version) VALUES (%s, %s, %s) "
                    "RETURNING map_id",
                    (name, json.dumps(record_to_meta(record)), int(record.settings_version)),
                )
                map_id = int(cur.fetchone()[0])
                cur.execute("SELECT pg_notify(%s, %s)", (CHANNEL, name))
        except pg_errors.UniqueViolation:
            raise ConflictError(f"map {name!r} exists already") from None
        return PgMapStore(self, map_id, name)

    def create(self, name: str, record: MapRecord) -> PgMapStore:
        return self._insert_map(name, record)

    def open(self, name: str) -> PgMapStore:
        with self.transaction() as cur:
            cur.execute("SELECT map_id FROM sgvloc_maps WHERE name = %s", (name,))
            row = cur.fetchone()
        if row is None:
            raise NotFoundError(f"map {name!r} does not exist")
        return PgMapStore(self, int(row[0]), name)

    def drop(self, store: MapStore) -> None:
        assert isinstance(store, PgMapStore)
        with self.transaction() as cur:
            cur.execute("DELETE FROM sgvloc_maps WHERE map_id = %s", (store.map_id,))
            if cur.rowcount != 1:
                raise NotFoundError(f"map {store.name!r} does not exist")
            cur.execute("SELECT pg_notify(%s, %s)", (CHANNEL, store.name))
        store.close()

    def staging(self, record: MapRecord) -> PgMapStore:
        return self._insert_map(f"{_STAGING}{record.name}-{uuid.uuid4().hex[:8]}", record)

    def publish(self, store: MapStore, name: str) -> None:
        assert isinstance(store, PgMapStore)
        try:
            with self.transaction() as cur:
                cur.execute(
                    "UPDATE sgvloc_maps SET name = %s, made = now() WHERE map_id = %s",
                    (name, store.map_id),
                )
                cur.execute("SELECT pg_notify(%s, %s)", (CHANNEL, name))
        except pg_errors.UniqueViolation:
            raise ConflictError(f"map {name!r} exists already") from None
        store.name = name

    # -- change notifications -----------------------------------------------------------

    def wait_for_change(self, timeout_s: float) -> bool:
        """LISTEN on a connection of its own; a lost connection is made again on the next
        call (the caller polls anyway, so a missed notification costs one poll period)."""
        with self._listen_lock:
            try:
                if self._listener is None or self._listener.closed:
                    self._listener = psycopg.connect(
                        self.url, autocommit=True, **self._connect_kwargs
                    )
                    with self._watchdog.watch(self._listener, self.timeout_s, probe=False):
                        self._listener.execute(f"LISTEN {CHANNEL}")
                got = False
                for _ in self._listener.notifies(timeout=timeout_s, stop_after=1):
                    got = True
                # drain what else arrived: one catch-up serves them all
                for _ in self._listener.notifies(timeout=0.001):
                    pass
                return got
            except psycopg.Error as exc:
                log.debug("change notifications unavailable: %s", exc)
                if self._listener is not None:
                    self._listener.close()
                    self._listener = None
        time.sleep(timeout_s)
        return False


class PgMapStore(MapStore):
    """One map's rows in the shared database. Thread-safe (a connection per call)."""

    def __init__(self, backend: PgBackend, map_id: int, name: str) -> None:
        self.backend = backend
        self.map_id = map_id
        self.name = name
        self.closed = False

    @property
    def incarnation(self) -> int:
        return self.map_id

    @contextmanager
    def _tx(self, read_snapshot: bool = False) -> Iterator[psycopg.Cursor]:
        if self.closed:
            raise StoreClosedError(f"map {self.name!r}: the store is closed")
        with self.backend.transaction(read_snapshot) as cur:
            yield cur

    def close(self) -> None:
        self.closed = True

    def _lock_map(self, cur: psycopg.Cursor) -> tuple[int, int]:
        """Lock the map's row for this transaction: ``(version, next_id)``."""
        cur.execute(
            "SELECT version, next_id FROM sgvloc_maps WHERE map_id = %s FOR UPDATE",
            (self.map_id,),
        )
        row = cur.fetchone()
        if row is None:
            raise StoreClosedError(f"map {self.name!r} was deleted")
        return int(row[0]), int(row[1])

    def _announce(self, cur: psycopg.Cursor) -> None:
        cur.execute("SELECT pg_notify(%s, %s)", (CHANNEL, self.name))

    # -- settings -----------------------------------------------------------------------

    def _meta(self, cur: psycopg.Cursor) -> tuple[dict[str, str], int, int]:
        cur.execute(
            "SELECT meta, settings_version, version FROM sgvloc_maps WHERE map_id = %s",
            (self.map_id,),
        )
        row = cur.fetchone()
        if row is None:
            raise StoreClosedError(f"map {self.name!r} was deleted")
        return dict(row[0]), int(row[1]), int(row[2])

    def record(self) -> MapRecord:
        with self._tx() as cur:
            meta, settings_version, _ = self._meta(cur)
        meta["settings_version"] = str(settings_version)
        return record_from_meta(meta, f"map {self.name!r}")

    def update_settings(
        self,
        localizer_config: LocalizerConfig,
        calibration: Calibration,
        last_self_test: dict[str, Any] | None = None,
        *,
        expect_settings_version: int | None = None,
    ) -> MapRecord:
        patch = {
            "localizer_config": localizer_config.model_dump_json(),
            "calibration": json.dumps(calibration.to_dict()),
            "settings_updated_at": utc_now(),
        }
        if last_self_test is not None:
            patch["last_self_test"] = json.dumps(last_self_test)
        with self._tx() as cur:
            self._lock_map(cur)
            if expect_settings_version is not None:
                if self._meta(cur)[1] != expect_settings_version:
                    raise SettingsChangedError(f"map {self.name!r}: settings changed")
            cur.execute(
                "UPDATE sgvloc_maps SET meta = meta || %s::jsonb, "
                "settings_version = settings_version + 1 WHERE map_id = %s",
                (json.dumps(patch), self.map_id),
            )
            self._announce(cur)
            # read in the same transaction: once it commits the change has landed, so
            # no later failure may answer it as failed
            meta, settings_version, _ = self._meta(cur)
        meta["settings_version"] = str(settings_version)
        return record_from_meta(meta, f"map {self.name!r}")

    def find_keys(self, keys: list[str]) -> dict[str, int]:
        if not keys:
            return {}
        with self._tx() as cur:
            cur.execute(
                "SELECT key, id FROM sgvloc_keyframes WHERE map_id = %s AND key = ANY(%s)",
                (self.map_id, list(keys)),
            )
            return {r[0]: int(r[1]) for r in cur.fetchall()}

    def get(self, keyframe_id: int) -> KeyframeRow:
        rows = self.fetch([int(keyframe_id)])
        if not rows:
            raise NotFoundError(f"keyframe {keyframe_id} does not exist")
        return rows[0]

    def fetch(self, ids: list[int], slim: bool = False) -> list[KeyframeRow]:
        with self._tx() as cur:
            cur.execute(
                f"SELECT {SLIM_COLUMNS if slim else ROW_COLUMNS} FROM sgvloc_keyframes "
                "WHERE map_id = %s AND id = ANY(%s) "
                "ORDER BY id",
                (self.map_id, [int(i) for i in ids]),
                binary=True,
            )
            return [keyframe_row(r) for r in cur.fetchall()]

    def _page(self, cur: psycopg.Cursor, last: int, chunk: int, slim: bool = False) -> list[tuple]:
        cur.execute(
            f"SELECT {SLIM_COLUMNS if slim else ROW_COLUMNS} FROM sgvloc_keyframes "
            "WHERE map_id = %s AND id > %s "
            "ORDER BY id LIMIT %s",
            (self.map_id, last, chunk),
            binary=True,
        )
        return cur.fetchall()

    def select(
        self, where: KeyframeFilter, *, after_id: int = 0, limit: int = 1000
    ) -> list[KeyframeSummary]:
        cond, args = _where(where)
        with self._tx() as cur:
            cur.execute(
                "SELECT id, key, T_map_sensor, metadata, created_at FROM sgvloc_keyframes "
                f"WHERE map_id = %s AND id > %s{cond} ORDER BY id LIMIT %s",
                [self.map_id, int(after_id), *args, int(limit)],
                binary=True,
            )
            rows = cur.fetchall()
        return [
            KeyframeSummary(int(r[0]), r[1], blob_to_array(r[2]), json.loads(r[3]), r[4])
            for r in rows
        ]

    def matching_ids(self, where: KeyframeFilter) -> list[int]:
        cond, args = _where(where)
        with self._tx() as cur:
            cur.execute(
                f"SELECT id FROM sgvloc_keyframes WHERE map_id = %s{cond} ORDER BY id",
                [self.map_id, *args],
            )
            return [int(r[0]) for r in cur.fetchall()]

    def extent(self) -> tuple[list[float], list[float]] | None:
        with self._tx() as cur:
            cur.execute(
                "SELECT min(x), min(y), min(z), max(x), max(y), max(z) FROM sgvloc_keyframes "
                "WHERE map_id = %s",
                (self.map_id,),
            )
            r = cur.fetchone()
        if r[0] is None:
            return None
        return [float(v) for v in r[:3]], [float(v) for v in r[3:]]

    def last_write(self) -> str | None:
        with self._tx() as cur:
            cur.execute("SELECT updated_at FROM sgvloc_maps WHERE map_id = %s", (self.map_id,))
            row = cur.fetchone()
        return None if row is None else row[0]

    def disk_bytes(self) -> int:
        """The stored size of the map's rows (values as PostgreSQL keeps them)."""
        with self._tx() as cur:
            cur.execute(
                "SELECT coalesce(sum(pg_column_size(k.*)), 0) FROM sgvloc_keyframes k "
                "WHERE map_id = %s",
                (self.map_id,),
            )
            return int(cur.fetchone()[0])

    @contextmanager
    def _snapshot(
        self, slim: bool = False
    ) -> Iterator[tuple[psycopg.Cursor, int, int, Iterator[KeyframeRow]]]:
        """One REPEATABLE READ transaction: its cursor, the version and every row of
        one state."""
        with self._tx(read_snapshot=True) as cur:
            version = self._meta(cur)[2]
            cur.execute("SELECT count(*) FROM sgvloc_keyframes WHERE map_id = %s", (self.map_id,))
            count = int(cur.fetchone()[0])

            def rows() -> Iterator[KeyframeRow]:
                last = 0
                while page := self._page(cur, last, 1000, slim):
                    yield from (keyframe_row(r) for r in page)
                    last = int(page[-1][0])

            yield cur, version, count, rows()

    @contextmanager
    def snapshot(self, slim: bool = False) -> Iterator[tuple[int, int, Iterator[KeyframeRow]]]:
        with self._snapshot(slim) as (_, version, count, rows):
            yield version, count, rows

    @contextmanager
    def archive_snapshot(self) -> Iterator[tuple[int, int, int, Iterator[KeyframeRow]]]:
        """As the base class, the next id read in the snapshot's own transaction (one
        connection per export, however many run at once)."""
        with self._snapshot() as (cur, version, count, rows):
            yield version, count, self._next_id(cur), rows

    def next_id(self) -> int:
        with self._tx() as cur:
            return self._next_id(cur)

    def _next_id(self, cur: psycopg.Cursor) -> int:
        cur.execute("SELECT next_id FROM sgvloc_maps WHERE map_id = %s", (self.map_id,))
        row = cur.fetchone()
        if row is None:
            raise StoreClosedError(f"map {self.name!r} was deleted")
        return int(row[0])

    def changes_since(self, version: int) -> list[Change] | None:
        with self._tx() as cur:
            _, _, current = self._meta(cur)
            if current <= version:
                return []
            cur.execute(
                "SELECT version, kind, ids FROM sgvloc_changes WHERE map_id = %s "
                "AND version > %s ORDER BY version",
                (self.map_id, int(version)),
            )
            rows = cur.fetchall()
        changes = [Change(int(v), k, [int(i) for i in ids]) for v, k, ids in rows]
        expected = list(range(int(version) + 1, current + 1))
        if [c.version for c in changes][: len(expected)] != expected:
            return None  # pruned (or an archive import set the version): reload the map
        return changes[: len(expected)]

    # -- writing ------------------------------------------------------------------------

    def _record_change(self, cur: psycopg.Cursor, version: int, kind: str, ids: list[int]) -> None:
        cur.execute(
            "INSERT INTO sgvloc_changes (map_id, version, kind, ids) VALUES (%s, %s, %s, %s)",
            (self.map_id, version, kind, ids),
        )
        if version > CHANGES_KEPT and version % 100 == 0:
            cur.execute(
                "DELETE FROM sgvloc_changes WHERE map_id = %s AND version <= %s",
                (self.map_id, version - CHANGES_KEPT),
            )
        self._announce(cur)

    def insert(self, rows: list[KeyframeRow]) -> tuple[list[int], int]:
        now = utc_now()
        try:
            with self._tx() as cur:
                version, next_id = self._lock_map(cur)
                ids = list(range(next_id, next_id + len(rows)))
                cur.executemany(
                    _INSERT,
                    [
                        (self.map_id, *row_values(row, i, now))
                        for row, i in zip(rows, ids, strict=True)
                    ],
                )
                version += 1
                cur.execute(
                    "UPDATE sgvloc_maps SET version = %s, next_id = %s, updated_at = %s "
                    "WHERE map_id = %s",
                    (version, next_id + len(rows), now, self.map_id),
                )
                self._record_change(cur, version, "insert", ids)
        except pg_errors.UniqueViolation as exc:
            detail = exc.diag.message_detail
            raise DuplicateKeyError(
                f"map {self.name!r}: a keyframe key was stored meanwhile ({detail})"
            ) from None
        for row, i in zip(rows, ids, strict=True):
            row.id, row.created_at = i, now
        return ids, version

    def delete(self, ids: list[int], *, set_version: int | None = None) -> int:
        """Delete keyframes (one transaction). ``set_version`` is not honoured: other
        replicas may have applied the version it would restore, so the undo of an insert
        is a delete of its own, one version later."""
        want = sorted({int(i) for i in ids})
        with self._tx() as cur:
            version, _ = self._lock_map(cur)
            cur.execute(
                "DELETE FROM sgvloc_keyframes WHERE map_id = %s AND id = ANY(%s) RETURNING id",
                (self.map_id, want),
            )
            gone = {int(r[0]) for r in cur.fetchall()}
            missing = [i for i in want if i not in gone]
            if missing:
                raise NotFoundError(f"keyframe {missing[0]} does not exist")
            version += 1
            cur.execute(
                "UPDATE sgvloc_maps SET version = %s, updated_at = %s WHERE map_id = %s",
                (version, utc_now(), self.map_id),
            )
            self._record_change(cur, version, "delete", want)
        return version

    def insert_exact(
        self, rows: list[KeyframeRow], version: int, next_id: int | None = None
    ) -> None:
        """Fill a staged map from an archive: ids and creation times kept, the version
        set (no change is recorded: replicas load a published map whole)."""
        with self._tx() as cur:
            _, current = self._lock_map(cur)
            cur.executemany(
                _INSERT,
                [(self.map_id, *row_values(row, int(row.id), row.created_at)) for row in rows],
            )
            top = max([current - 1, (next_id or 1) - 1, *(int(r.id) for r in rows)])
            cur.execute(  # made: a staged map being filled is not a crash's leftover
                "UPDATE sgvloc_maps SET version = %s, next_id = %s, updated_at = %s, "
                "made = now() WHERE map_id = %s",
                (int(version), top + 1, utc_now(), self.map_id),
            )
