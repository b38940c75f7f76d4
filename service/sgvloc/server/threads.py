"""Thread counts of the numeric libraries in a service process, set once at start-up.

The service runs CPU work on ``workers`` threads at once. Each library called inside a
request (Open3D and FAISS through OpenMP, NumPy and SciPy through OpenBLAS, numba, torch)
brings its own pool of one thread per core, so by default two workers on two cores run
four or more busy threads: they preempt each other, and a parallel region waits for its
slowest, descheduled thread. Every ``sgvloc`` command therefore gives each library a
fixed number of threads through the usual environment variables, before any of them is
loaded: ``serve`` ``threads_per_worker`` (default: usable cores // workers), the offline
commands ``--threads`` (default 1: one loop of small calls into several libraries, whose
idle OpenMP pools would spin on the cores the next call needs; ``train``: every core, one
large torch job at a time).
"""

from __future__ import annotations

import logging
import os
import sys

log = logging.getLogger(__name__)

#: the variables the libraries read when they are loaded
ENV_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")
_LIBRARIES = ("numpy", "scipy", "torch", "open3d", "faiss", "numba")


def limit_library_threads(n: int, *, force: bool = False) -> dict[str, str]:
    """Give every numeric library ``n`` threads, except where the environment already
    names a count (the operator's choice wins) unless ``force``; returns the variables in
    force.

    Must run before the libraries are imported: OpenMP and OpenBLAS read their
    environment once, when loaded. Once one of them is loaded (a command called inside a
    Python program that already uses them) nothing is changed and a warning says so.
    Raises ``ValueError`` if ``n < 1``.
    """
    if n < 1:
        raise ValueError(f"thread count must be >= 1, got {n}")
    loaded = [m for m in _LIBRARIES if sys.modules.get(m) is not None]
    if loaded:
        # too late to apply, and numba refuses to run once its setting differs from the
        # thread count it launched with: leave the environment as it is
        log.warning("thread limits not applied: %s already loaded", ", ".join(loaded))
        return {var: os.environ.get(var, "") for var in ENV_VARS}
    for var in ENV_VARS:
        if force:
            os.environ[var] = str(n)
        else:
            os.environ.setdefault(var, str(n))
    return {var: os.environ[var] for var in ENV_VARS}


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask, e.g. a container's cpuset)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        return os.cpu_count() or 1
