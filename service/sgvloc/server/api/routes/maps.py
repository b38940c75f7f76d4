"""Maps: create, list, describe, change settings, delete."""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Annotated, Any, TypeVar

import anyio.to_thread
from fastapi import APIRouter, Depends, Query, Request, Response

from sgvloc.core import leave_out
from sgvloc.core.confidence import shipped_calibration
from sgvloc.core.encoders import EncoderSpec
from sgvloc.core.errors import InputError
from sgvloc.core.localizer import Localizer

from ...maps import MapHandle, MapManager
from ...settings import Settings
from ..auth import authorize, principal_of
from ..body import encode
from ..deps import (
    BodyDep,
    ManagerDep,
    MapName,
    SettingsDep,
    Worker,
    WorkerDep,
    WriteWorkerDep,
    busy,
    served_map,
)
from ..errors import ApiError, validated
from ..openapi import body_doc, error_responses
from ..schemas import (
    CalibrationInfo,
    EncoderInfo,
    MapCreate,
    MapInfo,
    MapList,
    MapPatch,
    MapStats,
    SelfTestReport,
    SelfTestRequest,
    limits,
    map_top_k_problem,
    parse_calibration,
    patch_top_k,
)

router = APIRouter(prefix="/v1/maps", tags=["maps"], dependencies=[Depends(authorize)])

log = logging.getLogger(__name__)
T = TypeVar("T")
#: keyframes a self-test encodes again per worker task when it compares encoders
SELF_TEST_ENCODE_BATCH = 8


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
            global_descriptor=spec.learned.global_descriptor
            if spec.kind == "learned"
            else spec.kind,
            global_blocks=list(enc.blocks),
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
        self_test=handle.record.self_test,
        last_self_test=handle.record.last_self_test,
    )


def _check_top_k(top_k: int, settings: Settings) -> None:
    """A map's own top_k stays within max_top_k, as a request's (else its settings would
    take every localize of it past the limit): a 422 naming localizer.top_k."""
    why = map_top_k_problem(top_k, settings.max_top_k)
    if why:
        raise ApiError(422, "invalid_input", f"localizer.top_k: {why}", "localizer.top_k")


@router.post(
    "",
    status_code=201,
    response_model=MapInfo,
    operation_id="create_map",
    openapi_extra=body_doc(MapCreate),
    responses=error_responses(400, 408, 409, 413, 415, 422),
)
async def create_map(
    request: Request,
    body: BodyDep,
    manager: ManagerDep,
    settings: SettingsDep,
    worker: WriteWorkerDep,
) -> Response:
    """Create an empty map with an encoder and localizer settings."""

    caller = principal_of(request)

    def work() -> MapInfo:
        req = validated(MapCreate, body.decode(), limits(settings))
        if req.localizer is not None:
            _check_top_k(req.localizer.top_k, settings)
        if not caller.may_use_map(req.name):
            raise ApiError(403, "forbidden", f"this key may not use map {req.name!r}", "name")
        check_keypoint_budget(req.encoder, settings.max_keypoints)
        encoder = confine_model_path(req.encoder, settings.models_dir)
        try:
            handle = manager.create(
                req.name,
                encoder,
                req.localizer_config(),
                keep_clouds=req.keep_clouds,
                calibration=parse_calibration(req.calibration, "calibration"),
                self_test=req.self_test,
            )
        except InputError as exc:  # a model file's error names it by its name, not its path
            if settings.models_dir is not None:
                root = str(settings.models_dir.resolve())
                exc.args = tuple(str(a).replace(root + "/", "").replace(root, "") for a in exc.args)
            raise
        return map_info(handle)

    return encode(request, await worker.run(work), 201)


