"""What the map manager needs of a store: the records it keeps and the interface it calls.

A backend (:class:`StoreBackend`) creates and opens one :class:`MapStore` per map; the
map manager (:mod:`sgvloc.server.maps`) talks only to these two classes, so a second
backend slots in beside :mod:`.sqlite` without touching it.
"""

from __future__ import annotations

import ast
import errno
import io
import json
from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from sgvloc.core.confidence import Calibration
from sgvloc.core.config import LocalizerConfig
from sgvloc.core.encoders import EncoderSpec
from sgvloc.core.errors import SgvlocError, StorageFullError

INDEX_NAME = "index.faiss"  # the FAISS snapshot in a map's folder (a start-up cache)


class StoreError(SgvlocError):
    """A map database is missing, damaged or from an unknown schema."""


class StoreUnavailableError(StoreError):
    """The shared store cannot be reached now (503 ``store_unavailable``; retry)."""


class DuplicateKeyError(StoreError):
    """An insert met a keyframe key that another writer stored meanwhile; nothing was
    stored (the map manager decides again which keys are new)."""


def storage_full(exc: BaseException) -> StorageFullError | None:
    """A :class:`~sgvloc.core.errors.StorageFullError` if ``exc`` says that the disk is
    full (an OSError with ENOSPC/EDQUOT, or a database driver's "disk is full" / "No
    space left on device"), else None."""
    text = str(exc)
    full = (isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT)) or (
        "disk is full" in text or "No space left on device" in text
    )
    if not full:
        return None
    return StorageFullError(
        "no space left on the service's disk; nothing was stored (free space, retry)"
    )


def raise_if_full(exc: BaseException) -> None:
    """Raise :func:`storage_full`'s error from ``exc`` if the disk is full; call it where
    a failed write was rolled back."""
    full = storage_full(exc)
    if full is not None:
        raise full from exc


def utc_now() -> str:
    """The current time as ISO 8601 UTC with a ``Z`` suffix (millisecond precision)."""
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def array_to_blob(arr: np.ndarray) -> bytes:
    """An array as ``.npy`` bytes (dtype and shape included, no pickle)."""
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(arr), allow_pickle=False)
    return buf.getvalue()


_NPY_V1 = b"\x93NUMPY\x01\x00"
_HEADERS: dict[bytes, tuple[np.dtype, tuple[int, ...]]] = {}  # parsed .npy headers


def blob_to_array(blob: bytes) -> np.ndarray:
    """Inverse of :func:`array_to_blob` (a writable array).

    The ``.npy`` headers :func:`array_to_blob` writes repeat from row to row: each is
    parsed once and kept, so reading a map costs a copy per array instead of
    ``np.load``'s 60 us of parsing (what dominates a replica's start-up). Other headers
    go through ``np.load``."""
    blob = bytes(blob)
    if blob[:8] == _NPY_V1:
        end = 10 + int.from_bytes(blob[8:10], "little")
        head = blob[:end]
        spec = _HEADERS.get(head)
        if spec is None:
            d = ast.literal_eval(head[10:].decode("latin1"))
            if not d.get("fortran_order") and np.dtype(d["descr"]).kind in "biuf":
                spec = (np.dtype(d["descr"]), tuple(d["shape"]))
                if len(_HEADERS) < 4096:
                    _HEADERS[head] = spec
        if spec is not None:
            dtype, shape = spec
            return np.frombuffer(blob, dtype, offset=end).reshape(shape).copy()
    return np.load(io.BytesIO(blob), allow_pickle=False)


@dataclass(frozen=True)
class Change:
    """One write to a map, as the change feed of a shared store gives it: the map's
    ``version`` after it, and the keyframes it inserted or deleted."""

    version: int
    kind: str  # "insert" | "delete"
    ids: list[int]


