"""Bird's-eye-view (BEV) density raster of a scan, the same as the kitti-bev images.

The kitti-bev data set (BEVPlace's KITTI images, docs/EVALUATION.md, "Data")
stores one 151 x 151 grey image per scan. :func:`rasterize` makes that image from a 3-D
scan so that an encoder (or a model trained on those images) runs on raw scans:

1. keep points with ``|x|, |y|, |z| < 25`` m (sensor frame);
2. voxel-downsample at 0.4 m (one point per occupied voxel; :func:`voxel_downsample`,
   voxels aligned to the origin, so each voxel falls in exactly one BEV column);
3. count the voxels of each 0.4 m x 0.4 m column: ``n``;
4. density level ``k = clip(n - 1, 0, 10)`` (so columns with ``n <= 1``, mostly bare
   ground, are 0), grey value ``10 k`` (never above 255), normalised so the image maximum
   is 255, rounded half to even.

Pixel ``(r, c)`` is the column centred at ``x = (75 - r + 0.5) * 0.4``,
``y = (75 - c + 0.5) * 0.4`` (x forward = up, y left = left): ``r = 75 - floor(x / 0.4)``,
``c = 75 - floor(y / 0.4)``.

Grey levels: the data set's README states "counts capped at 10; counts <= 1 set to 0; x10". Read
literally that gives the levels ``{0, 51, 76, ..., 255}`` (9 non-zero levels, counts 2..10).
The released images have 10 non-zero levels ``k * 25.5`` (k = 1..10: 26, 51, ..., 255) and
no bare ground (level 1 lies on object edges), which is what step 4 produces: a column of
two voxels is level 1, one of eleven or more is level 10. Their levels are also rounded
half to even (76.5 -> 76, 127.5 -> 128), as OpenCV does when writing a float image.

Differences that cannot be removed: BEVPlace voxelised with Open3D, whose voxel grid starts
at the cropped cloud's minimum corner instead of the origin, so a column can count one voxel
more or less than here; and the released images come from KITTI's HDL-64 scans, which are
not in the project.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .errors import EmptyScanError, InputError
from .preprocess import (
    all_columns,
    as_points,
    even_subsample,
    finite,
    in_azimuth_window,
    plane_hypotheses,
    voxel_downsample,
)


class BEVRasterConfig(BaseModel):
    """Geometry and density scale of the BEV raster (defaults = the kitti-bev images)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    resolution: float = Field(0.4, ge=0.01, le=10.0, description="cell and voxel size (m)")
    extent: float = Field(25.0, gt=0.0, le=1000.0, description="keep |x|, |y|, |z| below this (m)")
    half_cells: int = Field(
        75, ge=1, le=1024, description="pixels from the centre to the border: image side 2 h + 1"
    )
    max_level: int = Field(
        10, ge=1, le=255, description="density level cap (voxels per column - 1)"
    )

    @property
    def size(self) -> int:
        """Image side in pixels."""
        return 2 * self.half_cells + 1


#: the kitti-bev raster
KITTI_BEV = BEVRasterConfig()


@dataclass(frozen=True)
class BEVRaster:
    """One scan as a BEV raster (all ``[S, S]``, ``S = config.size``).

    - ``image``: uint8 grey density image (the kitti-bev image);
    - ``counts``: int32 occupied voxels per column;
    - ``height``: float32 mean height (z, m) of the column's voxels, NaN where empty;
    - ``low``: float32 height of the column's lowest voxel, NaN where empty.
    """

    image: np.ndarray
    counts: np.ndarray
    height: np.ndarray
    low: np.ndarray
    config: BEVRasterConfig


def crop_box(points: np.ndarray, extent: float) -> np.ndarray:
    """Keep points with ``|x|``, ``|y|`` and ``|z|`` all strictly below ``extent``."""
    return points[all_columns(lambda c: np.abs(c) < extent, points)]


def prepare_points(points: np.ndarray, config: BEVRasterConfig = KITTI_BEV) -> np.ndarray:
    """Raw scan ``[P, 3+]`` -> the voxel cloud the raster counts ``[M, 3]`` float32.

    Finite points only, box crop to ``extent``, voxel centroids at ``resolution``.
    Raises :class:`InputError` on a malformed scan or if no point is left.
    """
    pts = as_points(points)
    if len(pts) == 0:
        raise InputError("scan is empty: no points to rasterise")
    pts = crop_box(finite(pts), config.extent)
    pts = voxel_downsample(pts, config.resolution)
    if len(pts) == 0:
        raise EmptyScanError(
            f"scan has no finite point with |x|, |y|, |z| < {config.extent} m; nothing to rasterise"
        )
    return pts


