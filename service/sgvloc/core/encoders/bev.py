"""Handcrafted bird's-eye-view encoder: OpenCV features on the BEV density image.

Needs no weights. Per scan (deterministic):

1. prepare: finite points, box crop and 0.4 m voxels (:func:`sgvloc.core.bev.prepare_points`);
   the voxel cloud is also what the localizer keeps for ICP;
2. raster: the kitti-bev density image of the cloud (:func:`sgvloc.core.bev.rasterize_cloud`);
3. global descriptor: the image's occupied pixels, weighted by their grey level, softly
   binned on a polar grid around the sensor (rings x sectors out to ``extent``), then the
   yaw-invariant DFT magnitudes per ring plus the ring key
   (:func:`~sgvloc.core.encoders.handcrafted.yaw_invariant_descriptor`);
4. keypoints: SIFT (or ORB) on the image, strongest first, lifted to metres with
   :func:`sgvloc.core.bev.pixel_to_metres`; ``z`` is 0 or the column's mean voxel height;
5. local features: RootSIFT (L2-normalised; or ORB's 256 bits as +-1/16, so that squared
   L2 distances are Hamming distances / 64 and rank the same way).

:meth:`BEVEncoder.encode_image` runs steps 3-5 on a kitti-bev PNG
(:func:`sgvloc.core.bev.load_bev_image`), keypoints at ``z = 0``; used by evaluation and
training on kitti-bev, where no 3-D scans exist.
"""

from __future__ import annotations

import logging

import numpy as np

from ..bev import (
    KITTI_BEV,
    BEVEncoderConfig,
    BEVRaster,
    BEVRasterConfig,
    pixel_to_metres,
    prepare_points,
    rasterize_cloud,
)
from ..errors import EmptyScanError, InputError
from ..features import EncoderIdentity, Features
from .base import Encoder
from .handcrafted import yaw_invariant_descriptor

log = logging.getLogger(__name__)

#: SIFT descriptor length
SIFT_DIM = 128
#: ORB descriptor length in bits
ORB_BITS = 256
#: ORB ignores this many pixels at the border (its patch size); the image is padded by it
ORB_BORDER = 31


def weighted_polar_grid(
    xy: np.ndarray, weights: np.ndarray, rings: int, sectors: int, max_radius: float
) -> np.ndarray:
    """Weighted soft counts on a polar grid around the origin: ``[rings, sectors]`` float64.

    Same binning as :func:`~sgvloc.core.encoders.handcrafted.polar_grid` (bilinear in ring
    and circular sector), each point adding its weight. Points at ``max_radius`` or beyond
    are ignored. ``xy`` ``[C, M, 2]`` (C sets of the same points moved, one ``weights``
    ``[M]``) gives ``[C, rings, sectors]``, each grid as the set alone would.
    """
    xy = np.asarray(xy, dtype=np.float64)  # [M, 2] or [C, M, 2]
    sets = xy if xy.ndim == 3 else xy[None]  # [C, M, 2]
    r = np.hypot(sets[..., 0], sets[..., 1])  # [C, M]
    inside = r < max_radius
    theta = np.arctan2(sets[..., 1], sets[..., 0]) % (2.0 * np.pi)
    u = r * (rings / max_radius) - 0.5
    v = theta * (sectors / (2.0 * np.pi)) - 0.5
    i0f, j0f = np.floor(u), np.floor(v)
    fu, fv = u - i0f, v - j0f
    i0 = np.clip(i0f.astype(np.int64), 0, rings - 1)
    i1 = np.clip(i0f.astype(np.int64) + 1, 0, rings - 1)
    j0 = j0f.astype(np.int64) % sectors
    j1 = (j0 + 1) % sectors
    cells = rings * sectors
    base = (np.arange(len(sets)) * cells)[:, None, None]
    # per set: its points' four corners one after another, in point order, as one set alone
    idx = base + np.stack(
        [i0 * sectors + j0, i0 * sectors + j1, i1 * sectors + j0, i1 * sectors + j1], 1
    )
    w = np.stack([(1 - fu) * (1 - fv), (1 - fu) * fv, fu * (1 - fv), fu * fv], 1)
    w = w * np.asarray(weights, dtype=np.float64)[None, None]
    keep = np.repeat(inside[:, None, :], 4, axis=1)  # [C, 4, M]
    grids = np.bincount(idx[keep], weights=w[keep], minlength=len(sets) * cells)
    grids = grids.reshape(len(sets), rings, sectors)
    return grids if xy.ndim == 3 else grids[0]


