"""Probes and metrics: liveness, readiness, Prometheus text."""

from __future__ import annotations

import anyio.to_thread
from fastapi import APIRouter, Depends, Request, Response

from ...maps import MapManager
from ..auth import ANONYMOUS, authorize, key_holder, principal_of
from ..body import encode
from ..deps import MetricsDep
from ..errors import ApiError
from ..openapi import error_responses
from ..schemas import Health, Ready

router = APIRouter(tags=["probes"], dependencies=[Depends(authorize)])


@router.get("/healthz", response_model=Health, operation_id="healthz")
async def healthz(request: Request) -> Response:
    """The process is alive (always open: no key needed)."""
    return encode(request, Health())


@router.get(
    "/readyz",
    response_model=Ready,
    operation_id="readyz",
    responses={
        503: {"model": Ready, "description": "maps still loading, or some failed to load"},
        **error_responses(401, 403, common=False),
    },
)
async def readyz(request: Request) -> Response:
    """Ready (200) once every map is loaded; 503 while loading, and 503 ``degraded``
    while a map folder failed to load (counted in ``failed_maps`` and listed with the
    reasons under ``failed`` for a caller with a key; fix it and POST
    ``/v1/maps/{map}/reload``, or remove the folder). ``store_reachable`` says whether a
    shared store answers. Open, or viewer/admin keys only, as the ``readyz_auth`` setting
    says."""
    manager: MapManager = request.app.state.manager
    store = manager.store_reachable
    if manager.load_error is not None:  # the process stops (its log says why)
        request.state.error_code = "failed"
        return encode(request, Ready(status="failed", maps=0, store_reachable=store), 503)
    if not manager.loaded.is_set():
        request.state.error_code = "loading"  # for the access line
        return encode(request, Ready(status="loading", maps=0, store_reachable=store), 503)
    maps, failed = len(manager.list()), dict(manager.failed)
    if not failed:
        return encode(request, Ready(status="ready", maps=maps, store_reachable=store))
    caller = principal_of(request)
    if caller is ANONYMOUS:  # an open probe: names and reasons only for a key's holder
        caller = key_holder(request) or ANONYMOUS
    request.state.error_code = "degraded"
    shown = {} if caller is ANONYMOUS else {
        name: why for name, why in failed.items() if caller.may_use_map(name)
    }  # fmt: skip
    return encode(
        request,
        Ready(
            status="degraded",
            maps=maps,
            failed=shown,
            failed_maps=len(failed),
            store_reachable=store,
        ),
        503,
    )


@router.get(
    "/metrics",
    response_class=Response,
    operation_id="metrics",
    responses={
        200: {"content": {"text/plain": {}}, "description": "Prometheus text format"},
        **error_responses(401, 403, common=False),
    },
)
async def metrics_text(request: Request, metrics: MetricsDep) -> Response:
    """Prometheus metrics of this process. Open, or viewer/admin keys only, as the
    ``metrics_auth`` setting says; a key limited to some maps may not read them (they
    name every map and key)."""
    caller = principal_of(request)
    if caller.maps is not None and caller is not ANONYMOUS:
        raise ApiError(
            403,
            "forbidden",
            "the metrics cover every map and key: a key limited to some maps may not read them",
        )
    # off the event loop: with hundreds of maps the text takes a good part of a second
    data, content_type = await anyio.to_thread.run_sync(metrics.render)
    return Response(data, media_type=content_type)