def ground_rotation(
    cloud: np.ndarray,
    radius: float = 15.0,
    threshold: float = 0.15,
    max_tilt_deg: float = 45.0,
    hypotheses: int = 256,
    min_inliers: int = 100,
    min_spread: float = 1.0,
) -> tuple[np.ndarray, float]:
    """Rotation ``R`` ``[3, 3]`` float64 that levels a scan's ground, and the tilt (degrees).

    A plane is fitted to the points ``[M, 3+]`` within ``radius`` (x/y) of the sensor:
    seeded RANSAC over ``hypotheses`` point triples (deterministic), keeping planes whose
    normal is within ``max_tilt_deg`` of the sensor's z axis and which pass below the
    sensor, with inliers within ``threshold`` m, then a least-squares refit on the inliers.
    ``R`` turns that normal onto +z by the smallest rotation (no yaw), so ``cloud @ R.T``
    is level. Identity and 0 when fewer than ``min_inliers`` points fit a plane or the
    inliers spread less than ``min_spread`` m (std) across their main direction.
    """
    pts = np.asarray(cloud, dtype=np.float64)[:, :3]
    pts = pts[np.einsum("ij,ij->i", pts[:, :2], pts[:, :2]) < radius * radius]
    if len(pts) < max(3, min_inliers):
        return np.eye(3), 0.0
    pts = even_subsample(pts, 4000)  # keeps the fit cheap and deterministic
    n, d = plane_hypotheses(pts, hypotheses)  # d > 0: the plane passes below the sensor
    keep = (n[:, 2] >= np.cos(np.radians(max_tilt_deg))) & (d > threshold)
    if not keep.any():
        return np.eye(3), 0.0
    n, d = n[keep], d[keep]
    inl = np.abs(pts @ n.T + d) <= threshold  # [M, H']
    best = int(inl.sum(axis=0).argmax())
    mask = inl[:, best]
    if mask.sum() < min_inliers:
        return np.eye(3), 0.0
    sel = pts[mask]
    centre = sel.mean(axis=0)
    _, sv, vt = np.linalg.svd(sel - centre, full_matrices=False)
    normal = vt[2] * (1.0 if vt[2, 2] >= 0 else -1.0)
    # a ground patch spreads both ways; a strip (a tilted plane cutting a wall) does not
    spread = sv[1] / np.sqrt(len(sel))  # inliers' std along their second axis (m)
    if normal[2] < np.cos(np.radians(max_tilt_deg)) or spread < min_spread:
        return np.eye(3), 0.0
    return _rotation_onto_z(normal), float(np.degrees(np.arccos(min(normal[2], 1.0))))


def _rotation_onto_z(n: np.ndarray) -> np.ndarray:
    """Smallest rotation ``[3, 3]`` taking the unit vector ``n`` (``n_z > 0``) onto +z."""
    v = np.array([n[1], -n[0], 0.0])  # n x z
    s, c = np.linalg.norm(v), n[2]
    if s < 1e-12:
        return np.eye(3)
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + k @ k * ((1.0 - c) / (s * s))


def metres_to_pixel(
    xy: np.ndarray, config: BEVRasterConfig = KITTI_BEV
) -> tuple[np.ndarray, np.ndarray]:
    """Continuous pixel coordinates ``(rows, cols)`` of points ``[N, 2+]`` (x, y in metres).

    Pixel centres are at integers: the inverse of :func:`pixel_to_metres`. The pixel that
    contains a point is ``floor(row + 0.5), floor(col + 0.5)``.
    """
    xy = np.asarray(xy, dtype=np.float64)
    h, res = config.half_cells, config.resolution
    return h + 0.5 - xy[:, 0] / res, h + 0.5 - xy[:, 1] / res


def pixel_to_metres(
    rows: np.ndarray, cols: np.ndarray, config: BEVRasterConfig = KITTI_BEV
) -> np.ndarray:
    """Metric ``(x, y)`` ``[N, 2]`` float64 of pixel coordinates (sub-pixel allowed).

    ``x = (h - r + 0.5) * res``, ``y = (h - c + 0.5) * res`` with ``h = half_cells``
    (75 for kitti-bev): an integer ``(r, c)`` maps to its cell centre.
    """
    h, res = config.half_cells, config.resolution
    r = np.asarray(rows, dtype=np.float64)
    c = np.asarray(cols, dtype=np.float64)
    return np.stack([(h - r + 0.5) * res, (h - c + 0.5) * res], axis=-1)


