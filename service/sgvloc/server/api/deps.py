"""Shared route dependencies as ``Annotated`` aliases (all cheap: ``async``, on the loop)."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import AsyncIterator, Callable
from typing import Annotated, Any, TypeVar

import anyio
import anyio.to_thread
from fastapi import Depends, Path, Request
from pydantic import BeforeValidator

from sgvloc.core import cores
from sgvloc.core.deadline import deadline
from sgvloc.core.errors import CallerGone, NotFoundError

from ..maps import MapHandle, MapManager
from ..metrics import Metrics
from ..settings import Settings
from .body import BodyHold, RawBody, read_body
from .errors import ApiError

T = TypeVar("T")

#: the pause between two reads of a request's messages while waiting for its client to
#: disconnect, should one arrive that is not the disconnect (s)
DISCONNECT_POLL_S = 0.1


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


async def get_manager(request: Request) -> MapManager:
    """The map manager, once every map is loaded (503 ``unavailable`` before)."""
    manager: MapManager = request.app.state.manager
    if not manager.loaded.is_set():
        settings: Settings = request.app.state.settings
        raise busy(503, "unavailable", "maps are still loading; retry shortly", settings)
    return manager


def busy(status: int, code: str, message: str, settings: Settings) -> ApiError:
    """A 429/503 answer with ``Retry-After``."""
    return ApiError(status, code, message, headers={"Retry-After": str(settings.retry_after_s)})


def make_pools(state: Any, settings: Settings) -> None:
    """The worker tokens on ``app.state``: ``cpu_limiter`` (``workers``), the share of
    them that map changes and long jobs may hold (``write_limiter``, ``write_workers``)
    and the threads that run the work (``thread_limiter``)."""
    state.cpu_limiter = anyio.CapacityLimiter(settings.workers)
    state.write_limiter = anyio.CapacityLimiter(settings.write_limit)
    state.thread_limiter = anyio.CapacityLimiter(settings.workers)


class Worker:
    """Runs CPU work (decoding, encoding, FAISS, re-ranking, pose, SQLite) in the
    service's worker threads (``settings.workers`` at once), never on the event loop.

    A request waits at most ``request_timeout_s`` for a free worker; past that it is
    answered 503 ``queue_timeout`` with ``Retry-After`` (it never started, so nothing
    happened). Work that has started runs to its end: a half-done insert is never cut.
    With a ``gate`` (map changes and long jobs: ``write_workers``) the work first takes
    one of the gate's tokens, so that such work never holds every worker.
    """

    def __init__(
        self,
        limiter: anyio.CapacityLimiter,
        threads: anyio.CapacityLimiter,
        settings: Settings,
        metrics: Metrics,
        gate: anyio.CapacityLimiter | None = None,
    ) -> None:
        self._limiter = limiter
        self._settings = settings
        self._threads = threads
        self._metrics = metrics
        self._gate = gate

    async def run(
        self,
        fn: Callable[[], T],
        *,
        deadline_at: float | None = None,
        request: Request | None = None,
    ) -> T:
        """Run ``fn`` on a worker thread. With ``deadline_at`` (``time.monotonic()``
        seconds) the wait for a worker ends there too, and the engine stops the work at
        its next step once it has passed (503 ``deadline_exceeded``). With ``request``
        (whose body has been read; work that changes nothing), a client that closes its
        connection stops the wait at once and the work at its next step
        (:class:`~sgvloc.core.errors.CallerGone`, logged as 499 ``caller_gone``): a
        client that gave up, say after its read timeout and before resending, holds no
        worker for an answer nobody reads."""
        if request is None:
            return await self._run(fn, deadline_at, None, anyio.CancelScope())
        gone = threading.Event()
        waiting = anyio.CancelScope()

        async def watch() -> None:
            # one receive that waits for the disconnect (the body is read already):
            # polling would resume reading the socket each time and buffer whatever a
            # client pipelines behind this request
            while (await request.receive()).get("type") != "http.disconnect":
                await anyio.sleep(DISCONNECT_POLL_S)  # not expected: never spin
            gone.set()
            waiting.cancel()

        outcome: dict[str, Any] = {}
        async with anyio.create_task_group() as tg:
            tg.start_soon(watch)
            try:
                outcome["value"] = await self._run(fn, deadline_at, gone, waiting)
            except Exception as exc:  # raised below, not as a task group's ExceptionGroup
                outcome["error"] = exc
            finally:
                tg.cancel_scope.cancel()
        if "error" in outcome:
            raise outcome["error"]
        return outcome["value"]

    async def _run(
        self,
        fn: Callable[[], T],
        deadline_at: float | None,
        gone: threading.Event | None,
        waiting: anyio.CancelScope,
    ) -> T:
        timeout = self._settings.request_timeout_s
        if deadline_at is not None:
            timeout = max(0.0, min(timeout, deadline_at - time.monotonic()))
        gated = acquired = False
        waited_from = time.monotonic()
        self._metrics.queue_waiting.inc()
        try:
            with waiting, anyio.move_on_after(timeout):
                if self._gate is not None:
                    await self._gate.acquire()
                    gated = True
                await self._limiter.acquire()
                acquired = True
        finally:  # also when the client went away while waiting
            self._metrics.queue_waiting.dec()
            self._metrics.queue_wait.observe(time.monotonic() - waited_from)
            if gated and not acquired:
                self._gate.release()  # type: ignore[union-attr]
        if not acquired and gone is not None and gone.is_set():
            raise CallerGone("the caller went away while waiting for a worker")
        if not acquired:
            which = "worker" if gated or self._gate is None else "worker for map changes"
            limit = "" if which == "worker" else f" (write_workers={self._settings.write_limit})"
            raise busy(
                503,
                "queue_timeout",
                f"no {which} was free within request_timeout_s="
                f"{self._settings.request_timeout_s:g} s{limit}; retry later",
                self._settings,
            )
        try:
            # the token taken above is the bound; ``threads`` (as many) only keeps the
            # work off anyio's default pool of 40
            def limited() -> T:
                with cores.busy(), deadline(deadline_at, gone):
                    return fn()

            return await anyio.to_thread.run_sync(limited, limiter=self._threads)
        finally:
            self._limiter.release()
            if self._gate is not None:
                self._gate.release()


async def served_map(manager: MapManager, name: str) -> MapHandle:
    """``manager.get(name)``; on a shared store a map another replica made since this one
    last caught up is loaded first (off the event loop) rather than answered 404."""
    try:
        return manager.get(name)
    except NotFoundError:
        if not manager.shared:
            raise
    return await anyio.to_thread.run_sync(lambda: manager.get(name, load=True))


async def get_worker(request: Request) -> Worker:
    """A worker for localizations and reads."""
    state = request.app.state
    return Worker(state.cpu_limiter, state.thread_limiter, state.settings, state.metrics)


async def get_write_worker(request: Request) -> Worker:
    """A worker for map changes and long jobs: at most ``write_workers`` run at once."""
    state = request.app.state
    return Worker(
        state.cpu_limiter,
        state.thread_limiter,
        state.settings,
        state.metrics,
        gate=state.write_limiter,
    )


class Admission:
    """Counts localize requests in flight (admitted, not answered yet): at most
    ``max_inflight_localize``; the next one is answered 429 at once instead of queueing
    without bound. Used on the event loop only, so a plain counter is enough."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.inflight = 0


