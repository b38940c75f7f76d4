"""The most recent localizations of a map (in memory; see ``sgvloc.server.recent``)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request, Response
from pydantic import BaseModel, Field

from ...recent import DEFAULT_SIZE, RecentLocalizations
from ..auth import authorize
from ..body import encode
from ..deps import ManagerDep, MapName, served_map
from ..openapi import error_responses

router = APIRouter(prefix="/v1/maps/{map}", tags=["localize"], dependencies=[Depends(authorize)])


class RecentLocalizationOut(BaseModel):
    """One localize answer, as remembered for the status page."""

    time: str = Field(description="when it was answered, ISO 8601 UTC")
    translation: list[float] | None = Field(
        description="x, y, z of the estimate in the map (accepted or not); null without one"
    )
    localized: bool
    verdict: str
    confidence: float
    keyframe_id: int | None
    map_version: int


class RecentLocalizationsOut(BaseModel):
    """``GET /v1/maps/{map}/localizations``: newest first."""

    map: str
    localizations: list[RecentLocalizationOut]


@router.get(
    "/localizations",
    response_model=RecentLocalizationsOut,
    operation_id="recent_localizations",
    responses=error_responses(404),
)
async def recent_localizations(
    request: Request,
    map_name: MapName,
    manager: ManagerDep,
    limit: Annotated[
        int, Query(ge=1, le=DEFAULT_SIZE, description="at most this many, newest first")
    ] = 100,
) -> Response:
    """The map's most recent localize answers, newest first: time, estimated position,
    verdict, confidence, matched keyframe and map version. Kept in memory (the last
    500 per map), not across restarts."""
    await served_map(manager, map_name)  # 404 (or 503 map_unavailable) for a map that is not served
    recent: RecentLocalizations = request.app.state.recent
    entries = recent.newest(map_name, limit)
    return encode(
        request,
        RecentLocalizationsOut(
            map=map_name,
            localizations=[RecentLocalizationOut(**e.to_dict()) for e in entries],
        ),
    )
