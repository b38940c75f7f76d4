"""BEVNet: the small 2-D CNN of the learned BEV encoder, and its cell geometry.

On the kitti-bev density image ``[1, 151, 151]`` (zero-padded to 152 at the bottom/right,
so pixel coordinates do not move and the sensor, at pixel 75.5, is the padded image's
centre):

- a U-shaped CNN (strides 2, 4, 8) whose output cells are 2 x 2 pixels (0.8 m): a local
  descriptor map ``[D, 76, 76]`` (L2-normalised per cell) and a saliency map ``[76, 76]``;
- global descriptor: GeM over the stride-8 features, a linear layer, L2-normalised.

Used by :mod:`sgvloc.core.encoders.learned` (inference) and :mod:`sgvloc.tools.train`.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from .bev import metres_to_pixel, pixel_to_metres

#: side of the padded input image (151 -> 152, divisible by 8)
INPUT_SIZE = 152
#: output cells per side (2 x 2 pixels each)
CELLS = INPUT_SIZE // 2


# ---------------------------------------------------------------------------------------
# model


def _block(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class GeM(nn.Module):
    """Generalised-mean pooling over H x W with a learned exponent."""

    def __init__(self, p: float = 3.0, eps: float = 1e-6) -> None:
        super().__init__()
        self.p = nn.Parameter(torch.tensor(p))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [B, C, H, W] -> [B, C]
        return x.clamp(min=self.eps).pow(self.p).mean(dim=(2, 3)).pow(1.0 / self.p)


class BEVNet(nn.Module):
    """BEV image -> (global [B, G], local descriptor map [B, D, 76, 76], saliency [B, 76, 76])."""

    def __init__(self, width: int = 32, local_dim: int = 64, global_dim: int = 256) -> None:
        super().__init__()
        w = width
        self.local_dim, self.global_dim, self.width = local_dim, global_dim, width
        self.stem = nn.Sequential(_block(1, w), _block(w, w, 2))  # [B, w, 76, 76]
        self.enc2 = nn.Sequential(_block(w, 2 * w, 2), _block(2 * w, 2 * w))  # 38
        self.enc3 = nn.Sequential(_block(2 * w, 4 * w, 2), _block(4 * w, 4 * w))  # 19
        self.dec2 = _block(6 * w, 2 * w)
        self.dec1 = _block(3 * w, 2 * w)
        self.local_head = nn.Conv2d(2 * w, local_dim, 1)
        self.saliency_head = nn.Conv2d(2 * w, 1, 1)
        self.gem = GeM()
        self.global_head = nn.Linear(4 * w, global_dim)

    def forward(self, img: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``img`` ``[B, 1, 152, 152]`` in [0, 1]."""
        s1 = self.stem(img)  # [B, w, 76, 76]
        s2 = self.enc2(s1)  # [B, 2w, 38, 38]
        s3 = self.enc3(s2)  # [B, 4w, 19, 19]
        d2 = self.dec2(torch.cat([F.interpolate(s3, size=s2.shape[-2:]), s2], dim=1))
        d1 = self.dec1(torch.cat([F.interpolate(d2, size=s1.shape[-2:]), s1], dim=1))
        local = F.normalize(self.local_head(d1), dim=1)  # [B, D, 76, 76]
        saliency = self.saliency_head(d1)[:, 0]  # [B, 76, 76] logits
        g = F.normalize(self.global_head(self.gem(s3)), dim=1)  # [B, G]
        return g, local, saliency

    def global_descriptor(self, img: torch.Tensor) -> torch.Tensor:
        """The global descriptor alone ``[B, G]`` (the encoder half of :meth:`forward`)."""
        s3 = self.enc3(self.enc2(self.stem(img)))
        return F.normalize(self.global_head(self.gem(s3)), dim=1)


def cut_faint(images: np.ndarray, min_grey: int) -> np.ndarray:
    """Zero the pixels darker than ``min_grey`` (uint8 in, uint8 out; a copy if any change).

    The faintest levels of the density image (columns of two or three voxels) are mostly
    ground returns of a tilted or rough-ground sensor and the fringes of objects; they are
    what differs most between LiDARs, so the network neither sees nor describes them.
    """
    images = np.asarray(images)
    if min_grey <= 0:
        return images
    return np.where(images < min_grey, 0, images).astype(np.uint8)


def to_input(images: np.ndarray) -> torch.Tensor:
    """uint8 images ``[B, 151, 151]`` -> float tensor ``[B, 1, 152, 152]`` in [0, 1]."""
    x = torch.from_numpy(np.asarray(images, dtype=np.float32) / 255.0)
    return F.pad(x, (0, INPUT_SIZE - x.shape[-1], 0, INPUT_SIZE - x.shape[-2]))[:, None]


def occupied_cells(images: torch.Tensor) -> torch.Tensor:
    """``[B, 1, 152, 152]`` -> bool ``[B, 76, 76]``: cells with an occupied pixel."""
    return F.max_pool2d(images, 2)[:, 0] > 0


def cell_to_metres(cells_r: np.ndarray, cells_c: np.ndarray) -> np.ndarray:
    """Metric ``(x, y)`` ``[N, 2]`` of output cell centres (cell covers pixels 2i, 2i+1)."""
    return pixel_to_metres(2 * np.asarray(cells_r) + 0.5, 2 * np.asarray(cells_c) + 0.5)


def metres_to_cell(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Output cell ``(rows, cols)`` (int, may be out of range) containing metric points."""
    r, c = metres_to_pixel(xy)
    return np.floor((r + 0.5) / 2).astype(np.int64), np.floor((c + 0.5) / 2).astype(np.int64)
