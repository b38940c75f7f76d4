"""The map manager: every map of the data directory, in memory and on disk.

Each map is a :class:`~sgvloc.server.store.MapStore` (the source of truth, from a
:class:`~sgvloc.server.store.StoreBackend`; SQLite by default) plus a
:class:`~sgvloc.core.localizer.Localizer` rebuilt from it at start-up. The manager is
thread-safe:

- localizations run concurrently (the Localizer's readers-writer lock);
- writes to one map (insert, delete, snapshot) are serialised by that map's write lock;
  encoding happens before the lock is taken, so a slow batch does not block other
  writers while it is being encoded;
- the table of maps has its own short lock.

Insert order: validate and encode everything (no lock) -> one SQLite transaction for
the batch (the insert is acknowledged only once it commits) -> add to the Localizer; if
that fails the rows are deleted again and the version restored, so nothing partial
remains. FAISS snapshots are a start-up cache: written after ``snapshot_every`` keyframe
changes, at most ``snapshot_delay_s`` after an unsaved change, and at shutdown; a
snapshot that does not hold exactly the stored ids is ignored and rebuilt.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import json
import logging
import os
import re
import shutil
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import IO, Any, TypeVar

import numpy as np
from pydantic import ValidationError

from sgvloc.core import leave_out
from sgvloc.core.cache import FetchCache
from sgvloc.core.confidence import Calibration, shipped_calibration
from sgvloc.core.config import INDEX_SETTINGS, LocalizerConfig
from sgvloc.core.encoders import Encoder, EncoderSpec, make_encoder
from sgvloc.core.errors import (
    ConflictError,
    EncoderMismatchError,
    InputError,
    NotFoundError,
    SgvlocError,
)
from sgvloc.core.features import Features
from sgvloc.core.localizer import Keyframe, LocalizationResult, Localizer
from sgvloc.core.pose import check_rigid
from sgvloc.core.prior import Prior
from sgvloc.core.retrieval import FaissIndex
from sgvloc.core.sgv import check_runnable as sgv_check_runnable
from sgvloc.core.tracking import Seed

from .archive import ArchiveError, read_archive, write_archive
from .store import (
    INDEX_NAME,
    DuplicateKeyError,
    KeyframeFilter,
    KeyframeRow,
    KeyframeSummary,
    MapRecord,
    MapStore,
    SettingsChangedError,
    SharedBackend,
    SqliteBackend,
    StoreBackend,
    StoreClosedError,
    StoreError,
    StoreUnavailableError,
    no_nul,
    raise_if_full,
    utc_now,
)

log = logging.getLogger(__name__)
T = TypeVar("T")

MAP_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")  # whole name: fullmatch
#: tries of a settings change on a shared store that other replicas keep changing
SETTINGS_TRIES = 5
_TMP_PREFIX = ".tmp-"
_TRASH_PREFIX = ".deleted-"
#: the file whose lock keeps a second process off a maps folder
LOCK_NAME = ".lock"
#: longest a request waits for a map another thread is loading or deleting (seconds)
LOAD_WAIT_S = 10.0
#: a spooled upload untouched this long (seconds) was left by a crash
SPOOL_ABANDONED_S = 3600.0


# -- inputs ------------------------------------------------------------------------------


@dataclass
class FeaturesIn:
    """Precomputed features sent by a client, with an optional claim of their encoder.

    ``encoder`` names the encoder that produced them (the map encoder's identity name,
    e.g. ``"handcrafted"`` or ``"precomputed:egonn"``, or for precomputed maps the bare
    network name ``"egonn"``); ``fingerprint`` its exact identity. Both optional: unclaimed
    features are taken to come from the map's encoder if their dimensions fit.
    """

    global_descriptor: np.ndarray  # [G]
    keypoints: np.ndarray  # [N, 3]
    local_features: np.ndarray  # [N, D]
    encoder: str | None = None
    fingerprint: str | None = None


@dataclass
class KeyframeIn:
    """One keyframe to insert: a pose and exactly one of a raw scan or features."""

    T_map_sensor: np.ndarray  # [4, 4]
    points: np.ndarray | None = None  # [P, 3+]
    features: FeaturesIn | None = None
    key: str | None = None
    metadata: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class InsertResult:
    """Per input keyframe, in order: its id and whether it was created now."""

    ids: list[int]
    created: list[bool]
    map_version: int


def field_error(exc: SgvlocError, where: str) -> SgvlocError:
    """The same error naming the request field ``where`` (prefixed to a field it names).

    The result has ``field`` (e.g. ``keyframes[3].T_map_sensor``) and its message starts
    with it; ``raw_message`` keeps the engine's own message.
    """
    inner = getattr(exc, "field", None)
    raw = getattr(exc, "raw_message", str(exc))
    if inner:
        where = f"{where}{inner}" if inner.startswith("[") else f"{where}.{inner}"
    new = type(exc)(f"{where}: {raw}")
    new.field = where  # type: ignore[attr-defined]
    new.raw_message = raw  # type: ignore[attr-defined]
    return new


class _Unchanged(Exception):
    """A settings change that changes nothing (raised out of a change, caught), with the
    settings it found (on a shared store, perhaps newer than this replica's)."""

    def __init__(self, record: MapRecord) -> None:
        super().__init__("unchanged")
        self.record = record


def check_runnable(config: LocalizerConfig) -> None:
    """Refuse localizer settings this machine cannot run (``sgv.device`` ``"cuda"``
    without CUDA, ...) as an input error naming ``localizer.sgv``: given at creation, in a
    PATCH or an import, they would otherwise fail every localization of the map."""
    try:
        sgv_check_runnable(config.sgv)
    except ConflictError as exc:
        raise field_error(InputError(str(exc)), "localizer.sgv") from None


@functools.cache
def _candidate_fingerprint(name: str) -> str:
    """The encoder fingerprint a self-test candidate's spec builds (fixed per process:
    the code and the shipped weights)."""
    return make_encoder(EncoderSpec(**leave_out.spec_of(name))).identity.fingerprint


@contextmanager
def at_field(where: str) -> Iterator[None]:
    """Re-raise input errors inside the block as naming the request field ``where`` (a
    deadline, a conflict or a store's error is no field's fault)."""
    try:
        yield
    except (InputError, EncoderMismatchError) as exc:
        raise field_error(exc, where) from None


def _merge(base: dict[str, Any], patch: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``patch`` applied: nested dicts merged key by key, the rest replaced."""
    out = dict(base)
    for key, value in patch.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _folder_bytes(folder: Path) -> int:
    """Bytes of the files under ``folder`` (files that vanish meanwhile count 0)."""
    total = 0
    for p in folder.rglob("*"):
        try:
            total += p.stat().st_size if p.is_file() else 0
        except OSError:
            pass
    return total


def _encoder_features(
    encoder: Encoder, g: np.ndarray, keypoints: np.ndarray, local: np.ndarray, map_name: str
) -> Features:
    """Arrays as ``encoder``'s Features, checked: values and shapes (InputError),
    dimensions of another encoder (EncoderMismatchError), the encoder's own checks."""
    ident = encoder.identity
    feats = Features.validated(g, keypoints, local, ident)
    gd, d = feats.global_descriptor.shape[0], feats.local_features.shape[1]
    if gd != encoder.global_dim or (feats.num_keypoints and d != encoder.local_dim):
        raise EncoderMismatchError(
            f"features have global_dim={gd}, local_dim={d}, but map {map_name!r} "
            f"uses encoder {ident.name!r} with global_dim={encoder.global_dim}, "
            f"local_dim={encoder.local_dim}: they come from another encoder"
        )
    if not feats.num_keypoints and d != encoder.local_dim:  # no rows: the encoder's width
        feats = replace(feats, local_features=np.zeros((0, encoder.local_dim), np.float32))
    encoder.check(feats)
    return feats


#: what an inserted keyframe's key and metadata may be (the API's limits)
KEY_MAX_CHARS = 256
SEQUENCE_MAX_CHARS = 256
TAGS_MAX = 64
TAG_NAME_MAX_CHARS, TAG_VALUE_MAX_CHARS = 256, 1024


def _check_text(value: Any, what: str, max_chars: int, min_chars: int = 1) -> None:
    """A string a store keeps: ``min_chars`` to ``max_chars``, no NUL, valid Unicode."""
    if not isinstance(value, str) or not min_chars <= len(value) <= max_chars:
        raise InputError(f"{what} must be a string of {min_chars} to {max_chars} characters")
    try:
        no_nul(value)
    except ValueError as exc:
        raise InputError(f"{what} {exc}") from None


def _check_metadata(metadata: Any) -> None:
    """Keyframe metadata as an insert stores it: an object of JSON values without NaN or
    infinity, its ``timestamp``, ``sequence`` and ``tags`` of the API's types and sizes."""
    if not isinstance(metadata, dict):
        raise InputError("metadata is not an object")
    try:
        json.dumps(metadata, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise InputError(f"metadata is not plain JSON: {exc}") from None
    stamp = metadata.get("timestamp")
    if stamp is not None and (isinstance(stamp, bool) or not isinstance(stamp, int | float)):
        raise InputError("metadata.timestamp must be a number of seconds")
    if metadata.get("sequence") is not None:
        _check_text(metadata["sequence"], "metadata.sequence", SEQUENCE_MAX_CHARS)
    tags = metadata.get("tags")
    if tags is not None:
        if not isinstance(tags, dict) or len(tags) > TAGS_MAX:
            raise InputError(f"metadata.tags must be an object of at most {TAGS_MAX} entries")
        for name, value in tags.items():
            _check_text(name, "a metadata.tags name", TAG_NAME_MAX_CHARS, min_chars=0)
            _check_text(value, f"metadata.tags.{name}", TAG_VALUE_MAX_CHARS, min_chars=0)


def _check_cloud(cloud: np.ndarray, max_range: float) -> None:
    """A stored cloud as the encoder prepares one: finite ``[N, 3]`` points within the
    map's range of the sensor."""
    if cloud.ndim != 2 or cloud.shape[1] != 3 or not np.issubdtype(cloud.dtype, np.floating):
        raise InputError(f"cloud must be [N, 3] floats, got {cloud.dtype} {list(cloud.shape)}")
    if len(cloud) and not (
        np.isfinite(cloud).all() and np.abs(cloud).max() <= max_range * 1.001 + 1e-3
    ):
        raise InputError(f"cloud holds points that are not finite or beyond {max_range:g} m")


def _damaged(encoder: Encoder, keyframes: list[Keyframe]) -> str | None:
    """Which stored keyframes fail an insert's checks of poses and features (searched
    only once a map failed to load), or None."""
    bad = []
    for kf in keyframes:
        f = kf.features
        try:
            check_rigid(kf.T_map_sensor, "T_map_sensor")
            _encoder_features(encoder, f.global_descriptor, f.keypoints, f.local_features, "")
        except SgvlocError as exc:
            bad.append(f"keyframe {kf.id}: {exc}")
    if not bad:
        return None
    more = f" (and {len(bad) - 3} more)" if len(bad) > 3 else ""
    return "; ".join(bad[:3]) + more + ": the stored rows are damaged; delete or repair them"


def _lock_folder(maps_dir: Path) -> int:
    """Lock the maps folder of the embedded store for this process (a POSIX lock on its
    ``.lock`` file, which holds the owner's pid): two processes on one folder would each
    serve their own copy of the maps and overwrite each other's files. The lock goes
    with the process, even a killed one. Returns the lock file's descriptor."""
    try:
        maps_dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(maps_dir / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:  # not a folder, no permission, a full or read-only disk
        raise StoreError(
            f"cannot use {maps_dir} as the maps folder: {exc.strerror or exc}"
        ) from None
    try:
        fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
        os.close(fd)
        raise StoreError(
            f"{maps_dir} is in use by another sgvloc process (pid {holder}): the embedded "
            "store serves one process per data directory; run replicas over PostgreSQL "
            "(docs/SCALING.md)"
        ) from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


def _keyframe(encoder: Encoder, row: KeyframeRow) -> Keyframe:
    """A stored keyframe as the localizer holds it."""
    feats = Features(row.global_descriptor, row.keypoints, row.local_features, encoder.identity)
    return Keyframe(row.id, row.T_map_sensor, feats, row.cloud, row.metadata)


def _slim(kf: Keyframe) -> Keyframe:
    """A keyframe without keypoints, local features and cloud (what a replica that
    fetches them per query keeps in memory)."""
    f = kf.features
    feats = Features(
        f.global_descriptor,
        np.zeros((0, 3), np.float32),
        np.zeros((0, f.local_features.shape[1]), np.float32),
        f.encoder,
    )
    return Keyframe(kf.id, kf.T_map_sensor, feats, None, kf.metadata)


class MapUnavailableError(SgvlocError):
    """The map's folder exists but could not be loaded (503 until it is reloaded)."""


class StaleError(SgvlocError):
    """This replica has not caught up with the map version a request asked for (503
    ``stale`` with Retry-After: another replica, or this one a moment later, can answer)."""


# -- one map -----------------------------------------------------------------------------


@dataclass
class MapHandle:
    """A loaded map: its store, its localizer and its write lock."""

    name: str
    path: Path | None  # the map's folder; None in a shared store (no local files)
    record: MapRecord
    store: MapStore
    localizer: Localizer
    write_lock: threading.Lock = field(default_factory=threading.Lock)
    unsaved: int = 0  # keyframe changes since the last snapshot
    unsaved_since: float | None = None  # monotonic time of the first unsaved change
    snapshot_failures: int = 0  # failed saves in a row (the next try backs off)
    snapshot_retry_at: float = 0.0  # monotonic time before which no save is tried
    closed: bool = False

    @property
    def encoder(self) -> Encoder:
        return self.localizer.encoder

    @property
    def version(self) -> int:
        return self.localizer.version

    @property
    def num_keyframes(self) -> int:
        return len(self.localizer)

    @property
    def index_path(self) -> Path | None:
        return None if self.path is None else self.path / INDEX_NAME


class MapManager:
    """Owns every map by name. See the module docstring for the guarantees.

    ``on_change(name, keyframes)`` is called after a map is loaded, created or changed
    (``keyframes`` = its size) and after it is deleted (``keyframes`` = None); the HTTP
    layer uses it for the keyframe gauge.
    """

    def __init__(
        self,
        maps_dir: Path,
        *,
        snapshot_every: int = 1000,
        snapshot_delay_s: float = 30.0,
        on_change: Callable[[str, int | None], None] | None = None,
        backend: StoreBackend | SharedBackend | None = None,
        follow_poll_s: float = 1.0,
        features_in_memory: bool = True,
        feature_cache: int = 4096,
    ) -> None:
        self.maps_dir = Path(maps_dir)
        self.backend = backend or SqliteBackend()
        #: a store other replicas write too: maps are followed, not kept in folders
        self.shared = isinstance(self.backend, SharedBackend)
        self.follow_poll_s = follow_poll_s
        #: False: keep only poses and global descriptors in memory and fetch the
        #: candidates' local features and clouds from the store per query, through an
        #: LRU cache of ``feature_cache`` keyframes per map
        self.features_in_memory = features_in_memory
        self.feature_cache = feature_cache
        self.follow_errors = 0  # failed catch-ups in a row (the store is unreachable)
        self._load_waits = False  # loading waits for a store that does not answer
        self.snapshot_every = snapshot_every
        self.snapshot_delay_s = snapshot_delay_s
        self._on_change = on_change or (lambda name, n: None)
        self._maps: dict[str, MapHandle] = {}
        self._reserved: set[str] = set()  # names being created
        self._lock = threading.Lock()
        self.failed: dict[str, str] = {}  # map folders that could not be loaded -> why
        #: shared store: the incarnation of each map in ``failed`` when it failed
        self._failed_incarnation: dict[str, int | None] = {}
        self.loaded = threading.Event()
        #: why loading the maps failed as a whole (the process is unfit to serve), or None
        self.load_error: str | None = None
        self._stop = threading.Event()
        self._snapshotter: threading.Thread | None = None
        #: the embedded store's folder lock (one process per folder)
        self._folder_lock = None if self.shared else _lock_folder(self.maps_dir)

    # -- start-up and shutdown ----------------------------------------------------------

    def load_all(self) -> None:
        """Load every map folder; a map that fails is logged and listed in ``failed``.
        With a shared store: connect (waiting while it cannot be reached) and load every
        map it holds."""
        self._remove_leftovers()
        if self.shared:
            self._load_all_shared()
            return
        for folder in sorted(p for p in self.maps_dir.iterdir() if p.is_dir()):
            if self._stop.is_set():
                log.warning("shutting down: maps from %r on were not loaded", folder.name)
                break
            name = folder.name
            if not MAP_NAME_RE.fullmatch(name):
                log.warning("ignoring folder %s: not a valid map name", folder)
                continue
            t0 = time.perf_counter()
            try:
                handle = self._load(folder)
            except Exception as exc:  # one bad folder never keeps the others from loading
                why = str(exc) or type(exc).__name__
                log.error("map %r could not be loaded: %s", name, why)
                self.failed[name] = self._scrubbed(why, folder)
                continue
            self._serve_loaded(handle, t0)
        self.loaded.set()

    def _remove_leftovers(self) -> None:
        """Remove what a crash left in the maps folder: half-built and deleted map folders
        and spooled uploads (files). With a shared store the folder holds only uploads,
        and only those untouched for :data:`SPOOL_ABANDONED_S` go (an upload being
        received is written to all the time)."""
        self.maps_dir.mkdir(parents=True, exist_ok=True)
        now = time.time()
        for leftover in self.maps_dir.iterdir():
            if not leftover.name.startswith((_TMP_PREFIX, _TRASH_PREFIX)):
                continue
            try:
                if leftover.is_dir() and not leftover.is_symlink():
                    if self.shared:
                        continue
                    log.info("removing leftover folder %s", leftover)
                    shutil.rmtree(leftover, ignore_errors=True)
                elif not self.shared or now - leftover.stat().st_mtime > SPOOL_ABANDONED_S:
                    log.info("removing leftover file %s", leftover)
                    leftover.unlink(missing_ok=True)
            except OSError as exc:
                log.warning("could not remove leftover %s: %s", leftover, exc)

    def _load_all_shared(self) -> None:
        backend = self.backend
        assert isinstance(backend, SharedBackend)

        def catalog_now() -> dict[str, Any]:
            backend.start()
            return backend.catalog()

        catalog = self._until_the_store_answers(catalog_now, "")
        if catalog is None:  # stopped meanwhile
            return
        log.info("store: %s, %d map(s)", backend.describe(), len(catalog))
        for name in sorted(catalog):
            if self._stop.is_set():
                log.warning("shutting down: maps from %r on were not loaded", name)
                return

            def load(name: str = name) -> None:
                with contextlib.suppress(NotFoundError):  # deleted elsewhere since
                    self._load_named(name)

            # ready only once every map is served
            self._until_the_store_answers(load, f"map {name!r}: ")
        self.loaded.set()

    def _until_the_store_answers(self, fn: Callable[[], T], what: str) -> T | None:
        """``fn()``, tried again with growing pauses (0.5 s doubling to 10 s) while the
        shared store does not answer; None if the manager stops first."""
        wait = 0.5
        while not self._stop.is_set():
            try:
                out = fn()
            except StoreUnavailableError as exc:
                self._load_waits = True
                log.warning("%s%s; trying again in %.0f s", what, exc, wait)
                self._stop.wait(wait)
                wait = min(10.0, wait * 2)
                continue
            self._load_waits = False
            return out
        return None

    @property
    def store_reachable(self) -> bool | None:
        """A shared store: False while the last call of the loading or of the catch-up
        with the other replicas failed (the log says why); None for SQLite."""
        if not self.shared:
            return None
        return self.follow_errors == 0 and not self._load_waits

    def _load_named(self, name: str) -> None:
        """Load map ``name`` from the shared store and serve it (or list it as failed;
        an unreachable store is left to the next catch-up)."""
        backend = self.backend
        assert isinstance(backend, SharedBackend)
        with self._lock:
            if name in self._maps or name in self._reserved:
                return
            self._reserved.add(name)
        t0 = time.perf_counter()
        store = None
        try:
            store = backend.open(name)
            handle = self._load_store(store, None, name)
        except (StoreUnavailableError, NotFoundError):
            raise
        except StoreClosedError:  # deleted while it loaded: nothing to serve, nothing failed
            log.info("map %r was deleted while it loaded", name)
            return
        except Exception as exc:
            why = str(exc) or type(exc).__name__
            log.error("map %r could not be loaded: %s", name, why)
            self.failed[name] = why
            # which map failed: one made again under the name is tried afresh (sync)
            self._failed_incarnation[name] = getattr(store, "incarnation", None)
            return
        finally:
            with self._lock:
                self._reserved.discard(name)
        self._serve_loaded(handle, t0)

    def _serve_loaded(self, handle: MapHandle, t0: float) -> None:
        """Publish a map loaded at start-up or from the shared store (since ``t0``)."""
        self._publish(handle)
        log.info(
            "loaded map %r: %d keyframes, version %d, in %.2f s",
            handle.name,
            handle.num_keyframes,
            handle.version,
            time.perf_counter() - t0,
        )

    def _load(self, folder: Path) -> MapHandle:
        return self._load_store(self.backend.open(folder), folder, folder.name)  # type: ignore[arg-type]

    def _load_store(self, store: MapStore, folder: Path | None, name: str) -> MapHandle:
        """A map in memory from its store (closed again if it fails)."""
        try:
            record = store.record()
            if record.name != name:
                raise StoreError(f"{folder or name}: database names map {record.name!r}")
            encoder = make_encoder(record.encoder_spec)
            if encoder.identity.fingerprint != record.encoder_fingerprint:
                raise StoreError(
                    f"map {record.name!r} was built with encoder fingerprint "
                    f"{record.encoder_fingerprint}, but its spec now builds "
                    f"{encoder.identity.fingerprint} (changed encoder code or model file); "
                    "its stored features cannot be mixed with new ones"
                )
            localizer = Localizer(
                encoder,
                record.localizer_config,
                keep_clouds=record.keep_clouds,
                calibration=record.calibration,
            )
            self._attach_source(localizer, store)
            version, keyframes = self._read_keyframes(store, encoder)
            handle = MapHandle(name, folder, record, store, localizer)
            index = self._usable_snapshot(handle, [kf.id for kf in keyframes])
            try:
                localizer.restore(keyframes, version, index)
            except Exception as exc:  # a damaged row: say which, if the checks can
                raise StoreError(_damaged(encoder, keyframes) or str(exc)) from None
            if index is None:
                self._save_snapshot(handle)
            return handle
        except BaseException:
            store.close()
            raise

    def _read_keyframes(self, store: MapStore, encoder: Encoder) -> tuple[int, list[Keyframe]]:
        """The map's version and keyframes from one consistent read of its store (without
        local features and clouds when they are fetched per query)."""
        with store.snapshot(slim=not self.features_in_memory) as (version, _, rows):
            return version, [_keyframe(encoder, row) for row in rows]

    def _attach_source(self, localizer: Localizer, store: MapStore) -> None:
        """Without features in memory: the localizer fetches whole keyframes from
        ``store`` (one read per query for the candidates it does not hold)."""
        if self.features_in_memory:
            return
        encoder = localizer.encoder

        def fetch(ids: list[int]) -> dict[int, Keyframe]:
            return {row.id: _keyframe(encoder, row) for row in store.fetch(ids)}

        localizer.keyframe_source = FetchCache(fetch, self.feature_cache)

    def _usable_snapshot(self, handle: MapHandle, ids: list[int]) -> FaissIndex | None:
        """The saved FAISS snapshot if it agrees with the store, else None (logged)."""
        path = handle.index_path
        if path is None:  # a shared store keeps no snapshot: the index is built
            return None
        if not path.exists():
            log.info("map %r: no index snapshot, rebuilding from the store", handle.name)
            return None
        try:
            index = FaissIndex.load(path)
        except SgvlocError as exc:
            log.warning("map %r: index snapshot unreadable (%s), rebuilding", handle.name, exc)
            return None
        cfg = handle.record.localizer_config.retrieval
        snap_ids = index.ids().tolist()
        if (
            index.dim != handle.encoder.global_dim
            or index.config.index_settings() != cfg.index_settings()
        ):
            why = "dimension or retrieval settings differ"
        elif snap_ids != ids:
            why = f"it holds {len(snap_ids)} ids, the store {len(ids)} (or different ones)"
        else:
            log.info("map %r: using index snapshot (%d ids)", handle.name, len(ids))
            return index
        log.warning(
            "map %r: index snapshot disagrees with the store (%s), rebuilding", handle.name, why
        )
        return None

    def start_snapshotter(self) -> None:
        """Start the background thread that saves changed maps' snapshots, or with a
        shared store the one that follows the other replicas' changes."""
        if self._snapshotter is None:
            loop, name = (
                (self._follow_loop, "sgvloc-follow")
                if self.shared
                else (self._snapshot_loop, "sgvloc-snapshots")
            )
            self._snapshotter = threading.Thread(target=loop, name=name, daemon=True)
            self._snapshotter.start()

    # -- following a shared store -------------------------------------------------------

    def _follow_loop(self) -> None:
        """Catch up whenever a change is announced, and at least every ``follow_poll_s``."""
        backend = self.backend
        assert isinstance(backend, SharedBackend)
        while not self._stop.is_set():
            backend.wait_for_change(self.follow_poll_s)
            if self._stop.is_set():
                return
            try:
                self.sync()
            except Exception as exc:  # the thread must live on: the next round tries again
                self.follow_errors += 1
                expected = isinstance(exc, (StoreUnavailableError, *backend.errors))
                level = logging.WARNING if self.follow_errors == 1 else logging.DEBUG
                log.log(
                    level if expected else logging.ERROR,
                    "catching up with the store failed (serving what is held): %s",
                    exc,
                    exc_info=not expected,
                )
                self._stop.wait(min(5.0, 0.5 * self.follow_errors))
                continue
            if self.follow_errors:
                log.info("caught up with the store again after %d failed tries", self.follow_errors)
            self.follow_errors = 0

    def sync(self) -> None:
        """Bring every map in line with the shared store: load maps made elsewhere, drop
        maps deleted elsewhere, apply keyframe changes and settings changes."""
        backend = self.backend
        assert isinstance(backend, SharedBackend)
        with self._lock:  # before the catalog: a map made here meanwhile is not dropped
            local = dict(self._maps)
        catalog = backend.catalog()
        for name, handle in local.items():
            with self._lock:
                if name in self._reserved:  # being deleted here: the delete decides
                    continue
            entry = catalog.get(name)
            if entry is None or entry[0] != getattr(handle.store, "incarnation", None):
                self._forget(handle, "deleted by another replica")
        for name in list(self.failed):
            entry, failed_as = catalog.get(name), self._failed_incarnation.get(name)
            if entry is None or (failed_as is not None and entry[0] != failed_as):
                # gone (not degraded), or made again under the name: tried afresh below
                self.failed.pop(name, None)
                self._failed_incarnation.pop(name, None)
        problems = []  # one map that cannot catch up holds back none of the others
        for name, (_, version, settings_version) in catalog.items():
            with self._lock:
                handle = self._maps.get(name)
                if name in self._reserved:  # a delete here holds it (maybe for seconds,
                    continue  # waiting on the store): the other maps catch up meanwhile
            if handle is None:
                if name not in self.failed:
                    try:
                        self._load_named(name)
                    except NotFoundError:  # deleted between the catalog and the load
                        pass
                continue
            try:
                if version != handle.version:
                    self.sync_map(handle)
                if settings_version != handle.record.settings_version:
                    self._refresh_settings(handle)
            except StoreClosedError:  # deleted since the catalog: the next round drops it
                continue
            except (StoreUnavailableError, *backend.errors):  # the store itself: the round
                raise
            except Exception as exc:  # this map's data (settings of a newer version, ...)
                problems.append(f"map {name!r}: {exc}")
        if problems:  # counted as a failed round, after every other map caught up
            raise StoreError("; ".join(problems))

    def sync_map(self, handle: MapHandle) -> None:
        """Catch one map up with the shared store now (no-op for a local store)."""
        if self.shared:
            with handle.write_lock:
                if not handle.closed:
                    self._catch_up(handle)

    def _forget(self, handle: MapHandle, why: str) -> None:
        with self._lock:
            if self._maps.get(handle.name) is handle:
                del self._maps[handle.name]
        with handle.write_lock:
            handle.closed = True
            handle.store.close()
        self._on_change(handle.name, None)
        log.info("map %r: %s", handle.name, why)

    def _refresh_settings(self, handle: MapHandle) -> None:
        with handle.write_lock:
            if handle.closed:
                return
            record = handle.store.record()
            cal = record.calibration or shipped_calibration(record.encoder_spec.kind)
            handle.localizer.update_settings(record.localizer_config, cal)
            handle.record = record
        log.info("map %r: settings version %d applied", handle.name, record.settings_version)

    def _catch_up(self, handle: MapHandle, until: int | None = None) -> None:
        """Apply the store's changes after the version held, up to ``until`` (all when
        None). Call under the map's write lock. A feed that no longer reaches back
        reloads the map whole."""
        have = handle.localizer.version
        changes = handle.store.changes_since(have)
        if changes is None:
            log.warning("map %r: too far behind the change feed, reloading it", handle.name)
            version, keyframes = self._read_keyframes(handle.store, handle.encoder)
            if until is None or version <= until:
                handle.localizer.restore(keyframes, version)
            self._on_change(handle.name, handle.num_keyframes)
            return
        changes = [c for c in changes if until is None or c.version <= until]
        if not changes:
            return
        add: set[int] = set()
        remove: set[int] = set()
        for change in changes:
            if change.kind == "insert":
                add |= set(change.ids)
                remove -= set(change.ids)
            else:
                add -= set(change.ids)
                remove |= set(change.ids)
        rows = handle.store.fetch(sorted(add), slim=not self.features_in_memory) if add else []
        handle.localizer.apply_changes(
            [_keyframe(handle.encoder, row) for row in rows], sorted(remove), changes[-1].version
        )
        self._on_change(handle.name, handle.num_keyframes)
        log.debug("map %r: caught up to version %d", handle.name, handle.version)

    def _before_own(self, handle: MapHandle, version: int) -> bool:
        """After this replica's write made ``version``: apply the writes of other
        replicas that came before it, so that the own change can follow. False when that
        failed (the follower applies everything later; the write itself is stored)."""
        if not self.shared:
            return True
        try:
            self._catch_up(handle, until=version - 1)
        except StoreError as exc:  # an unreachable store among them
            log.warning("map %r: catching up after a write failed (%s); later", handle.name, exc)
            return False
        return handle.localizer.version == version - 1

    def _snapshot_loop(self) -> None:
        tick = min(1.0, self.snapshot_delay_s / 4)
        while not self._stop.wait(tick):
            now = time.monotonic()
            for handle in self.list():
                since = handle.unsaved_since
                due = since is not None and now - since >= self.snapshot_delay_s
                if due and now >= handle.snapshot_retry_at:
                    try:
                        self.snapshot(handle.name)
                    except NotFoundError:  # deleted since the list was taken
                        continue
                    except Exception:  # the loop goes on for every other map
                        log.exception("map %r: saving the index snapshot failed", handle.name)

    def _scrubbed(self, why: str, folder: Path) -> str:
        """``why`` as callers may see it: the map's name, never the server's paths."""
        return (
            why.replace(str(folder), f"map {folder.name}")
            .replace(str(self.maps_dir.resolve()), "<maps>")
            .replace(str(self.maps_dir), "<maps>")
        )

    def reload(self, name: str) -> MapHandle:
        """Load a map whose folder failed to load (at start-up or by an earlier reload),
        once its cause is fixed, without a restart. Raises :class:`ConflictError` if the
        map is loaded, :class:`NotFoundError` if there is no such folder, and
        :class:`MapUnavailableError` if it still cannot be loaded."""
        with self._lock:
            if name in self._maps or name in self._reserved:
                raise ConflictError(
                    f"map {name!r} is loaded (or being created or deleted); nothing to reload"
                )
            self._reserved.add(name)
        folder = self.maps_dir / name
        try:
            if not MAP_NAME_RE.fullmatch(name) or not (self.shared or folder.is_dir()):
                self.failed.pop(name, None)
                raise NotFoundError(f"map {name!r} does not exist")
            try:
                if self.shared:
                    try:
                        store = self.backend.open(name)  # type: ignore[arg-type]
                    except NotFoundError:
                        self.failed.pop(name, None)
                        raise
                    handle = self._load_store(store, None, name)
                else:
                    handle = self._load(folder)
            except (NotFoundError, StoreUnavailableError):
                raise
            except Exception as exc:
                why = str(exc) or type(exc).__name__
                log.error("map %r could not be reloaded: %s", name, why)
                self.failed[name] = self._scrubbed(why, folder)
                raise MapUnavailableError(
                    f"map {name!r} still cannot be loaded: {self.failed[name]}"
                ) from None
            self._publish(handle)
        finally:
            with self._lock:
                self._reserved.discard(name)
        log.info("reloaded map %r: %d keyframes", name, handle.num_keyframes)
        return handle

    def _publish(self, handle: MapHandle) -> None:
        """Serve a map that was just created or loaded (under a reservation of its name,
        or at start-up)."""
        with self._lock:
            self._maps[handle.name] = handle
        self.failed.pop(handle.name, None)
        self._on_change(handle.name, handle.num_keyframes)

    def stop_loading(self) -> None:
        """Make :meth:`load_all` stop after the map it is loading (shutdown)."""
        self._stop.set()

    def close(self) -> None:
        """Stop the snapshot thread, save every changed map's snapshot, close the stores."""
        self._stop.set()
        if self._snapshotter is not None:
            self._snapshotter.join(timeout=30)
        with self._lock:
            handles = list(self._maps.values())
            self._maps.clear()
        for handle in handles:
            with handle.write_lock:
                if handle.unsaved:
                    self._save_snapshot(handle)
                handle.closed = True
                handle.store.close()
        if isinstance(self.backend, SharedBackend):
            self.backend.close()
        if self._folder_lock is not None:
            os.close(self._folder_lock)
            self._folder_lock = None

    # -- maps ---------------------------------------------------------------------------

    def list(self) -> list[MapHandle]:
        """The loaded maps, by name."""
        with self._lock:
            return [self._maps[n] for n in sorted(self._maps)]

    def get(self, name: str, *, load: bool = False) -> MapHandle:
        """A loaded map; raises :class:`MapUnavailableError` for a map whose folder failed
        to load, else :class:`NotFoundError`. ``load`` (a shared store; call off the event
        loop): a map another replica made since this one last caught up is loaded now
        rather than answered 404 (an insert or a localize right after its creation)."""
        with self._lock:
            handle = self._maps.get(name)
        loadable = load and self.shared and name not in self.failed  # failed: reload only
        if handle is None and loadable and MAP_NAME_RE.fullmatch(name):
            try:
                self._load_named(name)
            except NotFoundError:
                pass
            deadline = time.monotonic() + LOAD_WAIT_S
            while True:  # the follower may be loading it (or a delete ending) meanwhile
                with self._lock:
                    handle = self._maps.get(name)
                    busy = name in self._reserved
                if handle is not None or not busy or time.monotonic() > deadline:
                    break
                time.sleep(0.02)
        if handle is None:
            why = self.failed.get(name)
            if why is not None:
                raise MapUnavailableError(
                    f"map {name!r} could not be loaded ({why}); fix the cause, then POST "
                    f"/v1/maps/{name}/reload (admin)"
                )
            raise NotFoundError(f"map {name!r} does not exist")
        return handle

    @staticmethod
    def _check_name(name: str) -> None:
        if not MAP_NAME_RE.fullmatch(name):
            raise field_error(
                InputError(
                    f"map name {name!r} is invalid: use 1-64 letters, digits, '_', '.' or '-', "
                    "starting with a letter or digit"
                ),
                "name",
            )

    def _reserve(self, name: str, taken: str = "") -> None:
        """Reserve a new map's name while it is built (ConflictError if taken, ending
        with ``taken``: what to do instead)."""
        with self._lock:
            if name in self._maps or name in self._reserved:
                raise ConflictError(f"map {name!r} exists already{taken}")
            if not self.shared and (self.maps_dir / name).exists():
                why = self.failed.get(name, "unknown reason")
                raise ConflictError(
                    f"a folder for map {name!r} exists but could not be loaded ({why}); "
                    "remove it from the data directory first"
                )
            self._reserved.add(name)

    @contextmanager
    def _reserving(self, name: str, taken: str = "") -> Iterator[None]:
        """Hold ``name`` (ConflictError if taken) while a new map is made under it."""
        self._reserve(name, taken)
        try:
            yield
        finally:
            with self._lock:
                self._reserved.discard(name)

    @contextmanager
    def _building(self, name: str, taken: str = "") -> Iterator[tuple[Path, Path]]:
        """Reserve ``name`` and give ``(tmp, folder)``: a new map is built whole in
        ``tmp`` (store, index snapshot) and renamed to ``folder`` by the block, so a map
        folder exists only once it is complete. If the block fails, both are removed (a
        full disk raises :class:`~sgvloc.core.errors.StorageFullError`)."""
        self._reserve(name, taken)
        try:
            self.maps_dir.mkdir(parents=True, exist_ok=True)
            tmp = self.maps_dir / f"{_TMP_PREFIX}{name}-{uuid.uuid4().hex[:8]}"
            tmp.mkdir()
            folder = self.maps_dir / name
            try:
                yield tmp, folder
            except BaseException as exc:
                for leftover in (tmp, folder):
                    if leftover.exists():
                        shutil.rmtree(leftover, ignore_errors=True)
                raise_if_full(exc)
                raise
        finally:
            with self._lock:
                self._reserved.discard(name)

    def create(
        self,
        name: str,
        encoder_spec: EncoderSpec | None = None,
        localizer_config: LocalizerConfig | None = None,
        *,
        keep_clouds: bool = True,
        calibration: Calibration | None = None,
        self_test: dict[str, Any] | None = None,
    ) -> MapHandle:
        """Create an empty map. Raises InputError (bad name/spec) or ConflictError (exists).

        ``calibration``: the confidence model (default: the one shipped for the encoder's
        kind), recorded with the map so that its answers do not change with an upgrade.
        ``self_test``: the encoder self-test the map was chosen by, recorded as given.
        """
        self._check_name(name)
        encoder_spec = encoder_spec or EncoderSpec()
        localizer_config = localizer_config or LocalizerConfig()
        check_runnable(localizer_config)

        def build() -> tuple[MapRecord, Localizer]:
            with at_field("encoder"):
                encoder = make_encoder(encoder_spec)
            record = MapRecord(
                name=name,
                encoder_spec=encoder_spec,
                localizer_config=localizer_config,
                encoder_fingerprint=encoder.identity.fingerprint,
                keep_clouds=keep_clouds and encoder_spec.kind != "precomputed",
                created_at=utc_now(),
                calibration=calibration or shipped_calibration(encoder_spec.kind),
                self_test=self_test,
            )
            localizer = Localizer(
                encoder,
                localizer_config,
                keep_clouds=record.keep_clouds,
                calibration=record.calibration,
            )
            return record, localizer

        if isinstance(self.backend, SharedBackend):
            with self._reserving(name):
                record, localizer = build()
                store = self.backend.create(name, record)
                self._attach_source(localizer, store)
                handle = MapHandle(name, None, record, store, localizer)
                self._publish(handle)
        else:
            with self._building(name) as (tmp, folder):
                record, localizer = build()
                self.backend.create(tmp, record).close()
                localizer.index.save(tmp / INDEX_NAME)
                tmp.rename(folder)
                handle = MapHandle(name, folder, record, self.backend.open(folder), localizer)
                self._publish(handle)
        log.info("created map %r (encoder %r)", name, localizer.encoder.identity.name)
        return handle

    def delete(self, name: str, force: bool = False) -> None:
        """Delete a map and its folder; raises :class:`NotFoundError`, or
        :class:`MapUnavailableError` for a map that failed to load, unless ``force``
        (then its folder or rows go, unread: :meth:`_discard_failed`)."""
        shared = self.shared
        if shared:  # a map another replica made since this one last caught up
            with contextlib.suppress(NotFoundError, MapUnavailableError):
                self.get(name, load=True)
        with self._lock:
            # a shared store's map is served until its rows are gone (the drop may wait
            # on the store for seconds, and fail); a folder is renamed away at once
            handle = self._maps.get(name) if shared else self._maps.pop(name, None)
            if handle is not None:  # neither the follower nor a reload loads it meanwhile
                self._reserved.add(name)
        if handle is None:
            why = self.failed.get(name)
            if why is not None and force:
                self._discard_failed(name, why)
                return
            if why is not None:  # its folder or rows are left to the operator
                raise MapUnavailableError(
                    f"map {name!r} could not be loaded ({why}), so it is not deleted: fix "
                    f"the cause and POST /v1/maps/{name}/reload (admin), or delete it "
                    f"unread with DELETE /v1/maps/{name}?force=true (its keyframes are lost)"
                )
            raise NotFoundError(f"map {name!r} does not exist")
        trash = None
        try:
            with handle.write_lock:
                if handle.closed:  # a delete beside this one got there first
                    raise NotFoundError(f"map {name!r} does not exist")
                if shared:
                    try:  # on StoreUnavailableError nothing changed: it is still served
                        self.backend.drop(handle.store)  # one transaction; replicas follow
                    except NotFoundError:  # another replica deleted it meanwhile
                        pass
                    with self._lock:
                        if self._maps.get(name) is handle:
                            del self._maps[name]
                handle.closed = True
                handle.store.close()
                if handle.path is not None:  # a map folder: one atomic rename, then clean-up
                    trash = self._trash_path(name)
                    handle.path.rename(trash)
        finally:
            with self._lock:
                self._reserved.discard(name)
        if trash is not None:
            shutil.rmtree(trash, ignore_errors=True)
        self._on_change(name, None)
        log.info("deleted map %r", name)

    def _trash_path(self, name: str) -> Path:
        """Where a deleted map's folder is renamed before it is removed (one atomic step;
        a crash leaves it to :meth:`_remove_leftovers`)."""
        return self.maps_dir / f"{_TRASH_PREFIX}{name}-{uuid.uuid4().hex[:8]}"

    def _discard_failed(self, name: str, why: str) -> None:
        """Delete a map that could not be loaded without reading it: its folder, or its
        rows of a shared store (the other replicas drop it from their failed list)."""
        with self._lock:
            if name in self._maps or name in self._reserved or name not in self.failed:
                raise ConflictError(f"map {name!r} is being loaded, made or deleted; retry")
            self._reserved.add(name)
        try:
            if isinstance(self.backend, SharedBackend):
                with contextlib.suppress(NotFoundError):  # gone already
                    store = self.backend.open(name)
                    try:
                        failed_as = self._failed_incarnation.get(name)
                        if failed_as is not None and store.incarnation != failed_as:
                            # deleted elsewhere and made again: not the map that failed
                            raise ConflictError(
                                f"map {name!r} was made again since it failed to load here; "
                                "retry once this replica has followed"
                            )
                        self.backend.drop(store)
                    finally:
                        store.close()
            else:
                folder = self.maps_dir / name
                if folder.exists():
                    trash = self._trash_path(name)
                    try:
                        folder.rename(trash)
                    except OSError as exc:
                        raise MapUnavailableError(
                            f"map {name!r}: its folder could not be removed ({exc.strerror})"
                        ) from None
                    shutil.rmtree(trash, ignore_errors=True)
            with self._lock:
                self.failed.pop(name, None)
                self._failed_incarnation.pop(name, None)
        finally:
            with self._lock:
                self._reserved.discard(name)
        self._on_change(name, None)
        log.warning("deleted map %r unread: it could not be loaded (%s)", name, why)

    def update_settings(
        self,
        name: str,
        localizer: dict[str, Any] | None = None,
        calibration: Calibration | None = None,
    ) -> MapHandle:
        """Change a map's localizer settings and/or calibration after creation.

        ``localizer`` is merged into the current settings (nested objects key by key)
        and validated whole; the index's retrieval settings cannot change (it was built
        with them; the query's, ``combine`` and the offsets, can). Stored in one
        transaction, then swapped into the running map; the keyframe version is unchanged.
        """
        handle = self.get(name, load=True)
        with handle.write_lock:
            if handle.closed:
                raise NotFoundError(f"map {name!r} does not exist")

            def change(base: MapRecord) -> tuple[LocalizerConfig, Calibration]:
                current = base.localizer_config
                if not localizer:
                    config = current
                else:
                    merged = _merge(current.model_dump(), localizer)
                    try:
                        config = LocalizerConfig.model_validate(merged)
                    except ValidationError as exc:
                        err = exc.errors()[0]
                        where = ".".join(str(x) for x in err["loc"])
                        raise field_error(InputError(err["msg"]), f"localizer.{where}") from None
                    if config.sgv != current.sgv:  # settings it leaves alone stay as they are
                        check_runnable(config)
                    if config.retrieval.index_settings() != current.retrieval.index_settings():
                        raise field_error(
                            InputError(
                                "the index's retrieval settings cannot change after creation "
                                f"({', '.join(INDEX_SETTINGS)}: the index was built with "
                                "them): create a new map"
                            ),
                            "localizer.retrieval",
                        )
                before = self._calibration_of(handle, base)
                cal = calibration or before
                if config == current and cal.fingerprint == before.fingerprint:
                    raise _Unchanged(base)  # nothing to record: no new settings version
                return config, cal

            try:
                record = self._write_settings(handle, change)
            except _Unchanged as same:
                if same.record.settings_version != handle.record.settings_version:
                    # another replica's change this one has not followed yet: answer it
                    found = same.record
                    handle.localizer.update_settings(
                        found.localizer_config, self._calibration_of(handle, found)
                    )
                    handle.record = found
                return handle
            config, cal = record.localizer_config, self._calibration_of(handle, record)
            handle.localizer.update_settings(config, cal)
            handle.record = record
        log.info(
            "map %r: settings changed (settings version %d, calibration %s)",
            name,
            record.settings_version,
            cal.fingerprint,
        )
        return handle

    def _write_settings(
        self,
        handle: MapHandle,
        change: Callable[[MapRecord], tuple[LocalizerConfig, Calibration]],
        last_self_test: dict[str, Any] | None = None,
    ) -> MapRecord:
        """Store ``change`` applied to the map's settings (call under the write lock).
        On a shared store the settings are read from the store, and written only if no
        other replica changed them meanwhile (else read again, a few times), so that two
        replicas' PATCHes never undo each other."""
        if not self.shared:
            config, cal = change(handle.record)
            return handle.store.update_settings(config, cal, last_self_test)
        for _ in range(SETTINGS_TRIES):
            base = handle.store.record()
            config, cal = change(base)
            try:
                return handle.store.update_settings(
                    config, cal, last_self_test, expect_settings_version=base.settings_version
                )
            except SettingsChangedError:
                continue
        raise ConflictError(
            f"map {handle.name!r}: its settings kept changing under other replicas' writes; retry"
        )

    @staticmethod
    def _calibration_of(handle: MapHandle, record: MapRecord) -> Calibration:
        """The calibration a record answers with (none stored: the one running, which
        is the shipped one of its encoder kind)."""
        stored = record.calibration
        return stored if stored is not None else handle.localizer.calibration

    def self_test_plan(
        self, name: str, queries: int, gap_s: float, gap_keyframes: int, radius_m: float
    ) -> tuple[int, leave_out.Plan]:
        """The map's version and the queries of its leave-out self-test
        (:mod:`sgvloc.core.leave_out`)."""
        handle = self.get(name, load=True)
        version = handle.version
        ids, xyz, stamps = handle.localizer.keyframe_table()
        plan = leave_out.plan(
            ids,
            xyz,
            stamps,
            queries=queries,
            gap_s=gap_s,
            gap_keyframes=gap_keyframes,
            radius_m=radius_m,
        )
        return version, plan

    def _unchanged(self, name: str, version: int) -> MapHandle:
        """The map, if still at the self-test's ``version`` (else 409)."""
        handle = self.get(name, load=True)
        if handle.version != version:
            raise ConflictError(
                f"map {name!r} changed during the self-test (version {version} -> "
                f"{handle.version}); run it again"
            )
        return handle

    def self_test_query(
        self,
        name: str,
        version: int,
        plan: leave_out.Plan,
        keyframe_id: int,
        radius_m: float,
        candidate: Localizer | None = None,
    ) -> dict[str, Any]:
        """One query of a self-test: its record (409 if the map changed since the plan).
        With ``candidate`` (:meth:`self_test_candidate`) that encoder answers it."""
        handle = self._unchanged(name, version)
        loc = handle.localizer if candidate is None else candidate
        inside = keyframe_id in plan.in_coverage
        if candidate is not None and not candidate.holds(keyframe_id):
            return leave_out.unanswered(keyframe_id, inside)
        kf, result = loc.localize_keyframe(keyframe_id, plan.searched(keyframe_id))
        top = result.reranked[0].keyframe_id if result.reranked else None
        at = None if top is None else loc.keyframe(top).T_map_sensor[:3, 3]
        return leave_out.record(keyframe_id, inside, kf.T_map_sensor, result, at, radius_m)

    def self_test_candidate(
        self, name: str, version: int, spec: dict[str, Any], max_keyframes: int
    ) -> Localizer:
        """An empty localizer with the encoder ``spec`` and the map's localizer settings
        (its verdict from the shipped calibration of that encoder's kind), to measure
        that encoder on the map's keyframes (:meth:`self_test_encode`). 422 on
        ``encoders`` if the map keeps no clouds to encode again or has more than
        ``max_keyframes`` (the candidate holds its own copy of every keyframe)."""
        handle = self._unchanged(name, version)
        self.check_comparable(handle, max_keyframes)
        with at_field("encoders"):
            encoder = make_encoder(EncoderSpec(**spec))
        return Localizer(encoder, handle.record.localizer_config)

    def own_candidate(self, name: str) -> str | None:
        """The self-test candidate (:data:`sgvloc.core.leave_out.CANDIDATES`) whose spec
        builds the map's encoder (the same fingerprint), or None."""
        fingerprint = self.get(name, load=True).record.encoder_fingerprint
        return next(
            (c for c in leave_out.CANDIDATES if _candidate_fingerprint(c) == fingerprint), None
        )

    def check_comparable(self, handle: MapHandle, max_keyframes: int) -> None:
        """422 on ``encoders`` unless other encoders can be measured on the map: it keeps
        its keyframes' clouds and has at most ``max_keyframes``."""
        name = handle.name
        if handle.num_keyframes > max_keyframes:
            raise field_error(
                InputError(
                    f"map {name!r} has {handle.num_keyframes} keyframes; encoders are "
                    f"compared on maps of at most {max_keyframes} (max_self_test_keyframes): "
                    "leave out encoders, or compare them on a sample of the raw scans "
                    "(sgvloc build-map --choose-encoder --dry-run --limit N)"
                ),
                "encoders",
            )
        if not handle.record.keep_clouds:
            raise field_error(
                InputError(
                    f"map {name!r} keeps no keyframe clouds (keep_clouds is false): other "
                    "encoders cannot be measured on it; leave out encoders, or compare "
                    "them on the raw scans (sgvloc build-map --choose-encoder --dry-run)"
                ),
                "encoders",
            )

    def self_test_encode(
        self, name: str, version: int, candidate: Localizer, ids: list[int]
    ) -> int:
        """Encode the map's keyframes ``ids`` again from their stored clouds into
        ``candidate``, ids and poses kept. Returns how many it could not encode: stored
        without a cloud (inserted as features), or nothing in the cloud the candidate
        can describe (an empty BEV image, too few points)."""
        handle = self._unchanged(name, version)
        whole = handle.localizer.whole_keyframes(ids)
        made, skipped = [], 0
        for i in ids:
            kf = whole.get(int(i))
            if kf is None:
                raise ConflictError(f"keyframe {i} was removed during the self-test")
            if kf.cloud is None:
                skipped += 1
                continue
            try:
                made.append(
                    candidate.make_keyframe(kf.T_map_sensor, scan=kf.cloud, keyframe_id=int(i))
                )
            except InputError:
                skipped += 1
        candidate.add_keyframes(made)
        return skipped

    def record_self_test(self, name: str, summary: dict[str, Any]) -> MapHandle:
        """Store a self-test's summary with the map's settings (``last_self_test``)."""
        handle = self.get(name, load=True)
        with handle.write_lock:
            if handle.closed:
                raise NotFoundError(f"map {name!r} does not exist")
            record = self._write_settings(
                handle,
                lambda base: (base.localizer_config, self._calibration_of(handle, base)),
                summary,
            )
            handle.localizer.update_settings(
                record.localizer_config, self._calibration_of(handle, record)
            )
            handle.record = record
        log.info("map %r: self-test recorded (%s)", name, summary.get("figures"))
        return handle

    # -- keyframes ----------------------------------------------------------------------

    def _features(self, handle: MapHandle, f: FeaturesIn) -> Features:
        """Client features as this map's Features; 409 if they are another encoder's."""
        encoder = handle.encoder
        ident = encoder.identity
        spec = handle.record.encoder_spec
        if f.encoder is not None and f.encoder not in (ident.name, spec.name):
            raise field_error(
                EncoderMismatchError(
                    f"features come from encoder {f.encoder!r}, but map {handle.name!r} "
                    f"uses {ident.name!r} (fingerprint {ident.fingerprint})"
                ),
                "features.encoder",
            )
        if f.fingerprint is not None and f.fingerprint != ident.fingerprint:
            raise field_error(
                EncoderMismatchError(
                    f"features have encoder fingerprint {f.fingerprint!r}, but map "
                    f"{handle.name!r} uses {ident.name!r} (fingerprint {ident.fingerprint})"
                ),
                "features.fingerprint",
            )
        # JSON cannot say the shape of an empty array: [] is no keypoints, [N, 3] and
        # [N, D] with N = 0 (MessagePack sends the shape itself)
        kp, lf = np.asarray(f.keypoints), np.asarray(f.local_features)
        if kp.size == 0 and lf.size == 0:
            kp, lf = kp.reshape(0, 3), lf.reshape(0, encoder.local_dim)
        with at_field("features"):
            return _encoder_features(encoder, f.global_descriptor, kp, lf, handle.name)

    def _check_scan_allowed(self, handle: MapHandle) -> None:
        spec = handle.record.encoder_spec
        if spec.kind == "precomputed":
            raise field_error(
                EncoderMismatchError(
                    f"map {handle.name!r} takes precomputed features from {spec.name!r} "
                    f"(global_dim={spec.global_dim}, local_dim={spec.local_dim}), not raw "
                    "scans: send features instead of points"
                ),
                "points",
            )

    def _make_keyframe(self, handle: MapHandle, item: KeyframeIn) -> Keyframe:
        with at_field("T_map_sensor"):
            T = check_rigid(item.T_map_sensor, "T_map_sensor")
        if (item.points is None) == (item.features is None):
            raise InputError("give exactly one of points or features")
        if item.points is not None:
            self._check_scan_allowed(handle)
            with at_field("points"):
                return handle.localizer.make_keyframe(T, scan=item.points, metadata=item.metadata)
        assert item.features is not None
        feats = self._features(handle, item.features)
        return handle.localizer.make_keyframe(T, features=feats, metadata=item.metadata)

    def insert(self, name: str, items: list[KeyframeIn]) -> InsertResult:
        """Insert keyframes all-or-nothing; known keys return their ids, created=False."""
        handle = self.get(name, load=True)
        if not items:
            raise field_error(InputError("at least one keyframe is required"), "keyframes")
        keys = [it.key for it in items if it.key is not None]
        seen: dict[str, int] = {}
        for i, it in enumerate(items):
            if it.key is None:
                continue
            if it.key in seen:
                raise field_error(
                    InputError(f"key {it.key!r} appears twice (also keyframes[{seen[it.key]}])"),
                    f"keyframes[{i}].key",
                )
            seen[it.key] = i

        # 1. validate and encode, outside any lock (known keys are skipped)
        known = handle.store.find_keys(keys) if keys else {}
        prepared: dict[int, Keyframe] = {}
        for i, it in enumerate(items):
            if it.key is not None and it.key in known:
                continue
            with at_field(f"keyframes[{i}]"):
                prepared[i] = self._make_keyframe(handle, it)

        with handle.write_lock:
            if handle.closed:
                raise NotFoundError(f"map {name!r} does not exist")
            for attempt in range(3):
                # keys may have appeared (or gone) while encoding: decide again under the lock
                known = handle.store.find_keys(keys) if keys else {}
                for i, it in enumerate(items):
                    if i not in prepared and (it.key is None or it.key not in known):
                        with at_field(f"keyframes[{i}]"):
                            prepared[i] = self._make_keyframe(handle, it)
                new = [
                    i for i in sorted(prepared) if items[i].key is None or items[i].key not in known
                ]
                ids: dict[int, int] = {}
                if not new:
                    if self.shared and known:  # the keys may be another replica's write
                        self._catch_up(handle)  # newer than this copy: answer after it
                    version = handle.version
                    break
                # 2. one store transaction for the batch (the acknowledgement point)
                rows = [self._row(items[i], prepared[i]) for i in new]
                try:
                    new_ids, version = handle.store.insert(rows)
                except DuplicateKeyError:  # another replica stored one of the keys first
                    if attempt == 2:
                        raise ConflictError(
                            "keys of this batch keep being stored by other writers; retry"
                        ) from None
                    continue
                kfs = []
                for i, kf_id in zip(new, new_ids, strict=True):
                    prepared[i].id = kf_id
                    kfs.append(prepared[i])
                    ids[i] = kf_id
                # 3. into the localizer (after other replicas' earlier writes); if that
                # fails, undo the rows
                if self._before_own(handle, version):
                    try:
                        handle.localizer.add_keyframes(
                            kfs if self.features_in_memory else [_slim(kf) for kf in kfs]
                        )
                    except BaseException:
                        log.exception("map %r: in-memory insert failed, undoing the rows", name)
                        handle.store.delete(new_ids, set_version=version - 1)
                        raise
                    if handle.localizer.version != version:  # keep both counters equal
                        handle.localizer.version = version
                self._mark_unsaved(handle, len(new))
                break
        out_ids = [ids[i] if i in ids else known[items[i].key] for i in range(len(items))]
        created = [i in ids for i in range(len(items))]
        if new:
            self._on_change(name, handle.num_keyframes)
        return InsertResult(out_ids, created, version)

    @staticmethod
    def _row(item: KeyframeIn, kf: Keyframe) -> KeyframeRow:
        f = kf.features
        return KeyframeRow(
            T_map_sensor=kf.T_map_sensor,
            global_descriptor=f.global_descriptor,
            keypoints=f.keypoints,
            local_features=f.local_features,
            cloud=kf.cloud,
            metadata=kf.metadata,
            key=item.key,
        )

    def get_keyframe(self, name: str, keyframe_id: int) -> KeyframeRow:
        """A stored keyframe; raises :class:`NotFoundError`."""
        handle = self.get(name, load=True)
        try:
            return handle.store.get(keyframe_id)
        except StoreClosedError:  # the map was deleted meanwhile
            raise NotFoundError(f"map {name!r} does not exist") from None

    def delete_keyframe(self, name: str, keyframe_id: int) -> int:
        """Delete one keyframe; returns the map's new version."""
        handle = self.get(name, load=True)
        with handle.write_lock:
            if handle.closed:
                raise NotFoundError(f"map {name!r} does not exist")
            if self.shared:
                self._catch_up(handle)  # a keyframe another replica just stored is known
            handle.localizer.keyframe(keyframe_id)  # NotFoundError before touching anything
            version = handle.store.delete([keyframe_id])
            self._remove_own(handle, [keyframe_id], version)
        self._on_change(name, handle.num_keyframes)
        return version

    def _remove_own(self, handle: MapHandle, ids: list[int], version: int) -> None:
        """Take keyframes this replica deleted from the store (as ``version``) out of
        memory (call under the write lock)."""
        if self._before_own(handle, version):
            handle.localizer.apply_changes([], ids, version)
        self._mark_unsaved(handle, len(ids))

    def list_keyframes(
        self, name: str, where: KeyframeFilter, *, after_id: int = 0, limit: int = 1000
    ) -> list[KeyframeSummary]:
        """Keyframes matching ``where`` with ``id > after_id``, by id (at most ``limit``)."""
        handle = self.get(name, load=True)
        try:
            return handle.store.select(where, after_id=after_id, limit=limit)
        except StoreClosedError:
            raise NotFoundError(f"map {name!r} does not exist") from None

    def delete_keyframes(self, name: str, where: KeyframeFilter) -> tuple[int, int]:
        """Delete every keyframe matching ``where`` in one transaction (one version
        step; none when nothing matches). Returns ``(deleted, map version)``."""
        handle = self.get(name, load=True)
        with handle.write_lock:
            if handle.closed:
                raise NotFoundError(f"map {name!r} does not exist")
            for attempt in range(3):
                ids = handle.store.matching_ids(where)
                if not ids:
                    return 0, handle.version
                try:
                    version = handle.store.delete(ids)
                    break
                except NotFoundError:
                    # another replica deleted one of them between the match and the
                    # delete (nothing was deleted): match again
                    if not self.shared or attempt == 2:
                        raise
            self._remove_own(handle, ids, version)
        self._on_change(name, handle.num_keyframes)
        log.info("map %r: deleted %d keyframes (version %d)", name, len(ids), version)
        return len(ids), version

    def stats(self, name: str) -> dict[str, Any]:
        """Size and shape of a map: keyframes, extent, disk and memory use, index kind,
        last write."""
        handle = self.get(name, load=True)
        try:
            extent = handle.store.extent()
            last_write = handle.store.last_write()
            disk = handle.store.disk_bytes() if handle.path is None else _folder_bytes(handle.path)
        except StoreClosedError:
            raise NotFoundError(f"map {name!r} does not exist") from None
        return {
            "map": name,
            "version": handle.version,
            "keyframes": handle.num_keyframes,
            "extent": None if extent is None else {"min": extent[0], "max": extent[1]},
            "disk_bytes": disk,
            "memory_bytes": handle.localizer.memory_bytes(),
            "index_kind": handle.localizer.index.kind,
            "created_at": handle.record.created_at,
            "last_write": last_write,
        }

    # -- archives -----------------------------------------------------------------------

    @contextmanager
    def export_archive(self, name: str) -> Iterator[Iterator[bytes]]:
        """The map as an archive (:mod:`sgvloc.server.archive`), a stream of byte blocks
        read from one consistent state of the store; writers are not blocked."""
        handle = self.get(name, load=True)
        try:
            with handle.store.archive_snapshot() as (version, count, next_id, rows):
                yield write_archive(handle.record, version, count, rows, next_id)
        except StoreClosedError:
            raise NotFoundError(f"map {name!r} does not exist") from None

    def import_archive(
        self,
        fileobj: IO[bytes],
        name: str | None = None,
        *,
        fix_spec: Callable[[EncoderSpec], EncoderSpec] | None = None,
        check_name: Callable[[str], None] | None = None,
        check_settings: Callable[[LocalizerConfig], None] | None = None,
    ) -> MapHandle:
        """Create a map from an archive, under ``name`` or the archived name.

        Ids, keys, metadata, creation times, version, settings and calibration are kept.
        The archive's encoder must build here with the same fingerprint (else
        :class:`EncoderMismatchError`); ``fix_spec`` may adjust its spec first (the
        service confines model paths); ``check_name`` may refuse the final name and
        ``check_settings`` the archived localizer settings (by raising) before anything is
        built. A damaged or foreign archive raises
        :class:`~sgvloc.server.archive.ArchiveError` and leaves nothing behind.
        """
        header, chunks = read_archive(fileobj)
        record = header.record
        name = name or record.name
        self._check_name(name)
        if check_name is not None:
            check_name(name)
        spec = fix_spec(record.encoder_spec) if fix_spec else record.encoder_spec
        if check_settings is not None:
            check_settings(record.localizer_config)
        check_runnable(record.localizer_config)
        with at_field("encoder"):
            encoder = make_encoder(spec)
        if encoder.identity.fingerprint != record.encoder_fingerprint:
            raise EncoderMismatchError(
                f"the archive's map was built with encoder {encoder.identity.name!r} "
                f"fingerprint {record.encoder_fingerprint}, but its spec builds "
                f"{encoder.identity.fingerprint} here (other weights or encoder code): its "
                "features cannot be used with this server"
            )
        record = replace(record, name=name, encoder_spec=spec)

        def fill(store: MapStore) -> None:
            filled = False
            for rows in chunks:
                for row in rows:
                    self._check_archived(encoder, row, spec.preprocess.max_range)
                try:
                    store.insert_exact(rows, header.version, header.next_id)
                except self.backend.errors as exc:
                    raise_if_full(exc)
                    raise ArchiveError(f"the archive's keyframes clash: {exc}") from None
                filled = True
            if not filled:  # no keyframes: the version and the next id all the same
                store.insert_exact([], header.version, header.next_id)

        taken = "; import it under another name (?name=, sgvloc map import --name)"
        if isinstance(self.backend, SharedBackend):
            # filled under a hidden name, published (renamed) in one step at the end
            with self._reserving(name, taken):
                store = self.backend.staging(record)
                try:
                    fill(store)
                    self.backend.publish(store, name)
                except BaseException:
                    with contextlib.suppress(Exception):
                        self.backend.drop(store)
                    raise
                try:
                    handle = self._load_store(store, None, name)
                except StoreUnavailableError as exc:  # published: the import stands
                    raise StoreUnavailableError(
                        f"map {name!r} was imported, but the store stopped answering before "
                        f"this replica could load it ({exc}); every replica serves it once "
                        "the store answers again: do not import it again"
                    ) from None
                self._publish(handle)
        else:
            with self._building(name, taken) as (tmp, folder):
                store = self.backend.create(tmp, record)
                try:
                    fill(store)
                finally:
                    store.close()
                tmp.rename(folder)
                handle = self._load(folder)
                self._publish(handle)
        log.info(
            "imported map %r: %d keyframes, version %d (exported by sgvloc %s)",
            name,
            handle.num_keyframes,
            handle.version,
            header.sgvloc_version,
        )
        return handle

    @staticmethod
    def _check_archived(encoder: Encoder, row: KeyframeRow, max_range: float) -> None:
        """An archived keyframe as strictly as an inserted one (ArchiveError if not): the
        archive's checksums only say it was not damaged, not that it was made here."""
        try:
            if not 0 < row.id < 2**62:
                raise InputError("bad id")
            if row.key is not None:
                _check_text(row.key, "key", KEY_MAX_CHARS)
            _check_metadata(row.metadata)
            check_rigid(row.T_map_sensor, "T_map_sensor")
            _encoder_features(
                encoder, row.global_descriptor, row.keypoints, row.local_features, "archived"
            )
            if row.cloud is not None:
                _check_cloud(row.cloud, max_range)
        except SgvlocError as exc:
            raise ArchiveError(f"archived keyframe {row.id} is invalid: {exc}") from None

    # -- localization -------------------------------------------------------------------

    def localize(
        self,
        name: str,
        *,
        points: np.ndarray | None = None,
        features: FeaturesIn | None = None,
        top_k: int | None = None,
        rerank: str | None = None,
        refine: str | None = None,
        prior: Prior | None = None,
        min_confidence: float | None = None,
        seed: Seed | None = None,
    ) -> LocalizationResult:
        """Localize a scan (or features) in map ``name``; with ``seed``, track."""
        handle = self.get(name, load=True)
        if (points is None) == (features is None):
            raise InputError("give exactly one of points or features")
        if seed is not None and features is not None:
            raise field_error(
                InputError("tracking needs the raw scan (points), not features"), "seed"
            )
        options = {
            "top_k": top_k,
            "rerank_method": rerank,
            "refine": refine,
            "prior": prior,
            "min_confidence": min_confidence,
            "seed": seed,
        }
        if points is not None:
            self._check_scan_allowed(handle)
            with at_field("points"):
                return handle.localizer.localize(points, **options)
        assert features is not None
        query = self._features(handle, features)
        return handle.localizer.localize(features=query, **options)

    # -- snapshots ----------------------------------------------------------------------

    def _mark_unsaved(self, handle: MapHandle, changes: int) -> None:
        """Count changes (call under the write lock); save now past ``snapshot_every``
        changes, or half the map's keyframes when that is more: a map being built is
        saved a bounded number of times (each save writes the whole index), not once
        per ``snapshot_every`` keyframes (the snapshot thread saves the rest within
        ``snapshot_delay_s``)."""
        if handle.path is None:  # a shared store: no snapshot to keep
            return
        handle.unsaved += changes
        if handle.unsaved_since is None:
            handle.unsaved_since = time.monotonic()
        due = max(self.snapshot_every, handle.num_keyframes // 2)
        if handle.unsaved >= due and time.monotonic() >= handle.snapshot_retry_at:
            self._save_snapshot(handle)

    def snapshot(self, name: str) -> None:
        """Save a map's FAISS snapshot now (under its write lock, so it matches the store)."""
        handle = self.get(name)
        with handle.write_lock:
            if not handle.closed:
                self._save_snapshot(handle)

    @staticmethod
    def _save_snapshot(handle: MapHandle) -> None:
        if handle.index_path is None:
            return
        t0 = time.perf_counter()
        try:
            handle.localizer.index.save(handle.index_path)
        except (OSError, RuntimeError) as exc:  # the store is intact; retry later
            # back off: 10 s, 20 s, ... at most 10 min between tries; one ERROR, then WARNINGs
            handle.snapshot_failures += 1
            wait = min(600.0, 10.0 * 2 ** (handle.snapshot_failures - 1))
            handle.snapshot_retry_at = time.monotonic() + wait
            level = logging.ERROR if handle.snapshot_failures == 1 else logging.WARNING
            log.log(
                level,
                "map %r: saving the index snapshot failed (%d in a row), next try in %.0f s: %s",
                handle.name,
                handle.snapshot_failures,
                wait,
                exc,
            )
            return
        if handle.snapshot_failures:
            log.info("map %r: index snapshot saved again", handle.name)
        handle.snapshot_failures, handle.snapshot_retry_at = 0, 0.0
        handle.unsaved, handle.unsaved_since = 0, None
        log.debug("map %r: index snapshot saved in %.3f s", handle.name, time.perf_counter() - t0)
