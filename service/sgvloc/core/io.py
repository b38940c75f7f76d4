"""Reading and writing LiDAR scans, and KITTI-layout sequences.

Formats (dispatched on the extension by :func:`read_scan`):

- ``.bin``: KITTI velodyne, float32 ``x y z intensity`` per point, little-endian;
- ``.pcd``: PCD v0.7 (also older headers), ``DATA ascii | binary | binary_compressed``
  (LZF), any ``FIELDS/SIZE/TYPE/COUNT`` layout with ``x y z`` anywhere;
- ``.ply``: ``ascii | binary_little_endian | binary_big_endian`` with a ``vertex``
  element holding ``x y z`` (and optionally intensity) as the first element;
- ``.npy`` / ``.npz``: arrays ``[P, 3]`` or ``[P, 4+]`` (column 3 is intensity).

Every reading problem raises :class:`~sgvloc.core.errors.ScanFormatError` whose message
names the file and what is wrong. The parsers are our own (numpy structured dtypes), so
extra fields are never silently mangled and errors stay precise.

:class:`KittiSequence` walks a KITTI-odometry folder (``velodyne/*.bin``, ``poses.txt``
with the row-major top 3x4 of ``T_world_sensor`` per line, ``times.txt``).
"""

from __future__ import annotations

import logging
import operator
import os
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

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


def _header_lines(
    raw: bytes, path: Path, kind: str, is_last: Callable[[str], bool]
) -> tuple[list[tuple[int, str]], int]:
    """Split a text header off ``raw``.

    Returns ``(lines, offset)``: ``lines`` as ``(line_number, text)`` up to and including
    the line for which ``is_last`` is true, ``offset`` the first byte after it.
    """
    lines: list[tuple[int, str]] = []
    pos = 0
    lineno = 0
    while True:
        if pos >= len(raw):
            what = "file is empty" if not raw else "header ends before its last line"
            raise ScanFormatError(f"{path}: not a valid {kind} file: {what}")
        if pos > _MAX_HEADER_BYTES:
            raise ScanFormatError(
                f"{path}: not a valid {kind} file: no end of header in the first "
                f"{_MAX_HEADER_BYTES} bytes"
            )
        nl = raw.find(b"\n", pos)
        end = len(raw) if nl < 0 else nl
        lineno += 1
        try:
            text = raw[pos:end].decode("ascii").rstrip("\r")
        except UnicodeDecodeError:
            raise ScanFormatError(
                f"{path}: not a valid {kind} file: header line {lineno} is not ASCII text"
            ) from None
        pos = end + 1
        lines.append((lineno, text))
        if is_last(text):
            return lines, min(pos, len(raw))
        if nl < 0:
            raise ScanFormatError(
                f"{path}: not a valid {kind} file: header ends before its last line"
            )


def _parse_ascii_table(
    text: str, n: int, ncols: int, path: Path, first_line: int, allow_extra: bool = False
) -> np.ndarray:
    """Parse ``n`` whitespace-separated rows of ``ncols`` numbers -> ``[n, ncols]`` float64.

    More than ``n`` non-blank lines is an error unless ``allow_extra`` (other data follows).
    """
    rows = [(k, ln) for k, ln in enumerate(text.split("\n"), start=first_line) if ln.strip()]
    if len(rows) < n:
        raise ScanFormatError(
            f"{path}: header says {n} points but the ascii data has only {len(rows)} lines"
        )
    if len(rows) > n and not allow_extra:
        raise ScanFormatError(
            f"{path}: header says {n} points but the ascii data has {len(rows)} lines"
        )
    rows = rows[:n]
    tokens = " ".join(ln for _, ln in rows).split()
    if len(tokens) != n * ncols:
        for k, ln in rows:
            if len(ln.split()) != ncols:
                raise ScanFormatError(
                    f"{path}: line {k} has {len(ln.split())} values, expected {ncols}"
                )
    try:
        vals = np.array(tokens, dtype=np.float64)
    except ValueError:
        for k, ln in rows:
            for tok in ln.split():
                try:
                    float(tok)
                except ValueError:
                    raise ScanFormatError(f"{path}: line {k}: {tok!r} is not a number") from None
        raise
    return vals.reshape(n, ncols)  # [n, ncols]


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
# PCD

