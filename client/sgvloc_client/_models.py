"""Typed request and result objects of the client.

Results are built from the service's response bodies (JSON or MessagePack, see
``docs/API.md``). Transforms are 4x4 row-major float64 ndarrays named by their frames:
``T_map_sensor`` maps points of the sensor frame into the map frame. Quaternions are
``[x, y, z, w]`` (scalar last). Each result keeps the decoded body in ``raw`` so fields
added by newer services stay reachable.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np


def _pose(value: Any) -> np.ndarray | None:
    """A 4x4 float64 transform (writable copy), or None."""
    if value is None:
        return None
    return np.array(value, dtype=np.float64).reshape(4, 4)


def _vector(value: Any) -> np.ndarray | None:
    return None if value is None else np.array(value, dtype=np.float64).reshape(-1)


# --------------------------------------------------------------------------------------
# Requests


@dataclass
class KeyframeIn:
    """One keyframe to insert into a map.

    - ``T_map_sensor``: ``[4, 4]`` pose of the scan in the map frame (sent as float64);
    - ``points``: ``[P, 3]`` or ``[P, 4]`` (x y z [intensity]) scan in the sensor frame
      (sent as float32); or
    - ``features``: precomputed ``{"global_descriptor": [G], "keypoints": [N, 3],
      "local_features": [N, D]}`` for maps with a ``precomputed`` encoder;
    - ``key``: optional client-chosen unique key; a keyframe whose key is already in the
      map is not inserted again (``created: false``), which makes retries safe;
    - ``metadata``: optional ``{"timestamp": float, "sequence": str, "tags": {str: str}}``.

    Exactly one of ``points`` / ``features`` must be given; shapes and values are checked
    by the service, whose error names the offending field.
    """

    T_map_sensor: Any
    points: Any = None
    features: Mapping[str, Any] | None = None
    key: str | None = None
    metadata: Mapping[str, Any] | None = None

    def to_body(self) -> dict[str, Any]:
        """The request body of this keyframe, with arrays as little-endian ndarrays."""
        body: dict[str, Any] = {"T_map_sensor": np.asarray(self.T_map_sensor, dtype=np.float64)}
        if self.points is not None:
            body["points"] = points_array(self.points)
        if self.features is not None:
            body["features"] = features_body(self.features)
        if self.key is not None:
            body["key"] = self.key
        if self.metadata is not None:
            body["metadata"] = dict(self.metadata)
        return body

    @classmethod
    def coerce(cls, value: KeyframeIn | Mapping[str, Any]) -> KeyframeIn:
        """Accept a :class:`KeyframeIn` or a dict with the same fields."""
        if isinstance(value, KeyframeIn):
            return value
        if not isinstance(value, Mapping):
            kind = type(value).__name__
            raise TypeError(f"a keyframe must be a KeyframeIn or a dict, got {kind}")
        unknown = set(value) - {"T_map_sensor", "points", "features", "key", "metadata"}
        if unknown:
            raise TypeError(f"unknown keyframe field(s): {', '.join(sorted(unknown))}")
        if "T_map_sensor" not in value:
            raise TypeError("a keyframe needs T_map_sensor")
        return cls(**value)


def points_array(points: Any) -> np.ndarray:
    """A scan as a float32 array (shape unchecked: the service names shape errors)."""
    arr = np.asarray(points)
    if arr.dtype.kind not in "fiub":
        raise TypeError(f"points must be a numeric array, got dtype {arr.dtype}")
    return arr.astype(np.float32, copy=False)


def features_body(features: Mapping[str, Any]) -> dict[str, Any]:
    """Precomputed features with float32 arrays; other entries are passed through."""
    return {
        k: np.asarray(v, dtype=np.float32)
        if k in ("global_descriptor", "keypoints", "local_features")
        else v
        for k, v in features.items()
    }


# --------------------------------------------------------------------------------------
# Results


@dataclass(frozen=True)
class EncoderInfo:
    """The encoder a map was built with; ``fingerprint`` identifies it exactly."""

    kind: str
    name: str
    fingerprint: str
    global_dim: int | None
    local_dim: int | None
    spec: dict[str, Any]
    #: what the global descriptor is ("polar", "network", "polar+network", ...)
    global_descriptor: str = ""
    #: its blocks' lengths; several are searched one by one and merged
    global_blocks: tuple[int, ...] = ()

    @classmethod
    def from_body(cls, d: Mapping[str, Any]) -> EncoderInfo:
        return cls(
            kind=d.get("kind", ""),
            name=d.get("name", ""),
            fingerprint=d.get("fingerprint", ""),
            global_dim=d.get("global_dim"),
            local_dim=d.get("local_dim"),
            spec=dict(d.get("spec") or {}),
            global_descriptor=d.get("global_descriptor", ""),
            global_blocks=tuple(d.get("global_blocks") or ()),
        )


@dataclass(frozen=True)
class MapInfo:
    """A map: name, version (changes on every insert/delete), size and settings.

    ``localizer`` holds its full localizer settings (``top_k``, ``rerank``, ``verdict``,
    ...), ``calibration`` the confidence model it answers with (``name``,
    ``fingerprint``, ``encoder_kind``); ``settings_version`` counts changes made with
    :meth:`Client.update_map`.
    """

    name: str
    version: int
    keyframes: int
    encoder: EncoderInfo
    retrieval: dict[str, Any]
    index_kind: str
    created_at: Any
    keep_clouds: bool = True
    localizer: dict[str, Any] = field(default_factory=dict)
    calibration: dict[str, Any] = field(default_factory=dict)
    settings_version: int = 0
    #: the encoder self-test the map was built after (None: built without one)
    self_test: dict[str, Any] | None = None
    #: the summary of the latest leave-out self-test (``self_test_map``; None: never run)
    last_self_test: dict[str, Any] | None = None
    raw: dict[str, Any] = field(repr=False, compare=False, default_factory=dict)

    @classmethod
    def from_body(cls, d: Mapping[str, Any]) -> MapInfo:
        return cls(
            name=d["name"],
            version=int(d["version"]),
            keyframes=int(d["keyframes"]),
            encoder=EncoderInfo.from_body(d.get("encoder") or {}),
            retrieval=dict(d.get("retrieval") or {}),
            index_kind=d.get("index_kind", ""),
            created_at=d.get("created_at"),
            keep_clouds=bool(d.get("keep_clouds", True)),
            localizer=dict(d.get("localizer") or {}),
            calibration=dict(d.get("calibration") or {}),
            settings_version=int(d.get("settings_version") or 0),
            self_test=d.get("self_test"),
            last_self_test=d.get("last_self_test"),
            raw=dict(d),
        )


@dataclass(frozen=True)
class InsertResult:
    """Result of an insert: per keyframe, in request order, its id and whether it is new."""

    ids: list[int]
    created: list[bool]
    map_version: int

    @property
    def num_created(self) -> int:
        """How many keyframes were actually added (the others had known keys)."""
        return sum(self.created)

    @classmethod
    def from_body(cls, d: Mapping[str, Any]) -> InsertResult:
        return cls(
            ids=[int(i) for i in d["ids"]],
            created=[bool(c) for c in d["created"]],
            map_version=int(d["map_version"]),
        )


@dataclass(frozen=True)
class Keyframe:
    """A stored keyframe (``GET /v1/maps/{map}/keyframes/{id}``)."""

    id: int
    key: str | None
    T_map_sensor: np.ndarray  # [4, 4] float64
    metadata: dict[str, Any]
    num_keypoints: int
    created_at: Any
    raw: dict[str, Any] = field(repr=False, compare=False, default_factory=dict)

    @classmethod
    def from_body(cls, d: Mapping[str, Any]) -> Keyframe:
        return cls(
            id=int(d["id"]),
            key=d.get("key"),
            T_map_sensor=_pose(d["T_map_sensor"]),
            metadata=dict(d.get("metadata") or {}),
            num_keypoints=int(d.get("num_keypoints") or 0),
            created_at=d.get("created_at"),
            raw=dict(d),
        )


@dataclass(frozen=True)
class KeyframeDeleted:
    """Result of deleting a keyframe: its id and the map's new version."""

    id: int
    map_version: int

    @classmethod
    def from_body(cls, d: Mapping[str, Any]) -> KeyframeDeleted:
        return cls(id=int(d["deleted"]), map_version=int(d["map_version"]))


