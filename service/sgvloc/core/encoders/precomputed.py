"""Encoder for maps whose clients run their own network (EgoNN, LoGG3D-Net, ...).

The service never sees the network: clients send the global descriptor, keypoints and
local features, and this encoder only validates them against the map's declared
dimensions and tags them with the map's identity.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import InputError
from ..features import EncoderIdentity, Features
from .base import Encoder


class PrecomputedEncoder(Encoder):
    """Stands for an external network ``name`` with fixed output dimensions."""

    def __init__(self, name: str, global_dim: int, local_dim: int) -> None:
        if not name:
            raise InputError("a precomputed encoder needs a non-empty name (e.g. 'egonn')")
        if global_dim < 1 or local_dim < 1:
            raise InputError(
                f"precomputed encoder dimensions must be positive, got "
                f"global_dim={global_dim}, local_dim={local_dim}"
            )
        self.name = name
        self.global_dim = int(global_dim)
        self.local_dim = int(local_dim)
        self.identity = EncoderIdentity(
            name=f"precomputed:{name}",
            params={"global_dim": self.global_dim, "local_dim": self.local_dim},
        )

    def encode(self, points: np.ndarray) -> Features:
        """Always raises :class:`InputError`: this map takes features, not scans."""
        return self.encode_cloud(points)

    def encode_cloud(self, cloud: np.ndarray) -> Features:
        """Always raises :class:`InputError`: this map takes features, not scans."""
        raise InputError(
            f"this map uses precomputed features from {self.name!r} "
            f"(global_dim={self.global_dim}, local_dim={self.local_dim}): send "
            "global_descriptor, keypoints and local_features instead of a raw scan"
        )

    def from_arrays(self, global_descriptor: Any, keypoints: Any, local_features: Any) -> Features:
        """Validate client-computed features and tag them with this encoder's identity.

        ``global_descriptor [G]``, ``keypoints [N, 3]``, ``local_features [N, D]`` with
        ``G``/``D`` the declared dimensions; numeric and finite. The descriptor is
        L2-normalised. Raises :class:`InputError` naming the offending field.
        """
        return Features.validated(
            global_descriptor,
            keypoints,
            local_features,
            self.identity,
            global_dim=self.global_dim,
            local_dim=self.local_dim,
        )