@dataclass(frozen=True)
class MapRecord:
    """A map's settings as stored: what it needs to be rebuilt in memory.

    ``calibration``: the confidence model the map answers with (None in maps made before
    maps recorded one: the shipped calibration of its encoder kind applies).
    ``settings_version`` counts changes of the settings after creation (PATCH), made at
    ``settings_updated_at``; they never change the keyframe ``version``.
    """

    name: str
    encoder_spec: EncoderSpec
    localizer_config: LocalizerConfig
    encoder_fingerprint: str
    keep_clouds: bool
    created_at: str
    calibration: Calibration | None = None
    settings_version: int = 0
    settings_updated_at: str | None = None
    #: the encoder self-test the map was built after (``sgvloc build-map --choose-encoder``)
    self_test: dict[str, Any] | None = None
    #: the summary of the latest leave-out self-test of the served map
    last_self_test: dict[str, Any] | None = None


def record_to_meta(record: MapRecord) -> dict[str, str]:
    """A map's settings as text values (the form both backends store)."""
    meta = {
        "name": record.name,
        "encoder_spec": record.encoder_spec.model_dump_json(),
        "localizer_config": record.localizer_config.model_dump_json(),
        "encoder_fingerprint": record.encoder_fingerprint,
        "keep_clouds": json.dumps(record.keep_clouds),
        "created_at": record.created_at,
        "settings_version": str(record.settings_version),
    }
    if record.settings_updated_at is not None:
        meta["settings_updated_at"] = record.settings_updated_at
    if record.calibration is not None:
        meta["calibration"] = json.dumps(record.calibration.to_dict())
    if record.self_test is not None:
        meta["self_test"] = json.dumps(record.self_test)
    if record.last_self_test is not None:
        meta["last_self_test"] = json.dumps(record.last_self_test)
    return meta


def record_from_meta(m: dict[str, str], where: str) -> MapRecord:
    """Inverse of :func:`record_to_meta`; :class:`StoreError` naming ``where`` if damaged."""
    try:
        return MapRecord(
            name=m["name"],
            encoder_spec=EncoderSpec.model_validate_json(m["encoder_spec"]),
            localizer_config=LocalizerConfig.stored(m["localizer_config"]),
            encoder_fingerprint=m["encoder_fingerprint"],
            keep_clouds=bool(json.loads(m["keep_clouds"])),
            created_at=m["created_at"],
            calibration=Calibration.from_dict(json.loads(m["calibration"]))
            if "calibration" in m
            else None,
            settings_version=int(m.get("settings_version", "0")),
            settings_updated_at=m.get("settings_updated_at"),
            self_test=json.loads(m["self_test"]) if "self_test" in m else None,
            last_self_test=json.loads(m["last_self_test"]) if "last_self_test" in m else None,
        )
    except (KeyError, ValueError) as exc:
        raise StoreError(f"{where}: damaged map settings: {exc}") from None


@dataclass
class KeyframeRow:
    """One keyframe as stored. ``id`` is 0 until the row is inserted."""

    T_map_sensor: np.ndarray  # [4, 4] float64
    global_descriptor: np.ndarray  # [G] float32
    keypoints: np.ndarray  # [N, 3] float32
    local_features: np.ndarray  # [N, D] float32
    cloud: np.ndarray | None = None  # [M, 3] float32, for ICP refinement
    metadata: dict[str, Any] = field(default_factory=dict)
    key: str | None = None
    id: int = 0
    created_at: str = ""


#: the columns of a keyframe row, in the order :func:`keyframe_row` reads them
ROW_COLUMNS = (
    "id, key, T_map_sensor, global_descriptor, keypoints, local_features, cloud, "
    "metadata, created_at"
)
#: the same without local features and cloud (for a replica that fetches them per query)
SLIM_COLUMNS = "id, key, T_map_sensor, global_descriptor, NULL, NULL, NULL, metadata, created_at"
_NO_KEYPOINTS = np.zeros((0, 3), np.float32)
_NO_FEATURES = np.zeros((0, 0), np.float32)