@dataclass(frozen=True)
class RecentLocalization:
    """One of a map's recent localize answers (``GET /v1/maps/{map}/localizations``):
    when (``time``, ISO 8601 UTC), where (``translation`` ``[3]`` of the estimate, accepted
    or not; None without one), the verdict, its ``confidence``, the matched keyframe and
    the map version that answered."""

    time: str
    translation: np.ndarray | None  # [3]
    localized: bool
    verdict: str
    confidence: float
    keyframe_id: int | None
    map_version: int

    @classmethod
    def from_body(cls, d: Mapping[str, Any]) -> RecentLocalization:
        kf = d.get("keyframe_id")
        return cls(
            time=str(d["time"]),
            translation=_vector(d.get("translation")),
            localized=bool(d["localized"]),
            verdict=str(d.get("verdict", "")),
            confidence=float(d.get("confidence") or 0.0),
            keyframe_id=None if kf is None else int(kf),
            map_version=int(d["map_version"]),
        )


@dataclass(frozen=True)
class Candidate:
    """A keyframe proposed for a query: retrieval similarity, rank and re-ranking score."""

    keyframe_id: int
    similarity: float
    retrieval_rank: int
    score: float | None

    @classmethod
    def from_body(cls, d: Mapping[str, Any]) -> Candidate:
        score = d.get("score")
        return cls(
            keyframe_id=int(d["keyframe_id"]),
            similarity=float(d["similarity"]),
            retrieval_rank=int(d["retrieval_rank"]),
            score=None if score is None else float(score),
        )


