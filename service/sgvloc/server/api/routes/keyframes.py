"""Keyframes: bulk insert (all-or-nothing, idempotent keys), list and bulk delete by
filters, read, delete."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request, Response

from ...store import KeyframeFilter
from ..auth import authorize
from ..body import encode
from ..deps import BodyDep, KeyframeId, ManagerDep, MapName, SettingsDep, WorkerDep, WriteWorkerDep
from ..errors import ApiError, validated
from ..openapi import body_doc, error_responses
from ..schemas import (
    InsertOut,
    KeyframeBatch,
    KeyframeDeleted,
    KeyframeOut,
    KeyframePage,
    KeyframesDeleted,
    KeyframeSummaryOut,
    limits,
)

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
    worker: WriteWorkerDep,
) -> Response:
    """Insert keyframes: all or none; a known key returns its id with created=false."""

    def work() -> InsertOut:
        manager.get(map_name, load=True)  # 404 before decoding a large body for nothing
        req = validated(KeyframeBatch, body.decode(), limits(settings))
        result = manager.insert(map_name, [kf.to_input() for kf in req.keyframes])
        return InsertOut(ids=result.ids, created=result.created, map_version=result.map_version)

    return encode(request, await worker.run(work), 201)


def keyframe_filter(
    key_prefix: Annotated[
        str | None, Query(min_length=1, max_length=256, description="keys starting with this")
    ] = None,
    bbox: Annotated[
        str | None,
        Query(
            description="x_min,y_min,x_max,y_max: positions inside this box (map coordinates, "
            "inclusive)",
            max_length=200,
        ),
    ] = None,
    time_min: Annotated[
        float | None,
        Query(allow_inf_nan=False, description="metadata timestamp >= this (seconds)"),
    ] = None,
    time_max: Annotated[
        float | None,
        Query(allow_inf_nan=False, description="metadata timestamp <= this (seconds)"),
    ] = None,
    sequence: Annotated[
        str | None, Query(min_length=1, max_length=256, description="metadata sequence")
    ] = None,
) -> KeyframeFilter:
    """The filters of a listing or bulk delete, from the query string (422 naming the
    parameter when one is malformed)."""
    for name, text in (("key_prefix", key_prefix), ("sequence", sequence)):
        if text is not None and "\x00" in text:
            raise ApiError(422, "invalid_input", f"{name} must not contain a NUL character", name)
    box = None
    if bbox is not None:
        try:
            values = [float(v) for v in bbox.split(",")]
        except ValueError:
            values = []
        if len(values) != 4 or not all(abs(v) < float("inf") for v in values):
            raise ApiError(
                422,
                "invalid_input",
                "bbox must be four finite numbers: x_min,y_min,x_max,y_max",
                "bbox",
            )
        if values[0] > values[2] or values[1] > values[3]:
            raise ApiError(
                422, "invalid_input", "bbox needs x_min <= x_max and y_min <= y_max", "bbox"
            )
        box = (values[0], values[1], values[2], values[3])
    if time_min is not None and time_max is not None and time_min > time_max:
        raise ApiError(422, "invalid_input", "time_min is after time_max", "time_min")
    return KeyframeFilter(key_prefix, box, time_min, time_max, sequence)


FilterDep = Annotated[KeyframeFilter, Depends(keyframe_filter)]


def _cursor(cursor: str | None) -> int:
    if cursor is None:
        return 0
    # ASCII digits only: str.isdigit() also takes superscripts, which int() refuses
    if not (cursor.isascii() and cursor.isdigit()) or len(cursor) > 19 or int(cursor) > 2**63 - 1:
        raise ApiError(
            422, "invalid_input", "cursor must be a next_cursor of an earlier page", "cursor"
        )
    return int(cursor)


@router.get(
    "",
    response_model=KeyframePage,
    operation_id="list_keyframes",
    responses=error_responses(404, 422),
)
async def list_keyframes(
    request: Request,
    map_name: MapName,
    where: FilterDep,
    manager: ManagerDep,
    worker: WorkerDep,
    limit: Annotated[int, Query(ge=1, le=1000, description="keyframes per page")] = 100,
    cursor: Annotated[
        str | None, Query(max_length=32, description="next_cursor of the previous page")
    ] = None,
) -> Response:
    """List keyframes (id, key, pose, metadata) by id, one page at a time, optionally
    filtered by key prefix, bounding box, metadata time range and sequence."""
    after = _cursor(cursor)

    def work() -> KeyframePage:
        rows = manager.list_keyframes(map_name, where, after_id=after, limit=limit + 1)
        more = len(rows) > limit
        rows = rows[:limit]
        return KeyframePage(
            keyframes=[
                KeyframeSummaryOut(
                    id=r.id,
                    key=r.key,
                    T_map_sensor=r.T_map_sensor.tolist(),
                    position=r.T_map_sensor[:3, 3].tolist(),
                    metadata=r.metadata,
                    created_at=r.created_at,
                )
                for r in rows
            ],
            next_cursor=str(rows[-1].id) if more else None,
        )

    return encode(request, await worker.run(work))


@router.delete(
    "",
    response_model=KeyframesDeleted,
    operation_id="delete_keyframes",
    responses=error_responses(404, 422),
)
async def delete_keyframes(
    request: Request,
    map_name: MapName,
    where: FilterDep,
    manager: ManagerDep,
    worker: WriteWorkerDep,
    all: Annotated[
        bool, Query(description="delete every keyframe (required when no filter is given)")
    ] = False,
) -> Response:
    """Delete every keyframe matching the filters in one transaction (one version step).
    Without filters nothing is deleted unless ``all=true``."""
    if where.empty and not all:
        raise ApiError(
            422,
            "invalid_input",
            "give at least one filter (key_prefix, bbox, time_min, time_max, sequence), or "
            "all=true to delete every keyframe",
            "all",
        )
    deleted, version = await worker.run(lambda: manager.delete_keyframes(map_name, where))
    return encode(request, KeyframesDeleted(deleted=deleted, map_version=version))


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
    worker: WriteWorkerDep,
) -> Response:
    """Delete one keyframe."""
    version = await worker.run(lambda: manager.delete_keyframe(map_name, keyframe_id))
    return encode(request, KeyframeDeleted(deleted=keyframe_id, map_version=version))