def check_keypoint_budget(spec: EncoderSpec | None, max_keypoints: int) -> None:
    """422 when the encoder of a new map would make more keypoints per scan than
    ``max_keypoints`` (re-ranking and pose cost grow with its square)."""
    spec = spec or EncoderSpec()
    sections = {"handcrafted": spec.handcrafted, "bev": spec.bev, "learned": spec.learned}
    section = sections.get(spec.kind)
    if section is not None and section.num_keypoints > max_keypoints:
        raise ApiError(
            422,
            "invalid_input",
            f"{section.num_keypoints} keypoints per scan; the limit is {max_keypoints} "
            "(max_keypoints)",
            f"encoder.{spec.kind}.num_keypoints",
        )


def confine_model_path(spec: EncoderSpec | None, models_dir: Path | None) -> EncoderSpec | None:
    """``spec`` with its ``model_path`` resolved inside ``models_dir``; 422 with one message
    for any other path (or any path when no models directory is configured), so a caller
    learns nothing about the server's files and never has one loaded as a model."""
    if spec is None or spec.model_path is None:
        return spec
    refused = ApiError(
        422,
        "invalid_input",
        "model files must be in the service's models directory (SGVLOC_MODELS_DIR): give "
        "a file name there",
        "encoder.model_path",
    )
    if models_dir is None:
        raise refused
    root = models_dir.resolve()
    path = (root / spec.model_path).resolve()
    if not path.is_relative_to(root) or not path.is_file():
        raise refused
    return spec.model_copy(update={"model_path": str(path)})


@router.get("", response_model=MapList, operation_id="list_maps", responses=error_responses(422))
async def list_maps(
    request: Request,
    manager: ManagerDep,
    limit: Annotated[
        int | None,
        Query(ge=1, le=1000, description="maps per page (unset: every map, as before paging)"),
    ] = None,
    cursor: Annotated[
        str | None, Query(max_length=64, description="next_cursor of the previous page")
    ] = None,
    prefix: Annotated[
        str | None, Query(max_length=64, description="only maps whose name starts with this")
    ] = None,
) -> Response:
    """List the loaded maps that the caller's key may use, by name, one page at a time
    (``limit`` per page; pass ``next_cursor`` as ``cursor`` for the next; without
    ``limit``, every map after ``cursor``, as clients from before paging expect),
    optionally only those whose name starts with ``prefix``."""
    caller = principal_of(request)

    def listing() -> Response:  # off the event loop: hundreds of maps take tens of ms
        matching = [
            h
            for h in manager.list()
            if (not prefix or h.name.startswith(prefix)) and caller.may_use_map(h.name)
        ]
        after = [h for h in matching if cursor is None or h.name > cursor]
        page = after if limit is None else after[:limit]
        more = len(after) > len(page)
        return encode(
            request,
            MapList(
                maps=[map_info(h) for h in page],
                next_cursor=page[-1].name if more else None,
                total=len(matching),
            ),
        )

    return await anyio.to_thread.run_sync(listing)


@router.get(
    "/{map}", response_model=MapInfo, operation_id="get_map", responses=error_responses(404)
)
async def get_map(request: Request, map_name: MapName, manager: ManagerDep) -> Response:
    """Describe one map."""
    return encode(request, map_info(await served_map(manager, map_name)))


@router.get(
    "/{map}/stats",
    response_model=MapStats,
    operation_id="map_stats",
    responses=error_responses(404),
)
async def map_stats(
    request: Request, map_name: MapName, manager: ManagerDep, worker: WorkerDep
) -> Response:
    """A map's size: keyframes, extent, disk and memory use, index kind, last write."""
    return encode(request, MapStats(**await worker.run(lambda: manager.stats(map_name))))


@router.patch(
    "/{map}",
    response_model=MapInfo,
    operation_id="update_map",
    openapi_extra=body_doc(MapPatch),
    responses=error_responses(400, 404, 408, 413, 415, 422),
)
async def update_map(
    request: Request,
    map_name: MapName,
    body: BodyDep,
    manager: ManagerDep,
    settings: SettingsDep,
    worker: WriteWorkerDep,
) -> Response:
    """Change a map's localizer settings or calibration (its keyframes and version stay)."""

    def work() -> MapInfo:
        handle = manager.get(map_name, load=True)  # 404 before the body is judged
        req = validated(MapPatch, body.decode(), limits(settings))
        top_k = patch_top_k(req.localizer)
        if top_k is not None:
            _check_top_k(top_k, settings)
        cal = req.calibration
        calibration = (
            shipped_calibration(handle.record.encoder_spec.kind)
            if cal == "shipped"
            else parse_calibration(cal, "calibration")
        )
        return map_info(manager.update_settings(map_name, req.localizer, calibration))

    return encode(request, await worker.run(work))


