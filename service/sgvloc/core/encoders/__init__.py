"""Encoders: scan -> global descriptor, keypoints and local features.

- :class:`HandcraftedEncoder` (default, no weights): yaw-invariant polar-grid descriptor,
  FPFH at curvature keypoints;
- :class:`PrecomputedEncoder`: the client sends features from its own network;
- :class:`BEVEncoder` (no weights): SIFT/ORB on the bird's-eye-view density image,
  polar/FFT global descriptor;
- :class:`LearnedEncoder`: a small CNN on the same BEV image, trained in-project
  (:mod:`sgvloc.tools.train`), weights shipped in the package (torch imported when built);
- :class:`TorchScriptEncoder`: a learned model loaded from a TorchScript file (torch is
  imported only when one is built).

A map stores its :class:`EncoderSpec`; :func:`make_encoder` rebuilds the encoder from it.
"""

from .base import Encoder, EncoderSpec, make_encoder
from .bev import BEVEncoder
from .handcrafted import HandcraftedEncoder
from .learned import LearnedEncoder
from .precomputed import PrecomputedEncoder
from .torchscript import TorchScriptEncoder

__all__ = [
    "BEVEncoder",
    "Encoder",
    "EncoderSpec",
    "HandcraftedEncoder",
    "LearnedEncoder",
    "PrecomputedEncoder",
    "TorchScriptEncoder",
    "make_encoder",
]
