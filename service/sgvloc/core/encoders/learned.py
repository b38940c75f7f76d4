"""Learned BEV encoder: a small CNN (:class:`sgvloc.core.bevnet.BEVNet`) trained in-project.

Per scan (deterministic):

1. prepare: finite points, box crop and 0.4 m voxels (:func:`sgvloc.core.bev.prepare_points`),
   as the handcrafted BEV encoder; the voxel cloud is what the localizer keeps for ICP;
2. level (``level``, scans): the cloud turned so that its ground plane is level
   (:func:`sgvloc.core.bev.level_cloud`, a seeded RANSAC plane fit) and re-voxelised,
   as the network was trained on scans of a level car-mounted sensor;
3. raster: the kitti-bev density image of the cloud (:func:`sgvloc.core.bev.rasterize_cloud`),
   the input the network was trained on, without its faintest pixels (grey level below the
   ``min_grey`` the weights were trained with, :func:`sgvloc.core.bevnet.cut_faint`);
4. network: local descriptor map and saliency over 0.8 m cells, global descriptor;
5. keypoints: the most salient occupied cells (optionally only local maxima of the
   saliency, ``nms_radius``), lifted to metres at the grey-weighted centroid of the cell's
   2 x 2 pixels (``keypoint_xy``) and, for scans, at the height of the cell's lowest voxel
   (``keypoint_z``), then turned back into the sensor frame; local features are the
   descriptors of those cells. With ``local_features = "fpfh"`` the scan is prepared as
   the handcrafted encoder prepares it (range crop, 0.3 m voxels: the cloud kept for
   ICP), the network sees its box-cropped 0.4 m voxels, and the keypoints and local
   features are FPFH at its curvature keypoints
   (:func:`sgvloc.core.encoders.handcrafted.keypoint_features`): a 70-degree scan leaves
   the network 20-34 cells to take keypoints from, too few for the pose step, while the
   network's global descriptor still finds the place;
6. global descriptor (``global_descriptor``): the network's, with ``global_rotations = 4``
   the mean of the descriptors of the image turned by 0, 90, 180 and 270 degrees about the
   sensor (exact pixel turns, as the sensor is the centre of the padded input),
   re-normalised, which makes it invariant to quarter turns and flattens the yaw
   dependence between them; or ``"polar"``: the polar/FFT descriptor of the same image
   (:func:`sgvloc.core.encoders.bev.polar_fft_descriptor`, yaw-invariant by construction);
   or ``"polar+network"``: both, each normalised, as two blocks of one vector
   (``global_blocks``), which retrieval searches one by one and merges.

The network runs in torch, or in ONNX Runtime on CPU (``runtime``; ``"auto"`` picks ONNX
Runtime when it is installed and the weights have their ONNX export beside them,
``<weights>.onnx``, made by ``sgvloc export-onnx`` and recording the weights' SHA-256; the
package ships one for its weights). Both give the same outputs to about 1e-5; torch stays
the path for training, CUDA and in-memory models.

The weights file (``model_path``; the weights shipped in the package when unset) holds
``{"format": "sgvloc-bevnet", "arch": {...}, "state_dict": {...}, "meta": {...}}``
(:func:`sgvloc.tools.train.export_weights` writes one). Its SHA-256 is part of the identity, so
features of different weights never mix.
"""

from __future__ import annotations

import logging
import math
import threading
from pathlib import Path
from typing import Any

import numpy as np

from sgvloc.about import PACKAGE_DIR

from .. import cores
from ..bev import (
    KITTI_BEV,
    BEVRaster,
    LearnedEncoderConfig,
    level_cloud,
    pixel_to_metres,
    prepare_points,
    rasterize_cloud,
)
from ..errors import EmptyScanError, InputError
from ..features import EncoderIdentity, Features
from .base import Encoder
from .bev import polar_fft_descriptor, polar_fft_descriptors
from .handcrafted import HandcraftedEncoder, keypoint_features
from .torchscript import file_sha256

log = logging.getLogger(__name__)