@dataclass(frozen=True)
class PoseInfo:
    """Diagnostics of the pose estimate (RANSAC, then optional ICP refinement)."""

    inliers: int
    num_correspondences: int
    fitness: float
    inlier_rmse: float
    refined: bool

    @classmethod
    def from_body(cls, d: Mapping[str, Any]) -> PoseInfo:
        return cls(
            inliers=int(d["inliers"]),
            num_correspondences=int(d["num_correspondences"]),
            fitness=float(d["fitness"]),
            inlier_rmse=float(d["inlier_rmse"]),
            refined=bool(d["refined"]),
        )


@dataclass(frozen=True)
class Prior:
    """Where the sensor is believed to be (e.g. from GNSS), sent with a localize request.

    ``position``: ``[x, y]`` or ``[x, y, z]`` in map coordinates; only keyframes within
    ``radius_m`` of it are searched and an estimate outside that radius is rejected. With
    ``yaw_deg`` (heading of the sensor's x axis in the map) an estimate whose heading is
    more than ``yaw_tolerance_deg`` off is rejected too.
    """

    position: Any
    radius_m: float
    yaw_deg: float | None = None
    yaw_tolerance_deg: float | None = None

    def to_body(self) -> dict[str, Any]:
        position = np.asarray(self.position, dtype=np.float64)
        if position.ndim != 1:
            raise TypeError(f"Prior.position must be [x, y] or [x, y, z], got {self.position!r}")
        body: dict[str, Any] = {
            "position": [float(x) for x in position],
            "radius_m": float(self.radius_m),
        }
        if self.yaw_deg is not None:
            body["yaw_deg"] = float(self.yaw_deg)
        if self.yaw_tolerance_deg is not None:
            body["yaw_tolerance_deg"] = float(self.yaw_tolerance_deg)
        return body

    @classmethod
    def coerce(cls, value: Prior | Mapping[str, Any]) -> Prior:
        """Accept a :class:`Prior` or a dict with the same fields."""
        if isinstance(value, Prior):
            return value
        if not isinstance(value, Mapping):
            raise TypeError(f"a prior must be a Prior or a dict, got {type(value).__name__}")
        return cls(**value)