def keyframe_row(r: tuple) -> KeyframeRow:
    """A row read as :data:`ROW_COLUMNS` (or :data:`SLIM_COLUMNS`: no keypoints, local
    features or cloud) as a :class:`KeyframeRow`; a column that cannot be decoded is a
    :class:`StoreError` naming the keyframe and the column."""
    column = "id"
    try:
        kf_id = int(r[0])
        column = "T_map_sensor"
        T = blob_to_array(r[2])
        column = "global_descriptor"
        g = blob_to_array(r[3])
        column = "keypoints"
        kp = _NO_KEYPOINTS if r[4] is None else blob_to_array(r[4])
        column = "local_features"
        lf = _NO_FEATURES if r[5] is None else blob_to_array(r[5])
        column = "cloud"
        cloud = None if r[6] is None else blob_to_array(r[6])
        column = "metadata"
        metadata = json.loads(r[7])
    except Exception as exc:
        why = "not a plain numeric array" if "pickle" in str(exc) else str(exc)
        raise StoreError(f"keyframe {r[0]}: its stored {column} cannot be read ({why})") from None
    return KeyframeRow(
        T, g, kp, lf, cloud=cloud, metadata=metadata, key=r[1], id=kf_id, created_at=r[8]
    )


def position(T: np.ndarray) -> tuple[float, float, float]:
    """The translation of a pose as three floats (the stores' position columns)."""
    x, y, z = np.asarray(T, dtype=np.float64)[:3, 3]
    return float(x), float(y), float(z)


def row_values(row: KeyframeRow, keyframe_id: int | None, created_at: str) -> tuple:
    """A keyframe as the values of both stores' insert: id, key, the arrays as ``.npy``
    blobs, metadata as JSON, creation time, position."""
    T = np.asarray(row.T_map_sensor, dtype=np.float64)
    return (
        keyframe_id,
        row.key,
        array_to_blob(T),
        array_to_blob(row.global_descriptor),
        array_to_blob(row.keypoints),
        array_to_blob(row.local_features),
        None if row.cloud is None else array_to_blob(row.cloud),
        json.dumps(row.metadata),
        created_at,
        *position(T),
    )


@dataclass(frozen=True)
class KeyframeFilter:
    """Which keyframes a listing or a bulk delete means; every given field must hold.

    ``bbox``: ``(x_min, y_min, x_max, y_max)`` of the keyframe position in map
    coordinates (inclusive); ``time_min``/``time_max``: the ``timestamp`` of its
    metadata (seconds, inclusive); ``sequence``: its metadata ``sequence`` (compared as
    text); ``key_prefix``: the start of its key (keyframes without a key never match).
    """

    key_prefix: str | None = None
    bbox: tuple[float, float, float, float] | None = None
    time_min: float | None = None
    time_max: float | None = None
    sequence: str | None = None

    @property
    def empty(self) -> bool:
        """True when no field is given: the filter matches every keyframe."""
        return all(
            v is None
            for v in (self.key_prefix, self.bbox, self.time_min, self.time_max, self.sequence)
        )


@dataclass(frozen=True)
class KeyframeSummary:
    """A keyframe without its features: what a listing returns."""

    id: int
    key: str | None
    T_map_sensor: np.ndarray  # [4, 4] float64
    metadata: dict[str, Any]
    created_at: str


class SettingsChangedError(StoreError):
    """The map's stored settings changed since they were read (another replica's PATCH)."""


class StoreClosedError(StoreError):
    """The store was closed meanwhile (its map is being deleted)."""


