"""Reading scans from files on the client side (numpy only: no torch, no Open3D).

:func:`read_scan` returns ``[P, 4]`` float32 ``x y z intensity`` (intensity 0 where the
file has none), ready for :meth:`Client.localize` or :class:`KeyframeIn`. Formats, chosen
by extension: KITTI ``.bin``, ``.npy`` / ``.npz``, ``.pcd`` (ascii, binary,
binary_compressed) and ``.ply`` (ascii and binary). The parsers are the engine's own
(:mod:`sgvloc.core.io`, part of the base install and free of heavy imports): ``.bin``,
``.npy`` and ``.npz`` need numpy alone, ``.pcd`` the ``pypcd4`` package and ``.ply``
``plyfile`` (both in the service extra, or ``pip install`` them beside the SDK). Their
errors, a missing package's included, are :class:`ScanFileError` naming the file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ._errors import ScanFileError

__all__ = ["SCAN_EXTENSIONS", "read_kitti_bin", "read_scan"]

SCAN_EXTENSIONS = (".bin", ".pcd", ".ply", ".npy", ".npz")


def read_kitti_bin(path: str | os.PathLike) -> np.ndarray:
    """Read a KITTI velodyne ``.bin`` (float32 ``x y z intensity``) -> ``[P, 4]`` float32."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ScanFileError(f"{p}: cannot read scan file: {exc.strerror or exc}") from None
    if len(raw) % 16:
        raise ScanFileError(
            f"{p}: KITTI .bin size {len(raw)} bytes is not a multiple of 16 "
            "(4 float32 x y z intensity per point)"
        )
    return np.frombuffer(raw, dtype="<f4").reshape(-1, 4).astype(np.float32)  # [P, 4]


def read_scan(path: str | os.PathLike) -> np.ndarray:
    """Read a scan file of any supported format -> ``[P, 4]`` float32 ``x y z intensity``."""
    p = Path(path)
    if p.suffix.lower() == ".bin":
        return read_kitti_bin(p)
    if p.suffix.lower() not in SCAN_EXTENSIONS:
        raise ScanFileError(
            f"{p}: unknown scan file extension {p.suffix!r} "
            f"(expected one of {', '.join(SCAN_EXTENSIONS)})"
        )
    # Lazy: sgvloc.core.io imports numpy only, but keep the client's import light.
    from sgvloc.core import io
    from sgvloc.core.errors import InputError

    try:
        return io.read_scan(p).xyzi()  # [P, 4]
    except InputError as exc:
        raise ScanFileError(str(exc)) from None
    except ModuleNotFoundError as exc:  # the client-only install
        package = {".pcd": "pypcd4", ".ply": "plyfile"}.get(p.suffix.lower(), exc.name)
        raise ScanFileError(
            f"{p}: reading {p.suffix} files needs the {package} package (pip install "
            f"{package}, or the service extra)"
        ) from None
