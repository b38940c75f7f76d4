"""Map archives: one file that moves a map between servers, exactly.

An archive is a tar file, written and read as a stream (``tarfile`` ``w|``/``r|``), so
neither side ever holds a whole map in memory::

    manifest.json            format, format version, the map's settings, encoder identity,
                             calibration, version and keyframe count (always first)
    keyframes/000000.npz     up to CHUNK keyframes: ids, poses, descriptors, keypoints,
    keyframes/000001.npz     local features, clouds (ragged arrays with counts) and a
    ...                      JSON array of key, metadata and created_at per keyframe
    SHA256SUMS               the SHA-256 of every member above (always last)

Arrays are ``.npy`` inside ``.npz`` (no pickle). Importing keeps keyframe ids, keys,
metadata, creation times, the map version and its settings, so the imported map gives
the same answers. A damaged, truncated or foreign archive is refused with
:class:`ArchiveError` naming what is wrong, and leaves nothing behind (the map manager
builds the map aside and moves it into place last).
"""

from __future__ import annotations

import hashlib
import io
import json
import tarfile
import zipfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from datetime import datetime
from typing import IO, Any

import numpy as np

from sgvloc.about import __version__
from sgvloc.core.confidence import Calibration
from sgvloc.core.config import LocalizerConfig
from sgvloc.core.encoders import EncoderSpec
from sgvloc.core.errors import InputError

from .store import KeyframeRow, MapRecord, plain_json, utc_now

FORMAT = "sgvloc-map-archive"
#: the version this sgvloc writes: 2 since the settings a manifest carries outgrew what
#: the readers of version 1 accept (those now refuse it by its version, not as damaged)
FORMAT_VERSION = 2
#: the versions it reads: a version 1 archive has the settings of its day, and a
#: setting added since takes the value that keeps the map's answers (ADDED_SETTINGS)
READABLE_VERSIONS = (1, 2)
CHUNK = 256  # keyframes per member
MANIFEST = "manifest.json"
SUMS = "SHA256SUMS"
MAX_MEMBER_BYTES = 1 << 30  # no honest chunk comes near this; a bigger one is refused
MAX_SELF_TEST_BYTES = 1 << 18  # a self-test's settings or summary, as JSON
#: the largest extended tar header (pax, GNU long name) an archive may carry. This
#: sgvloc writes none (short ASCII names, members far under 8 GiB), a re-packing tool
#: may add a few short ones; ``tarfile`` reads one whole into memory before any member
#: check, and before Python 3.11.10 / 3.12.6 parses it in quadratic time (CVE-2024-6232)
MAX_EXTENDED_HEADER_BYTES = 8192
_EXTENDED_TYPES = (
    tarfile.XHDTYPE,
    tarfile.XGLTYPE,
    tarfile.GNUTYPE_LONGNAME,
    tarfile.GNUTYPE_LONGLINK,
)


class ArchiveError(InputError):
    """The file is not a usable sgvloc map archive (damaged, truncated, foreign)."""


# -- writing ----------------------------------------------------------------------------


def _manifest(record: MapRecord, version: int, count: int, next_id: int | None) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "sgvloc_version": __version__,
        "exported_at": utc_now(),
        "map": {
            "name": record.name,
            "encoder_spec": record.encoder_spec.model_dump(mode="json"),
            "encoder_fingerprint": record.encoder_fingerprint,
            "localizer_config": record.localizer_config.model_dump(mode="json"),
            "keep_clouds": record.keep_clouds,
            "created_at": record.created_at,
            "calibration": None if record.calibration is None else record.calibration.to_dict(),
            "settings_version": record.settings_version,
            "settings_updated_at": record.settings_updated_at,
            "self_test": record.self_test,
            "last_self_test": record.last_self_test,
        },
        "version": int(version),
        "keyframes": int(count),
        # ids are never reused after a delete: the map made from the archive goes on
        # from here, not from its highest id still present
        "next_id": None if next_id is None else int(next_id),
        "chunk": CHUNK,
    }


