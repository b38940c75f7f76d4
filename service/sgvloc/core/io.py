"""Reading and writing LiDAR scan files as :class:`Scan` (dispatch: :func:`read_scan`).

- ``.bin``: KITTI velodyne, float32 ``x y z intensity`` per point, little-endian;
- ``.pcd``: ``DATA ascii | binary | binary_compressed``, any ``FIELDS/SIZE/TYPE/COUNT``
  layout with ``x y z`` anywhere (decoded by pypcd4);
- ``.ply``: ``ascii | binary_little_endian | binary_big_endian`` with ``x y z`` (and
  optionally intensity) in the first element, ``vertex`` (decoded by plyfile);
- ``.npy`` / ``.npz``: arrays ``[P, 3]`` or ``[P, 4+]`` (column 3 is intensity).

Every reading problem raises :class:`~sgvloc.core.errors.ScanFormatError` whose message
names the file and what is wrong. Sequences of scans: :mod:`sgvloc.core.sequence`.
"""

from __future__ import annotations

import logging
import os
import struct
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError, ScanFormatError

log = logging.getLogger(__name__)

PathLike = str | os.PathLike

SCAN_EXTENSIONS = (".bin", ".pcd", ".ply", ".npy", ".npz")
# Field / property names read as intensity, in order of preference (compared lower-case).
INTENSITY_NAMES = ("intensity", "scalar_intensity", "i", "reflectance")
_MAX_HEADER_BYTES = 1 << 16


# --------------------------------------------------------------------------------------
# Scan


@dataclass(frozen=True, eq=False)
class Scan:
    """One LiDAR scan in its sensor frame.

    - ``points``: ``[P, 3]`` float32, metres (rows may be non-finite; preprocessing drops
      them);
    - ``intensity``: ``[P]`` float32, or ``None`` when the source has none;
    - ``source``: the file path or a short description of where the scan came from.

    Arrays are converted to contiguous float32 on construction; wrong shapes raise
    :class:`InputError`.
    """

    points: np.ndarray
    intensity: np.ndarray | None = None
    source: str = "array"

    def __post_init__(self) -> None:
        pts = np.asarray(self.points)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise InputError(f"{self.source}: points must have shape [P, 3], got {list(pts.shape)}")
        if pts.dtype.kind not in "fiu":
            raise InputError(f"{self.source}: points must be numeric, got dtype {pts.dtype}")
        object.__setattr__(self, "points", np.ascontiguousarray(pts, dtype=np.float32))
        if self.intensity is not None:
            inten = np.asarray(self.intensity)
            if inten.shape != (len(pts),):
                raise InputError(
                    f"{self.source}: intensity must have shape [{len(pts)}], "
                    f"got {list(inten.shape)}"
                )
            if inten.dtype.kind not in "fiu":
                raise InputError(
                    f"{self.source}: intensity must be numeric, got dtype {inten.dtype}"
                )
            object.__setattr__(self, "intensity", np.ascontiguousarray(inten, dtype=np.float32))

    def __len__(self) -> int:
        return len(self.points)

    def xyzi(self) -> np.ndarray:
        """``[P, 4]`` float32 ``x y z intensity`` (intensity 0 where the scan has none)."""
        out = np.zeros((len(self.points), 4), dtype=np.float32)  # [P, 4]
        out[:, :3] = self.points
        if self.intensity is not None:
            out[:, 3] = self.intensity
        return out


def scan_from_array(arr: np.ndarray, source: str = "array") -> Scan:
    """Make a :class:`Scan` from an array ``[P, 3]`` (xyz) or ``[P, 4+]`` (xyz, intensity).

    Columns past the fourth are ignored. Rows with NaN/inf are kept (preprocessing drops
    them); their count is logged. Raises :class:`InputError` on a wrong shape or dtype.
    """
    a = np.asarray(arr)
    if a.ndim != 2 or a.shape[1] < 3:
        raise InputError(
            f"{source}: scan array must have shape [P, 3] or [P, 4+], got {list(a.shape)}"
        )
    if a.dtype.kind not in "fiu":
        raise InputError(f"{source}: scan array must be real numbers, got dtype {a.dtype}")
    points = a[:, :3]
    if a.dtype.kind == "f":
        bad = int((~np.isfinite(points).all(axis=1)).sum())
        if bad:
            log.debug("%s: %d of %d rows have non-finite coordinates", source, bad, len(a))
    intensity = a[:, 3] if a.shape[1] >= 4 else None
    return Scan(points=points, intensity=intensity, source=source)