@router.post(
    "/{map}/self-test",
    response_model=SelfTestReport,
    operation_id="self_test_map",
    openapi_extra=body_doc(SelfTestRequest),
    responses=error_responses(400, 404, 409, 413, 415, 422, 429),
)
async def self_test_map(
    request: Request,
    map_name: MapName,
    body: BodyDep,
    manager: ManagerDep,
    settings: SettingsDep,
    worker: WriteWorkerDep,
) -> Response:
    """Localize a sample of the map's own keyframes against the others, leaving out each
    one's own stretch of the drive: Recall@1, pose success and false accepts of the map as
    it is served (:mod:`sgvloc.core.leave_out`). With ``encoders``, each of them is
    measured on the same queries from the keyframes' stored clouds, and the best is
    named. Each query and each batch of keyframes encoded takes a worker on its own, so
    localizations go on beside it; a client that leaves stops it. The summary is
    recorded with the map (``last_self_test``). 409 if keyframes change meanwhile."""
    # parsed in a worker thread, as every body (a large one would hold the event loop)
    req = await worker.run(lambda: validated(SelfTestRequest, body.decode()))
    version, plan = await worker.run(
        lambda: manager.self_test_plan(
            map_name, req.queries, req.gap_s, req.gap_keyframes, req.radius_m
        )
    )
    guard = contextlib.ExitStack()
    if req.encoders:  # refused before any work, not after the map's own queries
        manager.check_comparable(manager.get(map_name), settings.max_self_test_keyframes)
        guard.enter_context(_one_comparison(request, map_name, settings))
    with guard:
        return await _self_test(request, map_name, req, version, plan, manager, settings, worker)


@contextlib.contextmanager
def _one_comparison(request: Request, map_name: str, settings: Settings) -> Iterator[None]:
    """One self-test that compares encoders at a time in this process (429 otherwise):
    each holds a copy of its map's keyframes per candidate, so that concurrent ones
    cannot add up past what one is bounded to (max_self_test_keyframes)."""
    state = request.app.state
    running = getattr(state, "comparing_encoders", None)
    if running is not None:
        raise busy(
            429,
            "overloaded",
            f"a self-test comparing encoders is running (map {running!r}); one runs at a "
            "time: retry when it ends, or leave out encoders",
            settings,
        )
    state.comparing_encoders = map_name  # no await between the check and this
    try:
        yield
    finally:
        state.comparing_encoders = None