_PCD_KEYS = (
    "VERSION",
    "FIELDS",
    "SIZE",
    "TYPE",
    "COUNT",
    "WIDTH",
    "HEIGHT",
    "VIEWPOINT",
    "POINTS",
    "DATA",
)
_PCD_TYPES = {"F": ("f", (2, 4, 8)), "U": ("u", (1, 2, 4, 8)), "I": ("i", (1, 2, 4, 8))}


def _pcd_int(path: Path, key: str, vals: list[str], lineno: int) -> int:
    if len(vals) != 1:
        raise ScanFormatError(f"{path}: header line {lineno}: {key} needs one value, got {vals}")
    try:
        v = int(vals[0])
    except ValueError:
        raise ScanFormatError(
            f"{path}: header line {lineno}: {key} {vals[0]!r} is not an integer"
        ) from None
    if v < 0:
        raise ScanFormatError(f"{path}: header line {lineno}: {key} is negative ({v})")
    return v


def _parse_pcd_header(lines: list[tuple[int, str]], path: Path) -> dict:
    h: dict = {}
    for lineno, text in lines:
        s = text.strip()
        if not s or s.startswith("#"):
            continue
        key, *vals = s.split()
        key = key.upper()
        if key not in _PCD_KEYS:
            raise ScanFormatError(
                f"{path}: not a valid PCD file: header line {lineno} starts with unknown key "
                f"{key[:40]!r}"
            )
        if key in h:
            raise ScanFormatError(f"{path}: header line {lineno}: {key} given twice")
        h[key] = (vals, lineno)
    if "FIELDS" not in h:
        raise ScanFormatError(f"{path}: PCD header has no FIELDS line")
    fields = h["FIELDS"][0]
    nf = len(fields)
    if nf == 0:
        raise ScanFormatError(f"{path}: PCD header FIELDS is empty")
    for key in ("SIZE", "TYPE"):
        if key not in h:
            raise ScanFormatError(f"{path}: PCD header has no {key} line")
    sizes_s, ln = h["SIZE"]
    types, ln_t = h["TYPE"]
    counts_s, ln_c = h.get("COUNT", (["1"] * nf, 0))
    for key, vals, ln_k in (
        ("SIZE", sizes_s, ln),
        ("TYPE", types, ln_t),
        ("COUNT", counts_s, ln_c),
    ):
        if len(vals) != nf:
            raise ScanFormatError(
                f"{path}: header line {ln_k}: {key} has {len(vals)} entries but FIELDS has {nf}"
            )
    try:
        sizes = [int(v) for v in sizes_s]
        counts = [int(v) for v in counts_s]
    except ValueError:
        raise ScanFormatError(f"{path}: PCD SIZE/COUNT values must be integers") from None
    dtypes = []
    for name, size, typ, cnt in zip(fields, sizes, types, counts, strict=True):
        kind = _PCD_TYPES.get(typ.upper())
        if kind is None or size not in kind[1]:
            raise ScanFormatError(
                f"{path}: field {name!r} has unsupported TYPE {typ} SIZE {size} "
                "(F: 2/4/8, U/I: 1/2/4/8)"
            )
        if cnt < 1:
            raise ScanFormatError(f"{path}: field {name!r} has COUNT {cnt} (must be >= 1)")
        dtypes.append((np.dtype(f"<{kind[0]}{size}"), cnt))
    if "DATA" not in h:
        raise ScanFormatError(f"{path}: PCD header has no DATA line")
    data_vals, ln_d = h["DATA"]
    data = data_vals[0].lower() if len(data_vals) == 1 else ""
    if data not in ("ascii", "binary", "binary_compressed"):
        raise ScanFormatError(
            f"{path}: header line {ln_d}: DATA must be ascii, binary or binary_compressed, "
            f"got {' '.join(data_vals)!r}"
        )
    width = _pcd_int(path, "WIDTH", *h["WIDTH"]) if "WIDTH" in h else None
    height = _pcd_int(path, "HEIGHT", *h["HEIGHT"]) if "HEIGHT" in h else 1
    points = _pcd_int(path, "POINTS", *h["POINTS"]) if "POINTS" in h else None
    if points is None and width is None:
        raise ScanFormatError(f"{path}: PCD header has neither POINTS nor WIDTH")
    if points is None:
        points = width * height
    elif width is not None and width * height != points:
        raise ScanFormatError(
            f"{path}: PCD header WIDTH {width} x HEIGHT {height} != POINTS {points}"
        )
    return {"fields": fields, "dtypes": dtypes, "data": data, "n": points}


