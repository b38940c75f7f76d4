"""Dynamic batching: the network forwards and the SpectralGV scoring of concurrent
localizations, run as one batch each.

A localization runs on its own thread from start to end. With batching on, the two
stages that gain from a batch hand their input to a :class:`MicroBatcher` instead of
running it: the first caller of a stage becomes the batch's leader and waits up to
``wait_ms`` for other callers of the same stage and kind (the same network weights and
runtime; the same SGV settings), at most ``max_size`` in all, then runs them as one call
(the encoder's forward over the stacked images; one SGV kernel call over every (query,
candidate) pair, padded to a common size), and every caller continues with its own
slice on its own thread (keypoint selection, RANSAC, ICP, the verdict: in parallel).

The leader waits only while other localizations are under way that have not reached
this stage yet and so could still join (:func:`localizing` counts them, per stage): a
lone request never waits, nor does one whose peers are all past the stage. With ``wait_ms = 0``
nothing is batched and every stage runs exactly as without this module. Batched and
unbatched answers are the same: ONNX Runtime's and the numba kernel's results do not
depend on the batch around them (tested), and requests for different maps share a batch
whenever their network or SGV settings are the same.

On CPU a batch of images is no cheaper per image than one image (measured by
``sgvloc bench --only http --batch-wait-ms``), so batching is off by default there and
on (2 ms) when CUDA is present.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Hashable, Iterator
from dataclasses import dataclass, field
from typing import Any

#: wait used when the setting is "auto" and CUDA is present
CUDA_WAIT_MS = 2.0
#: the stages that batch, in the order a localization reaches them
STAGES = ("forward", "sgv")


@dataclass
class _Batch:
    items: list[Any] = field(default_factory=list)
    results: list[Any] | None = None
    error: BaseException | None = None
    done: threading.Event = field(default_factory=threading.Event)


class MicroBatcher:
    """Collects the calls of concurrent threads per key and runs each group as one.

    ``run(key, item, fn)`` returns ``fn(items)[i]`` for this caller's ``item``, where
    ``fn`` maps a list of items to a list of results of the same length. Thread-safe.
    ``observe(stage, size, wait_s)`` is called by each leader (metrics).
    """

    def __init__(
        self,
        wait_ms: float,
        max_size: int,
        observe: Callable[[str, int, float], None] | None = None,
    ) -> None:
        if wait_ms < 0 or max_size < 1:
            raise ValueError("wait_ms must be >= 0 and max_size >= 1")
        self.wait_ms = float(wait_ms)
        self.max_size = int(max_size)
        self._observe = observe
        self._cond = threading.Condition()
        self._open: dict[Hashable, _Batch] = {}
        #: per stage: localizations under way that have not reached it yet
        self._ahead: dict[str, int] = {stage: 0 for stage in STAGES}
        self._reached = threading.local()  # this thread's stages reached in its localization
        #: per stage: batches run, items in them, the largest batch, and the batches whose
        #: leader waited the whole ``wait_ms`` for peers that had not arrived
        self.stats: dict[str, dict[str, int]] = {}

    @property
    def enabled(self) -> bool:
        return self.wait_ms > 0 and self.max_size > 1

    @contextlib.contextmanager
    def localizing(self) -> Iterator[None]:
        """Count this thread's localization as under way: a possible member of the next
        batch of every stage until it reaches that stage or ends."""
        if getattr(self._reached, "stages", None) is not None:  # nested: counted already
            yield
            return
        with self._cond:
            for stage in STAGES:
                self._ahead[stage] += 1
        self._reached.stages = set()
        try:
            yield
        finally:
            with self._cond:
                for stage in STAGES:
                    if stage not in self._reached.stages:
                        self._ahead[stage] -= 1
                self._cond.notify_all()
            self._reached.stages = None

    def run(
        self, stage: str, key: Hashable, item: Any, fn: Callable[[list[Any]], list[Any]]
    ) -> Any:
        if not self.enabled:
            return fn([item])[0]
        key = (stage, key)
        reached = getattr(self._reached, "stages", None)
        with self._cond:
            if reached is not None and stage in self._ahead and stage not in reached:
                reached.add(stage)
                self._ahead[stage] -= 1
            batch = self._open.get(key)
            leader = batch is None
            if leader:
                batch = self._open[key] = _Batch()
            index = len(batch.items)
            batch.items.append(item)
            if len(batch.items) >= self.max_size:
                del self._open[key]  # full: the next caller starts a new batch
            self._cond.notify_all()
        if not leader:
            batch.done.wait()
        else:
            t0 = time.perf_counter()
            deadline = t0 + self.wait_ms / 1e3
            with self._cond:
                waited_out = False  # the wait ended by its deadline, peers still to come
                while self._open.get(key) is batch and self._ahead.get(stage, 0) > 0:
                    left = deadline - time.perf_counter()
                    if left <= 0:
                        waited_out = True
                        break
                    self._cond.wait(left)
                if self._open.get(key) is batch:
                    del self._open[key]
            waited = time.perf_counter() - t0
            try:
                batch.results = fn(batch.items)
                if len(batch.results) != len(batch.items):
                    raise RuntimeError("a batched stage did not return one result per item")
            except BaseException as exc:  # every member sees the failure
                batch.error = exc
            finally:
                self._record(stage, len(batch.items), waited, waited_out)
                batch.done.set()
        if batch.error is not None:
            raise batch.error
        assert batch.results is not None
        return batch.results[index]

    def _record(self, stage: str, size: int, waited: float, waited_out: bool) -> None:
        with self._cond:
            s = self.stats.setdefault(
                stage, {"batches": 0, "items": 0, "largest": 0, "waited_out": 0}
            )
            s["batches"] += 1
            s["items"] += size
            s["largest"] = max(s["largest"], size)
            s["waited_out"] += waited_out
        if self._observe is not None:
            self._observe(stage, size, waited)


_current: MicroBatcher | None = None


def configure(wait_ms: float | None, max_size: int, observe=None) -> MicroBatcher:
    """Install the process's batcher: ``wait_ms`` None = auto (``CUDA_WAIT_MS`` when CUDA
    is present, else 0 = off). Returns it."""
    global _current
    if wait_ms is None:
        import torch

        wait_ms = CUDA_WAIT_MS if torch.cuda.is_available() else 0.0
    _current = MicroBatcher(wait_ms, max_size, observe)
    return _current


def current() -> MicroBatcher | None:
    """The installed batcher when it batches, else None (every stage runs directly)."""
    b = _current
    return b if b is not None and b.enabled else None


def installed() -> MicroBatcher | None:
    """The installed batcher, batching or not (None before :func:`configure`)."""
    return _current


def reset() -> None:
    """Remove the installed batcher (nothing is batched)."""
    global _current
    _current = None


@contextlib.contextmanager
def localizing() -> Iterator[None]:
    """Mark one localization under way for the installed batcher (no-op without one)."""
    b = current()
    if b is None:
        yield
    else:
        with b.localizing():
            yield