class MapStore(ABC):
    """One map's stored settings and keyframes: the source of truth of that map.

    Implementations are thread-safe. Writers are serialised by the caller (the map
    manager holds a per-map write lock). Every write is one transaction that bumps the
    map's version and is durable once the call returns.
    """

    @abstractmethod
    def close(self) -> None: ...

    @abstractmethod
    def record(self) -> MapRecord:
        """The map's stored settings; raises :class:`StoreError` if they are damaged."""

    @abstractmethod
    def update_settings(
        self,
        localizer_config: LocalizerConfig,
        calibration: Calibration,
        last_self_test: dict[str, Any] | None = None,
        *,
        expect_settings_version: int | None = None,
    ) -> MapRecord:
        """Replace the localizer settings and calibration (and, if given, the latest
        self-test's summary) in one transaction; bumps ``settings_version`` (not the
        keyframe version). Returns the new record. ``expect_settings_version``: write
        only if the stored settings are still that version, else raise
        :class:`SettingsChangedError` and change nothing (another writer came first)."""

    @abstractmethod
    def find_keys(self, keys: list[str]) -> dict[str, int]:
        """The ids of those ``keys`` that exist: ``{key: id}``."""

    @abstractmethod
    def get(self, keyframe_id: int) -> KeyframeRow:
        """One keyframe; raises :class:`~sgvloc.core.errors.NotFoundError`, or
        :class:`StoreClosedError` once the store is closed."""

    @abstractmethod
    def select(
        self, where: KeyframeFilter, *, after_id: int = 0, limit: int = 1000
    ) -> list[KeyframeSummary]:
        """Up to ``limit`` keyframes matching ``where`` with ``id > after_id``, by id."""

    @abstractmethod
    def matching_ids(self, where: KeyframeFilter) -> list[int]:
        """The ids of every keyframe matching ``where``, ascending."""

    @abstractmethod
    def extent(self) -> tuple[list[float], list[float]] | None:
        """The keyframe positions' bounding box ``(min xyz, max xyz)``; None when empty."""

    @abstractmethod
    def last_write(self) -> str | None:
        """When keyframes were last inserted or deleted (ISO 8601 UTC); None if never
        (or before the store recorded it)."""

    @abstractmethod
    def disk_bytes(self) -> int:
        """Bytes the store takes on disk."""

    @abstractmethod
    def snapshot(
        self, slim: bool = False
    ) -> AbstractContextManager[tuple[int, int, Iterator[KeyframeRow]]]:
        """A consistent read of the whole map without blocking writers: ``(version,
        count, keyframes in id order)``, valid inside the ``with`` block; ``slim``: rows
        without keypoints, local features and cloud."""

    @contextmanager
    def archive_snapshot(self) -> Iterator[tuple[int, int, int, Iterator[KeyframeRow]]]:
        """:meth:`snapshot` and the map's :meth:`next_id` of that state (read after the
        snapshot here, so at least its next id: ids only grow): ``(version, count,
        next_id, keyframes)``, for an archive."""
        with self.snapshot() as (version, count, rows):
            yield version, count, self.next_id(), rows

    @abstractmethod
    def insert_exact(
        self, rows: list[KeyframeRow], version: int, next_id: int | None = None
    ) -> None:
        """Insert rows keeping their ``id`` and ``created_at`` and set the version, in
        one transaction (to fill a new store from an archive); later inserts get ids
        from ``next_id`` on (when given) and above every id inserted."""

    @abstractmethod
    def next_id(self) -> int:
        """The smallest id the next insert may get: above every id the map ever had."""

    @abstractmethod
    def insert(self, rows: list[KeyframeRow]) -> tuple[list[int], int]:
        """Insert keyframes in one transaction and bump the version.

        Fills ``row.id`` and ``row.created_at``; returns ``(ids, new_version)``. Nothing
        is stored if any row fails.
        """

    @abstractmethod
    def delete(self, ids: list[int], *, set_version: int | None = None) -> int:
        """Delete keyframes in one transaction; returns the new version.

        The version is bumped, or set to ``set_version`` (to undo an insert whose
        in-memory half failed; a shared store bumps instead, since other replicas may
        have seen the insert). Unknown ids raise ``NotFoundError``, deleting nothing.
        """

    def changes_since(self, version: int) -> list[Change] | None:
        """The writes after ``version``, in order; None when the feed no longer reaches
        back that far (reload the whole map). A store only this process writes has no
        feed: nothing changes behind the caller's back."""
        return []

    @abstractmethod
    def fetch(self, ids: list[int], slim: bool = False) -> list[KeyframeRow]:
        """Those of ``ids`` that exist, in id order, in one read (``slim``: see
        :meth:`snapshot`)."""