async def _self_test(
    request: Request,
    map_name: str,
    req: SelfTestRequest,
    version: int,
    plan: leave_out.Plan,
    manager: MapManager,
    settings: Settings,
    worker: Worker,
) -> Response:
    """The self-test's queries, those of each encoder compared, and its record."""
    t0 = time.monotonic()

    def step(fn: Callable[[], T]) -> Awaitable[T]:
        deadline = time.monotonic() + settings.request_timeout_s
        return worker.run(fn, deadline_at=deadline, request=request)

    async def answers(candidate: Localizer | None = None) -> list[dict[str, Any]]:
        return [
            await step(
                lambda kf=kf: manager.self_test_query(
                    map_name, version, plan, kf, req.radius_m, candidate
                )
            )
            for kf in plan.in_coverage + plan.out_of_coverage
        ]

    records = await answers()
    own_seconds = round(time.monotonic() - t0, 2)
    handle = manager.get(map_name)
    summary = {
        "format": leave_out.FORMAT,
        "map_version": version,
        "encoder": handle.record.encoder_spec.kind,
        "basis": plan.basis,
        "settings": req.model_dump(),
        "figures": leave_out.summarise(records),
    }
    candidate_records: dict[str, list[dict[str, Any]]] = {}  # answered, not recorded
    if req.encoders:
        compared: dict[str, dict[str, Any]] = {}
        # the map's own encoder, when it is a candidate, is measured too (its answers as
        # served, at no cost) and wins ties: a rebuild is worth it only for a better one
        own = await step(lambda: manager.own_candidate(map_name))
        order = ([own] if own else []) + [n for n in req.encoders if n != own]
        ids = [int(i) for i in plan.ids]
        for name in order:
            t1, spec, unencoded = time.monotonic(), leave_out.spec_of(name), 0
            if name == own:  # the map's own encoder: its answers as served
                fingerprint = handle.record.encoder_fingerprint
                answered, seconds = records, own_seconds
            else:
                candidate = await step(
                    lambda spec=spec: manager.self_test_candidate(
                        map_name, version, spec, settings.max_self_test_keyframes
                    )
                )
                fingerprint = candidate.encoder.identity.fingerprint
                for at in range(0, len(ids), SELF_TEST_ENCODE_BATCH):
                    batch = ids[at : at + SELF_TEST_ENCODE_BATCH]
                    unencoded += await step(
                        lambda batch=batch, c=candidate: manager.self_test_encode(
                            map_name, version, c, batch
                        )
                    )
                answered = await answers(candidate)
                del candidate  # its copy of the map is not kept past its turn
                seconds = round(time.monotonic() - t1, 2)
            compared[name] = {
                "encoder": spec,
                "fingerprint": fingerprint,
                "figures": leave_out.summarise(answered),
                "unencoded": unencoded,
                "seconds": seconds,
            }
            candidate_records[name] = answered
            log.info(
                "map %r: self-test measured encoder %s (%d of %d): %s in %.1f s",
                map_name,
                name,
                len(compared),
                len(order),
                compared[name]["figures"],
                compared[name]["seconds"],
            )
        figures_of = {n: c["figures"] for n, c in compared.items()}
        chosen = leave_out.choose(figures_of, tuple(order))
        summary |= {
            "encoders": compared,
            "chosen": chosen,
            "rule": leave_out.RULE,
            "warning": leave_out.warning(figures_of, chosen),
        }
    summary["seconds"] = round(time.monotonic() - t0, 2)
    await worker.run(lambda: manager.record_self_test(map_name, summary))
    report = SelfTestReport(**summary, records=records)
    for name, recs in candidate_records.items():
        report.encoders[name] = report.encoders[name] | {"records": recs}  # type: ignore[index]
    return encode(request, report)


@router.post(
    "/{map}/reload",
    response_model=MapInfo,
    operation_id="reload_map",
    responses=error_responses(404, 409, 503),
)
async def reload_map(
    request: Request, map_name: MapName, manager: ManagerDep, worker: WriteWorkerDep
) -> Response:
    """Load a map whose folder failed to load (listed under ``failed`` by ``/readyz``),
    after its cause is fixed, without a restart (admin). 409 if the map is loaded, 503
    ``map_unavailable`` (with the reason) if it still cannot be loaded."""
    return encode(request, map_info(await worker.run(lambda: manager.reload(map_name))))


@router.delete(
    "/{map}",
    status_code=204,
    response_class=Response,
    operation_id="delete_map",
    responses=error_responses(404, 409),
)
async def delete_map(
    map_name: MapName,
    manager: ManagerDep,
    worker: WriteWorkerDep,
    force: Annotated[
        bool,
        Query(
            description="also delete a map that could not be loaded (503 map_unavailable "
            "otherwise), unread: its folder or rows, with every keyframe"
        ),
    ] = False,
) -> Response:
    """Delete a map with all its keyframes."""
    await worker.run(lambda: manager.delete(map_name, force=force))
    return Response(status_code=204)