def polar_fft_descriptor(
    image: np.ndarray, raster: BEVRasterConfig = KITTI_BEV, rings: int = 20, sectors: int = 60
) -> np.ndarray:
    """Yaw-invariant global descriptor ``[rings * (sectors // 2 + 1)]`` float32 of a BEV
    density image (not normalised): the grey levels (/255) of its pixels on a polar grid
    around the sensor, then :func:`yaw_invariant_descriptor`."""
    return polar_fft_descriptors(image, np.zeros((1, 2)), raster, rings, sectors)[0]


def polar_fft_descriptors(
    image: np.ndarray,
    centres: np.ndarray,
    raster: BEVRasterConfig = KITTI_BEV,
    rings: int = 20,
    sectors: int = 60,
) -> np.ndarray:
    """:func:`polar_fft_descriptor` with the polar grid about each of ``centres`` ``[C, 2]``
    (metres from the sensor in the image plane) instead of the sensor: ``[C, D]`` float32.

    About a centre ``c`` the descriptor is the one a sensor standing at ``c`` would have
    had of the same surroundings (less what the scan did not reach), and yaw-invariant
    as ever: retrieval with it finds a revisit that passed a few metres to the side or
    in the opposite direction (``RetrievalConfig.offset_m``)."""
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
    if len(centres) == 0:
        return np.zeros((0, rings * (sectors // 2 + 1)), np.float32)
    rows, cols = np.nonzero(image)
    xy = pixel_to_metres(rows, cols, raster)[None] - centres[:, None]  # [C, M, 2]
    grids = weighted_polar_grid(xy, image[rows, cols] / 255.0, rings, sectors, raster.extent)
    return yaw_invariant_descriptor(grids)  # all centres at once


def orb_bits_to_float(desc: np.ndarray) -> np.ndarray:
    """ORB descriptors ``[N, 32]`` uint8 -> ``[N, 256]`` float32 of +-1/16 (unit rows).

    ``|a - b|^2 = hamming(a, b) / 64``, so L2 nearest neighbours are Hamming ones.
    """
    bits = np.unpackbits(np.asarray(desc, dtype=np.uint8), axis=1)  # [N, 256]
    return ((bits.astype(np.float32) * 2.0 - 1.0) / np.sqrt(ORB_BITS)).astype(np.float32)


def _l2_rows(x: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(x, axis=1, keepdims=True)
    return (x / np.where(norm > 0, norm, 1.0)).astype(np.float32)


class BEVEncoder(Encoder):
    """BEV density image -> polar/FFT global descriptor + SIFT/ORB keypoints in metres."""

    NAME = "bev"
    VERSION = "1"
    describes_displaced = True  # its global descriptor is a polar/FFT one

    def __init__(self, config: BEVEncoderConfig | None = None) -> None:
        import cv2

        self.config = config or BEVEncoderConfig()
        c = self.config
        self.global_dim = c.rings * (c.sectors // 2 + 1)
        self.local_dim = SIFT_DIM if c.detector == "sift" else ORB_BITS
        self.preprocess_config = None  # prepare() is overridden: box crop + 0.4 m voxels
        self.identity = EncoderIdentity(
            name=self.NAME,
            version=self.VERSION,
            params={
                "encoder": c.model_dump(),
                "density": "clip(voxels_per_column - 1, 0, max_level) * 10, max -> 255",
                "global_weight": "grey/255, sqrt, rfft magnitude + ring mean",
                "orb_border_pad": ORB_BORDER,
                "opencv_major": int(cv2.__version__.split(".")[0]),
            },
        )

    # -- scans -------------------------------------------------------------------------

    def prepare(self, points: np.ndarray) -> np.ndarray:
        """Raw scan ``[P, 3+]`` -> the 0.4 m voxel cloud in the box ``[M, 3]`` float32.

        Raises :class:`InputError` on a malformed scan or one with no point in the box.
        """
        return prepare_points(points, self.config.raster)

    def encode_cloud(self, cloud: np.ndarray) -> Features:
        """Encode a cloud made by :meth:`prepare` ``[M, 3]``.

        Raises :class:`InputError` if the raster is empty (no column of two voxels).
        """
        return self.encode_query(cloud, None)

    def encode_query(self, cloud: np.ndarray, centres: np.ndarray | None = None) -> Features:
        """:meth:`encode_cloud`, with the global descriptor about ``centres`` ``[C, 2]``
        too (:meth:`Encoder.encode_query`)."""
        raster = rasterize_cloud(np.asarray(cloud, dtype=np.float32), self.config.raster)
        return self._encode(raster.image, raster, centres)

    def raster(self, points: np.ndarray) -> BEVRaster:
        """The BEV raster this encoder describes for a raw scan (for inspection)."""
        return rasterize_cloud(self.prepare(points), self.config.raster)

    # -- images ------------------------------------------------------------------------

    def encode_image(self, image: np.ndarray, centres: np.ndarray | None = None) -> Features:
        """Encode a BEV density image ``[S, S]`` uint8 (e.g. a kitti-bev PNG); ``z = 0``
        (``centres`` as for :meth:`encode_query`).

        Raises :class:`InputError` if the image has the wrong shape or dtype, or is empty.
        """
        img = np.asarray(image)
        s = self.config.raster.size
        if img.shape != (s, s) or img.dtype != np.uint8:
            raise InputError(
                f"BEV image is {list(img.shape)} {img.dtype}; expected [{s}, {s}] uint8"
            )
        return self._encode(img, None, centres)

    # -- shared ------------------------------------------------------------------------

    def global_descriptor(self, image: np.ndarray) -> np.ndarray:
        """Yaw-invariant descriptor ``[G]`` float32 of a density image (not normalised)."""
        c = self.config
        return polar_fft_descriptor(image, c.raster, c.rings, c.sectors)

    def keypoints(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Detect and describe: pixel rows ``[N]``, cols ``[N]`` and local features ``[N, D]``.

        Strongest response first; ties broken by position, so the order is deterministic.
        """
        import cv2

        c = self.config
        img = image
        if c.blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), c.blur_sigma)
        pad = 0
        if c.detector == "sift":
            det = cv2.SIFT_create(
                nfeatures=c.num_keypoints, contrastThreshold=c.sift_contrast_threshold
            )
        else:
            pad = ORB_BORDER
            img = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0)
            det = cv2.ORB_create(
                nfeatures=c.num_keypoints, fastThreshold=c.orb_fast_threshold, edgeThreshold=pad
            )
        kps, desc = det.detectAndCompute(img, None)
        if desc is None or len(kps) == 0:
            return np.zeros(0), np.zeros(0), np.zeros((0, self.local_dim), np.float32)
        pts = np.array([k.pt for k in kps], dtype=np.float64) - pad  # [N, 2] (col, row)
        resp = np.array([k.response for k in kps], dtype=np.float64)
        ang = np.array([k.angle for k in kps], dtype=np.float64)
        order = np.lexsort((ang, pts[:, 0], pts[:, 1], -resp))[: c.num_keypoints]
        pts, desc = pts[order], desc[order]
        if c.detector == "sift":
            d = np.asarray(desc, dtype=np.float64)
            if c.root_sift:
                d = np.sqrt(d / np.maximum(d.sum(axis=1, keepdims=True), 1e-12))
            feats = _l2_rows(d)
        else:
            feats = orb_bits_to_float(desc)
        return pts[:, 1], pts[:, 0], feats

    def _encode(
        self, image: np.ndarray, raster: BEVRaster | None, centres: np.ndarray | None = None
    ) -> Features:
        c = self.config
        g = self.global_descriptor(image)
        if not np.any(g):
            raise EmptyScanError(
                "BEV image is empty (no column with two or more occupied 0.4 m voxels); "
                "nothing to describe"
            )
        rows, cols, feats = self.keypoints(image)
        xy = pixel_to_metres(rows, cols, c.raster)  # [N, 2]
        z = np.zeros(len(xy))
        if raster is not None and c.keypoint_z == "column_mean" and len(xy):
            r = np.clip(np.floor(rows + 0.5).astype(np.int64), 0, c.raster.size - 1)
            cc = np.clip(np.floor(cols + 0.5).astype(np.int64), 0, c.raster.size - 1)
            zc = raster.height[r, cc]
            z = np.where(np.isfinite(zc), zc, 0.0)
        kp = np.column_stack([xy, z]).reshape(-1, 3)
        log.debug("BEV encoder: %d keypoints", len(kp))
        f = Features.validated(
            g, kp, feats, self.identity, global_dim=self.global_dim, local_dim=self.local_dim
        )
        if centres is None or not len(centres):
            return f
        return f.with_variants(
            0, polar_fft_descriptors(image, centres, c.raster, c.rings, c.sectors)
        )


__all__ = [
    "BEVEncoder",
    "orb_bits_to_float",
    "polar_fft_descriptor",
    "polar_fft_descriptors",
    "weighted_polar_grid",
]