def _as_scan(scan: Scan | np.ndarray) -> Scan:
    return scan if isinstance(scan, Scan) else scan_from_array(scan)


def _scan_from_columns(
    get: Callable[[str], np.ndarray | None], names: list[str], path: Path, n: int
) -> Scan:
    """Assemble a Scan from named columns; ``get(name)`` returns ``[n]`` or None."""
    lower = {nm.lower(): nm for nm in reversed(names)}  # first occurrence wins
    missing = [c for c in ("x", "y", "z") if c not in lower]
    if missing:
        raise ScanFormatError(
            f"{path}: no {'/'.join(missing)} field (fields are {' '.join(names) or 'none'})"
        )
    points = np.empty((n, 3), dtype=np.float32)  # [P, 3]
    for k, c in enumerate("xyz"):
        points[:, k] = get(lower[c])
    intensity = None
    for cand in INTENSITY_NAMES:
        if cand in lower:
            intensity = np.asarray(get(lower[cand]), dtype=np.float32)
            break
    return Scan(points=points, intensity=intensity, source=str(path))


# --------------------------------------------------------------------------------------
# Helpers shared by the parsers


def _read_bytes(path: PathLike) -> tuple[Path, bytes]:
    p = Path(path)
    if not p.exists():
        raise ScanFormatError(f"{p}: scan file not found")
    if p.is_dir():
        raise ScanFormatError(f"{p}: is a directory, not a scan file")
    try:
        return p, p.read_bytes()
    except OSError as e:
        raise ScanFormatError(f"{p}: cannot read file: {e}") from e


# --------------------------------------------------------------------------------------
# KITTI .bin


def read_kitti_bin(path: PathLike) -> Scan:
    """Read a KITTI velodyne ``.bin`` (float32 ``x y z intensity`` per point)."""
    p, raw = _read_bytes(path)
    if len(raw) % 16:
        raise ScanFormatError(
            f"{p}: KITTI .bin size {len(raw)} bytes is not a multiple of 16 "
            "(4 float32 x y z intensity per point)"
        )
    a = np.frombuffer(raw, dtype="<f4").reshape(-1, 4)  # [P, 4]
    return Scan(points=a[:, :3], intensity=a[:, 3], source=str(p))


def write_kitti_bin(path: PathLike, scan: Scan | np.ndarray) -> Path:
    """Write a scan as KITTI ``.bin`` (intensity 0 where the scan has none)."""
    p = Path(path)
    p.write_bytes(_as_scan(scan).xyzi().astype("<f4").tobytes())
    return p


# --------------------------------------------------------------------------------------
# PCD (pypcd4) and PLY (plyfile). The libraries decode; the checks here turn every problem
# into a ScanFormatError that names the file and what is wrong.

_PCD_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT")
_PCD_KEYS += ("POINTS", "DATA")


