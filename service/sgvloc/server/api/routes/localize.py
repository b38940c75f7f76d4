"""Localize a scan (or precomputed features) in a map."""

from __future__ import annotations

import time
from functools import partial
from typing import Annotated

import anyio
import anyio.to_thread
import numpy as np
from fastapi import APIRouter, Depends, Query, Request, Response
from scipy.spatial.transform import Rotation

from sgvloc.core.errors import SgvlocError
from sgvloc.core.localizer import LocalizationResult
from sgvloc.core.rerank import Candidate

from ...maps import MapManager, StaleError
from ..auth import authorize, principal_of
from ..body import encode
from ..deps import (
    BodyDep,
    ManagerDep,
    MapName,
    MetricsDep,
    SettingsDep,
    WorkerDep,
    localize_slot,
)
from ..errors import validated
from ..openapi import body_doc, error_responses
from ..schemas import (
    CandidateOut,
    EstimateOut,
    LocalizeBody,
    LocalizeOut,
    PoseOut,
    PriorOut,
    TimingsOut,
    TrackingOut,
    limits,
)

router = APIRouter(prefix="/v1/maps/{map}", tags=["localize"], dependencies=[Depends(authorize)])


def _candidates(cands: list[Candidate]) -> list[CandidateOut]:
    return [
        CandidateOut(
            keyframe_id=c.keyframe_id,
            similarity=c.similarity,
            retrieval_rank=c.retrieval_rank,
            score=c.score,
        )
        for c in cands
    ]


def _finite(x: float) -> float:
    return float(x) if np.isfinite(x) else -1.0


def _estimate(result: LocalizationResult) -> EstimateOut | None:
    T, T_kf = result.T_map_sensor_estimate, result.T_keyframe_sensor_estimate
    if T is None or T_kf is None:
        return None
    return EstimateOut(
        T_map_sensor=T.tolist(),
        T_keyframe_sensor=T_kf.tolist(),
        translation=T[:3, 3].tolist(),
        # scipy's quaternions are scalar-last: [x, y, z, w]
        quaternion_xyzw=Rotation.from_matrix(T[:3, :3]).as_quat().tolist(),
    )


def localize_out(name: str, result: LocalizationResult) -> LocalizeOut:
    """The response body of one localization."""
    pose = result.pose
    estimate = _estimate(result)
    accepted = estimate if result.localized else None
    evidence = None if result.evidence is None else result.evidence.to_dict()
    return LocalizeOut(
        map=name,
        map_version=result.map_version,
        localized=result.localized,
        verdict=result.verdict,
        reason=result.reason,
        confidence=result.confidence,
        min_confidence=result.min_confidence,
        keyframe_id=result.keyframe_id,
        T_map_sensor=accepted and accepted.T_map_sensor,
        T_keyframe_sensor=accepted and accepted.T_keyframe_sensor,
        translation=accepted and accepted.translation,
        quaternion_xyzw=accepted and accepted.quaternion_xyzw,
        estimate=estimate,
        evidence=evidence
        and {k: _finite(v) if isinstance(v, float) else v for k, v in evidence.items()},
        prior=None if result.prior is None else PriorOut(**result.prior),
        mode=result.mode,
        tracking=None
        if result.tracking is None
        else TrackingOut(
            **{k: _finite(v) if isinstance(v, float) else v for k, v in result.tracking.items()}
        ),
        pose=None
        if pose is None
        else PoseOut(
            inliers=pose.inliers,
            num_correspondences=pose.num_correspondences,
            fitness=_finite(pose.fitness),
            inlier_rmse=_finite(pose.inlier_rmse),
            refined=pose.refined,
            icp={k: _finite(v) if isinstance(v, float) else v for k, v in pose.icp.items()},
        ),
        retrieved=_candidates(result.retrieved),
        reranked=_candidates(result.reranked),
        top1_changed=result.top1_changed,
        rerank_method=result.rerank_method,
        timings_ms=TimingsOut(**result.timings_ms),
    )


@router.post(
    "/localize",
    response_model=LocalizeOut,
    operation_id="localize",
    openapi_extra=body_doc(LocalizeBody),
    responses=error_responses(400, 404, 408, 409, 413, 415, 422, 429),
)
async def localize(
    request: Request,
    map_name: MapName,
    body: BodyDep,  # read (within body_timeout_s) before the slot: slow uploads hold none
    manager: ManagerDep,
    settings: SettingsDep,
    metrics: MetricsDep,
    worker: WorkerDep,
    min_map_version: Annotated[
        int | None,
        Query(
            ge=0,
            le=2**63 - 1,  # beyond any version a map can reach: a 422, not a 503 to retry
            description="answer from this map version or later (read-your-writes after an "
            "insert on another replica): the replica waits up to catch_up_wait_s to catch "
            "up, else 503 stale with Retry-After",
        ),
    ] = None,
) -> Response:
    """Localize a scan: retrieve, re-rank, estimate the pose against the top-1.

    At most ``max_inflight_localize`` localize requests are admitted at once; beyond
    that the answer is 429 with ``Retry-After``. Waiting and computing end within
    ``request_timeout_s`` of the body's arrival: past it the work stops at its next step
    and the answer is 503 ``deadline_exceeded``."""
    deadline_at = time.monotonic() + settings.request_timeout_s
    key_name = principal_of(request).name  # for the metrics: the key's name, never the key
    if min_map_version is not None:  # waits off the worker threads, holding no slot
        await _caught_up(manager, map_name, min_map_version, settings.catch_up_wait_s)

    def work() -> LocalizeOut:
        handle = manager.get(map_name, load=True)
        req = validated(LocalizeBody, body.decode(), limits(settings))
        result = manager.localize(
            map_name,
            points=req.points,
            features=None if req.features is None else req.features.to_input(),
            top_k=req.top_k,
            rerank=req.rerank,
            refine=req.refine,
            prior=None if req.prior is None else req.prior.to_prior(),
            min_confidence=req.min_confidence,
            seed=None if req.seed is None else req.seed.to_seed(),
        )
        metrics.observe_localization(result, map_name, key_name)
        # for the status page
        request.app.state.recent.record(map_name, result, lambda: not handle.closed)
        return localize_out(map_name, result)

    async with localize_slot(request):
        out = await worker.run(work, deadline_at=deadline_at, request=request)
        return encode(request, out)


async def _caught_up(manager: MapManager, name: str, version: int, wait_s: float) -> None:
    """Return once map ``name`` is at ``version`` or later on this replica; StaleError
    after ``wait_s`` (catch-ups run in the default thread pool, not the CPU workers; a
    map another replica made meanwhile is loaded there too)."""
    handle = await anyio.to_thread.run_sync(partial(manager.get, name, load=True))
    deadline = time.monotonic() + wait_s
    while handle.version < version:
        if manager.shared:
            try:
                await anyio.to_thread.run_sync(manager.sync_map, handle)
            except SgvlocError:  # an unreachable store: the answer is stale, not an error
                pass
        if handle.version >= version:
            return
        if time.monotonic() >= deadline:
            raise StaleError(
                f"map {name!r} is at version {handle.version} on this replica, not yet at "
                f"min_map_version {version} (waited {wait_s:g} s); retry"
            )
        await anyio.sleep(0.02)