def lzf_decompress(data: bytes, expected_size: int) -> bytes:
    """Decompress an LZF stream (liblzf format, as in PCD ``binary_compressed``).

    Raises :class:`ValueError` on a corrupt stream or a size other than ``expected_size``.
    """
    src = memoryview(data)
    out = bytearray()
    ip, n_in = 0, len(src)
    while ip < n_in:
        ctrl = src[ip]
        ip += 1
        if ctrl < 32:  # literal run of ctrl + 1 bytes
            run = ctrl + 1
            if ip + run > n_in:
                raise ValueError("literal run past the end of the compressed data")
            out += src[ip : ip + run]
            ip += run
        else:  # back reference: length (3 bits, extended), offset (13 bits)
            length = ctrl >> 5
            if length == 7:
                if ip >= n_in:
                    raise ValueError("back reference past the end of the compressed data")
                length += src[ip]
                ip += 1
            if ip >= n_in:
                raise ValueError("back reference past the end of the compressed data")
            ref = len(out) - ((ctrl & 0x1F) << 8) - src[ip] - 1
            ip += 1
            length += 2
            if ref < 0:
                raise ValueError("back reference before the start of the output")
            if ref + length <= len(out):
                out += out[ref : ref + length]
            else:  # overlapping copy: the last `period` bytes repeat
                chunk = bytes(out[ref:])
                reps = length // len(chunk) + 1
                out += (chunk * reps)[:length]
        if len(out) > expected_size:
            raise ValueError(f"decompresses to more than the expected {expected_size} bytes")
    if len(out) != expected_size:
        raise ValueError(f"decompresses to {len(out)} bytes, expected {expected_size}")
    return bytes(out)


