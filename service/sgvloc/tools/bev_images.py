"""``sgvloc bev-images``: a KITTI-layout scan sequence as a kitti-bev image sequence.

Each scan becomes ``imgs/NNNNNN.png``, its bird's-eye-view density image made by the
project's rasteriser (:func:`sgvloc.core.bev.rasterize`, which reproduces the kitti-bev
images), with ``pose.txt`` (row-major top 3x4 of ``T_world_sensor``) and ``times.txt``
beside it. Image encoders and ``sgvloc eval``/``calibrate`` then read it like the
kitti-bev sequences, e.g. to evaluate or calibrate the 2-D (``planar``) path on a
synthetic town.
"""

from __future__ import annotations

from pathlib import Path

from sgvloc.core.errors import InputError, SgvlocError

from .staging import staged


def export_bev_images(
    src: Path, out: Path, *, overwrite: bool = False, progress: bool = False
) -> int:
    """Write the image sequence of ``src`` to ``out``; returns the number of images."""
    import cv2
    import numpy as np
    from tqdm import tqdm

    from sgvloc.core.bev import rasterize
    from sgvloc.core.sequence import KittiSequence

    seq = KittiSequence(src)
    if seq.poses is None or seq.times is None:
        raise InputError(f"{src}: needs poses.txt and times.txt")
    imgs = Path(out) / "imgs"
    if imgs.exists() and any(imgs.iterdir()) and not overwrite:
        raise InputError(f"{out}: already holds images (imgs/); replace them with --overwrite")
    # written aside: a run that fails or is interrupted leaves the previous images whole
    with staged(Path(out), ("imgs", "pose.txt", "times.txt")) as stage:
        (stage / "imgs").mkdir()
        scans = tqdm(seq, desc="bev-images", unit="scan", disable=not progress)
        for i, frame in enumerate(scans):
            try:
                image = rasterize(frame.scan().points).image
            except SgvlocError as exc:
                raise InputError(f"{frame.path}: {exc}") from None
            if not cv2.imwrite(str(stage / "imgs" / f"{i:06d}.png"), image):
                raise InputError(f"{out}: cannot write image {i}")
        rows = np.asarray(seq.poses)[:, :3, :].reshape(len(seq), 12)
        np.savetxt(stage / "pose.txt", rows, fmt="%.9g")
        np.savetxt(stage / "times.txt", np.asarray(seq.times), fmt="%.6f")
    return len(seq)