def _pack_chunk(rows: list[KeyframeRow]) -> bytes:
    clouds = [r.cloud for r in rows if r.cloud is not None]
    arrays = {
        "ids": np.array([r.id for r in rows], dtype=np.int64),
        "T_map_sensor": np.stack([np.asarray(r.T_map_sensor, np.float64) for r in rows]),
        "global_descriptor": np.stack([r.global_descriptor for r in rows]),
        "keypoint_counts": np.array([len(r.keypoints) for r in rows], dtype=np.int64),
        "keypoints": np.concatenate([r.keypoints for r in rows]),
        "local_features": np.concatenate([r.local_features for r in rows]),
        "cloud_counts": np.array(
            [-1 if r.cloud is None else len(r.cloud) for r in rows], dtype=np.int64
        ),
        "clouds": np.concatenate(clouds) if clouds else np.zeros((0, 3), np.float32),
        "records": np.frombuffer(
            json.dumps(
                [{"key": r.key, "metadata": r.metadata, "created_at": r.created_at} for r in rows]
            ).encode(),
            dtype=np.uint8,
        ),
    }
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


class _Sink:
    """A write-only file object that hands out what was written since the last call."""

    def __init__(self) -> None:
        self._parts: list[bytes] = []

    def write(self, data: bytes) -> int:
        self._parts.append(bytes(data))
        return len(data)

    def take(self) -> bytes:
        out, self._parts = b"".join(self._parts), []
        return out


def write_archive(
    record: MapRecord,
    version: int,
    count: int,
    rows: Iterable[KeyframeRow],
    next_id: int | None = None,
) -> Iterator[bytes]:
    """The archive of a map as a stream of byte blocks (one per member, roughly).

    ``rows``: every keyframe, in id order (read lazily: the archive is never whole in
    memory); ``count`` must equal their number (checked).
    """
    sink = _Sink()
    sums: list[tuple[str, str]] = []
    with tarfile.open(fileobj=sink, mode="w|", format=tarfile.PAX_FORMAT) as tar:  # type: ignore[call-overload]

        def add(name: str, data: bytes) -> bytes:
            info = tarfile.TarInfo(name)
            info.size, info.mode = len(data), 0o644
            tar.addfile(info, io.BytesIO(data))
            sums.append((hashlib.sha256(data).hexdigest(), name))
            return sink.take()

        manifest = _manifest(record, version, count, next_id)
        yield add(MANIFEST, json.dumps(manifest, indent=1).encode())
        chunk: list[KeyframeRow] = []
        written = 0
        for row in rows:
            chunk.append(row)
            if len(chunk) == CHUNK:
                yield add(f"keyframes/{written // CHUNK:06d}.npz", _pack_chunk(chunk))
                written += len(chunk)
                chunk = []
        if chunk:
            yield add(f"keyframes/{written // CHUNK:06d}.npz", _pack_chunk(chunk))
            written += len(chunk)
        if written != count:
            raise RuntimeError(f"the map changed while it was exported ({written} != {count})")
        yield add(SUMS, "".join(f"{h}  {n}\n" for h, n in sums).encode())
    yield sink.take()


# -- reading ----------------------------------------------------------------------------


@dataclass(frozen=True)
class ArchiveHeader:
    """What the manifest says: the map's record (under its archived name), its version
    and keyframe count."""

    record: MapRecord
    version: int
    keyframes: int
    sgvloc_version: str
    next_id: int | None = None  # the id the map's next insert gets (None: not recorded)


def _object_or_none(value: Any, name: str) -> dict[str, Any] | None:
    if value is None:
        return None
    if not isinstance(value, dict):
        raise TypeError(f"{name} is a {type(value).__name__}, not an object")
    try:  # as the API refuses it: non-finite numbers, NUL, lone surrogates, deep nesting
        plain_json(value)
    except ValueError as exc:
        raise ValueError(f"{name} {exc}") from None
    return value


def _timestamp(value: Any, name: str) -> str:
    """An ISO 8601 time as the stores write it (``utc_now``), checked."""
    if isinstance(value, str) and len(value) <= 40:
        try:  # "...Z" as the stores write it; Python before 3.11 reads no "Z"
            datetime.fromisoformat(value[:-1] + "+00:00" if value.endswith("Z") else value)
            return value
        except ValueError:
            pass
    shown = repr(value) if len(repr(value)) <= 60 else repr(value)[:57] + "..."
    raise ValueError(f"{name} {shown} is not an ISO 8601 time")


def _bool(value: Any, name: str) -> bool:
    if isinstance(value, bool):
        return value
    raise TypeError(f"{name} is a {type(value).__name__}, not true or false")


