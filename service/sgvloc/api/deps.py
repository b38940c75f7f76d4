"""Shared route dependencies as ``Annotated`` aliases (all cheap: ``async``, on the loop)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, TypeVar

import anyio
import anyio.to_thread
from fastapi import Depends, Path, Request

from ..maps import MapManager
from ..metrics import Metrics
from ..settings import Settings
from .body import RawBody, read_body
from .errors import ApiError

T = TypeVar("T")


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


async def get_manager(request: Request) -> MapManager:
    """The map manager, once every map is loaded (503 ``unavailable`` before)."""
    manager: MapManager = request.app.state.manager
    if not manager.loaded.is_set():
        raise ApiError(503, "unavailable", "maps are still loading; retry shortly")
    return manager


class Worker:
    """Runs CPU work (decoding, encoding, FAISS, re-ranking, pose, SQLite) in the
    service's worker threads (``settings.workers`` at once), never on the event loop."""

    def __init__(self, limiter: anyio.CapacityLimiter) -> None:
        self._limiter = limiter

    async def run(self, fn: Callable[[], T]) -> T:
        return await anyio.to_thread.run_sync(fn, limiter=self._limiter)


async def get_worker(request: Request) -> Worker:
    return Worker(request.app.state.cpu_limiter)


async def get_body(
    request: Request, settings: Annotated[Settings, Depends(get_settings)]
) -> RawBody:
    """The raw request body, within ``max_body_bytes`` (413) and of a known type (415)."""
    return await read_body(request, settings.max_body_bytes)


SettingsDep = Annotated[Settings, Depends(get_settings)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
ManagerDep = Annotated[MapManager, Depends(get_manager)]
WorkerDep = Annotated[Worker, Depends(get_worker)]
BodyDep = Annotated[RawBody, Depends(get_body)]
MapName = Annotated[str, Path(alias="map", description="map name")]
KeyframeId = Annotated[int, Path(alias="id", description="keyframe id")]
