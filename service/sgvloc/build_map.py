"""Build a map from a KITTI-layout sequence by inserting its scans into a running service.

The sequence's poses (``poses.txt``, ``T_world_sensor``) become the keyframes'
``T_map_sensor``: the map frame is the sequence's world frame. Each keyframe's key is
``<folder name>/<scan stem>`` (e.g. ``00/000042``), so re-running the same build resumes
where it stopped: scans already in the map are answered ``created: false`` and not stored
twice. Everything goes through the HTTP API (:mod:`sgvloc_client`), so this runs on any
machine that can reach the service and needs neither torch nor FAISS locally.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sgvloc_client import Client, Conflict, KeyframeIn, MapInfo, NotFound
from tqdm import tqdm

from .core.errors import ConflictError, InputError, NotFoundError
from .core.io import KittiSequence

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BuildMapResult:
    """What a :func:`build_map` run did.

    ``scans``: scans sent; ``created``: keyframes newly stored; ``existing``: scans whose
    key was already in the map (a resumed or repeated run); ``keyframes`` and
    ``map_version``: the map's state afterwards.
    """

    map: str
    scans: int
    created: int
    existing: int
    keyframes: int
    map_version: int


def parse_encoder(value: str | Mapping[str, Any] | None) -> dict[str, Any] | None:
    """An encoder option: None, a kind (``"handcrafted"``), or a JSON EncoderSpec object."""
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
    return {"kind": text}


def select_frames(n: int, every: int = 1, limit: int | None = None) -> list[int]:
    """Indices of the scans to insert: every ``every``-th of ``n``, at most ``limit``."""
    if every < 1:
        raise InputError(f"every must be >= 1, got {every}")
    if limit is not None and limit < 0:
        raise InputError(f"limit must be >= 0, got {limit}")
    return list(range(0, n, every))[:limit]


def _ensure_map(client: Client, name: str, create: bool, encoder: dict[str, Any] | None) -> MapInfo:
    """The target map, created if allowed; an existing map must use the asked encoder."""
    try:
        info = client.get_map(name)
    except NotFound:
        if not create:
            raise NotFoundError(f"map {name!r} does not exist (and create is off)") from None
        try:
            info = client.create_map(name, encoder=encoder)
            log.info("created map %s (encoder %s)", name, info.encoder.name or info.encoder.kind)
            return info
        except Conflict:  # created meanwhile by someone else
            info = client.get_map(name)
    wanted = (encoder or {}).get("kind")
    if wanted and info.encoder.kind and wanted != info.encoder.kind:
        raise ConflictError(
            f"map {name!r} exists with encoder kind {info.encoder.kind!r}, "
            f"not the requested {wanted!r}"
        )
    log.info("map %s exists with %d keyframes; resuming", name, info.keyframes)
    return info


def build_map(
    source: Path | str,
    target: str | Client,
    map_name: str,
    *,
    create: bool = True,
    encoder: str | Mapping[str, Any] | None = None,
    batch_size: int = 16,
    every: int = 1,
    limit: int | None = None,
    progress: bool = True,
) -> BuildMapResult:
    """Insert a KITTI-layout sequence into map ``map_name`` of a running service.

    Args:
        source: folder with ``velodyne/*.bin`` (or ``scans/``, any scan format of
            :mod:`sgvloc.core.io`) and ``poses.txt``; ``times.txt`` is optional.
        target: the service's base URL, or a :class:`sgvloc_client.Client`.
        map_name: the map to fill.
        create: create the map if it does not exist (else a missing map is an error).
        encoder: encoder for a new map: a kind or an EncoderSpec (dict or JSON text).
            For an existing map, a different kind is an error.
        batch_size: keyframes per insert request.
        every: insert every n-th scan only.
        limit: insert at most this many scans (after ``every``).
        progress: show a tqdm progress bar.

    Raises :class:`~sgvloc.core.errors.InputError` for a bad sequence or option, and the
    client's exceptions (:mod:`sgvloc_client`) for service errors.
    """
    if batch_size < 1:
        raise InputError(f"batch_size must be >= 1, got {batch_size}")
    root = Path(source)
    seq = KittiSequence(root)
    if seq.poses is None:
        raise InputError(f"{root}: no poses.txt; a map needs a pose for every keyframe")
    frames = select_frames(len(seq), every, limit)
    prefix = root.resolve().name
    spec = parse_encoder(encoder)

    client = Client(target) if isinstance(target, str) else target
    created = existing = 0
    try:
        _ensure_map(client, map_name, create, spec)
        with tqdm(
            total=len(frames), desc=f"build-map {map_name}", unit="scan", disable=not progress
        ) as bar:
            for start in range(0, len(frames), batch_size):
                batch = []
                for i in frames[start : start + batch_size]:
                    frame = seq[i]
                    metadata: dict[str, Any] = {"sequence": prefix}
                    if frame.time is not None:
                        metadata["timestamp"] = frame.time
                    batch.append(
                        KeyframeIn(
                            T_map_sensor=frame.T_world_sensor,
                            points=frame.scan().xyzi(),  # [P, 4]
                            key=f"{prefix}/{frame.path.stem}",
                            metadata=metadata,
                        )
                    )
                result = client.insert_keyframes(map_name, batch)
                created += result.num_created
                existing += len(batch) - result.num_created
                bar.update(len(batch))
                bar.set_postfix(new=created, existing=existing)
        info = client.get_map(map_name)
    finally:
        if client is not target:
            client.close()
    log.info(
        "map %s: %d scans sent, %d new keyframes, %d already present, %d keyframes in all",
        map_name,
        len(frames),
        created,
        existing,
        info.keyframes,
    )
    return BuildMapResult(
        map=map_name,
        scans=len(frames),
        created=created,
        existing=existing,
        keyframes=info.keyframes,
        map_version=info.version,
    )
