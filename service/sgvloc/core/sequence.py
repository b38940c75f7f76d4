"""KITTI-layout sequences: a folder of scans with poses and times.

:class:`KittiSequence` walks a KITTI-odometry folder (``velodyne/*.bin``, ``poses.txt``
with the row-major top 3x4 of ``T_world_sensor`` per line, ``times.txt``); the readers of
those text files and two pose helpers live here too.
"""

from __future__ import annotations

import logging
import operator
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError, ScanFormatError
from .io import SCAN_EXTENSIONS, PathLike, Scan, read_scan

log = logging.getLogger(__name__)


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