#: weights file format tag
WEIGHTS_FORMAT = "sgvloc-bevnet"
#: the weights shipped with the package (sgvloc/weights/)
SHIPPED_WEIGHTS = "bevnet-v1.pt"
#: global_descriptor "polar": the grid of the 'bev' encoder's default
POLAR_RINGS, POLAR_SECTORS = 20, 60
POLAR_DIM = POLAR_RINGS * (POLAR_SECTORS // 2 + 1)


#: the ONNX model's metadata key holding the SHA-256 of the weights it was exported from
ONNX_WEIGHTS_KEY = "sgvloc_weights_sha256"
RUNTIMES = ("auto", "torch", "onnx")


def onnx_path(weights: str | Path) -> Path:
    """Where the ONNX export of a weights file lives: beside it, suffix ``.onnx``."""
    return Path(weights).with_suffix(".onnx")


def onnxruntime_available() -> bool:
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        return False
    return True


class OnnxNet:
    """BEVNet's forward pass in ONNX Runtime (CPU), called like the torch model: tensors
    in, ``(global, local, saliency)`` tensors out. Sessions are thread-safe; ``threads``
    intra-op threads per call (the service's thread policy), more while cores are spare."""

    def __init__(self, path: Path, model: Any, threads: int) -> None:
        self._path = path
        self._threads = max(1, threads)
        self._sessions: dict[int, Any] = {}
        self._lock = threading.Lock()
        self._model = model  # the torch model: global_descriptor() of turned images
        for n in {self._threads, max(self._threads, cores.cores())}:
            self._session(n)

    def _session(self, threads: int) -> Any:
        """The session with ``threads`` intra-op threads (one per count, made once): a call
        takes the spare cores (:mod:`sgvloc.core.cores`); ONNX Runtime's CPU kernels split
        outputs, not sums, so every count gives the same outputs."""
        session = self._sessions.get(threads)
        if session is None:
            import onnxruntime as ort

            with self._lock:
                session = self._sessions.get(threads)
                if session is None:
                    opts = ort.SessionOptions()
                    opts.intra_op_num_threads = threads
                    opts.inter_op_num_threads = 1
                    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
                    session = ort.InferenceSession(
                        str(self._path), opts, providers=["CPUExecutionProvider"]
                    )
                    self._sessions[threads] = session
        return session

    @staticmethod
    def weights_sha256(path: Path) -> str | None:
        """The weights SHA-256 recorded in an ONNX export ("" when absent); None when the
        file cannot be loaded (truncated, not ONNX)."""
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
        try:
            sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        except Exception:  # onnxruntime's own errors share no public base class
            return None
        return sess.get_modelmeta().custom_metadata_map.get(ONNX_WEIGHTS_KEY, "")

    def __call__(self, x: Any) -> tuple[Any, Any, Any]:
        import torch

        session = self._session(max(self._threads, cores.threads()))
        outs = session.run(None, {"image": x.numpy()})
        return tuple(torch.from_numpy(o) for o in outs)  # type: ignore[return-value]

    def global_descriptor(self, x: Any) -> Any:
        return self._model.global_descriptor(x)


def _pick_runtime(runtime: str, device: str, weights: Path | None, sha256: str) -> Path | None:
    """The ONNX file to run, or None for torch; raises :class:`InputError` when
    ``runtime="onnx"`` cannot be honoured."""
    if runtime not in RUNTIMES:
        raise InputError(f"learned encoder: runtime must be one of {RUNTIMES}, got {runtime!r}")
    if runtime == "torch":
        return None
    why = ""
    path = onnx_path(weights) if weights is not None else None
    if device != "cpu":
        why = f"ONNX Runtime is used on CPU only (device {device!r})"
    elif path is None:
        why = "an in-memory model has no ONNX export"
    elif not onnxruntime_available():
        why = "onnxruntime is not installed"
    elif not path.is_file():
        why = f"no ONNX export at {str(path)!r} (make one with 'sgvloc export-onnx')"
    elif (recorded := OnnxNet.weights_sha256(path)) is None:
        why = f"{str(path)!r} cannot be loaded (damaged, or not an ONNX model)"
    elif recorded != sha256:
        why = f"{str(path)!r} was exported from other weights"
    if not why:
        return path
    if runtime == "onnx":
        raise InputError(f"learned encoder: runtime 'onnx' unavailable: {why}")
    log.debug("learned encoder runs in torch: %s", why)
    return None


def shipped_weights_path() -> Path:
    """Path of the weights file shipped in the package."""
    return PACKAGE_DIR / "weights" / SHIPPED_WEIGHTS


def load_weights(path: str | Path) -> tuple[Any, dict[str, Any]]:
    """Build a :class:`BEVNet` (eval mode, CPU) from a weights file; returns (model, meta).

    ``meta["min_grey"]`` is the input cut the network was trained with
    (:func:`sgvloc.core.bevnet.cut_faint`).

    Raises :class:`InputError` if the file is missing or not an sgvloc BEVNet weights file.
    """
    import torch

    from ..bevnet import BEVNet

    path = Path(path)
    if not path.is_file():
        raise InputError(f"learned encoder: weights file {str(path)!r} does not exist")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is a bad file
        raise InputError(f"learned encoder: cannot read weights {str(path)!r}: {exc}") from None
    if not isinstance(blob, dict) or blob.get("format") != WEIGHTS_FORMAT:
        raise InputError(
            f"learned encoder: {str(path)!r} is not an sgvloc BEVNet weights file "
            f"(expected format {WEIGHTS_FORMAT!r}; a training checkpoint is exported with "
            "'sgvloc export-weights')"
        )
    arch = blob["arch"]
    model = BEVNet(int(arch["width"]), int(arch["local_dim"]), int(arch["global_dim"]))
    try:
        model.load_state_dict(blob["state_dict"])
    except RuntimeError as exc:
        raise InputError(f"learned encoder: weights {str(path)!r} do not fit: {exc}") from None
    meta = dict(blob.get("meta", {}))
    meta["min_grey"] = int(arch.get("min_grey", 0))
    return model.eval(), meta


class LearnedEncoder(Encoder):
    """BEV density image -> BEVNet global descriptor, salient cells and their descriptors."""

    NAME = "bevnet"
    VERSION = "1"

    def __init__(
        self,
        config: LearnedEncoderConfig | None = None,
        model_path: str | Path | None = None,
        device: str = "cpu",
        runtime: str = "auto",
    ) -> None:
        """Load the weights (``model_path``, or the shipped ones) onto ``device``
        (``"cpu"``, ``"cuda"`` or ``"auto"``), to run in ``runtime`` (``"auto"``,
        ``"torch"`` or ``"onnx"``; see the module docstring).

        Raises :class:`InputError` if the weights cannot be loaded, CUDA is absent or
        ``runtime="onnx"`` cannot be honoured.
        """
        path = Path(model_path) if model_path else shipped_weights_path()
        model, meta = load_weights(path)
        sha = file_sha256(path)
        self._setup(model, config, sha[:16], device, meta, runtime, path, sha)

    @classmethod
    def from_model(
        cls,
        model: Any,
        config: LearnedEncoderConfig | None = None,
        weights_id: str = "",
        min_grey: int = 0,
    ) -> LearnedEncoder:
        """An encoder around an in-memory model (training, tests) trained on images cut
        at ``min_grey``."""
        self = cls.__new__(cls)
        self._setup(model.eval(), config, weights_id, "cpu", {"min_grey": min_grey})
        return self

    def _setup(
        self,
        model: Any,
        config: LearnedEncoderConfig | None,
        weights_id: str,
        device: str,
        meta: dict[str, Any],
        runtime: str = "torch",
        weights: Path | None = None,
        sha256: str = "",
    ) -> None:
        import torch

        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        if device == "cuda" and not torch.cuda.is_available():
            raise InputError("learned encoder: device 'cuda' requested but CUDA is absent")
        self.device = torch.device(device)
        self.config = config or LearnedEncoderConfig()
        # a query's polar block about displaced centres, where the descriptor has one
        self.describes_displaced = "polar" in self.config.global_descriptor.split("+")
        self.model = model.to(self.device).eval()
        onnx_file = _pick_runtime(runtime, device, weights, sha256)
        #: what runs the network: the torch model or an :class:`OnnxNet`
        self.net: Any = (
            OnnxNet(onnx_file, self.model, torch.get_num_threads()) if onnx_file else self.model
        )
        self.runtime = "onnx" if onnx_file else "torch"
        self.meta = meta
        self.min_grey = int(meta.get("min_grey", 0))
        kinds = self.config.global_descriptor.split("+")
        dims = {"polar": POLAR_DIM, "network": int(model.global_dim)}
        self.global_blocks = tuple(dims[k] for k in kinds)
        self.global_dim = sum(self.global_blocks)
        self.local_dim = int(model.local_dim)
        self.preprocess_config = None  # prepare() is overridden: box crop + 0.4 m voxels
        #: with local_features "fpfh": the handcrafted encoder whose preprocessing,
        #: keypoints and FPFH make the local part
        self.fpfh: Any = None
        encoder = self.config.model_dump()
        if self.config.local_features == "fpfh":
            self.fpfh = HandcraftedEncoder()
            self.preprocess_config = self.fpfh.preprocess_config
            self.local_dim = self.fpfh.local_dim
        else:
            del encoder["local_features"]  # the identity of maps made before the option
        self.identity = EncoderIdentity(
            name=self.NAME,
            version=self.VERSION,
            params={
                "weights_sha256": weights_id,
                "arch": {
                    "width": int(model.width),
                    "local_dim": self.local_dim,
                    "global_dim": int(model.global_dim),
                },
                "min_grey": self.min_grey,
                "encoder": encoder,
                "raster": KITTI_BEV.model_dump(),
            },
        )
        if self.fpfh is not None:
            self.identity.params["fpfh"] = self.fpfh.identity.params

    # -- scans -------------------------------------------------------------------------

    def prepare(self, points: np.ndarray) -> np.ndarray:
        """Raw scan ``[P, 3+]`` -> the 0.4 m voxel cloud in the box ``[M, 3]`` float32
        (with ``local_features = "fpfh"``: the handcrafted encoder's 0.3 m voxel cloud)."""
        if self.fpfh is not None:
            return self.fpfh.prepare(points)
        return prepare_points(points, KITTI_BEV)

    def encode_cloud(self, cloud: np.ndarray) -> Features:
        """Encode a cloud made by :meth:`prepare` ``[M, 3]``.

        Raises :class:`InputError` if the raster is empty (no column of two voxels).
        """
        return self.encode_query(cloud, None)

    def encode_query(
        self,
        cloud: np.ndarray,
        centres: np.ndarray | None = None,
        *,
        local: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> Features:
        """:meth:`encode_cloud`, with the polar block about ``centres`` ``[C, 2]`` too (in
        the levelled frame; a ring of them is the same in any frame) when the global
        descriptor has one (:meth:`Encoder.encode_query`).

        ``local``: with ``local_features = "fpfh"``, the keypoints and FPFH rows that
        :attr:`fpfh` (the handcrafted encoder) already made of this cloud, taken instead
        of computing them again (the evaluation's feature cache holds them).
        """
        cloud = np.asarray(cloud, dtype=np.float32)
        if self.fpfh is None:
            return self._encode_scan(cloud, centres)
        # the network on the box-cropped 0.4 m voxels for the place, FPFH for the pose
        f = self._encode_scan(prepare_points(cloud, KITTI_BEV), centres, keypoints=False)
        kp, local = local if local is not None else keypoint_features(cloud, self.fpfh.config)
        g = Features.validated(
            f.global_descriptor,
            kp,
            local,
            self.identity,
            global_dim=self.global_dim,
            local_dim=self.local_dim,
        )
        return Features(
            g.global_descriptor, g.keypoints, g.local_features, g.encoder, f.global_variants
        )

    def _encode_scan(
        self, cloud: np.ndarray, centres: np.ndarray | None, keypoints: bool = True
    ) -> Features:
        """The network's features of a 0.4 m voxel cloud (levelled first when ``level``),
        keypoints in the sensor frame; none when not ``keypoints``."""
        if not self.config.level:
            raster = rasterize_cloud(cloud, KITTI_BEV)
            return self._encode(raster.image, raster, centres, keypoints)
        level, R = level_cloud(cloud, KITTI_BEV)
        raster = rasterize_cloud(level, KITTI_BEV)
        f = self._encode(raster.image, raster, centres, keypoints)
        kp = (f.keypoints.astype(np.float64) @ R).astype(np.float32)  # back to the sensor frame
        return Features(f.global_descriptor, kp, f.local_features, f.encoder, f.global_variants)

    # -- images ------------------------------------------------------------------------

    def encode_image(self, image: np.ndarray, centres: np.ndarray | None = None) -> Features:
        """Encode a kitti-bev density image ``[151, 151]`` uint8; keypoints at ``z = 0``
        (``centres`` as for :meth:`encode_query`).

        Raises :class:`InputError` if the image has the wrong shape or dtype, or is empty,
        or if the local features are FPFH (an image has no points to compute them on).
        """
        if self.fpfh is not None:
            raise InputError(
                "the learned encoder with local_features 'fpfh' describes 3-D scans only: "
                "a BEV image has no points for FPFH (use local_features 'network')"
            )
        img = np.asarray(image)
        s = KITTI_BEV.size
        if img.shape != (s, s) or img.dtype != np.uint8:
            raise InputError(
                f"BEV image is {list(img.shape)} {img.dtype}; expected [{s}, {s}] uint8"
            )
        return self._encode(img, None, centres)

    # -- shared ------------------------------------------------------------------------

    def _forward(self, x: Any) -> tuple[Any, Any, Any]:
        """The network on one image ``[1, 1, 152, 152]``, batched with concurrent
        localizations' images when dynamic batching is on (:mod:`sgvloc.core.batching`)."""
        from .. import batching

        batcher = batching.current()
        if batcher is None:
            return self.net(x)
        key = (self.identity.params["weights_sha256"], self.runtime, str(self.device))
        return batcher.run("forward", key, x, self._forward_many)

    def _forward_many(self, xs: list[Any]) -> list[tuple[Any, Any, Any]]:
        import torch

        with torch.inference_mode():
            g, local, sal = self.net(torch.cat(xs))
        return [(g[i : i + 1], local[i : i + 1], sal[i : i + 1]) for i in range(len(xs))]

    def _encode(
        self,
        image: np.ndarray,
        raster: BEVRaster | None,
        centres: np.ndarray | None = None,
        keypoints: bool = True,
    ) -> Features:
        import torch
        import torch.nn.functional as F

        from ..bevnet import CELLS, cell_to_metres, cut_faint, occupied_cells, to_input

        image = cut_faint(image, self.min_grey)
        if not image.any():
            raise EmptyScanError(
                "BEV image is empty (no column with two or more occupied 0.4 m voxels"
                + (f", none at grey level {self.min_grey} or above" if self.min_grey else "")
                + "); nothing to describe"
            )
        c = self.config
        with torch.inference_mode():
            x = to_input(image[None]).to(self.device)  # [1, 1, 152, 152]
            g, local, sal = self._forward(x)
            blocks = c.global_descriptor.split("+")
            if "network" in blocks and c.global_rotations == 4:
                turned = torch.cat([torch.rot90(x, t, dims=(2, 3)) for t in (1, 2, 3)])
                g = torch.cat([g, self.net.global_descriptor(turned)])
                g = F.normalize(g.mean(dim=0, keepdim=True), dim=1)
            occ = occupied_cells(x)[0]
            s = sal[0].masked_fill(~occ, -math.inf)
            if c.nms_radius:
                r = c.nms_radius
                peak = s == F.max_pool2d(s[None, None], 2 * r + 1, stride=1, padding=r)[0, 0]
                s = s.masked_fill(~peak, -math.inf)
            s = s.flatten()
            k = int(min(c.num_keypoints, int(torch.isfinite(s).sum()))) if keypoints else 0
            idx = torch.topk(s, k).indices if k else torch.zeros(0, dtype=torch.long)
            feats = (
                local[0].flatten(1)[:, idx.to(self.device)].T.float().cpu().numpy()
                if keypoints
                else np.zeros((0, self.local_dim), np.float32)  # the caller's local part
            )
            parts = [
                polar_fft_descriptor(image, KITTI_BEV, POLAR_RINGS, POLAR_SECTORS)
                if b == "polar"
                else g[0].float().cpu().numpy()
                for b in blocks
            ]
            g_np = parts[0] if len(parts) == 1 else _concat_unit(parts)
        idx_np = idx.cpu().numpy()
        rows, cols = idx_np // CELLS, idx_np % CELLS
        if c.keypoint_xy == "centroid":
            # grey-weighted centroid of the cell's 2 x 2 pixels (the cell has an occupied one)
            pad = np.zeros((CELLS * 2, CELLS * 2))
            pad[: image.shape[0], : image.shape[1]] = image
            w = pad.reshape(CELLS, 2, CELLS, 2)[rows, :, cols, :]  # [N, 2, 2]
            tot = w.sum(axis=(1, 2))
            dr = w[:, 1, :].sum(axis=1) / tot  # [N] share of the lower pixel row
            dc = w[:, :, 1].sum(axis=1) / tot
            xy = pixel_to_metres(2 * rows + dr, 2 * cols + dc).reshape(-1, 2)
        else:
            xy = cell_to_metres(rows, cols).reshape(-1, 2)
        z = np.zeros(len(xy))
        if raster is not None and c.keypoint_z != "zero" and len(xy):
            # over the cell's 2 x 2 columns: the lowest voxel, or the voxel-weighted mean
            low = c.keypoint_z == "column_min"
            hgt = np.full((CELLS * 2, CELLS * 2), np.nan)
            cnt = np.zeros((CELLS * 2, CELLS * 2))
            hgt[: KITTI_BEV.size, : KITTI_BEV.size] = raster.low if low else raster.height
            cnt[: KITTI_BEV.size, : KITTI_BEV.size] = raster.counts
            blocks = hgt.reshape(CELLS, 2, CELLS, 2)[rows, :, cols, :].reshape(len(rows), -1)
            with np.errstate(all="ignore"):
                if low:
                    zc = np.nanmin(blocks, axis=1)
                else:
                    w = cnt.reshape(CELLS, 2, CELLS, 2)[rows, :, cols, :].reshape(len(rows), -1)
                    zc = np.nansum(blocks * w, axis=1) / w.sum(axis=1)
            z = np.where(np.isfinite(zc), zc, 0.0)
        kp = np.column_stack([xy, z]).reshape(-1, 3)
        f = Features.validated(
            g_np, kp, feats, self.identity, global_dim=self.global_dim, local_dim=self.local_dim
        )
        kinds = c.global_descriptor.split("+")
        if centres is None or not len(centres) or "polar" not in kinds:
            return f
        polars = polar_fft_descriptors(image, centres, KITTI_BEV, POLAR_RINGS, POLAR_SECTORS)
        return f.with_variants(sum(self.blocks[: kinds.index("polar")]), polars)


def _concat_unit(parts: list[np.ndarray]) -> np.ndarray:
    """Blocks normalised one by one, concatenated, scaled to unit length: the inner
    product of two such descriptors is the mean of their blocks' cosine similarities."""
    unit = [p / max(float(np.linalg.norm(p)), 1e-12) for p in parts]
    return (np.concatenate(unit) / math.sqrt(len(unit))).astype(np.float32)


__all__ = [
    "LearnedEncoder",
    "OnnxNet",
    "load_weights",
    "onnx_path",
    "shipped_weights_path",
]