def read_pcd(path: PathLike) -> Scan:
    """Read a PCD file (``DATA ascii``, ``binary`` or ``binary_compressed``).

    Any field layout is accepted as long as ``x``, ``y`` and ``z`` exist with COUNT 1;
    ``intensity`` (or ``i``) becomes :attr:`Scan.intensity`, other fields are ignored.
    """
    p, raw = _read_bytes(path)
    lines, offset = _header_lines(raw, p, "PCD", lambda t: t.strip().upper().startswith("DATA"))
    h = _parse_pcd_header(lines, p)
    fields, dtypes, n = h["fields"], h["dtypes"], h["n"]
    for c in ("x", "y", "z"):
        if c in fields and dtypes[fields.index(c)][1] != 1:
            raise ScanFormatError(
                f"{p}: field {c!r} has COUNT {dtypes[fields.index(c)][1]}, expected 1"
            )
    # Unique internal names: PCD allows repeated names (e.g. "_" padding).
    first = {}
    for k, name in enumerate(fields):
        first.setdefault(name, k)
    point_size = sum(dt.itemsize * cnt for dt, cnt in dtypes)
    body = raw[offset:]

    if h["data"] == "ascii":
        try:
            text = body.decode("ascii")
        except UnicodeDecodeError:
            raise ScanFormatError(f"{p}: DATA ascii section contains non-ASCII bytes") from None
        ncols = sum(cnt for _, cnt in dtypes)
        table = _parse_ascii_table(text, n, ncols, p, first_line=len(lines) + 1)  # [n, ncols]
        starts = np.cumsum([0] + [cnt for _, cnt in dtypes])

        def get(name: str) -> np.ndarray:
            return table[:, starts[first[name]]]

    elif h["data"] == "binary":
        need = n * point_size
        if len(body) < need:
            raise ScanFormatError(
                f"{p}: truncated PCD: header says {n} points x {point_size} bytes = {need} "
                f"bytes of binary data, but only {len(body)} bytes follow the header "
                f"({len(body) // max(point_size, 1)} complete points)"
            )
        if len(body) - need >= point_size:
            raise ScanFormatError(
                f"{p}: PCD header says {n} points but {len(body)} bytes of binary data follow "
                f"({len(body) // point_size} points of {point_size} bytes)"
            )
        dt = np.dtype([(f"f{k}", d if c == 1 else (d, (c,))) for k, (d, c) in enumerate(dtypes)])
        rec = np.frombuffer(body, dtype=dt, count=n)

        def get(name: str) -> np.ndarray:
            col = rec[f"f{first[name]}"]
            return col if col.ndim == 1 else col[:, 0]

    else:  # binary_compressed: sizes, LZF stream of the fields one after another
        if n == 0:
            return _scan_from_columns(lambda _: np.zeros(0, np.float32), fields, p, 0)
        if len(body) < 8:
            raise ScanFormatError(f"{p}: truncated PCD: binary_compressed data has no size header")
        csize, usize = struct.unpack("<II", body[:8])
        need = n * point_size
        if usize != need:
            raise ScanFormatError(
                f"{p}: PCD binary_compressed says {usize} uncompressed bytes, but {n} points x "
                f"{point_size} bytes = {need}"
            )
        if len(body) - 8 < csize:
            raise ScanFormatError(
                f"{p}: truncated PCD: {csize} compressed bytes announced, only "
                f"{len(body) - 8} present"
            )
        try:
            buf = lzf_decompress(body[8 : 8 + csize], usize)
        except ValueError as e:
            raise ScanFormatError(f"{p}: corrupt binary_compressed PCD data: {e}") from None
        offsets = np.cumsum([0] + [n * d.itemsize * c for d, c in dtypes])

        def get(name: str) -> np.ndarray:
            k = first[name]
            d, c = dtypes[k]
            col = np.frombuffer(buf, dtype=d, count=n * c, offset=int(offsets[k]))
            return col.reshape(n, c)[:, 0]

    return _scan_from_columns(get, fields, p, n)


def write_pcd(path: PathLike, scan: Scan | np.ndarray, binary: bool = True) -> Path:
    """Write a PCD v0.7 file with float32 ``x y z`` (and ``intensity`` if the scan has it)."""
    s = _as_scan(scan)
    p = Path(path)
    has_i = s.intensity is not None
    nf = 4 if has_i else 3
    n = len(s)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\n"
        "VERSION 0.7\n"
        f"FIELDS x y z{' intensity' if has_i else ''}\n"
        f"SIZE {' '.join(['4'] * nf)}\n"
        f"TYPE {' '.join(['F'] * nf)}\n"
        f"COUNT {' '.join(['1'] * nf)}\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
        f"DATA {'binary' if binary else 'ascii'}\n"
    )
    data = s.xyzi()[:, :nf]  # [P, nf]
    if binary:
        body = data.astype("<f4").tobytes()
    else:
        # %.9g round-trips float32 exactly
        body = "".join(" ".join(f"{v:.9g}" for v in row) + "\n" for row in data.tolist()).encode()
    p.write_bytes(header.encode("ascii") + body)
    return p