@contextlib.asynccontextmanager
async def localize_slot(request: Request) -> AsyncIterator[None]:
    """Hold a localize slot for the request's work, or 429 at once when all are taken.
    Taken after the body arrived and after any catch-up wait (``min_map_version``), so
    that neither a slow upload nor a wait for another replica's write holds one."""
    admission: Admission = request.app.state.admission
    settings: Settings = request.app.state.settings
    if admission.inflight >= admission.limit:
        raise busy(
            429,
            "overloaded",
            f"{admission.inflight} localize requests are in flight (max_inflight_localize="
            f"{admission.limit}); retry later",
            settings,
        )
    admission.inflight += 1
    try:
        yield
    finally:
        admission.inflight -= 1


async def get_body(
    request: Request, settings: Annotated[Settings, Depends(get_settings)]
) -> AsyncIterator[RawBody]:
    """The raw request body, within ``max_body_bytes`` (``max_json_body_bytes`` for JSON;
    413) and ``body_timeout_s`` (408) and of a known type (415); its lists hold at most
    as many items as the largest field may (``max_points``, ``max_batch``,
    ``max_keypoints``). Its bytes count against ``max_body_memory_bytes`` (503 when the
    bodies of other requests fill it) until the request is done."""
    hold = BodyHold(request.app.state.body_budget)
    try:
        yield await read_body(
            request,
            settings.max_body_bytes,
            settings.body_timeout_s,
            json_limit=settings.max_json_body_bytes,
            max_list_len=max(
                settings.max_points, settings.max_batch, settings.max_keypoints, 65536
            ),
            max_items=settings.max_batch,
            hold=hold,
        )
    finally:
        hold.close()


SettingsDep = Annotated[Settings, Depends(get_settings)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
ManagerDep = Annotated[MapManager, Depends(get_manager)]
WorkerDep = Annotated[Worker, Depends(get_worker)]
WriteWorkerDep = Annotated[Worker, Depends(get_write_worker)]
# released when the route returns, before its answer is sent (a slow reader holds none)
BodyDep = Annotated[RawBody, Depends(get_body, scope="function")]
MapName = Annotated[str, Path(alias="map", description="map name")]


def _digits(value: Any) -> Any:
    """A keyframe id in a path is decimal digits (not ``+1``, ``1_0`` or ``1.0``)."""
    if isinstance(value, str) and not (value.isascii() and value.isdigit()):
        raise ValueError("must be a keyframe id: decimal digits only")
    return value


KeyframeId = Annotated[
    int,
    Path(alias="id", ge=0, le=2**63 - 1, description="keyframe id"),
    BeforeValidator(_digits),
]