def _pcd_header(raw: bytes, p: Path) -> tuple[Any, list[str], bytes]:
    """``(pypcd4 MetaData, FIELDS, data bytes)`` of a PCD file, the header checked."""
    from pydantic import ValidationError
    from pypcd4.pypcd4 import PCD_TYPE_TO_NUMPY_TYPE, MetaData

    lines: dict[str, list[str]] = {}
    pos = lineno = 0
    while "DATA" not in lines:
        end = raw.find(b"\n", pos)
        if end < 0 or pos > _MAX_HEADER_BYTES:
            raise ScanFormatError(f"{p}: not a valid PCD file: no DATA line ends the header")
        try:
            text = raw[pos:end].decode("ascii").strip()
        except UnicodeDecodeError:
            raise ScanFormatError(f"{p}: not a valid PCD file: header is not ASCII") from None
        lineno, pos = lineno + 1, end + 1
        if not text or text.startswith("#"):
            continue
        key, *vals = text.split()
        if key.upper() not in _PCD_KEYS:
            raise ScanFormatError(
                f"{p}: not a valid PCD file: header line {lineno} starts with unknown key "
                f"{key.upper()[:40]!r}"
            )
        lines[key.upper()] = vals
    fields = lines.get("FIELDS", [])
    if not fields:
        raise ScanFormatError(f"{p}: not a valid PCD file: the header has no FIELDS")
    named = [f for f in fields if f != "_"]  # "_" pads, and may come more than once
    if len(set(named)) != len(named):
        raise ScanFormatError(f"{p}: PCD FIELDS names a field twice: {' '.join(fields)}")
    lines.setdefault("COUNT", ["1"] * len(fields))
    for key in ("SIZE", "TYPE", "COUNT"):
        if len(lines.get(key, [])) != len(fields):
            n = len(lines.get(key, []))
            raise ScanFormatError(f"{p}: PCD {key} has {n} entries but FIELDS has {len(fields)}")
    for name, typ, size in zip(fields, lines["TYPE"], lines["SIZE"], strict=True):
        if (typ.upper(), int(size) if size.isdigit() else 0) not in PCD_TYPE_TO_NUMPY_TYPE:
            raise ScanFormatError(
                f"{p}: field {name!r} has unsupported TYPE {typ} SIZE {size} (F: 4/8, U/I: 1/2/4/8)"
            )
    for name, count in zip(fields, lines["COUNT"], strict=True):
        if name in ("x", "y", "z") and count != "1":
            raise ScanFormatError(f"{p}: field {name!r} has COUNT {count}, expected 1")
    lines.pop("VERSION", None)  # any version: the layout keys are what matters
    lines["DATA"] = [" ".join(lines["DATA"]).lower()]
    try:
        if "POINTS" not in lines and "WIDTH" in lines:
            lines["POINTS"] = [str(int(lines["WIDTH"][0]) * int(lines.get("HEIGHT", ["1"])[0]))]
        meta = MetaData.parse_header([f"{k} {' '.join(v)}" for k, v in lines.items()])
    except (ValidationError, ValueError, IndexError) as exc:
        raise ScanFormatError(f"{p}: not a valid PCD header: {_first_error(exc)}") from None
    if meta.width * meta.height != meta.points:
        raise ScanFormatError(
            f"{p}: PCD header WIDTH {meta.width} x HEIGHT {meta.height} != POINTS {meta.points}"
        )
    return meta, fields, raw[pos:]


def _first_error(exc: Exception) -> str:
    errors = getattr(exc, "errors", None)
    if errors:
        e = errors()[0]
        return f"{' '.join(map(str, e['loc'])).upper()}: {e['msg']}"
    return str(exc)


def _check_pcd_size(p: Path, meta: Any, point_size: int, body: bytes) -> bytes:
    """The data section as pypcd4 reads it; a wrong size is an error naming both counts."""
    n = meta.points
    if meta.data == "ascii":
        rows = [b" ".join(ln.split()) for ln in body.splitlines() if ln.strip()]
        if len(rows) != n:
            raise ScanFormatError(
                f"{p}: header says {n} points but the ascii data has {len(rows)} lines"
            )
        return b"\n".join(rows) + b"\n"
    if meta.data == "binary":
        if len(body) < n * point_size:
            raise ScanFormatError(
                f"{p}: truncated PCD: header says {n} points x {point_size} bytes = "
                f"{n * point_size} bytes of binary data, but only {len(body)} bytes follow the "
                f"header ({len(body) // point_size} complete points)"
            )
        if len(body) - n * point_size >= point_size:
            raise ScanFormatError(
                f"{p}: PCD header says {n} points but {len(body)} bytes of binary data follow "
                f"({len(body) // point_size} points of {point_size} bytes)"
            )
        return body
    if len(body) < 8:
        raise ScanFormatError(f"{p}: truncated PCD: binary_compressed data has no size header")
    csize, usize = struct.unpack("<II", body[:8])
    if usize != n * point_size:
        raise ScanFormatError(
            f"{p}: PCD binary_compressed says {usize} uncompressed bytes, but {n} points x "
            f"{point_size} bytes = {n * point_size}"
        )
    if len(body) - 8 < csize:
        raise ScanFormatError(
            f"{p}: truncated PCD: {csize} compressed bytes announced, only {len(body) - 8} present"
        )
    return body


