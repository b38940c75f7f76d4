"""sgvloc: LiDAR localization in a prior map of keyframes.

Retrieve the top-k keyframes by global descriptor (FAISS), re-rank them with Spectral
Geometric Verification (SpectralGV), and estimate the pose against the re-ranked top-1
with RANSAC. The engine lives in :mod:`sgvloc.core`; importing this package is cheap
(no torch, FAISS or Open3D until a core module is used).
"""

from .about import __version__

__all__ = ["__version__"]
