"""Build a map from a KITTI-layout sequence: into a running service, or a data directory.

The sequence's poses (``poses.txt``, ``T_world_sensor``) become the keyframes'
``T_map_sensor``: the map frame is the sequence's world frame. Each keyframe's key is
``<prefix>/<scan stem>`` (e.g. ``00/000042``), the prefix being the folder's name unless
given (``key_prefix``, ``--key-prefix``), so re-running the same build resumes where it
stopped: scans already in the map are answered ``created: false`` and not stored twice. A
build resumed from a renamed or moved folder keeps its keys with the old name as prefix
(``--key-prefix``); without one, the build is refused when the map holds its scans at the
same poses under another prefix, which it would otherwise store a second time.

Two targets, one loop (:func:`build_map`), each behind a small :class:`KeyframeSink`:

- a service URL (or :class:`sgvloc_client.Client`): everything goes through the HTTP API,
  so this runs on any machine that can reach the service and needs neither torch nor
  FAISS locally (:class:`ClientSink`);
- a data directory (a :class:`~pathlib.Path`): the keyframes go straight into the map
  stores through :class:`sgvloc.server.maps.MapManager`, with the same validation, encoding and
  all-or-nothing batches, and the FAISS snapshot is saved at the end, so a service started
  later on that directory loads the map without rebuilding its index
  (:class:`DataDirSink`). This needs the ``service`` extra (imported lazily). No service
  may be running on that directory meanwhile: it would not see the new keyframes (its maps
  live in memory) and would later overwrite the snapshot with one that misses them (then
  rebuilt at its next start). Stop it first, or give its URL instead.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from tqdm import tqdm

from sgvloc.core import leave_out
from sgvloc.core.errors import ConflictError, EmptyScanError, InputError, NotFoundError
from sgvloc.core.sequence import KittiSequence
from sgvloc_client import Client, Conflict, NotFound, Overloaded
from sgvloc_client import KeyframeIn as ClientKeyframeIn

if TYPE_CHECKING:
    from sgvloc.server.maps import MapManager

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BuildMapResult:
    """What a :func:`build_map` run did.

    ``scans``: scans sent; ``created``: keyframes newly stored; ``existing``: scans whose
    key was already in the map (a resumed or repeated run); ``keyframes`` and
    ``map_version``: the map's state afterwards; ``skipped``: the keys of scans in which
    the map's encoder found nothing to describe (too sparse for it), left out.
    """

    map: str
    scans: int
    created: int
    existing: int
    keyframes: int
    map_version: int
    skipped: tuple[str, ...] = ()


@dataclass(frozen=True)
class ScanKeyframe:
    """One keyframe to insert, whatever the target: a pose, a raw scan and its key."""

    T_map_sensor: np.ndarray  # [4, 4]
    points: np.ndarray  # [P, 4] x y z intensity
    key: str
    metadata: dict[str, Any] = field(default_factory=dict)


class KeyframeSink(Protocol):
    """Where :func:`build_map` sends its batches (a service, or a data directory)."""

    def ensure_map(
        self,
        name: str,
        create: bool,
        encoder: dict[str, Any] | None,
        self_test: Mapping[str, Any] | None = None,
    ) -> bool:
        """Make sure map ``name`` exists (created if allowed, recording ``self_test``) with
        the asked encoder kind; True if this call created it."""
        ...

    def discard(self, name: str) -> None:
        """Delete map ``name`` again (one this build created and put nothing into)."""
        ...

    def insert(self, name: str, batch: list[ScanKeyframe]) -> int:
        """Insert one batch all-or-nothing; returns how many keyframes were new."""
        ...

    def state(self, name: str) -> tuple[int, int]:
        """``(keyframes, version)`` of the map now."""
        ...

    def positions(
        self, name: str, key_prefix: str | None, bbox: tuple[float, ...] | None = None
    ) -> dict[str, np.ndarray]:
        """Key -> position ``[3]`` of the map's keyed keyframes whose key starts so (any,
        for None) and that lie in ``bbox`` = (x_min, y_min, x_max, y_max), if given."""
        ...

    def close(self) -> None:
        """Release what the sink opened (and save what must be saved)."""
        ...


def _self_test_not_recorded(name: str, self_test: Mapping[str, Any] | None) -> None:
    if self_test is not None:
        log.warning(
            "map %s already exists: the self-test is not recorded with it (it is recorded "
            "when the map is created)",
            name,
        )


def parse_encoder(value: str | Mapping[str, Any] | None) -> dict[str, Any] | None:
    """An encoder option: None, a kind (``"handcrafted"``) or a self-test candidate's name
    (``"learned-fpfh"``, :data:`sgvloc.core.leave_out.SPECS`), or a JSON EncoderSpec
    object."""
    if value is None or isinstance(value, Mapping):
        return None if value is None else dict(value)
    text = value.strip()
    if text.startswith("{"):
        try:
            spec = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(f"encoder: not valid JSON: {exc}") from None
        if not isinstance(spec, dict):
            raise InputError("encoder: the JSON must be an object")
        return spec
    return leave_out.spec_of(text)


def select_frames(
    n: int,
    every: int = 1,
    limit: int | None = None,
    *,
    until: float | None = None,
    times: np.ndarray | None = None,
) -> list[int]:
    """Indices of the scans to insert: those of the first ``until`` seconds (by ``times``,
    counted from the first scan's, as ``sgvloc eval --db-until``), every ``every``-th of
    them, at most ``limit``."""
    if every < 1:
        raise InputError(f"every must be >= 1, got {every}")
    if limit is not None and limit < 0:
        raise InputError(f"limit must be >= 0, got {limit}")
    if until is None:
        return list(range(0, n, every))[:limit]
    if times is None:
        raise InputError("until: the sequence has no times.txt")
    if not math.isfinite(until) or until < 0:
        raise InputError(f"until must be a finite number of seconds >= 0, got {until}")
    t = np.asarray(times, dtype=np.float64)
    inside = np.flatnonzero(t - t[0] <= until).tolist() if len(t) else []
    return inside[::every][:limit]


def _check_encoder_kind(name: str, kind: str | None, encoder: dict[str, Any] | None) -> None:
    """An existing map must use the asked encoder kind (if one was asked)."""
    wanted = (encoder or {}).get("kind")
    if wanted and kind and wanted != kind:
        raise ConflictError(
            f"map {name!r} exists with encoder kind {kind!r}, not the requested {wanted!r}"
        )


# -- sinks ---------------------------------------------------------------------------------


class ClientSink:
    """Batches to a running service through the SDK (closes the client only if it made it)."""

    #: how long :meth:`state` waits for the replica it asks to show this build's writes
    CATCH_UP_S = 10.0
    #: how long a build waits for a service still loading its maps (just started)
    LOADING_WAIT_S = 300.0

    def __init__(self, target: str | Client) -> None:
        self.client = Client(target) if isinstance(target, str) else target
        self._owned = self.client is not target
        self._written: dict[str, int] = {}  # map -> the version its last insert made

    def ensure_map(
        self,
        name: str,
        create: bool,
        encoder: dict[str, Any] | None,
        self_test: Mapping[str, Any] | None = None,
    ) -> bool:
        client = self.client
        try:
            info = self._first_get(name)
        except NotFound:
            if not create:
                raise NotFoundError(f"map {name!r} does not exist (and create is off)") from None
            try:
                info = client.create_map(name, encoder=encoder, self_test=self_test)
                log.info(
                    "created map %s (encoder %s)", name, info.encoder.name or info.encoder.kind
                )
                return True
            except Conflict as conflict:  # created meanwhile by someone else?
                try:
                    info = client.get_map(name)
                except NotFound:  # no: the service refuses the name; say why
                    raise conflict from None
        _check_encoder_kind(name, info.encoder.kind, encoder)
        _self_test_not_recorded(name, self_test)
        log.info("map %s exists with %d keyframes; resuming", name, info.keyframes)
        return False

    def _first_get(self, name: str) -> Any:
        """``get_map``, waiting while the service answers that it is still loading its
        maps (a build started together with the service), at most LOADING_WAIT_S."""
        deadline = time.monotonic() + self.LOADING_WAIT_S
        said = False
        while True:
            try:
                return self.client.get_map(name)
            except Overloaded as exc:
                if exc.code != "unavailable" or time.monotonic() >= deadline:
                    raise
                if not said:
                    log.warning("the service is still loading its maps; waiting for it")
                    said = True
                time.sleep(1.0)

    def discard(self, name: str) -> None:
        self.client.delete_map(name)

    def insert(self, name: str, batch: list[ScanKeyframe]) -> int:
        items = [
            ClientKeyframeIn(
                T_map_sensor=kf.T_map_sensor, points=kf.points, key=kf.key, metadata=kf.metadata
            )
            for kf in batch
        ]
        result = self.client.insert_keyframes(name, items)
        self._written[name] = max(self._written.get(name, 0), result.map_version)
        return result.num_created

    def state(self, name: str) -> tuple[int, int]:
        """Keyframes and version of the map as some replica serves it, once that replica
        has caught up with this build's inserts (behind a load balancer the next request
        may reach a replica that has not yet followed them)."""
        written = self._written.get(name, 0)
        deadline = time.monotonic() + self.CATCH_UP_S
        while True:
            info = self.client.get_map(name)
            if info.version >= written or time.monotonic() >= deadline:
                break
            time.sleep(0.1)
        if info.version < written:
            log.warning(
                "map %s: the replica asked is at version %d, this build wrote version %d; "
                "its keyframe count may not include the last inserts yet",
                name,
                info.version,
                written,
            )
        return info.keyframes, info.version

    def positions(
        self, name: str, key_prefix: str | None, bbox: tuple[float, ...] | None = None
    ) -> dict[str, np.ndarray]:
        return {
            k.key: np.asarray(k.position, np.float64)
            for k in self.client.iter_keyframes(name, key_prefix=key_prefix, bbox=bbox)
            if k.key is not None
        }

    def close(self) -> None:
        if self._owned:
            self.client.close()


class DataDirSink:
    """Batches straight into the map stores of a data directory (:class:`MapManager`).

    Opening loads every map of the directory (as a starting service would); :meth:`close`
    saves the FAISS snapshot of every changed map and closes the stores. No service may
    run on the same directory meanwhile (see the module docstring).
    """

    def __init__(self, data_dir: Path) -> None:
        try:  # the service extra: torch, Open3D, FAISS, pydantic-settings
            from sgvloc.server.maps import MapManager
            from sgvloc.server.settings import Settings
        except ImportError as exc:
            raise InputError(
                f"building into a data directory needs the service extra "
                f"(pip install 'sgvloc[service]'): {exc}; or give a service URL instead"
            ) from None
        data_dir = Path(data_dir)
        if data_dir.exists() and not data_dir.is_dir():
            raise InputError(f"data directory {data_dir} is not a directory")
        settings = Settings(data_dir=data_dir)
        self.manager: MapManager = MapManager(
            settings.maps_dir,
            snapshot_every=settings.snapshot_every,
            snapshot_delay_s=settings.snapshot_delay_s,
        )
        self.manager.load_all()

    def ensure_map(
        self,
        name: str,
        create: bool,
        encoder: dict[str, Any] | None,
        self_test: Mapping[str, Any] | None = None,
    ) -> bool:
        from pydantic import ValidationError

        from sgvloc.core.encoders import EncoderSpec

        manager = self.manager
        if name in manager.failed:
            raise ConflictError(
                f"map {name!r} is in {manager.maps_dir} but could not be loaded: "
                f"{manager.failed[name]}"
            )
        try:
            handle = manager.get(name)
        except NotFoundError:
            if not create:
                raise NotFoundError(f"map {name!r} does not exist (and create is off)") from None
            try:
                spec = EncoderSpec.model_validate(encoder or {})
            except ValidationError as exc:
                raise InputError(f"encoder: {exc}") from None
            handle = manager.create(
                name, spec, self_test=None if self_test is None else dict(self_test)
            )
            log.info("created map %s (encoder %s)", name, handle.encoder.identity.name)
            return True
        _check_encoder_kind(name, handle.record.encoder_spec.kind, encoder)
        _self_test_not_recorded(name, self_test)
        log.info("map %s exists with %d keyframes; resuming", name, handle.num_keyframes)
        return False

    def discard(self, name: str) -> None:
        self.manager.delete(name)

    def insert(self, name: str, batch: list[ScanKeyframe]) -> int:
        from sgvloc.server.maps import KeyframeIn

        items = [
            KeyframeIn(
                T_map_sensor=kf.T_map_sensor, points=kf.points, key=kf.key, metadata=kf.metadata
            )
            for kf in batch
        ]
        return sum(self.manager.insert(name, items).created)

    def state(self, name: str) -> tuple[int, int]:
        handle = self.manager.get(name)
        return handle.num_keyframes, handle.version

    def positions(
        self, name: str, key_prefix: str | None, bbox: tuple[float, ...] | None = None
    ) -> dict[str, np.ndarray]:
        from sgvloc.server.store import KeyframeFilter

        out: dict[str, np.ndarray] = {}
        after = 0
        where = KeyframeFilter(key_prefix=key_prefix, bbox=bbox)
        while page := self.manager.list_keyframes(name, where, after_id=after):
            out.update((k.key, k.T_map_sensor[:3, 3]) for k in page if k.key is not None)
            after = page[-1].id
        return out

    def close(self) -> None:
        self.manager.close()  # saves the snapshot of every changed map


def key_prefix_for(root: Path, given: str | None) -> str:
    """The keys' prefix: ``given`` (checked) or the folder's name."""
    if given is None:
        return root.resolve().name
    prefix = given.strip().strip("/")
    if not prefix or any(not ch.isprintable() for ch in prefix) or len(prefix) > 200:
        raise InputError(
            f"key_prefix {given!r} must be 1-200 printable characters other than a bare '/'"
        )
    return prefix


# -- the build -----------------------------------------------------------------------------

#: a keyframe already in the map under a scan's key lies this close to the scan's pose (m)
RESUME_TOLERANCE_M = 0.01


def _check_resumed_poses(
    sink: KeyframeSink,
    name: str,
    prefix: str,
    seq: KittiSequence,
    frames: list[int],
    renamed: bool = True,
) -> None:
    """Refuse to resume into keyframes of another sequence: keys name the sequence by
    its prefix (by default its folder's name), so a different drive under the same
    prefix would be skipped scan by scan as "already present". Each scan whose key the
    map holds must sit where the map has it. With ``renamed`` (the prefix is the folder's
    name, not one given), a map holding none under this prefix is checked for the same
    scans under another (:func:`_check_not_renamed`)."""
    held = sink.positions(name, f"{prefix}/")
    if not held:
        if renamed:
            _check_not_renamed(sink, name, prefix, seq, frames)
        return
    for i in frames:
        key = f"{prefix}/{seq.paths[i].stem}"
        if key in held:
            off = float(np.linalg.norm(held[key] - seq.poses[i][:3, 3]))
            if off > RESUME_TOLERANCE_M:
                raise ConflictError(
                    f"map {name!r} holds keyframe {key!r} {off:.2f} m from this sequence's "
                    f"pose of that scan: is this another sequence under the same key prefix "
                    f"{prefix!r} (by default the folder's name)? Build it into another map, "
                    "or give it another --key-prefix"
                )


#: scans of a sequence looked up by :func:`_check_not_renamed`
RENAMED_SAMPLES = 8


def _check_not_renamed(
    sink: KeyframeSink, name: str, prefix: str, seq: KittiSequence, frames: list[int]
) -> None:
    """Refuse to add a sequence again under a new prefix: a build resumed from a renamed
    or moved folder would store every scan a second time. A few scans (the first two and
    others spread over the selection: an interrupted build holds the first ones) are
    looked up by position; one in the map as the same scan name at the same pose (within
    :data:`RESUME_TOLERANCE_M`) under another prefix means the map holds this sequence
    already. A scan at the origin is no evidence: every KITTI sequence starts there, as
    scan 000000."""
    if not frames:  # nothing selected (--limit 0): nothing to store twice
        return
    tol = RESUME_TOLERANCE_M
    spread = np.linspace(0, len(frames) - 1, RENAMED_SAMPLES).round().astype(int)
    samples = sorted({frames[j] for j in [*range(min(2, len(frames))), *spread.tolist()]})
    for i in samples:
        x, y, z = seq.poses[i][:3, 3]
        if max(abs(x), abs(y), abs(z)) <= tol:
            continue
        near = sink.positions(name, None, (x - tol, y - tol, x + tol, y + tol))
        stem = seq.paths[i].stem
        for key, pos in sorted(near.items()):
            old, _, tail = key.rpartition("/")
            if tail == stem and old and old != prefix and abs(float(pos[2]) - z) <= tol:
                raise ConflictError(
                    f"map {name!r} holds this sequence's scan {stem} already, as {key!r} "
                    f"(the same pose), under the key prefix {old!r}, not {prefix!r} (by "
                    f"default the folder's name): was the folder renamed or moved? Give "
                    f"--key-prefix {old} to resume that build; building it again under a "
                    "new prefix would store every scan twice"
                )


_EMPTY_SCAN_FIELD = re.compile(r"keyframes\[(\d+)\]\.points")


def _empty_scan(exc: Exception, size: int) -> int | None:
    """The batch index of the scan an insert refused as having nothing to describe (the
    engine's :class:`EmptyScanError`, or the service's 422 ``empty_scan``), else None."""
    if not (isinstance(exc, EmptyScanError) or getattr(exc, "code", None) == "empty_scan"):
        return None
    m = _EMPTY_SCAN_FIELD.fullmatch(str(getattr(exc, "field", "") or ""))
    return int(m.group(1)) if m and int(m.group(1)) < size else None


def insert_skipping_empty(
    insert: Callable[[list[Any]], int], batch: list[Any], skipped: list[str]
) -> tuple[int, list[Any]]:
    """``insert(batch)`` (all-or-nothing per call, returning how many were new); a scan in
    which the map's encoder finds nothing to describe is left out, its ``key`` appended to
    ``skipped``, and the rest inserted again. ``(keyframes new, the batch as inserted)``."""
    while batch:
        try:
            return insert(batch), batch
        except Exception as exc:
            i = _empty_scan(exc, len(batch))
            if i is None:
                raise
            log.warning("skipping %s: %s", batch[i].key, getattr(exc, "raw_message", exc))
            skipped.append(batch[i].key)
            batch = batch[:i] + batch[i + 1 :]
    return 0, batch


def build_map(
    source: Path | str,
    target: str | Client | os.PathLike[str],
    map_name: str,
    *,
    create: bool = True,
    encoder: str | Mapping[str, Any] | None = None,
    batch_size: int = 16,
    every: int = 1,
    limit: int | None = None,
    until: float | None = None,
    progress: bool = True,
    self_test: Mapping[str, Any] | None = None,
    key_prefix: str | None = None,
) -> BuildMapResult:
    """Insert a KITTI-layout sequence into map ``map_name`` of a service or a data directory.

    Args:
        source: folder with ``velodyne/*.bin`` (or ``scans/``, any scan format of
            :mod:`sgvloc.core.io`) and ``poses.txt``; ``times.txt`` is optional.
        target: where the map lives: the running service's base URL (a ``str``) or a
            :class:`sgvloc_client.Client`; or a service data directory (a
            :class:`~pathlib.Path`, ``<dir>/maps/<name>/``, created if missing), written
            directly (needs the ``service`` extra). No service may run on that directory
            meanwhile: it would not see the new keyframes; stop it first or give its URL.
        map_name: the map to fill.
        create: create the map if it does not exist (else a missing map is an error).
        encoder: encoder for a new map: a kind or an EncoderSpec (dict or JSON text).
            For an existing map, a different kind is an error.
        batch_size: keyframes per insert (one request, or one store transaction).
        every: insert every n-th scan only.
        limit: insert at most this many scans (after ``every``).
        until: insert only the scans of the first ``until`` seconds (``times.txt``,
            counted from the first scan; the database of ``sgvloc eval --db-until``).
        progress: show a tqdm progress bar.
        self_test: an encoder self-test (:func:`sgvloc.tools.self_test.self_test`) to
            record with a map this call creates.
        key_prefix: the first part of every key (``<prefix>/<scan stem>``) and the
            ``sequence`` metadata; default: the folder's name. Give the earlier name to
            resume a build from a renamed or moved folder.

    Raises :class:`~sgvloc.core.errors.InputError` for a bad sequence or option, the
    engine's errors (:mod:`sgvloc.core.errors`) for a data directory, and the client's
    exceptions (:mod:`sgvloc_client`) for service errors.
    """
    if batch_size < 1:
        raise InputError(f"batch_size must be >= 1, got {batch_size}")
    root = Path(source)
    seq = KittiSequence(root)
    if seq.poses is None:
        raise InputError(f"{root}: no poses.txt; a map needs a pose for every keyframe")
    frames = select_frames(len(seq), every, limit, until=until, times=seq.times)
    prefix = key_prefix_for(root, key_prefix)
    spec = parse_encoder(encoder)

    sink: KeyframeSink = (
        DataDirSink(Path(target)) if isinstance(target, os.PathLike) else ClientSink(target)
    )
    created = existing = 0
    skipped: list[str] = []
    made = False
    try:
        made = sink.ensure_map(map_name, create, spec, self_test)
        _check_resumed_poses(sink, map_name, prefix, seq, frames, renamed=key_prefix is None)
        with tqdm(
            total=len(frames), desc=f"build-map {map_name}", unit="scan", disable=not progress
        ) as bar:
            for start in range(0, len(frames), batch_size):
                batch = []
                chunk = frames[start : start + batch_size]
                for i in chunk:
                    frame = seq[i]
                    key = f"{prefix}/{frame.path.stem}"
                    points = frame.scan().xyzi()  # [P, 4]
                    if not np.isfinite(points[:, :3]).all(axis=1).any():
                        log.warning("skipping %s: %s holds no point", key, frame.path.name)
                        skipped.append(key)  # an empty file: nothing to describe either
                        continue
                    metadata: dict[str, Any] = {"sequence": prefix}
                    if frame.time is not None:
                        metadata["timestamp"] = frame.time
                    batch.append(
                        ScanKeyframe(
                            T_map_sensor=frame.T_world_sensor,
                            points=points,
                            key=key,
                            metadata=metadata,
                        )
                    )
                insert = partial(sink.insert, map_name)
                new, batch = insert_skipping_empty(insert, batch, skipped)
                created += new
                existing += len(batch) - new
                bar.update(len(chunk))  # once they are in
                bar.set_postfix(new=created, existing=existing, skipped=len(skipped))
        keyframes, version = sink.state(map_name)
    except BaseException:
        if made and created == existing == 0:  # nothing half-made stays behind
            try:
                sink.discard(map_name)
                log.warning(
                    "map %s, made by this build, was deleted again: nothing went in", map_name
                )
            except Exception as exc:  # noqa: BLE001 - the build's own error matters more
                log.warning(
                    "map %s, made by this build, is empty and could not be deleted: %s",
                    map_name,
                    exc,
                )
        raise
    finally:
        sink.close()
    log.info(
        "map %s: %d scans sent, %d new keyframes, %d already present, %d keyframes in all",
        map_name,
        len(frames),
        created,
        existing,
        keyframes,
    )
    return BuildMapResult(
        map=map_name,
        scans=len(frames),
        created=created,
        existing=existing,
        keyframes=keyframes,
        map_version=version,
        skipped=tuple(sorted(skipped)),
    )
