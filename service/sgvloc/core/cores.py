"""Spare cores: how many threads one localization may use right now.

A service on ``C`` cores runs several localizations at once, one per worker thread, and
holds every numeric library to one thread per worker (:mod:`sgvloc.server.threads`) so
that busy workers do not preempt each other. Under light load that leaves cores idle:
one localization alone on two cores uses one. So the service declares its cores here
(:func:`set_cores`), its worker threads count themselves while they run a request's CPU
work (:func:`busy`), and the stages that can split their work without changing a bit of
the answer ask :func:`threads` how many threads they may take: ``C // busy workers``,
at least 1. Today those are the network forward in ONNX Runtime (its kernels split the
output, not the sums: the same outputs at any thread count) and ICP with its fitness
pass (:mod:`sgvloc.core.icp_numba`: sums over fixed chunks of the points, added in chunk
order, so that the threads only decide who computes which chunk; :func:`split`), plus
small_gicp's fitness pass for maps that still use it (one query per point). small_gicp's
own parallel registration is not used: its sums vary in order, and the same request
must get the same pose.

Outside the service (evaluation, tools, tests) nothing calls :func:`set_cores`, so every
stage keeps one thread.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

_lock = threading.Lock()
_cores = 1
_busy = 0
_inside = threading.local()
_pool: ThreadPoolExecutor | None = None
_pool_size = 0


def set_cores(n: int) -> None:
    """Let localizations share ``n`` cores (the service: its usable CPUs; 1 = off)."""
    global _cores
    if n < 1:
        raise ValueError(f"cores must be >= 1, got {n}")
    with _lock:
        _cores = n


def cores() -> int:
    """The cores declared with :func:`set_cores` (1 unless the service declared more)."""
    return _cores


def threads() -> int:
    """Threads a stage may use now: the declared cores divided among the busy workers,
    at least 1."""
    return max(1, _cores // max(1, _busy))


@contextmanager
def busy() -> Iterator[None]:
    """Count the calling thread as busy with CPU work (once, however nested)."""
    global _busy
    if getattr(_inside, "on", False):
        yield
        return
    with _lock:
        _busy += 1
    _inside.on = True
    try:
        yield
    finally:
        _inside.on = False
        with _lock:
            _busy -= 1


def split(fn: Callable[[T], R], items: Sequence[T]) -> list[R]:
    """``[fn(item) for item in items]``, in order, on up to :func:`threads` threads: the
    caller's and helpers of a shared pool, each taking a contiguous run of the items.
    Helps only where ``fn`` releases the GIL (compiled kernels)."""
    n = min(threads(), len(items))
    if n <= 1:
        return [fn(item) for item in items]
    global _pool, _pool_size
    with _lock:
        if _pool is None or _pool_size < _cores - 1:
            _pool_size = _cores - 1
            _pool = ThreadPoolExecutor(max_workers=_pool_size, thread_name_prefix="sgvloc-core")
        pool = _pool
    runs = [items[len(items) * k // n : len(items) * (k + 1) // n] for k in range(n)]
    helpers = [pool.submit(lambda run=run: [fn(item) for item in run]) for run in runs[1:]]
    out = [fn(item) for item in runs[0]]
    for helper in helpers:
        out.extend(helper.result())
    return out