def _header(manifest: dict[str, Any]) -> ArchiveHeader:
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise ArchiveError(f"not an sgvloc map archive ({MANIFEST} names no {FORMAT!r} format)")
    fv = manifest.get("format_version")
    if type(fv) is not int or fv not in READABLE_VERSIONS:
        raise ArchiveError(
            f"archive format version {fv!r} is not supported (this sgvloc reads "
            f"{' and '.join(map(str, READABLE_VERSIONS))}); export it again with a "
            "matching sgvloc"
        )
    try:
        m = manifest["map"]
        record = MapRecord(
            name=str(m["name"]),
            encoder_spec=EncoderSpec.model_validate(m["encoder_spec"]),
            localizer_config=LocalizerConfig.stored(m["localizer_config"]),
            encoder_fingerprint=str(m["encoder_fingerprint"]),
            keep_clouds=_bool(m["keep_clouds"], "keep_clouds"),
            created_at=_timestamp(m["created_at"], "created_at"),
            calibration=None
            if m.get("calibration") is None
            else Calibration.from_dict(m["calibration"]),
            settings_version=int(m.get("settings_version", 0)),
            settings_updated_at=None
            if m.get("settings_updated_at") is None
            else _timestamp(m["settings_updated_at"], "settings_updated_at"),
            self_test=_object_or_none(m.get("self_test"), "self_test"),
            last_self_test=_object_or_none(m.get("last_self_test"), "last_self_test"),
        )
        version, count = int(manifest["version"]), int(manifest["keyframes"])
        next_id = manifest.get("next_id")
        next_id = None if next_id is None else int(next_id)
    except (KeyError, TypeError, ValueError) as exc:
        raise ArchiveError(f"the archive's manifest is damaged: {exc}") from None
    if not (
        0 <= version < 2**62
        and 0 <= count < 2**62
        and 0 <= record.settings_version < 2**62
        and (next_id is None or 1 <= next_id < 2**62)
    ):
        raise ArchiveError(
            "the archive's manifest is damaged: a version, count or next_id out of range"
        )
    for name in ("self_test", "last_self_test"):
        value = getattr(record, name)
        if value is not None and len(json.dumps(value).encode()) > MAX_SELF_TEST_BYTES:
            raise ArchiveError(
                f"the archive's manifest is damaged: {name} is longer than "
                f"{MAX_SELF_TEST_BYTES} bytes as JSON"
            )
    sgvloc_version = str(manifest.get("sgvloc_version", "?"))
    return ArchiveHeader(record, version, count, sgvloc_version, next_id)


def _unpack_chunk(data: bytes, name: str) -> list[KeyframeRow]:
    try:
        # arrays are stored as they are (np.savez): a compressed one could inflate to
        # any size before its length is checked
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            for info in zf.infolist():
                if info.compress_type != zipfile.ZIP_STORED or info.file_size > len(data):
                    raise ValueError(f"{info.filename} is compressed; archives store arrays raw")
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
        records = json.loads(a["records"].tobytes())
        ids, T, g = a["ids"], a["T_map_sensor"], a["global_descriptor"]
        kc, cc = a["keypoint_counts"], a["cloud_counts"]
        n = len(ids)
        if not (
            len(records) == n == len(T) == len(g) == len(kc) == len(cc)
            and T.shape[1:] == (4, 4)
            and int(kc.sum()) == len(a["keypoints"]) == len(a["local_features"])
            and int(cc[cc > 0].sum()) == len(a["clouds"])
            and (kc >= 0).all()
        ):
            raise ValueError("array lengths disagree")
        kp_at = np.concatenate([[0], np.cumsum(kc)])
        cl_at = np.concatenate([[0], np.cumsum(np.maximum(cc, 0))])
        rows = []
        for i in range(n):
            rec = records[i]
            cloud = None if cc[i] < 0 else a["clouds"][cl_at[i] : cl_at[i + 1]]
            rows.append(
                KeyframeRow(
                    id=int(ids[i]),
                    key=rec["key"],
                    T_map_sensor=T[i].astype(np.float64),
                    global_descriptor=g[i],
                    keypoints=a["keypoints"][kp_at[i] : kp_at[i + 1]],
                    local_features=a["local_features"][kp_at[i] : kp_at[i + 1]],
                    cloud=cloud,
                    metadata=rec["metadata"],
                    created_at=_timestamp(rec["created_at"], "created_at"),
                )
            )
        return rows
    except ArchiveError:
        raise
    except Exception as exc:  # any malformation of one member: name it
        raise ArchiveError(f"archive member {name} is damaged: {exc}") from None


