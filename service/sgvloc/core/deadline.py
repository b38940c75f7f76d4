"""A time limit on one call's work, checked between its steps.

The service gives each localize a deadline (``request_timeout_s`` after the request
arrived); the engine calls :func:`check` between its stages, between RANSAC batches and
between the candidates of registration-based re-ranking, and stops with
:class:`~sgvloc.core.errors.DeadlineExceeded` once it has passed. A localize changes
nothing, so stopping it midway loses nothing. The steps between checks are bounded by
the request limits (keypoints, ``top_k``, RANSAC iterations), so a call overruns its
deadline by at most one step. Without a deadline (the library's default) ``check`` does
nothing.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

from .errors import CallerGone, DeadlineExceeded

_local = threading.local()
#: set when the process shuts down: every call with a deadline stops at its next step
_abort = threading.Event()


@contextmanager
def deadline(at: float | None, gone: threading.Event | None = None) -> Iterator[None]:
    """Run the block with a deadline at ``at`` (``time.monotonic()`` seconds; None: no
    limit), for this thread; ``gone``, once set, stops it too (its caller went away)."""
    previous = getattr(_local, "at", None), getattr(_local, "gone", None)
    _local.at, _local.gone = at, gone
    try:
        yield
    finally:
        _local.at, _local.gone = previous


def check(step: str) -> None:
    """Raise :class:`DeadlineExceeded` if this thread's deadline has passed, or if
    :func:`abort_all` was called while it has one; :class:`CallerGone` once its ``gone``
    event is set."""
    gone = getattr(_local, "gone", None)
    if gone is not None and gone.is_set():
        raise CallerGone(f"the caller went away; stopped at {step}")
    at = getattr(_local, "at", None)
    if at is None:
        return
    if _abort.is_set():
        raise DeadlineExceeded(f"the service is shutting down; stopped at {step}")
    if time.monotonic() > at:
        raise DeadlineExceeded(f"the request ran past its time limit and was stopped at {step}")


def abort_all() -> None:
    """Stop every call that runs with a deadline at its next step (process shutdown)."""
    _abort.set()