# --------------------------------------------------------------------------------------
# PLY

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def read_ply(path: PathLike) -> Scan:
    """Read a PLY file whose first element is ``vertex`` with ``x y z`` properties.

    Formats ``ascii``, ``binary_little_endian`` and ``binary_big_endian``. Elements after
    ``vertex`` (faces, ...) are ignored; an element before it is an error.
    """
    p, raw = _read_bytes(path)
    if not (raw.startswith(b"ply\n") or raw.startswith(b"ply\r\n")):
        raise ScanFormatError(f"{p}: not a PLY file (does not start with 'ply')")
    lines, offset = _header_lines(raw, p, "PLY", lambda t: t.strip() == "end_header")
    fmt = None
    elements: list[list] = []  # [name, count, [(prop, dtype-code)], lineno]
    for lineno, text in lines[1:-1]:
        tok = text.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            if len(tok) != 3 or tok[1] not in (
                "ascii",
                "binary_little_endian",
                "binary_big_endian",
            ):
                raise ScanFormatError(f"{p}: header line {lineno}: unsupported format {text!r}")
            fmt = tok[1]
        elif tok[0] == "element":
            try:
                elements.append([tok[1], int(tok[2]), [], lineno])
            except (IndexError, ValueError):
                raise ScanFormatError(
                    f"{p}: header line {lineno}: bad element line {text!r}"
                ) from None
        elif tok[0] == "property":
            if not elements:
                raise ScanFormatError(f"{p}: header line {lineno}: property before any element")
            if len(tok) >= 2 and tok[1] == "list":
                elements[-1][2].append((tok[-1] if len(tok) == 5 else "?", "list"))
                continue
            if len(tok) != 3 or tok[1] not in _PLY_TYPES:
                raise ScanFormatError(f"{p}: header line {lineno}: bad property line {text!r}")
            elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]]))
        else:
            raise ScanFormatError(
                f"{p}: not a valid PLY file: header line {lineno} starts with unknown keyword "
                f"{tok[0][:40]!r}"
            )
    if fmt is None:
        raise ScanFormatError(f"{p}: PLY header has no format line")
    if not elements or elements[0][0] != "vertex":
        names = [e[0] for e in elements]
        if "vertex" not in names:
            raise ScanFormatError(f"{p}: PLY file has no vertex element")
        raise ScanFormatError(
            f"{p}: PLY vertex element must come first (elements are {' '.join(names)})"
        )
    _, n, props, _ = elements[0]
    names = [nm for nm, _ in props]
    if any(code == "list" for _, code in props):
        raise ScanFormatError(f"{p}: PLY vertex element has a list property (not supported)")
    if n < 0:
        raise ScanFormatError(f"{p}: PLY vertex count is negative ({n})")
    first = {}
    for k, nm in enumerate(names):
        first.setdefault(nm, k)
    body = raw[offset:]

    if fmt == "ascii":
        try:
            text = body.decode("ascii")
        except UnicodeDecodeError:
            raise ScanFormatError(f"{p}: ascii PLY data contains non-ASCII bytes") from None
        table = _parse_ascii_table(
            text, n, len(props), p, first_line=len(lines) + 1, allow_extra=len(elements) > 1
        )

        def get(name: str) -> np.ndarray:
            return table[:, first[name]]

    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        dt = np.dtype([(f"f{k}", order + code) for k, (_, code) in enumerate(props)])
        need = n * dt.itemsize
        if len(body) < need:
            raise ScanFormatError(
                f"{p}: truncated PLY: header says {n} vertices x {dt.itemsize} bytes = {need} "
                f"bytes, but only {len(body)} bytes follow the header"
            )
        if len(elements) == 1 and len(body) - need >= dt.itemsize:
            raise ScanFormatError(
                f"{p}: PLY header says {n} vertices but {len(body)} bytes of data follow "
                f"({len(body) // dt.itemsize} vertices of {dt.itemsize} bytes)"
            )
        rec = np.frombuffer(body, dtype=dt, count=n)

        def get(name: str) -> np.ndarray:
            return rec[f"f{first[name]}"]

    return _scan_from_columns(get, names, p, n)


def write_ply(path: PathLike, scan: Scan | np.ndarray, binary: bool = True) -> Path:
    """Write a PLY vertex cloud with float ``x y z`` (and ``intensity`` if present)."""
    s = _as_scan(scan)
    p = Path(path)
    has_i = s.intensity is not None
    props = ["x", "y", "z"] + (["intensity"] if has_i else [])
    header = (
        "ply\n"
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0\n"
        f"element vertex {len(s)}\n"
        + "".join(f"property float {nm}\n" for nm in props)
        + "end_header\n"
    )
    data = s.xyzi()[:, : len(props)]
    if binary:
        body = data.astype("<f4").tobytes()
    else:
        body = "".join(" ".join(f"{v:.9g}" for v in row) + "\n" for row in data.tolist()).encode()
    p.write_bytes(header.encode("ascii") + body)
    return p


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
    except (ValueError, OSError, EOFError) as e:
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
    except (InputError, ValueError, OSError, EOFError) as e:  # bad shape, corrupt member
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


