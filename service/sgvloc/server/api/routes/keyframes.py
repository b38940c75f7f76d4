"""Keyframes: bulk insert (all-or-nothing, idempotent keys), read, delete."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request, Response

from ..auth import authorize
from ..body import encode
from ..deps import BodyDep, KeyframeId, ManagerDep, MapName, SettingsDep, WorkerDep
from ..openapi import body_doc, error_responses
from ..schemas import InsertOut, KeyframeBatch, KeyframeDeleted, KeyframeOut, limits

router = APIRouter(
    prefix="/v1/maps/{map}/keyframes", tags=["keyframes"], dependencies=[Depends(authorize)]
)


@router.post(
    "",
    status_code=201,
    response_model=InsertOut,
    operation_id="insert_keyframes",
    openapi_extra=body_doc(KeyframeBatch),
    responses=error_responses(400, 404, 408, 409, 413, 415, 422),
)
async def insert_keyframes(
    request: Request,
    map_name: MapName,
    body: BodyDep,
    manager: ManagerDep,
    settings: SettingsDep,
    worker: WorkerDep,
) -> Response:
    """Insert keyframes: all or none; a known key returns its id with created=false."""

    def work() -> InsertOut:
        manager.get(map_name)  # 404 before decoding a large body for nothing
        req = KeyframeBatch.model_validate(body.decode(), context=limits(settings))
        result = manager.insert(map_name, [kf.to_input() for kf in req.keyframes])
        return InsertOut(ids=result.ids, created=result.created, map_version=result.map_version)

    return encode(request, await worker.run(work), 201)


@router.get(
    "/{id}",
    response_model=KeyframeOut,
    operation_id="get_keyframe",
    responses=error_responses(404),
)
async def get_keyframe(
    request: Request,
    map_name: MapName,
    keyframe_id: KeyframeId,
    manager: ManagerDep,
    worker: WorkerDep,
) -> Response:
    """Read one keyframe's pose and metadata."""

    def work() -> KeyframeOut:
        row = manager.get_keyframe(map_name, keyframe_id)
        return KeyframeOut(
            id=row.id,
            key=row.key,
            T_map_sensor=row.T_map_sensor.tolist(),
            metadata=row.metadata,
            num_keypoints=int(row.keypoints.shape[0]),
            created_at=row.created_at,
        )

    return encode(request, await worker.run(work))


@router.delete(
    "/{id}",
    response_model=KeyframeDeleted,
    operation_id="delete_keyframe",
    responses=error_responses(404),
)
async def delete_keyframe(
    request: Request,
    map_name: MapName,
    keyframe_id: KeyframeId,
    manager: ManagerDep,
    worker: WorkerDep,
) -> Response:
    """Delete one keyframe."""
    version = await worker.run(lambda: manager.delete_keyframe(map_name, keyframe_id))
    return encode(request, KeyframeDeleted(deleted=keyframe_id, map_version=version))