def column_indices(
    points: np.ndarray, config: BEVRasterConfig = KITTI_BEV
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integer pixel ``(rows, cols)`` of points ``[M, 2+]`` and a mask of those inside."""
    h, res = config.half_cells, config.resolution
    rows = h - np.floor(points[:, 0] / res).astype(np.int64)
    cols = h - np.floor(points[:, 1] / res).astype(np.int64)
    inside = (rows >= 0) & (rows < config.size) & (cols >= 0) & (cols < config.size)
    return rows, cols, inside


def density_image(counts: np.ndarray, max_level: int = 10) -> np.ndarray:
    """Grey image ``[S, S]`` uint8 from voxel counts per column (step 4 of the module doc).

    An image with no column of two voxels or more is all zeros.
    """
    level = np.clip(counts.astype(np.int64) - 1, 0, max_level)
    value = np.minimum(level * 10, 255).astype(np.float64)
    top = value.max()
    if top <= 0:
        return np.zeros(counts.shape, dtype=np.uint8)
    return np.rint(value / top * 255.0).astype(np.uint8)


def rasterize_cloud(cloud: np.ndarray, config: BEVRasterConfig = KITTI_BEV) -> BEVRaster:
    """BEV raster of a cloud already made by :func:`prepare_points` ``[M, 3]``."""
    size = config.size
    rows, cols, inside = column_indices(cloud, config)
    flat = rows[inside] * size + cols[inside]  # [m]
    counts = np.bincount(flat, minlength=size * size)
    zsum = np.bincount(flat, weights=cloud[inside, 2], minlength=size * size)
    with np.errstate(invalid="ignore", divide="ignore"):
        height = np.where(counts > 0, zsum / np.maximum(counts, 1), np.nan)
    low = np.full(size * size, np.inf)
    np.minimum.at(low, flat, cloud[inside, 2])
    low[np.isinf(low)] = np.nan
    counts = counts.reshape(size, size).astype(np.int32)
    return BEVRaster(
        image=density_image(counts, config.max_level),
        counts=counts,
        height=height.reshape(size, size).astype(np.float32),
        low=low.reshape(size, size).astype(np.float32),
        config=config,
    )


def rasterize(points: np.ndarray, config: BEVRasterConfig = KITTI_BEV) -> BEVRaster:
    """BEV raster of a raw scan ``[P, 3+]`` (x y z, extra columns ignored).

    Raises :class:`InputError` on a malformed scan or one with no point in the box.
    """
    return rasterize_cloud(prepare_points(points, config), config)


def level_cloud(
    cloud: np.ndarray, config: BEVRasterConfig = KITTI_BEV
) -> tuple[np.ndarray, np.ndarray]:
    """A cloud made by :func:`prepare_points` turned level on its ground plane
    (:func:`ground_rotation`) and voxelised again at ``config.resolution``: ``[M', 3]``
    float32 and the rotation ``R`` ``[3, 3]`` (levelled = sensor @ R.T)."""
    R, _ = ground_rotation(cloud)
    turned = (np.asarray(cloud, dtype=np.float64)[:, :3] @ R.T).astype(np.float32)
    return voxel_downsample(turned, config.resolution), R


def crop_image_azimuth(
    image: np.ndarray, fov_deg: float, config: BEVRasterConfig = KITTI_BEV
) -> np.ndarray:
    """A BEV image with the pixels outside a horizontal field of view centred on the
    sensor's forward axis set to 0: a pixel is kept when its centre
    (:func:`pixel_to_metres`) is in the window
    (:func:`sgvloc.core.preprocess.in_azimuth_window`, which
    :func:`sgvloc.core.preprocess.crop_azimuth` applies to points)."""
    img = np.asarray(image)
    if fov_deg >= 360.0:
        return img
    rows, cols = np.indices(img.shape[:2])
    xy = pixel_to_metres(rows.ravel(), cols.ravel(), config)
    keep = in_azimuth_window(xy[:, 0], xy[:, 1], fov_deg).reshape(img.shape[:2])
    return np.where(keep, img, 0).astype(img.dtype)


def load_bev_image(path: str | Path, config: BEVRasterConfig = KITTI_BEV) -> np.ndarray:
    """Read one kitti-bev PNG as ``[S, S]`` uint8.

    Raises :class:`InputError` if the file is missing, unreadable, or not ``S x S`` grey.
    """
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError(f"BEV image {path} does not exist")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"BEV image {path} could not be decoded")
    if img.ndim == 3:
        raise InputError(f"BEV image {path} has {img.shape[2]} channels; expected grey")
    if img.shape != (config.size, config.size) or img.dtype != np.uint8:
        raise InputError(
            f"BEV image {path} is {list(img.shape)} {img.dtype}; expected "
            f"[{config.size}, {config.size}] uint8"
        )
    return img


class BEVEncoderConfig(BaseModel):
    """Settings of the handcrafted BEV encoder (:mod:`sgvloc.core.encoders.bev`)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    raster: BEVRasterConfig = KITTI_BEV
    detector: Literal["orb", "sift"] = Field(
        "orb", description="OpenCV keypoints + descriptors on the density image"
    )
    num_keypoints: int = Field(256, ge=1, le=5000, description="keypoints at most per scan")
    sift_contrast_threshold: float = Field(
        0.04, gt=0.0, le=1.0, description="SIFT: weakest blob kept (OpenCV contrastThreshold)"
    )
    root_sift: bool = Field(True, description="SIFT: Hellinger (RootSIFT) descriptors")
    orb_fast_threshold: int = Field(10, ge=1, le=255, description="ORB: FAST corner threshold")
    blur_sigma: float = Field(
        1.0,
        ge=0.0,
        le=20.0,
        description="Gaussian blur of the image before detection (pixels); 0 = off",
    )
    keypoint_z: Literal["zero", "column_mean"] = Field(
        "zero",
        description="keypoint height: 0, or the mean voxel height of its column (scans only)",
    )
    rings: int = Field(20, ge=2, le=256, description="global descriptor: radial bins")
    sectors: int = Field(60, ge=4, le=720, description="global descriptor: angular bins")


class LearnedEncoderConfig(BaseModel):
    """Settings of the learned BEV encoder (:mod:`sgvloc.core.encoders.learned`).

    The raster is fixed to the kitti-bev one the network was trained on.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    num_keypoints: int = Field(
        256, ge=1, le=5776, description="keypoints at most per scan (most salient cells)"
    )
    nms_radius: int = Field(
        0,
        ge=0,
        le=4,
        description="keypoints: a cell is kept only if it is the most salient within this "
        "many cells (0: the most salient occupied cells, no suppression)",
    )
    keypoint_xy: Literal["centre", "centroid"] = Field(
        "centroid",
        description="keypoint position in its 0.8 m cell: the cell centre, or the "
        "grey-weighted centroid of its 2 x 2 pixels",
    )
    keypoint_z: Literal["zero", "column_mean", "column_min"] = Field(
        "column_min",
        description="keypoint height (scans; 0 for BEV images, which have no height): the "
        "height of the lowest voxel in its cell (column_min, the steadiest between "
        "viewpoints), the mean height of its cell's voxels (column_mean), or 0",
    )
    level: bool = Field(
        True,
        description="scans: rotate the voxel cloud so its fitted ground plane is level "
        "before rasterising (the network was trained on level car-mounted scans; a hand-held "
        "or tilted sensor otherwise changes the image), keypoints returned in the sensor frame",
    )
    global_descriptor: Literal["network", "polar", "polar+network"] = Field(
        "polar+network",
        description="global descriptor: the network's (GeM, 256-D), the polar/FFT "
        "descriptor of the same density image (620-D, as the 'bev' encoder's), or both "
        "(876-D, each block normalised; retrieval merges their candidates, see "
        "RetrievalConfig.combine; the default, chosen by SGV R@1 on held-out data, "
        "docs/RESULTS.md)",
    )
    local_features: Literal["network", "fpfh"] = Field(
        "network",
        description="scans: keypoints and local features from the network (its most "
        "salient 0.8 m cells), or FPFH at the curvature keypoints of the 0.3 m voxel cloud "
        "as the handcrafted encoder makes them, the global descriptor staying the "
        "network's: for narrow-field-of-view or sparse sensors, whose scans leave the "
        "network few cells to take keypoints from (docs/RESULTS.md, 'Narrow field of "
        "view'; `sgvloc build-map --choose-encoder` compares both); BEV images need "
        "'network'",
    )
    global_rotations: Literal[1, 4] = Field(
        1,
        description="network global descriptor: the image as it is (1), or the mean over "
        "the image turned by 0/90/180/270 degrees about the sensor (4: less dependent on "
        "the heading, three more network passes, about 35 ms per scan on one core)",
    )