def _header_size(field: bytes) -> int | None:
    """The size field of a tar header block: octal digits, or base-256 when its first
    byte has the high bit set; None when it is neither (``tarfile`` names the damage)."""
    if field[:1] and field[0] & 0x80:
        return int.from_bytes(field[1:], "big")
    digits = field.replace(b"\0", b" ").strip()
    try:
        return int(digits, 8) if digits else 0
    except ValueError:
        return None


def _check_extended_headers(fileobj: IO[bytes]) -> None:
    """Walk the tar header blocks of a seekable ``fileobj`` (and back to where it was)
    and refuse an extended header over :data:`MAX_EXTENDED_HEADER_BYTES`, before
    ``tarfile`` would read it whole; everything else is left to ``tarfile``."""
    start = fileobj.tell()
    try:
        while len(block := fileobj.read(512)) == 512 and block.count(0) < 512:
            size = _header_size(block[124:136])
            if size is None:
                return
            if block[156:157] in _EXTENDED_TYPES and size > MAX_EXTENDED_HEADER_BYTES:
                raise ArchiveError(
                    f"not an sgvloc map archive (an extended tar header of {size} B; at most "
                    f"{MAX_EXTENDED_HEADER_BYTES} B are read)"
                )
            fileobj.seek((size + 511) // 512 * 512, io.SEEK_CUR)
    finally:
        fileobj.seek(start)


def read_archive(fileobj: IO[bytes]) -> tuple[ArchiveHeader, Iterator[list[KeyframeRow]]]:
    """The header of an archive and an iterator over its keyframes, a chunk at a time.

    The iterator checks every member's SHA-256 against ``SHA256SUMS`` (the last member)
    and raises :class:`ArchiveError` at the end if any differs, if a member is missing
    or extra, or if the keyframe count disagrees with the manifest: a caller must only
    keep what it built once the iterator is exhausted without error. ``fileobj`` must
    be seekable (a spooled upload, a file): its tar headers are checked first.
    """
    _check_extended_headers(fileobj)
    try:
        tar = tarfile.open(fileobj=fileobj, mode="r|")  # type: ignore[call-overload]
    except tarfile.TarError as exc:
        raise ArchiveError(f"not an sgvloc map archive (not a tar file: {exc})") from None

    def members() -> Iterator[tuple[str, bytes]]:
        try:
            for info in tar:
                if not info.isfile():
                    raise ArchiveError(f"archive member {info.name} is not a file")
                if info.size > MAX_MEMBER_BYTES:
                    raise ArchiveError(f"archive member {info.name} is too large ({info.size} B)")
                f = tar.extractfile(info)
                assert f is not None
                data = f.read()
                if len(data) != info.size:
                    raise ArchiveError(f"the archive is truncated (in {info.name})")
                yield info.name, data
        except (tarfile.TarError, EOFError, OSError) as exc:
            raise ArchiveError(f"the archive is damaged or truncated: {exc}") from None

    stream = members()
    first = next(stream, None)
    if first is None or first[0] != MANIFEST:
        raise ArchiveError(f"not an sgvloc map archive (its first member is not {MANIFEST})")
    try:
        manifest = json.loads(first[1])
    except ValueError:
        raise ArchiveError(f"the archive's {MANIFEST} is not JSON") from None
    header = _header(manifest)
    sums = {MANIFEST: hashlib.sha256(first[1]).hexdigest()}

    def chunks() -> Iterator[list[KeyframeRow]]:
        seen = 0
        listed: dict[str, str] | None = None
        for name, data in stream:
            if listed is not None:
                raise ArchiveError(f"archive member {name} follows {SUMS}")
            if name == SUMS:
                listed = {}
                for line in data.decode(errors="replace").splitlines():
                    digest, _, member = line.partition("  ")
                    listed[member] = digest
                continue
            if not name.startswith("keyframes/") or name in sums:
                raise ArchiveError(f"unexpected archive member {name}")
            sums[name] = hashlib.sha256(data).hexdigest()
            rows = _unpack_chunk(data, name)
            seen += len(rows)
            yield rows
        if listed is None:
            raise ArchiveError(f"the archive is truncated (no {SUMS})")
        if listed != sums:
            bad = sorted(n for n in set(listed) | set(sums) if listed.get(n) != sums.get(n))
            raise ArchiveError(f"checksum mismatch: {', '.join(bad[:5])} (the archive is damaged)")
        if seen != header.keyframes:
            raise ArchiveError(
                f"the archive holds {seen} keyframes, its manifest says {header.keyframes}"
            )

    return header, chunks()