def read_pcd(path: PathLike) -> Scan:
    """Read a PCD file (``DATA ascii``, ``binary`` or ``binary_compressed``) with pypcd4.

    Any field layout is accepted as long as ``x``, ``y`` and ``z`` exist with COUNT 1;
    ``intensity`` (or ``i``) becomes :attr:`Scan.intensity`, other fields are ignored.
    """
    import io

    from pypcd4 import PointCloud

    p, raw = _read_bytes(path)
    meta, fields, body = _pcd_header(raw, p)
    dtype = meta.build_dtype()
    body = _check_pcd_size(p, meta, dtype.itemsize, body)
    try:
        pc = PointCloud.from_fileobj(io.BytesIO(meta.compose_header().encode() + body))
    except (ValueError, RuntimeError, TypeError) as exc:
        raise ScanFormatError(f"{p}: corrupt {meta.data.value} PCD data: {exc}") from None
    data = np.atleast_1d(pc.pc_data)
    names = [nm if nm in data.dtype.names else "_" for nm in fields]
    return _scan_from_columns(lambda nm: data[nm], names, p, meta.points)


def write_pcd(
    path: PathLike, scan: Scan | np.ndarray, binary: bool = True, compressed: bool = False
) -> Path:
    """Write a PCD v0.7 file with float32 ``x y z`` (and ``intensity`` if the scan has it):
    ``binary`` (default), ``binary_compressed`` (``compressed=True``) or ascii."""
    from pypcd4 import Encoding, PointCloud

    s = _as_scan(scan)
    p = Path(path)
    if s.intensity is None:
        pc = PointCloud.from_xyz_points(s.points)
    else:
        pc = PointCloud.from_xyzi_points(s.xyzi())
    if binary or compressed:
        pc.save(p, encoding=Encoding.BINARY_COMPRESSED if compressed else Encoding.BINARY)
    else:  # %.9g round-trips float32 exactly (pypcd4's ascii writer keeps 10 decimals)
        with p.open("wb") as f:
            f.write(pc.metadata.compose_header(Encoding.ASCII).encode())
            np.savetxt(f, s.xyzi()[:, : len(pc.fields)], fmt="%.9g")
    return p


def read_ply(path: PathLike) -> Scan:
    """Read a PLY file (``ascii``, ``binary_little_endian``, ``binary_big_endian``) with
    plyfile. Its first element must be ``vertex`` with ``x y z``; later elements (faces, ...)
    are ignored."""
    import io

    from plyfile import PlyData, PlyElementParseError, PlyListProperty, PlyParseError

    p, raw = _read_bytes(path)
    try:
        ply = PlyData.read(io.BytesIO(raw))
    except PlyElementParseError as exc:
        element = exc.element.name if exc.element is not None else "?"
        n = exc.element.count if exc.element is not None else "?"
        row = exc.row if exc.row is not None else 0
        header_end = raw.find(b"end_header")
        if b"format ascii" in raw[:header_end] and element == "vertex":
            lineno = raw[:header_end].count(b"\n") + 2 + row
            line = raw.split(b"\n")[lineno - 1] if lineno <= raw.count(b"\n") + 1 else b""
            expected = len(exc.element.properties)
            raise ScanFormatError(
                f"{p}: line {lineno} has {len(line.split())} values, expected {expected}"
            ) from None
        raise ScanFormatError(
            f"{p}: truncated or corrupt PLY: header says {n} vertices, reading stopped at "
            f"row {row} of element {element!r} ({exc.message})"
        ) from None
    except (PlyParseError, UnicodeDecodeError, ValueError) as exc:
        raise ScanFormatError(f"{p}: not a valid PLY file: {exc}") from None
    names = [e.name for e in ply.elements]
    if "vertex" not in names:
        raise ScanFormatError(f"{p}: PLY file has no vertex element")
    if names[0] != "vertex":
        raise ScanFormatError(
            f"{p}: PLY vertex element must come first (elements are {' '.join(names)})"
        )
    vertex = ply["vertex"]
    lists = [prop.name for prop in vertex.properties if isinstance(prop, PlyListProperty)]
    for name in ("x", "y", "z"):
        if name in lists:
            raise ScanFormatError(f"{p}: PLY property {name!r} is a list, expected a number")
    if len(names) == 1 and not lists:  # nothing may follow the vertices: a header lies
        _check_ply_rest(raw, vertex, ply.text, p)
    data = vertex.data
    columns = [nm for nm in data.dtype.names if nm not in lists]  # a list intensity: none
    return _scan_from_columns(lambda nm: data[nm], columns, p, len(data))