# --------------------------------------------------------------------------------------
# Poses and KITTI sequences


def _data_lines(path: Path) -> list[tuple[int, str]]:
    """Non-blank lines of a text file as ``(line_number, text)``."""
    try:
        text = path.read_text(encoding="ascii")
    except UnicodeDecodeError:
        raise ScanFormatError(f"{path}: not an ASCII text file") from None
    except OSError as e:
        raise ScanFormatError(f"{path}: cannot read file: {e}") from None
    return [(k, ln) for k, ln in enumerate(text.splitlines(), start=1) if ln.strip()]


def read_poses(path: PathLike, rotation_tol: float = 1e-2) -> np.ndarray:
    """Read a KITTI ``poses.txt``: per line the row-major top 3x4 (or full 4x4) of a pose.

    Returns ``[F, 4, 4]`` float64. A line with the wrong number of values, a non-number,
    non-finite values or a rotation block that is not a rotation (``|R^T R - I| >
    rotation_tol`` or ``det R < 0``) raises :class:`ScanFormatError` naming the file and
    line. Blank lines are skipped.
    """
    p = Path(path)
    if not p.exists():
        raise ScanFormatError(f"{p}: poses file not found")
    out = []
    for lineno, ln in _data_lines(p):
        tok = ln.split()
        if len(tok) not in (12, 16):
            raise ScanFormatError(
                f"{p}: line {lineno} has {len(tok)} values, expected 12 (row-major 3x4 pose)"
            )
        try:
            v = np.array([float(t) for t in tok], dtype=np.float64)
        except ValueError:
            raise ScanFormatError(f"{p}: line {lineno}: values are not all numbers") from None
        if not np.isfinite(v).all():
            raise ScanFormatError(f"{p}: line {lineno}: non-finite value in pose")
        T = np.eye(4)
        T[: len(tok) // 4] = v.reshape(-1, 4)
        if len(tok) == 16 and not np.allclose(T[3], [0, 0, 0, 1]):
            raise ScanFormatError(f"{p}: line {lineno}: last row of a 4x4 pose must be 0 0 0 1")
        R = T[:3, :3]
        err = np.abs(R.T @ R - np.eye(3)).max()
        if err > rotation_tol or np.linalg.det(R) <= 0:
            raise ScanFormatError(
                f"{p}: line {lineno}: rotation block is not a rotation "
                f"(|R^T R - I| = {err:.3g}, det = {np.linalg.det(R):.3g})"
            )
        out.append(T)
    return np.stack(out) if out else np.zeros((0, 4, 4))  # [F, 4, 4]


def read_times(path: PathLike) -> np.ndarray:
    """Read a KITTI ``times.txt`` (one time in seconds per line) -> ``[F]`` float64.

    Times must be finite and non-decreasing; a bad line raises :class:`ScanFormatError`
    naming the file and line.
    """
    p = Path(path)
    if not p.exists():
        raise ScanFormatError(f"{p}: times file not found")
    out: list[float] = []
    for lineno, ln in _data_lines(p):
        tok = ln.split()
        try:
            if len(tok) != 1:
                raise ValueError
            t = float(tok[0])
        except ValueError:
            raise ScanFormatError(
                f"{p}: line {lineno}: expected one number (seconds), got {ln.strip()[:60]!r}"
            ) from None
        if not np.isfinite(t):
            raise ScanFormatError(f"{p}: line {lineno}: time is not finite")
        if out and t < out[-1]:
            raise ScanFormatError(
                f"{p}: line {lineno}: time {t} is earlier than the previous line's {out[-1]}"
            )
        out.append(t)
    return np.asarray(out, dtype=np.float64)  # [F]


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``[..., 4, 4]`` (uses ``R^T``, exact for rotations)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4):
        raise InputError(f"pose must have shape [..., 4, 4], got {list(T.shape)}")
    R = T[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def relative_pose(T_world_i: np.ndarray, T_world_j: np.ndarray) -> np.ndarray:
    """``T_j_i = inv(T_world_j) @ T_world_i``: maps points of scan ``i`` into scan ``j``'s frame.

    Accepts ``[4, 4]`` or broadcastable ``[..., 4, 4]`` float arrays.
    """
    Ti = np.asarray(T_world_i, dtype=np.float64)
    if Ti.shape[-2:] != (4, 4):
        raise InputError(f"T_world_i must have shape [..., 4, 4], got {list(Ti.shape)}")
    return invert_pose(T_world_j) @ Ti


@dataclass(frozen=True, eq=False)
class Frame:
    """One scan of a :class:`KittiSequence`.

    ``time`` (seconds) and ``T_world_sensor`` (4x4 float64) are ``None`` when the
    sequence has no ``times.txt`` / ``poses.txt``. The points are read by :meth:`scan`.
    """

    index: int
    time: float | None
    T_world_sensor: np.ndarray | None
    path: Path

    def scan(self) -> Scan:
        """Read this frame's scan from disk."""
        return read_scan(self.path)


class KittiSequence:
    """A KITTI-odometry-layout folder of scans with optional poses and times.

    Scans are the files of ``root/velodyne/`` (or ``root/scans/``) with one extension
    among ``.bin .pcd .ply .npy .npz``, sorted by name. ``poses.txt`` (12 numbers per
    line, row-major top 3x4 of ``T_world_sensor``) and ``times.txt`` are optional; if
    present they must have one line per scan. Poses are used as given: no camera-to-LiDAR
    calibration is applied.

    Attributes: ``root``, ``paths`` (list of scan files), ``poses`` (``[F, 4, 4]`` float64
    or None), ``times`` (``[F]`` float64 or None).
    """

    def __init__(self, root: PathLike) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise ScanFormatError(f"{self.root}: sequence folder not found")
        self.paths = self._find_scans()
        n = len(self.paths)
        self.poses: np.ndarray | None = None  # [F, 4, 4]
        self.times: np.ndarray | None = None  # [F]
        poses_path, times_path = self.root / "poses.txt", self.root / "times.txt"
        if poses_path.exists():
            self.poses = read_poses(poses_path)
            if len(self.poses) != n:
                raise ScanFormatError(
                    f"{poses_path}: has {len(self.poses)} poses but {self.scan_dir} has {n} scans"
                )
        if times_path.exists():
            self.times = read_times(times_path)
            if len(self.times) != n:
                raise ScanFormatError(
                    f"{times_path}: has {len(self.times)} times but {self.scan_dir} has {n} scans"
                )
        log.debug(
            "sequence %s: %d scans, poses=%s, times=%s",
            self.root,
            n,
            self.poses is not None,
            self.times is not None,
        )

    def _find_scans(self) -> list[Path]:
        for sub in ("velodyne", "scans"):
            d = self.root / sub
            if not d.is_dir():
                continue
            files = sorted(f for f in d.iterdir() if f.suffix.lower() in SCAN_EXTENSIONS)
            if not files:
                raise ScanFormatError(
                    f"{d}: no scan files ({', '.join(SCAN_EXTENSIONS)}) in the folder"
                )
            exts = sorted({f.suffix.lower() for f in files})
            if len(exts) > 1:
                raise ScanFormatError(f"{d}: mixed scan file types {' '.join(exts)}; use one")
            self.scan_dir = d
            return files
        raise ScanFormatError(f"{self.root}: no velodyne/ or scans/ folder with scan files")

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, i: int) -> Frame:
        i = operator.index(i)
        n = len(self.paths)
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for a sequence of {n} scans")
        i = i % n
        return Frame(
            index=i,
            time=None if self.times is None else float(self.times[i]),
            T_world_sensor=None if self.poses is None else self.poses[i].copy(),
            path=self.paths[i],
        )

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def __repr__(self) -> str:
        return f"KittiSequence({str(self.root)!r}, {len(self)} scans)"
