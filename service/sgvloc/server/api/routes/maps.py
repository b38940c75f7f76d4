"""Maps: create, list, describe, change settings, delete."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request, Response

from sgvloc.core.confidence import shipped_calibration

from ...maps import MapHandle
from ..auth import authorize, principal_of
from ..body import encode
from ..deps import BodyDep, ManagerDep, MapName, SettingsDep, WorkerDep
from ..errors import ApiError
from ..openapi import body_doc, error_responses
from ..schemas import (
    CalibrationInfo,
    EncoderInfo,
    MapCreate,
    MapInfo,
    MapList,
    MapPatch,
    limits,
    parse_calibration,
)

router = APIRouter(prefix="/v1/maps", tags=["maps"], dependencies=[Depends(authorize)])


def map_info(handle: MapHandle) -> MapInfo:
    """The public description of a loaded map."""
    enc = handle.encoder
    spec = handle.record.encoder_spec
    cfg = handle.record.localizer_config
    cal = handle.localizer.calibration
    return MapInfo(
        name=handle.name,
        version=handle.version,
        keyframes=handle.num_keyframes,
        encoder=EncoderInfo(
            kind=spec.kind,
            name=enc.identity.name,
            fingerprint=enc.identity.fingerprint,
            global_dim=enc.global_dim,
            local_dim=enc.local_dim,
            spec=spec.model_dump(),
        ),
        retrieval=cfg.retrieval,
        localizer=cfg.model_dump(),
        index_kind=handle.localizer.index.kind,
        keep_clouds=handle.record.keep_clouds,
        created_at=handle.record.created_at,
        calibration=CalibrationInfo(
            name=cal.name, fingerprint=cal.fingerprint, encoder_kind=cal.encoder_kind
        ),
        settings_version=handle.record.settings_version,
        settings_updated_at=handle.record.settings_updated_at,
    )


@router.post(
    "",
    status_code=201,
    response_model=MapInfo,
    operation_id="create_map",
    openapi_extra=body_doc(MapCreate),
    responses=error_responses(400, 409, 413, 415, 422),
)
async def create_map(
    request: Request, body: BodyDep, manager: ManagerDep, settings: SettingsDep, worker: WorkerDep
) -> Response:
    """Create an empty map with an encoder and localizer settings."""

    caller = principal_of(request)

    def work() -> MapInfo:
        req = MapCreate.model_validate(body.decode(), context=limits(settings))
        if not caller.may_use_map(req.name):
            raise ApiError(403, "forbidden", f"this key may not use map {req.name!r}", "name")
        handle = manager.create(
            req.name,
            req.encoder,
            req.localizer_config(),
            keep_clouds=req.keep_clouds,
            calibration=parse_calibration(req.calibration, "calibration"),
        )
        return map_info(handle)

    return encode(request, await worker.run(work), 201)


@router.get("", response_model=MapList, operation_id="list_maps", responses=error_responses())
async def list_maps(request: Request, manager: ManagerDep) -> Response:
    """List the loaded maps (those the caller's key may use)."""
    caller = principal_of(request)
    handles = [h for h in manager.list() if caller.may_use_map(h.name)]
    return encode(request, MapList(maps=[map_info(h) for h in handles]))


@router.get(
    "/{map}", response_model=MapInfo, operation_id="get_map", responses=error_responses(404)
)
async def get_map(request: Request, map_name: MapName, manager: ManagerDep) -> Response:
    """Describe one map."""
    return encode(request, map_info(manager.get(map_name)))


@router.patch(
    "/{map}",
    response_model=MapInfo,
    operation_id="update_map",
    openapi_extra=body_doc(MapPatch),
    responses=error_responses(400, 404, 413, 415, 422),
)
async def update_map(
    request: Request,
    map_name: MapName,
    body: BodyDep,
    manager: ManagerDep,
    settings: SettingsDep,
    worker: WorkerDep,
) -> Response:
    """Change a map's localizer settings or calibration (its keyframes and version stay)."""

    def work() -> MapInfo:
        handle = manager.get(map_name)  # 404 before the body is judged
        req = MapPatch.model_validate(body.decode(), context=limits(settings))
        cal = req.calibration
        calibration = (
            shipped_calibration(handle.record.encoder_spec.kind)
            if cal == "shipped"
            else parse_calibration(cal, "calibration")
        )
        return map_info(manager.update_settings(map_name, req.localizer, calibration))

    return encode(request, await worker.run(work))


@router.delete(
    "/{map}",
    status_code=204,
    response_class=Response,
    operation_id="delete_map",
    responses=error_responses(404),
)
async def delete_map(map_name: MapName, manager: ManagerDep, worker: WorkerDep) -> Response:
    """Delete a map with all its keyframes."""
    await worker.run(lambda: manager.delete(map_name))
    return Response(status_code=204)