def _check_ply_rest(raw: bytes, vertex: Any, text: bool, p: Path) -> None:
    """A PLY file holding only vertices ends with them (ScanFormatError if more follows)."""
    start = raw.find(b"end_header")
    start = raw.find(b"\n", start) + 1
    body = raw[start:]
    if text:
        rows = [ln for ln in body.split(b"\n") if ln.strip()]
        extra = len(rows) - vertex.count
    else:
        extra = len(body) - vertex.count * vertex.data.dtype.itemsize
    if extra > 0:
        unit = "line(s)" if text else "byte(s)"
        raise ScanFormatError(
            f"{p}: the PLY header says {vertex.count} vertices but {extra} more {unit} follow"
        )


def write_ply(path: PathLike, scan: Scan | np.ndarray, binary: bool = True) -> Path:
    """Write a PLY vertex cloud with float ``x y z`` (and ``intensity`` if present)."""
    from plyfile import PlyData, PlyElement

    s = _as_scan(scan)
    names = ["x", "y", "z"] + (["intensity"] if s.intensity is not None else [])
    xyzi = s.xyzi()  # [P, 4]
    rec = np.zeros(len(s), dtype=[(nm, "<f4") for nm in names])
    for k, nm in enumerate(names):
        rec[nm] = xyzi[:, k]
    PlyData([PlyElement.describe(rec, "vertex")], text=not binary, byte_order="<").write(str(path))
    return Path(path)


# --------------------------------------------------------------------------------------
# numpy


def read_npy(path: PathLike) -> Scan:
    """Read a ``.npy`` array ``[P, 3]``/``[P, 4+]`` or a ``.npz`` with a ``points`` array.

    In an ``.npz``, an ``intensity`` array ``[P]`` is used if present; an archive holding a
    single array of any name is accepted too.
    """
    p = Path(path)
    if not p.exists():
        raise ScanFormatError(f"{p}: scan file not found")
    try:
        loaded = np.load(p, allow_pickle=False)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
        raise ScanFormatError(f"{p}: cannot read numpy file: {e}") from None
    try:
        if isinstance(loaded, np.ndarray):
            return scan_from_array(loaded, source=str(p))
        with loaded as z:
            keys = list(z.keys())
            if "points" in keys:
                arr = z["points"]
            elif len(keys) == 1:
                arr = z[keys[0]]
            else:
                raise ScanFormatError(
                    f"{p}: .npz has no 'points' array (arrays: {', '.join(keys) or 'none'})"
                )
            scan = scan_from_array(arr, source=str(p))
            if "intensity" in keys:
                scan = Scan(scan.points, z["intensity"], str(p))
            return scan
    except ScanFormatError:
        raise
    except (InputError, ValueError, OSError, EOFError, zipfile.BadZipFile) as e:  # corrupt
        msg = str(e)
        raise ScanFormatError(msg if msg.startswith(str(p)) else f"{p}: {msg}") from None


# --------------------------------------------------------------------------------------
# Dispatch

_READERS = {
    ".bin": read_kitti_bin,
    ".pcd": read_pcd,
    ".ply": read_ply,
    ".npy": read_npy,
    ".npz": read_npy,
}


def read_scan(path: PathLike) -> Scan:
    """Read a scan file, choosing the format from its extension (see module docstring)."""
    p = Path(path)
    reader = _READERS.get(p.suffix.lower())
    if reader is None:
        raise ScanFormatError(
            f"{p}: unknown scan file extension {p.suffix!r} (expected one of "
            f"{', '.join(SCAN_EXTENSIONS)})"
        )
    if not p.exists():
        raise ScanFormatError(f"{p}: scan file not found")
    return reader(p)
