"""The sequences an evaluation runs on: 3-D scans or kitti-bev images.

Two folder layouts:

- ``scans`` (KITTI odometry): ``velodyne/`` (or ``scans/``) scan files, ``poses.txt`` and
  ``times.txt`` (:class:`sgvloc.core.sequence.KittiSequence`);
- ``bev-images`` (kitti-bev, docs/EVALUATION.md, "Data"): ``imgs/NNNNNN.png`` (151 x 151 grey
  BEV density images) and ``pose.txt`` (row-major top 3x4 of ``T_world_lidar``). Scans
  were taken at 10 Hz, so scan ``i`` is at ``i * 0.1`` s unless a ``times.txt`` is there.
  Only encoders with an ``encode_image(image)`` method can describe these; there is no
  3-D cloud, so no ICP refinement.

A folder with scan files is read as ``scans`` even if it also holds ``imgs/``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from sgvloc.core.errors import InputError, ScanFormatError

#: kitti-bev scan rate (Hz): time of scan i = i / rate
BEV_RATE_HZ = 10.0


@dataclass(frozen=True)
class EvalSequence:
    """Files, ground-truth poses ``[F, 4, 4]`` (``T_world_sensor``) and times ``[F]`` (s)."""

    root: Path
    kind: Literal["scans", "bev-images"]
    paths: list[Path]
    poses: np.ndarray
    times: np.ndarray
    times_source: str

    def frames(self, start: int, stop: int | None) -> EvalSequence:
        """The sub-sequence of frames ``[start, stop)`` (``stop`` None: to the end)."""
        n = len(self.paths)
        stop = n if stop is None else stop
        if not 0 <= start < min(stop, n):
            raise InputError(f"{self.root}: frames {start}:{stop} select nothing of its {n}")
        sel = slice(start, stop)
        return EvalSequence(
            self.root, self.kind, self.paths[sel], self.poses[sel], self.times[sel],
            self.times_source,
        )  # fmt: skip


def open_sequence(root: str | Path) -> EvalSequence:
    """Open an evaluation sequence of either layout (see the module docstring).

    Raises :class:`InputError` if the folder is neither layout or lacks poses or times.
    """
    from sgvloc.core.sequence import KittiSequence, read_poses, read_times

    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: sequence folder not found")
    has_scans = any((root / sub).is_dir() for sub in ("velodyne", "scans"))
    imgs = root / "imgs"
    if not has_scans and imgs.is_dir():
        files = sorted(imgs.glob("*.png"))
        if not files:
            raise InputError(f"{imgs}: no .png images")
        pose_file = root / "pose.txt"
        if not pose_file.exists() and (root / "poses.txt").exists():
            pose_file = root / "poses.txt"
        try:
            poses = read_poses(pose_file)
        except ScanFormatError as exc:
            raise InputError(f"{root}: kitti-bev folder needs pose.txt: {exc}") from None
        if len(poses) != len(files):
            raise InputError(f"{root}: {len(files)} images in imgs/ but {len(poses)} poses")
        if (root / "times.txt").exists():
            times, source = read_times(root / "times.txt"), "times.txt"
            if len(times) != len(files):
                raise InputError(f"{root}: {len(files)} images but {len(times)} times")
        else:
            times = np.arange(len(files), dtype=np.float64) / BEV_RATE_HZ
            source = f"index / {BEV_RATE_HZ:g} Hz"
        return EvalSequence(root, "bev-images", files, poses, times, source)
    try:
        seq = KittiSequence(root)
    except ScanFormatError as exc:
        raise InputError(
            f"{exc} (an evaluation folder holds velodyne/ + poses.txt + times.txt, "
            "or kitti-bev imgs/ + pose.txt)"
        ) from None
    if seq.poses is None or seq.times is None:
        raise InputError(f"{root}: evaluation needs poses.txt and times.txt")
    return EvalSequence(root, "scans", list(seq.paths), seq.poses, seq.times, "times.txt")
