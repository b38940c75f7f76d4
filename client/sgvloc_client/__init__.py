"""Python client for the sgvloc LiDAR localization service.

    from sgvloc_client import Client

    with Client("http://127.0.0.1:8470") as c:
        c.create_map("campus")
        c.insert_keyframe("campus", T_map_sensor, points=scan, key="seq0/000042")
        loc = c.localize("campus", points=query)
        if loc.localized:
            print(loc.T_map_sensor)  # [4, 4], maps sensor points into the map frame

Bodies travel as MessagePack with arrays as raw little-endian bytes
(:mod:`sgvloc_client.wire`). :class:`AsyncClient` has the same methods as coroutines.
Errors: see :class:`SgvlocError` and the hierarchy documented in ``_errors``.
Reading scan files: :mod:`sgvloc_client.scans`. The package needs only numpy, httpx and
msgpack (no torch, FAISS or Open3D).
"""

from ._async import AsyncClient
from ._base import DEFAULT_BASE_URL, __version__
from ._client import Client
from ._errors import (
    APIError,
    BadRequest,
    Conflict,
    EmptyScan,
    EncoderMismatch,
    Forbidden,
    MapUnavailable,
    NotFound,
    Overloaded,
    PayloadTooLarge,
    ScanFileError,
    ServerError,
    SgvlocError,
    TransportError,
    Unauthorized,
)
from ._models import (
    Candidate,
    EncoderInfo,
    Estimate,
    InsertResult,
    Keyframe,
    KeyframeDeleted,
    KeyframeIn,
    KeyframePage,
    KeyframesDeleted,
    KeyframeSummary,
    Localization,
    MapInfo,
    MapPage,
    MapStats,
    PoseInfo,
    Prior,
    RecentLocalization,
    Seed,
)
from .scans import read_scan
from .tracking import AsyncTracker, MotionModel, Tracker

__all__ = [
    "DEFAULT_BASE_URL",
    "APIError",
    "AsyncClient",
    "AsyncTracker",
    "BadRequest",
    "Candidate",
    "Client",
    "Conflict",
    "EmptyScan",
    "EncoderInfo",
    "EncoderMismatch",
    "Estimate",
    "InsertResult",
    "Keyframe",
    "KeyframeDeleted",
    "KeyframeIn",
    "KeyframePage",
    "KeyframesDeleted",
    "KeyframeSummary",
    "Localization",
    "MapInfo",
    "MapPage",
    "MapStats",
    "MapUnavailable",
    "MotionModel",
    "NotFound",
    "Forbidden",
    "Overloaded",
    "PayloadTooLarge",
    "Unauthorized",
    "PoseInfo",
    "Prior",
    "RecentLocalization",
    "ScanFileError",
    "Seed",
    "ServerError",
    "SgvlocError",
    "Tracker",
    "TransportError",
    "__version__",
    "read_scan",
]
