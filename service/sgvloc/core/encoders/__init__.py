"""Encoders: scan -> global descriptor, keypoints and local features.

- :class:`HandcraftedEncoder` (default, no weights): yaw-invariant polar-grid descriptor,
  FPFH at curvature keypoints;
- :class:`PrecomputedEncoder`: the client sends features from its own network;
- :class:`TorchScriptEncoder`: a learned model loaded from a TorchScript file (torch is
  imported only when one is built).

A map stores its :class:`EncoderSpec`; :func:`make_encoder` rebuilds the encoder from it.
"""

from .base import Encoder, EncoderSpec, make_encoder
from .handcrafted import HandcraftedEncoder
from .precomputed import PrecomputedEncoder
from .torchscript import TorchScriptEncoder

__all__ = [
    "Encoder",
    "EncoderSpec",
    "HandcraftedEncoder",
    "PrecomputedEncoder",
    "TorchScriptEncoder",
    "make_encoder",
]
