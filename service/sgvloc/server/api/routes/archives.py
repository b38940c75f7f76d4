"""Map archives over HTTP: export a map as one streamed file, import one as a new map.

Neither side holds a whole map in memory: the export is written from one consistent read
of the store while the client downloads it; an upload is streamed into a temporary file
in the data directory (``max_import_bytes``; 408 when no byte arrives for
``body_timeout_s``), then imported by a worker thread (see :mod:`sgvloc.server.archive`).
"""

from __future__ import annotations

import os
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

import anyio
from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.responses import StreamingResponse
from starlette.background import BackgroundTask
from starlette.requests import ClientDisconnect

from sgvloc.core.config import LocalizerConfig
from sgvloc.core.encoders import EncoderSpec

from ..auth import authorize, principal_of
from ..body import encode, media_type
from ..deps import ManagerDep, MapName, SettingsDep, WriteWorkerDep
from ..errors import ApiError
from ..openapi import error_responses
from ..schemas import MapInfo, map_top_k_problem
from .maps import check_keypoint_budget, confine_model_path, map_info

router = APIRouter(tags=["maps"], dependencies=[Depends(authorize)])

ARCHIVE_TYPE = "application/x-tar"
_UPLOAD_TYPES = (ARCHIVE_TYPE, "application/octet-stream")


@router.get(
    "/v1/maps/{map}/export",
    response_class=StreamingResponse,
    operation_id="export_map",
    responses={
        200: {"content": {ARCHIVE_TYPE: {}}, "description": "the map archive (a tar stream)"},
        **error_responses(404),
    },
)
async def export_map(map_name: MapName, manager: ManagerDep) -> StreamingResponse:
    """Download a map as one archive: settings, encoder identity, calibration, version and
    every keyframe with its features and cloud, with checksums. Streamed from one
    consistent state of the map; writers are not blocked meanwhile."""

    def blocks() -> Iterator[bytes]:
        with manager.export_archive(map_name) as stream:
            yield from stream

    # the snapshot opens here, off the event loop: a map deleted meanwhile is a 404
    # before the answer starts, not an empty archive (and once started, the generator
    # closes the snapshot however the download ends)
    stream = blocks()
    first = await anyio.to_thread.run_sync(next, stream, b"")

    def rest() -> Iterator[bytes]:
        yield first
        yield from stream

    # a client that goes away mid-download leaves the stream unfinished: closing it after
    # the answer ends, however it ends, ends the snapshot's transaction now
    return StreamingResponse(
        rest(),
        media_type=ARCHIVE_TYPE,
        headers={"Content-Disposition": f'attachment; filename="{map_name}.sgvmap.tar"'},
        background=BackgroundTask(stream.close),
    )


async def _spool(request: Request, folder: Path, limit: int, idle_s: float) -> Path:
    """Write the request body into a new file in ``folder``: 413 beyond ``limit`` bytes,
    408 when no data arrives for ``idle_s`` seconds. The caller removes the file."""
    folder.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".tmp-import-{uuid.uuid4().hex[:8]}-", dir=folder)
    path = Path(name)
    try:
        with os.fdopen(fd, "wb") as f:
            size = 0
            chunks = request.stream().__aiter__()
            while True:
                with anyio.move_on_after(idle_s) as scope:
                    try:
                        chunk = await chunks.__anext__()
                    except StopAsyncIteration:
                        break
                    except ClientDisconnect:  # nobody to answer: not the service's error
                        raise ApiError(
                            400,
                            "bad_body",
                            "the client closed the connection before the archive was complete",
                        ) from None
                if scope.cancelled_caught:
                    raise ApiError(
                        408,
                        "request_timeout",
                        f"no data of the archive arrived for body_timeout_s={idle_s:g} s",
                        headers={"Connection": "close"},
                    )
                size += len(chunk)
                if size > limit:
                    raise ApiError(
                        413,
                        "payload_too_large",
                        f"the archive exceeds max_import_bytes={limit}",
                        headers={"Connection": "close"},
                    )
                await anyio.to_thread.run_sync(f.write, chunk)
    except BaseException:
        path.unlink(missing_ok=True)
        raise
    return path


@router.post(
    "/v1/map-archives",
    status_code=201,
    response_model=MapInfo,
    operation_id="import_map",
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {ARCHIVE_TYPE: {"schema": {"type": "string", "format": "binary"}}},
        }
    },
    responses=error_responses(403, 408, 409, 413, 415, 422, 507),
)
async def import_map(
    request: Request,
    manager: ManagerDep,
    settings: SettingsDep,
    worker: WriteWorkerDep,
    name: Annotated[
        str | None,
        Query(max_length=64, description="the new map's name (default: the archived name)"),
    ] = None,
) -> Response:
    """Create a map from an archive made by ``GET /v1/maps/{map}/export`` (any sgvloc
    server with the same encoder): same keyframe ids, keys, metadata, version, settings
    and answers. A damaged, truncated or foreign archive is refused (422) and leaves
    nothing; an archive whose encoder builds differently here is 409."""
    ctype = media_type(request.headers.get("content-type"))
    if ctype not in _UPLOAD_TYPES:
        raise ApiError(
            415,
            "unsupported_media_type",
            f"Content-Type {ctype or '(none)'!r} is not supported: send "
            + " or ".join(repr(t) for t in _UPLOAD_TYPES),
        )
    caller = principal_of(request)
    if name is not None and not caller.may_use_map(name):
        raise ApiError(403, "forbidden", f"this key may not use map {name!r}", "name")
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > settings.max_import_bytes:
        raise ApiError(
            413,
            "payload_too_large",
            f"the archive has {int(declared)} bytes, max_import_bytes is "
            f"{settings.max_import_bytes}",
        )
    spool = await _spool(
        request, manager.maps_dir, settings.max_import_bytes, settings.body_timeout_s
    )

    def fix_spec(spec: EncoderSpec) -> EncoderSpec:
        # a model file is looked up by its name in this server's models directory
        if spec.model_path is not None:
            spec = spec.model_copy(update={"model_path": Path(spec.model_path).name})
        check_keypoint_budget(spec, settings.max_keypoints)  # this server's limits, as
        return confine_model_path(spec, settings.models_dir) or spec  # for a new map

    def check_settings(cfg: LocalizerConfig) -> None:
        why = map_top_k_problem(cfg.top_k, settings.max_top_k)
        if why:
            raise ApiError(
                422,
                "invalid_input",
                f"the archived map's {why}",
                "localizer.top_k",
            )

    def check_name(final: str) -> None:  # the archived name, for a key bound to maps
        if not caller.may_use_map(final):
            raise ApiError(403, "forbidden", f"this key may not use map {final!r}", "name")

    def work() -> MapInfo:
        with open(spool, "rb") as f:
            handle = manager.import_archive(
                f, name, fix_spec=fix_spec, check_name=check_name, check_settings=check_settings
            )
        return map_info(handle)

    try:
        return encode(request, await worker.run(work), 201)
    finally:
        spool.unlink(missing_ok=True)