@dataclass(frozen=True)
class Seed:
    """A predicted pose for tracking, sent with a localize request: the service
    registers the scan against the map around ``T_map_sensor`` (``[4, 4]``) and trusts
    the fit only within ``sigma_m`` / ``sigma_yaw_deg`` (1 sigma, times the map's
    ``tracking.seed_sigmas``). :class:`~sgvloc_client.Tracker` makes these."""

    T_map_sensor: Any
    sigma_m: float
    sigma_yaw_deg: float

    def to_body(self) -> dict[str, Any]:
        return {
            "T_map_sensor": np.asarray(self.T_map_sensor, dtype=np.float64),
            "sigma_m": float(self.sigma_m),
            "sigma_yaw_deg": float(self.sigma_yaw_deg),
        }

    @classmethod
    def coerce(cls, value: Seed | Mapping[str, Any]) -> Seed:
        """Accept a :class:`Seed` or a dict with the same fields."""
        if isinstance(value, Seed):
            return value
        if not isinstance(value, Mapping):
            raise TypeError(f"a seed must be a Seed or a dict, got {type(value).__name__}")
        return cls(**value)


@dataclass(frozen=True)
class Estimate:
    """A pose estimate: ``T_map_sensor``, ``T_keyframe_sensor`` ``[4, 4]``, ``translation``
    ``[3]`` and ``quaternion_xyzw`` ``[4]``."""

    T_map_sensor: np.ndarray
    T_keyframe_sensor: np.ndarray
    translation: np.ndarray
    quaternion_xyzw: np.ndarray

    @classmethod
    def from_body(cls, d: Mapping[str, Any]) -> Estimate:
        return cls(
            T_map_sensor=_pose(d["T_map_sensor"]),
            T_keyframe_sensor=_pose(d["T_keyframe_sensor"]),
            translation=_vector(d["translation"]),
            quaternion_xyzw=_vector(d["quaternion_xyzw"]),
        )


@dataclass(frozen=True)
class Localization:
    """The answer to a localize request.

    ``localized`` is the verdict to act on. When it is False (``verdict`` gives the
    reason code, ``reason`` a sentence) the pose fields are None, and ``estimate`` still
    holds the best estimate (None only when there was none). ``T_map_sensor`` ``[4, 4]``
    places the query scan in the map; ``T_keyframe_sensor`` ``[4, 4]`` places it
    relative to the matched keyframe ``keyframe_id``; ``translation`` ``[3]`` and
    ``quaternion_xyzw`` ``[4]`` repeat ``T_map_sensor``. ``confidence`` is the calibrated
    probability that the estimate is within 2 m and 5 degrees, ``min_confidence`` the
    threshold applied, ``evidence`` what the confidence came from. ``map_version`` says
    which state of the map answered; ``prior`` how a prior restricted the search.
    ``mode``: ``"global"`` search, ``"tracked"`` (fitted around the request's seed) or
    ``"relocalized"`` (the seed's fit failed; the global path answered); ``tracking``
    describes the seeded fit (fitness, rmse_m, seed_offset_m, why, ...).
    """

    map: str
    map_version: int
    localized: bool
    reason: str
    keyframe_id: int | None
    T_map_sensor: np.ndarray | None  # [4, 4] float64
    T_keyframe_sensor: np.ndarray | None  # [4, 4] float64
    translation: np.ndarray | None  # [3]
    quaternion_xyzw: np.ndarray | None  # [4], scalar last
    pose: PoseInfo | None
    retrieved: list[Candidate]
    reranked: list[Candidate]
    top1_changed: bool
    rerank_method: str
    timings_ms: dict[str, float]
    verdict: str = ""
    confidence: float = 0.0
    min_confidence: float = 0.0
    estimate: Estimate | None = None
    evidence: dict[str, Any] = field(default_factory=dict)
    prior: dict[str, Any] | None = None
    mode: str = "global"
    tracking: dict[str, Any] | None = None
    raw: dict[str, Any] = field(repr=False, compare=False, default_factory=dict)

    @classmethod
    def from_body(cls, d: Mapping[str, Any]) -> Localization:
        kf = d.get("keyframe_id")
        return cls(
            map=d["map"],
            map_version=int(d["map_version"]),
            localized=bool(d["localized"]),
            reason=d.get("reason", ""),
            keyframe_id=None if kf is None else int(kf),
            T_map_sensor=_pose(d.get("T_map_sensor")),
            T_keyframe_sensor=_pose(d.get("T_keyframe_sensor")),
            translation=_vector(d.get("translation")),
            quaternion_xyzw=_vector(d.get("quaternion_xyzw")),
            pose=None if d.get("pose") is None else PoseInfo.from_body(d["pose"]),
            retrieved=[Candidate.from_body(c) for c in d.get("retrieved") or []],
            reranked=[Candidate.from_body(c) for c in d.get("reranked") or []],
            top1_changed=bool(d.get("top1_changed", False)),
            rerank_method=d.get("rerank_method", ""),
            timings_ms={k: float(v) for k, v in (d.get("timings_ms") or {}).items()},
            verdict=d.get("verdict", ""),
            confidence=float(d.get("confidence") or 0.0),
            min_confidence=float(d.get("min_confidence") or 0.0),
            estimate=None if d.get("estimate") is None else Estimate.from_body(d["estimate"]),
            evidence=dict(d.get("evidence") or {}),
            prior=None if d.get("prior") is None else dict(d["prior"]),
            mode=str(d.get("mode") or "global"),
            tracking=None if d.get("tracking") is None else dict(d["tracking"]),
            raw=dict(d),
        )


