"""The encoder interface, the serialisable spec a map stores, and the factory.

An encoder turns a raw scan into :class:`~sgvloc.core.features.Features`: a global
descriptor for retrieval plus keypoints and local features for re-ranking and pose. Each
encoder runs its own preprocessing, so its :class:`EncoderIdentity` covers every
parameter that changes its output; features are only comparable between equal identities.

The kinds:

- ``handcrafted``: polar-grid global descriptor + FPFH, no weights;
- ``precomputed``: the client runs its own network and sends features;
- ``torchscript``: a learned model loaded from a TorchScript file;
- ``bev``: SIFT/ORB on the bird's-eye-view density image + polar/FFT descriptor, no weights;
- ``learned`` (default): a small CNN on the same density image, trained in-project
  (weights shipped).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from ..bev import BEVEncoderConfig, LearnedEncoderConfig
from ..config import HandcraftedEncoderConfig, PreprocessConfig
from ..errors import InputError
from ..features import EncoderIdentity, Features
from ..preprocess import preprocess

#: upper bounds of a precomputed map's feature sizes (the shipped encoders: 620 and 64)
MAX_GLOBAL_DIM = 16384
MAX_LOCAL_DIM = 1024


class Encoder(ABC):
    """Turns one scan into :class:`Features` tagged with this encoder's identity.

    Subclasses set ``identity``, ``global_dim`` and ``local_dim`` (attributes or
    properties) and implement :meth:`encode`. Encoders are stateless after construction
    and safe to call from several threads.
    """

    #: name, version and every parameter that changes the output
    identity: EncoderIdentity
    #: length ``G`` of the global descriptor
    global_dim: int
    #: dimension ``D`` of one local feature row
    local_dim: int
    #: the global descriptor's blocks (their lengths, summing to ``global_dim``): one for
    #: most encoders; several when it concatenates separately normalised descriptors,
    #: which retrieval can search one by one and merge (``RetrievalConfig.combine``)
    global_blocks: tuple[int, ...] = ()

    @property
    def blocks(self) -> tuple[int, ...]:
        """:attr:`global_blocks`, or the whole descriptor as one block."""
        return tuple(self.global_blocks) or (int(self.global_dim),)

    #: whether :meth:`encode_query` (and ``encode_image``, where there is one) describes
    #: a query about displaced centres too
    describes_displaced: bool = False

    #: the preprocessing the encoder applies to raw scans (None if it takes no scans);
    #: the localizer reuses it to keep clouds for ICP refinement
    preprocess_config: PreprocessConfig | None = None

    def prepare(self, points: np.ndarray) -> np.ndarray:
        """Preprocess a raw scan ``[P, 3+]`` into the cloud this encoder works on ``[M, 3]``.

        Raises :class:`InputError` on a malformed scan, one that is empty after
        preprocessing, or if this encoder takes no raw scans.
        """
        if self.preprocess_config is None:
            raise InputError(f"encoder {self.identity.name!r} does not take raw scans")
        return preprocess(points, self.preprocess_config)

    def encode(self, points: np.ndarray) -> Features:
        """Encode a raw scan ``[P, 3]`` or ``[P, 3+C]`` (x y z, extra columns ignored).

        Raises :class:`InputError` on a malformed or empty scan.
        """
        return self.encode_cloud(self.prepare(points))

    @abstractmethod
    def encode_cloud(self, cloud: np.ndarray) -> Features:
        """Encode a cloud already preprocessed by :meth:`prepare` ``[M, 3]``."""

    def encode_query(self, cloud: np.ndarray, centres: np.ndarray | None = None) -> Features:
        """:meth:`encode_cloud` for a scan to be localized. An encoder whose global
        descriptor holds a polar/FFT block (``learned``, ``bev``) also computes it about each of
        ``centres`` ``[C, 2]`` (metres from the sensor, in the ground plane) into
        ``Features.global_variants``, which retrieval searches with too; the others
        return plain features."""
        return self.encode_cloud(cloud)

    def check(self, features: Features) -> None:
        """Refuse features from another encoder or with the wrong dimensions.

        Raises :class:`EncoderMismatchError` if ``features.encoder`` is not this encoder,
        :class:`InputError` if the arrays do not have this encoder's shapes.
        """
        self.identity.require_same(features.encoder)
        g, k, f = features.global_descriptor, features.keypoints, features.local_features
        if g.ndim != 1 or g.shape[0] != self.global_dim:
            raise InputError(
                f"global_descriptor has shape {list(g.shape)}, expected [{self.global_dim}]"
            )
        if k.ndim != 2 or k.shape[1] != 3:
            raise InputError(f"keypoints must have shape [N, 3], got {list(k.shape)}")
        if f.ndim != 2 or f.shape[0] != k.shape[0]:
            raise InputError(
                f"local_features has shape {list(f.shape)} but keypoints has "
                f"{k.shape[0]} rows; one feature row per keypoint is required"
            )
        if k.shape[0] > 0 and f.shape[1] != self.local_dim:
            raise InputError(
                f"local_features has dimension {f.shape[1]}, expected {self.local_dim}"
            )

    def __repr__(self) -> str:
        ident = self.identity
        return f"{type(self).__name__}(name={ident.name!r}, fingerprint={ident.fingerprint})"


class EncoderSpec(BaseModel):
    """Which encoder a map uses, with its settings; stored with the map (JSON).

    - ``kind="handcrafted"``: uses ``preprocess`` and ``handcrafted``;
    - ``kind="torchscript"``: uses ``preprocess``, ``model_path`` and ``device``;
    - ``kind="precomputed"``: uses ``name``, ``global_dim`` and ``local_dim``;
    - ``kind="bev"``: uses ``bev`` (its own box crop and voxels; ``preprocess`` is unused);
    - ``kind="learned"``: uses ``learned``, ``model_path`` (unset: the shipped weights),
      ``device`` and ``runtime`` (the same box crop and voxels as ``bev``).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    kind: Literal["handcrafted", "torchscript", "precomputed", "bev", "learned"] = "learned"
    preprocess: PreprocessConfig = PreprocessConfig()
    handcrafted: HandcraftedEncoderConfig = HandcraftedEncoderConfig()
    bev: BEVEncoderConfig = BEVEncoderConfig()
    learned: LearnedEncoderConfig = LearnedEncoderConfig()
    model_path: str | None = Field(
        None,
        description="torchscript: path of the model file; learned: path of a weights file "
        "(unset: the weights shipped with sgvloc)",
    )
    device: Literal["auto", "cpu", "cuda"] = Field(
        "cpu",
        description="torchscript, learned: where the model runs ('auto' = CUDA if present)",
    )
    runtime: Literal["auto", "torch", "onnx"] = Field(
        "auto",
        description="learned: what runs the network on CPU ('auto' = ONNX Runtime when "
        "installed and the weights have their ONNX export, else torch)",
    )
    name: str | None = Field(None, description="precomputed: the client's network, e.g. 'egonn'")
    global_dim: int | None = Field(
        None, ge=1, le=MAX_GLOBAL_DIM, description="precomputed: descriptor length"
    )
    local_dim: int | None = Field(
        None, ge=1, le=MAX_LOCAL_DIM, description="precomputed: local feature dim"
    )

    @model_validator(mode="after")
    def _check_kind_fields(self) -> EncoderSpec:
        if self.kind == "torchscript" and not self.model_path:
            raise ValueError("a torchscript encoder needs model_path")
        if self.kind == "precomputed":
            missing = [f for f in ("name", "global_dim", "local_dim") if getattr(self, f) is None]
            if missing:
                raise ValueError(f"a precomputed encoder needs {', '.join(missing)}")
        return self


def make_encoder(spec: EncoderSpec) -> Encoder:
    """Build the encoder a spec describes.

    Raises :class:`InputError` if a torchscript model or weights file is missing or
    unreadable.
    """
    if spec.kind == "handcrafted":
        from .handcrafted import HandcraftedEncoder

        return HandcraftedEncoder(spec.handcrafted, spec.preprocess)
    if spec.kind == "precomputed":
        from .precomputed import PrecomputedEncoder

        assert spec.name is not None and spec.global_dim is not None  # validated
        assert spec.local_dim is not None
        return PrecomputedEncoder(spec.name, spec.global_dim, spec.local_dim)
    if spec.kind == "bev":
        from .bev import BEVEncoder

        return BEVEncoder(spec.bev)
    if spec.kind == "learned":
        from .learned import LearnedEncoder

        return LearnedEncoder(
            spec.learned, spec.model_path, device=spec.device, runtime=spec.runtime
        )
    if spec.kind == "torchscript":
        from .torchscript import TorchScriptEncoder

        assert spec.model_path is not None  # validated
        return TorchScriptEncoder(spec.model_path, spec.preprocess, device=spec.device)
    raise InputError(f"unknown encoder kind {spec.kind!r}")  # pragma: no cover
