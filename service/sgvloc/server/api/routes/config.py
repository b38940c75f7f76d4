"""The service's configuration as clients may see it: limits and access settings."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request, Response

from sgvloc.about import __version__
from sgvloc.core import cores

from ...maps import MapManager
from ...settings import Settings
from ...store import SharedBackend
from ..auth import KeyRing, KeysError, authorize, principal_of, reload_keys
from ..body import encode
from ..deps import SettingsDep
from ..errors import ApiError
from ..openapi import error_responses
from ..schemas import AuthOut, BatchingOut, ConfigOut, KeysReloaded, LimitsOut, StoreOut

router = APIRouter(prefix="/v1", tags=["service"], dependencies=[Depends(authorize)])


@router.get(
    "/config",
    response_model=ConfigOut,
    operation_id="get_config",
    responses=error_responses(401, 403, common=False),
)
async def get_config(request: Request, settings: SettingsDep) -> Response:
    """Limits (body size, points, batch, top_k, localize admission, queue timeout) and
    access settings in force. Viewer or admin keys; to a key limited to some maps, the
    number of keys and the store's location are not shown (as /metrics, which names
    every map, is refused to it)."""
    ring: KeyRing = request.app.state.keyring
    s = settings
    whole = principal_of(request).maps is None
    return encode(
        request,
        ConfigOut(
            version=__version__,
            limits=LimitsOut(
                max_body_bytes=s.max_body_bytes,
                max_json_body_bytes=s.max_json_body_bytes,
                max_body_memory_bytes=s.body_memory_limit,
                max_points=s.max_points,
                max_keypoints=s.max_keypoints,
                max_batch=s.max_batch,
                max_top_k=s.max_top_k,
                max_import_bytes=s.max_import_bytes,
                max_self_test_keyframes=s.max_self_test_keyframes,
                max_inflight_localize=s.inflight_limit,
                request_timeout_s=s.request_timeout_s,
                retry_after_s=s.retry_after_s,
                header_timeout_s=s.header_timeout_s,
                body_timeout_s=s.body_timeout_s,
                send_timeout_s=s.send_timeout_s,
                workers=s.workers,
                write_workers=s.write_limit,
                threads_per_worker=s.library_threads,
                spare_cores=cores.cores(),
            ),
            auth=AuthOut(
                enabled=ring.enabled,
                keys=len(ring.keys) if whole else None,
                metrics=s.metrics_auth,
                readyz=s.readyz_auth,
            ),
            batching=_batching(),
            store=_store(request, s, whole),
            snapshot_every=s.snapshot_every,
            snapshot_delay_s=s.snapshot_delay_s,
            shutdown_timeout_s=s.shutdown_timeout_s,
        ),
    )


def _store(request: Request, s: Settings, whole: bool) -> StoreOut:
    manager: MapManager = request.app.state.manager
    shared = isinstance(manager.backend, SharedBackend)
    location = manager.backend.describe() if shared else "<data_dir>/maps"  # type: ignore[union-attr]
    return StoreOut(
        kind="postgresql" if shared else "sqlite",
        location=location if whole else None,
        local_features=s.local_features,
        feature_cache=s.feature_cache,
        follow_poll_s=s.follow_poll_s,
        catch_up_wait_s=s.catch_up_wait_s,
        caught_up_failures=manager.follow_errors,
    )


def _batching() -> BatchingOut:
    from sgvloc.core import batching

    b = batching.installed()
    if b is None:
        return BatchingOut(enabled=False, wait_ms=0.0, max_size=1)
    return BatchingOut(enabled=b.enabled, wait_ms=b.wait_ms, max_size=b.max_size)


@router.post(
    "/keys/reload",
    response_model=KeysReloaded,
    operation_id="reload_keys",
    responses=error_responses(401, 403, 409, 422, common=False),
)
async def reload_keys_route(request: Request, settings: SettingsDep) -> Response:
    """Read the keys file again (as SIGHUP does) and apply it at once: added keys work,
    revoked keys stop working. A file that cannot be used is a 422 and the previous keys
    stay in force. Admin keys only; 409 in development mode (there are no keys)."""
    if settings.dev:
        raise ApiError(409, "conflict", "development mode: authentication is off, no keys")
    try:
        ring = reload_keys(request.app)
    except KeysError as exc:
        raise ApiError(
            422, "invalid_input", f"keys file not reloaded, the previous keys stay: {exc}"
        ) from None
    by_role: dict[str, int] = {}
    for key in ring.keys:
        by_role[key.principal.role] = by_role.get(key.principal.role, 0) + 1
    return encode(request, KeysReloaded(keys=len(ring.keys), by_role=by_role))
