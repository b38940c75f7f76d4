"""Open3D, loaded once and held to the process's thread policy.

Open3D runs its parallel loops on oneAPI TBB, which reads none of the variables the
thread policy sets (``OMP_NUM_THREADS`` and the like, :mod:`sgvloc.server.threads`):
left alone, FPFH and normal estimation take every core whatever ``--threads`` or
``threads_per_worker`` say. Open3D 0.20 and later take a process-wide limit, set here
to ``OMP_NUM_THREADS`` when the policy has set it.
"""

from __future__ import annotations

import functools
import os
from types import ModuleType


@functools.cache
def open3d() -> ModuleType:
    """The ``open3d`` module, its threads limited to ``OMP_NUM_THREADS`` (when set)."""
    import open3d as o3d

    limit = getattr(o3d.utility, "set_max_threads", None)  # Open3D >= 0.20
    threads = os.environ.get("OMP_NUM_THREADS", "")
    if limit is not None and threads.isdigit() and int(threads) >= 1:
        limit(int(threads))
    return o3d