class SharedBackend(ABC):
    """A store that several replicas share (PostgreSQL): maps by name, a change feed.

    The map manager keeps no files for it: every replica rebuilds its maps from the
    store and follows its changes (:meth:`catalog`, :meth:`wait_for_change`,
    :meth:`MapStore.changes_since`).
    """

    errors: tuple[type[BaseException], ...] = ()

    @abstractmethod
    def start(self) -> None:
        """Connect and create or migrate the schema; :class:`StoreUnavailableError` if
        the store cannot be reached."""

    @abstractmethod
    def check_access(self) -> None:
        """Raise :class:`StoreError` if the store refuses this replica for good (bad
        credentials, no such database): an error to fix, not an outage to wait out. A
        store that cannot be reached passes (start-up waits for it)."""

    @abstractmethod
    def close(self) -> None: ...

    @abstractmethod
    def catalog(self) -> dict[str, tuple[int, int, int]]:
        """Every map: ``{name: (incarnation, version, settings_version)}``; the
        incarnation differs when a map was deleted and made again under the same name."""

    @abstractmethod
    def create(self, name: str, record: MapRecord) -> MapStore:
        """A new empty map; :class:`~sgvloc.core.errors.ConflictError` if it exists."""

    @abstractmethod
    def open(self, name: str) -> MapStore:
        """The map ``name``; :class:`~sgvloc.core.errors.NotFoundError` if none."""

    @abstractmethod
    def drop(self, store: MapStore) -> None:
        """Delete the map and everything in it (one transaction)."""

    @abstractmethod
    def staging(self, record: MapRecord) -> MapStore:
        """A map under a hidden name, to be filled and then :meth:`publish` ed."""

    @abstractmethod
    def publish(self, store: MapStore, name: str) -> None:
        """Give a staged map its name (ConflictError if taken), in one step."""

    @abstractmethod
    def wait_for_change(self, timeout_s: float) -> bool:
        """Block until another writer announces a change (True) or ``timeout_s`` passes."""

    def describe(self) -> str:
        """Where the store is, without credentials (for logs and /v1/config)."""
        return type(self).__name__


class StoreBackend(ABC):
    """Creates and opens the store of a map whose files live in ``folder``."""

    #: exception types of the backend's driver that mean "this store failed" (logged and
    #: reported per map, never fatal to the others)
    errors: tuple[type[BaseException], ...] = ()

    @abstractmethod
    def create(self, folder: Path, record: MapRecord) -> MapStore:
        """A new store in ``folder`` holding ``record`` and no keyframes."""

    @abstractmethod
    def open(self, folder: Path) -> MapStore:
        """The existing store in ``folder``; raises :class:`StoreError`."""


def no_nul(v: str) -> str:
    """``v`` if a store can keep it as text (ValueError if not)."""
    # stores keep text in PostgreSQL too, which refuses NUL in text and in jsonb
    if "\x00" in v:
        raise ValueError("must not contain a NUL character")
    try:  # a lone surrogate (JSON "\ud800") can be neither stored nor answered
        v.encode("utf-8")
    except UnicodeEncodeError:
        raise ValueError("must be valid Unicode text (it holds a lone surrogate)") from None
    return v


#: deepest nesting of a free-form JSON object a map records (self-test, calibration)
JSON_MAX_DEPTH = 32


def plain_json(value: Any, depth: int = 0) -> Any:
    """``value`` as plain JSON data that every store can keep and every answer can carry:
    arrays (MessagePack bodies decode into NumPy) become lists, NumPy scalars numbers;
    ValueError for other types, non-finite numbers, text that is not valid Unicode or
    holds NUL, or nesting deeper than :data:`JSON_MAX_DEPTH`."""
    if depth > JSON_MAX_DEPTH:
        raise ValueError(f"nested deeper than {JSON_MAX_DEPTH} levels")
    if isinstance(value, np.ndarray | np.generic):
        value = value.tolist()
    if value is None or isinstance(value, bool):
        return value
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        if not np.isfinite(value):
            raise ValueError("holds a number that is not finite")
        return value
    if isinstance(value, str):
        return no_nul(value)
    if isinstance(value, list | tuple):
        return [plain_json(v, depth + 1) for v in value]
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise ValueError(f"has a key of type {type(k).__name__}; keys must be text")
            out[no_nul(k)] = plain_json(v, depth + 1)
        return out
    raise ValueError(f"holds a value of type {type(value).__name__}, not JSON data")
