"""Small helpers shared by the engine's tests (importable: pytest puts this folder on
``sys.path`` when it imports the test modules here)."""

from __future__ import annotations

import numpy as np


def planar_pose(x: float = 0.0, y: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    """A 4x4 pose at ``(x, y, 0)`` turned ``yaw_deg`` about z."""
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:2, 3] = x, y
    return T