@dataclass(frozen=True)
class KeyframeSummary:
    """One keyframe of a listing (``GET /v1/maps/{map}/keyframes``): no features."""

    id: int
    key: str | None
    T_map_sensor: np.ndarray  # [4, 4] float64
    position: np.ndarray  # [3] float64, x y z in map coordinates
    metadata: dict[str, Any]
    created_at: Any

    @classmethod
    def from_body(cls, d: Mapping[str, Any]) -> KeyframeSummary:
        return cls(
            id=int(d["id"]),
            key=d.get("key"),
            T_map_sensor=_pose(d["T_map_sensor"]),
            position=np.asarray(d["position"], dtype=np.float64),
            metadata=dict(d.get("metadata") or {}),
            created_at=d.get("created_at"),
        )


@dataclass(frozen=True)
class KeyframePage:
    """One page of a keyframe listing; pass ``next_cursor`` for the next (None: last)."""

    keyframes: list[KeyframeSummary]
    next_cursor: str | None

    @classmethod
    def from_body(cls, d: Mapping[str, Any]) -> KeyframePage:
        return cls(
            keyframes=[KeyframeSummary.from_body(k) for k in d["keyframes"]],
            next_cursor=d.get("next_cursor"),
        )


@dataclass(frozen=True)
class MapPage:
    """One page of the map listing, by name; pass ``next_cursor`` for the next (None:
    last)."""

    maps: list[MapInfo]
    next_cursor: str | None
    #: maps matching the listing on all its pages (None from a service before paging)
    total: int | None = None

    @classmethod
    def from_body(cls, d: Mapping[str, Any]) -> MapPage:
        return cls(
            maps=[MapInfo.from_body(m) for m in d["maps"]],
            next_cursor=d.get("next_cursor"),
            total=d.get("total"),
        )


@dataclass(frozen=True)
class KeyframesDeleted:
    """Result of a bulk delete: how many keyframes went, and the map's version after."""

    deleted: int
    map_version: int

    @classmethod
    def from_body(cls, d: Mapping[str, Any]) -> KeyframesDeleted:
        return cls(deleted=int(d["deleted"]), map_version=int(d["map_version"]))


@dataclass(frozen=True)
class MapStats:
    """A map's size (``GET /v1/maps/{map}/stats``). ``extent`` is ``(min xyz, max xyz)``
    of the keyframe positions, None while the map is empty."""

    map: str
    version: int
    keyframes: int
    extent: tuple[np.ndarray, np.ndarray] | None
    disk_bytes: int
    memory_bytes: int
    index_kind: str
    created_at: Any
    last_write: Any

    @classmethod
    def from_body(cls, d: Mapping[str, Any]) -> MapStats:
        ext = d.get("extent")
        return cls(
            map=str(d["map"]),
            version=int(d["version"]),
            keyframes=int(d["keyframes"]),
            extent=None
            if ext is None
            else (np.asarray(ext["min"], np.float64), np.asarray(ext["max"], np.float64)),
            disk_bytes=int(d["disk_bytes"]),
            memory_bytes=int(d["memory_bytes"]),
            index_kind=str(d["index_kind"]),
            created_at=d.get("created_at"),
            last_write=d.get("last_write"),
        )
