"""Request and response models of the HTTP API (docs/API.md), one group per resource.

Requests are validated from the decoded body (JSON or MessagePack) with
``Model.model_validate(data, context=limits(settings))``: array fields accept nested
lists (JSON) or ndarrays (MessagePack) and become ndarrays; size limits come from the
validation context. Shape problems the engine knows better (rigid poses, feature
dimensions) are checked by the map manager, which names the field too.
"""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    Strict,
    StrictInt,
    StringConstraints,
    TypeAdapter,
    ValidationError,
    ValidationInfo,
    WithJsonSchema,
    field_validator,
    model_validator,
)
from pydantic.json_schema import SkipJsonSchema

from sgvloc.core import leave_out
from sgvloc.core.confidence import Calibration
from sgvloc.core.config import LocalizerConfig, RerankMethod, RetrievalConfig
from sgvloc.core.encoders import EncoderSpec
from sgvloc.core.errors import InputError
from sgvloc.core.pose import check_rigid
from sgvloc.core.prior import DEFAULT_YAW_TOLERANCE_DEG, Prior
from sgvloc.core.tracking import Seed

from ..maps import (
    KEY_MAX_CHARS,
    SEQUENCE_MAX_CHARS,
    TAG_NAME_MAX_CHARS,
    TAG_VALUE_MAX_CHARS,
    TAGS_MAX,
    FeaturesIn,
    KeyframeIn,
    at_field,
    field_error,
)
from ..settings import Settings
from ..store import no_nul, plain_json

#: bound of a map's recorded self-test (JSON bytes)
SELF_TEST_MAX_BYTES = 16384
_INT = TypeAdapter(int)


def limits(settings: Settings) -> dict[str, int]:
    """The validation context carrying the request size limits."""
    return {
        "max_points": settings.max_points,
        "max_keypoints": settings.max_keypoints,
        "max_batch": settings.max_batch,
        "max_top_k": settings.max_top_k,
    }


def _limit(info: ValidationInfo, name: str) -> int | None:
    return (info.context or {}).get(name)


def map_top_k_problem(top_k: int, cap: int | None) -> str | None:
    """Why a map's default top_k is refused: it must stay within max_top_k, as a
    request's (else a map setting would take every localize of it past the limit)."""
    if cap is not None and top_k > cap:
        return f"top_k {top_k} exceeds the limit of {cap} (max_top_k)"
    return None


def patch_top_k(localizer: dict[str, Any] | None) -> int | None:
    """The ``top_k`` a PATCH's localizer settings set, read as the merged settings will
    read it ("500" and 500.0 are 500 there); None when unset or unreadable (the merge
    then names what is wrong with it)."""
    top_k = (localizer or {}).get("top_k")
    if top_k is None or isinstance(top_k, bool):
        return None
    try:
        return _INT.validate_python(top_k)
    except ValidationError:
        return None


def _to_ndarray(value: Any) -> np.ndarray:
    if isinstance(value, np.ndarray):
        arr = value
    else:
        if not isinstance(value, list):
            raise ValueError(f"must be an array, got {type(value).__name__}")
        try:
            arr = np.asarray(value)  # its own dtype first: strings and booleans stay so
        except (ValueError, TypeError):
            raise ValueError("must be a rectangular array of numbers") from None
        if arr.dtype.kind == "O":  # null, or true/false, among numbers; integers beyond int64
            flat = arr.ravel()
            if any(v is None for v in flat):
                raise ValueError("holds null where a number belongs")
            if any(isinstance(v, bool | np.bool_) for v in flat):
                raise ValueError("holds true or false where a number belongs")
            try:
                arr = arr.astype(np.float64)
            except (ValueError, TypeError):
                raise ValueError("must be a rectangular array of numbers") from None
            except OverflowError:  # a JSON integer of more than 308 digits
                raise ValueError("holds a number beyond the float64 range") from None
        if arr.dtype.kind in "fiu":
            arr = arr.astype(np.float64, copy=False)
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"must be numeric, got dtype {arr.dtype}")
    return arr


#: a numeric array: nested lists in JSON, an ``__nd__`` map in MessagePack
Array = Annotated[
    Any,
    BeforeValidator(_to_ndarray),
    WithJsonSchema(
        {
            "type": "array",
            "description": "numeric array: nested lists (JSON) or an __nd__ map (MessagePack)",
        }
    ),
]
Matrix4 = Annotated[list[list[float]], Field(description="4x4 row-major float64")]


def _shape(arr: np.ndarray) -> list[int]:
    return [int(s) for s in arr.shape]


def check_points(arr: np.ndarray, max_points: int | None) -> np.ndarray:
    """A scan ``[P, 3|4]``, non-empty, finite, at most ``max_points`` rows."""
    if arr.ndim != 2 or arr.shape[1] not in (3, 4):
        raise ValueError(f"must have shape [P, 3] or [P, 4], got {_shape(arr)}")
    if arr.shape[0] == 0:
        raise ValueError("is empty: a scan needs at least one point")
    if max_points is not None and arr.shape[0] > max_points:
        raise ValueError(f"has {arr.shape[0]} points, the limit is {max_points}")
    bad = int(arr.size - np.count_nonzero(np.isfinite(arr)))
    if bad:
        raise ValueError(f"contains {bad} non-finite value(s) (NaN or inf)")
    return arr


class _In(BaseModel):
    model_config = ConfigDict(extra="forbid", arbitrary_types_allowed=True, allow_inf_nan=False)


# -- maps ---------------------------------------------------------------------------------


class MapCreate(_In):
    """``POST /v1/maps``."""

    name: str = Field(description="^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
    encoder: EncoderSpec | None = Field(None, description="defaults to the learned BEV encoder")
    retrieval: RetrievalConfig | None = Field(
        None, description="FAISS index settings (same as localizer.retrieval)"
    )
    localizer: LocalizerConfig | None = Field(None, description="top_k, rerank, sgv, pose, ...")
    keep_clouds: bool = Field(
        True,
        description="store each keyframe's preprocessed cloud, used by ICP refinement and "
        "verification (refine=icp, the default); false saves memory and disk",
    )
    calibration: dict[str, Any] | None = Field(
        None,
        description="confidence model as written by 'sgvloc calibrate' (default: the one "
        "shipped for the encoder kind); recorded with the map",
    )
    self_test: dict[str, Any] | None = Field(
        None,
        description="an encoder self-test to record with the map (sgvloc build-map "
        f"--choose-encoder writes one); JSON of at most {SELF_TEST_MAX_BYTES} bytes",
    )

    @field_validator("self_test", "calibration", mode="before")
    @classmethod
    def _plain(cls, v: Any) -> Any:
        return plain_json(v) if isinstance(v, dict) else v

    @field_validator("self_test")
    @classmethod
    def _self_test_size(cls, v: dict[str, Any] | None) -> dict[str, Any] | None:
        if v is not None and len(json.dumps(v).encode()) > SELF_TEST_MAX_BYTES:
            raise ValueError(f"longer than {SELF_TEST_MAX_BYTES} bytes as JSON")
        return v

    @model_validator(mode="after")
    def _one_retrieval(self) -> MapCreate:
        if (
            self.retrieval is not None
            and self.localizer is not None
            and "retrieval" in self.localizer.model_fields_set
        ):
            raise ValueError("give retrieval settings once: in retrieval or localizer.retrieval")
        return self

    def localizer_config(self) -> LocalizerConfig:
        cfg = self.localizer or LocalizerConfig()
        if self.retrieval is not None:
            cfg = cfg.model_copy(update={"retrieval": self.retrieval})
        return cfg


def parse_calibration(value: dict[str, Any] | str | None, where: str) -> Calibration | None:
    """A calibration from a request body: an object written by ``sgvloc calibrate``, or
    ``"shipped"`` (None here: the caller takes the shipped one)."""
    if value is None or value == "shipped":
        return None
    if isinstance(value, str):
        raise field_error(InputError("must be a calibration object or 'shipped'"), where)
    with at_field(where):
        return Calibration.from_dict(value)


class MapPatch(_In):
    """``PATCH /v1/maps/{map}``: change settings after creation (keyframes untouched)."""

    localizer: dict[str, Any] | None = Field(
        None,
        description="merged into the map's localizer settings, e.g. "
        '{"verdict": {"min_confidence": 0.9}, "top_k": 30}; retrieval cannot change',
    )
    calibration: Annotated[
        Any,
        WithJsonSchema({"anyOf": [{"type": "object"}, {"const": "shipped"}]}),
    ] = Field(
        None,
        description="a calibration written by 'sgvloc calibrate', or 'shipped' for the one "
        "this installation ships for the map's encoder kind",
    )

    # not a setting to change: named only to say why (keyframes hold its features)
    encoder: SkipJsonSchema[Any] = Field(None, exclude=True)

    @field_validator("calibration")
    @classmethod
    def _calibration(cls, v: Any) -> Any:
        if v is not None and v != "shipped" and not isinstance(v, dict):
            raise ValueError("must be a calibration object or 'shipped'")
        return plain_json(v) if isinstance(v, dict) else v

    @field_validator("encoder")
    @classmethod
    def _encoder(cls, v: Any) -> Any:
        raise ValueError(
            "cannot be changed: the keyframes hold this encoder's features; build a new "
            "map with the other encoder (sgvloc build-map, or POST /v1/maps and insert the "
            "scans again)"
        )

    @model_validator(mode="after")
    def _something(self) -> MapPatch:
        if self.localizer is None and self.calibration is None:
            raise ValueError("give localizer settings and/or a calibration to change")
        return self


class CalibrationInfo(BaseModel):
    """The confidence model a map answers with."""

    name: str
    fingerprint: str
    encoder_kind: str = Field(description="the encoder kind it was fitted for")


class EncoderInfo(BaseModel):
    """The encoder a map was built with."""

    kind: str
    name: str
    fingerprint: str
    global_dim: int
    global_descriptor: str = Field(
        description="what the global descriptor is: the encoder kind's own, or for the "
        "learned encoder 'polar', 'network' or 'polar+network'"
    )
    global_blocks: list[int] = Field(
        description="lengths of the descriptor's blocks (several: retrieval searches each "
        "and merges their candidates, localizer.retrieval.combine)"
    )
    local_dim: int
    spec: dict[str, Any]


class MapInfo(BaseModel):
    """A map: name, version, size and settings."""

    name: str
    version: int = Field(description="changes on every keyframe insert or delete")
    keyframes: int
    encoder: EncoderInfo
    retrieval: RetrievalConfig
    localizer: dict[str, Any] = Field(description="the map's full localizer settings")
    index_kind: str = Field(description="FAISS index in use now (ivf reads flat until trained)")
    keep_clouds: bool
    created_at: str = Field(description="ISO 8601 UTC")
    calibration: CalibrationInfo
    settings_version: int = Field(description="changes of the settings after creation (PATCH)")
    settings_updated_at: str | None = Field(description="ISO 8601 UTC of the last change")
    self_test: dict[str, Any] | None = Field(
        None,
        description="the encoder self-test the map was built after (sgvloc build-map "
        "--choose-encoder): figures per encoder and the one chosen",
    )
    last_self_test: dict[str, Any] | None = Field(
        None,
        description="the summary of the latest leave-out self-test of the served map "
        "(POST /v1/maps/{map}/self-test)",
    )


class SelfTestRequest(BaseModel):
    """``POST /v1/maps/{map}/self-test``: the map's keyframes localized against the others."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    queries: int = Field(
        50, ge=1, le=200, description="at most this many queries in coverage (as many out)"
    )
    gap_s: float = Field(
        30.0,
        gt=0,
        le=86400,
        description="leave out each query's keyframes closer than this in time "
        "(metadata.timestamp, seconds)",
    )
    gap_keyframes: int = Field(
        30,
        ge=1,
        le=100000,
        description="the same in insertion order, when not every keyframe has a timestamp",
    )
    radius_m: float = Field(
        5.0, gt=0, le=100, description="a keyframe left to search within this is a revisit"
    )
    encoders: list[str] | None = Field(
        None,
        min_length=1,
        max_length=len(leave_out.CANDIDATES),
        description="also measure these encoders on the same queries, each from the "
        "keyframes' stored clouds encoded again, and name the best: any of "
        + ", ".join(leave_out.CANDIDATES)
        + " (maps that keep clouds, of at most max_self_test_keyframes keyframes)",
    )

    @field_validator("encoders")
    @classmethod
    def _candidates(cls, v: list[str] | None) -> list[str] | None:
        if v is None:
            return v
        unknown = [n for n in v if n not in leave_out.CANDIDATES]
        if unknown:
            raise ValueError(
                f"unknown encoder {unknown[0]!r}: choose from {', '.join(leave_out.CANDIDATES)}"
            )
        if len(set(v)) != len(v):
            raise ValueError("names an encoder twice")
        return v


class SelfTestReport(BaseModel):
    """The figures of a map's leave-out self-test and its per-query records."""

    format: str
    map_version: int
    encoder: str = Field(description="the map's encoder kind (learned, handcrafted, bev, ...)")
    basis: str = Field(description="what the gap was measured in: timestamp | insertion order")
    settings: dict[str, Any]
    figures: dict[str, Any] = Field(
        description="queries, negatives, recall_at_1, pose_success, accepted_of_correct "
        "(percent), false_accepts, median_ms"
    )
    seconds: float
    records: list[dict[str, Any]]
    encoders: dict[str, dict[str, Any]] | None = Field(
        None,
        description="with encoders asked for: per encoder its spec, fingerprint, figures "
        "(as figures), keyframes it could not encode (unencoded), seconds and records "
        "(the records are not kept in last_self_test)",
    )
    chosen: str | None = Field(
        None,
        description="the best of encoders, by rule (ties: the map's own, then the order asked)",
    )
    rule: str | None = Field(None, description="how chosen was picked")
    warning: str | None = Field(
        None, description="set when even the chosen encoder localizes under half the queries"
    )


class MapList(BaseModel):
    """``GET /v1/maps``: one page of maps, by name."""

    maps: list[MapInfo]
    next_cursor: str | None = Field(
        None, description="pass as cursor for the next page; null on the last page"
    )
    total: int = Field(
        0, description="maps the key may use whose name starts with prefix, on every page"
    )


# -- keyframes ----------------------------------------------------------------------------


class FeaturesBody(_In):
    """Precomputed features; ``encoder``/``fingerprint`` optionally claim their encoder."""

    global_descriptor: Array
    keypoints: Array
    local_features: Array
    encoder: str | None = Field(
        None, description="encoder name (e.g. 'handcrafted', 'egonn'); 409 if not the map's"
    )
    fingerprint: str | None = Field(None, description="encoder fingerprint; 409 if not the map's")

    @field_validator("keypoints", "local_features")
    @classmethod
    def _rows(cls, v: np.ndarray, info: ValidationInfo) -> np.ndarray:
        cap = _limit(info, "max_keypoints")
        if v.ndim >= 1 and cap is not None and v.shape[0] > cap:
            raise ValueError(f"has {v.shape[0]} keypoints, the limit is {cap} (max_keypoints)")
        return v

    def to_input(self) -> FeaturesIn:
        return FeaturesIn(
            self.global_descriptor,
            self.keypoints,
            self.local_features,
            encoder=self.encoder,
            fingerprint=self.fingerprint,
        )


#: text a store keeps: any string without NUL characters
Text = Annotated[str, AfterValidator(no_nul)]
#: a keyframe tag's name and value
TagName = Annotated[str, StringConstraints(max_length=TAG_NAME_MAX_CHARS), AfterValidator(no_nul)]
TagValue = Annotated[str, StringConstraints(max_length=TAG_VALUE_MAX_CHARS), AfterValidator(no_nul)]


class KeyframeMetadata(_In):
    """Optional keyframe metadata."""

    timestamp: Annotated[float, Strict()] | None = Field(
        None, allow_inf_nan=False, description="seconds"
    )
    sequence: Text | None = Field(None, max_length=SEQUENCE_MAX_CHARS)
    tags: dict[TagName, TagValue] | None = Field(
        None,
        max_length=TAGS_MAX,
        description=f"at most {TAGS_MAX}; names up to {TAG_NAME_MAX_CHARS} characters, "
        f"values {TAG_VALUE_MAX_CHARS}",
    )


class KeyframeBody(_In):
    """One keyframe: a pose and exactly one of ``points`` / ``features``."""

    key: Text | None = Field(
        None, min_length=1, max_length=KEY_MAX_CHARS, description="makes the insert idempotent"
    )
    T_map_sensor: Array = Field(description="4x4 rigid transform, row-major")
    points: Array | None = Field(None, description="[P, 3|4] scan, sensor frame")
    features: FeaturesBody | None = None
    metadata: KeyframeMetadata | None = None

    @field_validator("points")
    @classmethod
    def _points(cls, v: np.ndarray | None, info: ValidationInfo) -> np.ndarray | None:
        return None if v is None else check_points(v, _limit(info, "max_points"))

    @model_validator(mode="after")
    def _one_source(self) -> KeyframeBody:
        if (self.points is None) == (self.features is None):
            raise ValueError("give exactly one of points or features")
        return self

    def to_input(self) -> KeyframeIn:
        meta = self.metadata.model_dump(exclude_none=True) if self.metadata else {}
        return KeyframeIn(
            T_map_sensor=self.T_map_sensor,
            points=self.points,
            features=None if self.features is None else self.features.to_input(),
            key=self.key,
            metadata=meta,
        )


class KeyframeBatch(_In):
    """``POST /v1/maps/{map}/keyframes``."""

    keyframes: list[KeyframeBody]

    @field_validator("keyframes")
    @classmethod
    def _count(cls, v: list[KeyframeBody], info: ValidationInfo) -> list[KeyframeBody]:
        cap = _limit(info, "max_batch")
        if not v:
            raise ValueError("at least one keyframe is required")
        if cap is not None and len(v) > cap:
            raise ValueError(f"has {len(v)} keyframes, the limit per request is {cap}")
        return v

    @field_validator("keyframes", mode="before")
    @classmethod
    def _count_early(cls, v: Any, info: ValidationInfo) -> Any:
        # refuse an oversized batch before validating every item in it
        cap = _limit(info, "max_batch")
        if isinstance(v, list) and cap is not None and len(v) > cap:
            raise ValueError(f"has {len(v)} keyframes, the limit per request is {cap}")
        return v


class InsertOut(BaseModel):
    """Per keyframe, in request order: its id and whether it was created now."""

    ids: list[int]
    created: list[bool]
    map_version: int


class KeyframeOut(BaseModel):
    """A stored keyframe."""

    id: int
    key: str | None
    T_map_sensor: Matrix4
    metadata: dict[str, Any]
    num_keypoints: int
    created_at: str


class KeyframeDeleted(BaseModel):
    """``DELETE /v1/maps/{map}/keyframes/{id}``."""

    deleted: int
    map_version: int


class KeyframeSummaryOut(BaseModel):
    """One keyframe of a listing (no features)."""

    id: int
    key: str | None
    T_map_sensor: Matrix4
    position: list[float] = Field(description="x, y, z of the pose in map coordinates")
    metadata: dict[str, Any]
    created_at: str


class KeyframePage(BaseModel):
    """``GET /v1/maps/{map}/keyframes``: one page of a listing, by id."""

    keyframes: list[KeyframeSummaryOut]
    next_cursor: str | None = Field(
        description="pass as ``cursor`` for the next page; null on the last page"
    )


class KeyframesDeleted(BaseModel):
    """``DELETE /v1/maps/{map}/keyframes``: how many keyframes one transaction deleted."""

    deleted: int
    map_version: int


class ExtentOut(BaseModel):
    """The bounding box of the keyframe positions (map coordinates, metres)."""

    min: list[float]
    max: list[float]


class MapStats(BaseModel):
    """``GET /v1/maps/{map}/stats``."""

    map: str
    version: int
    keyframes: int
    extent: ExtentOut | None = Field(description="null while the map is empty")
    disk_bytes: int = Field(description="the map's folder: store, index snapshot")
    memory_bytes: int = Field(
        description="keyframe arrays (features, clouds, poses) and index vectors held in memory"
    )
    index_kind: str
    created_at: str
    last_write: str | None = Field(
        description="last keyframe insert or delete (null if none since this was recorded)"
    )


# -- localize -----------------------------------------------------------------------------


#: a finite number: an integer or a float, not a string, a boolean, NaN or inf
Finite = Annotated[float, Field(strict=True, allow_inf_nan=False)]


class PriorBody(_In):
    """A prior pose: position (map frame) within a radius, optionally a heading."""

    position: list[Finite] = Field(
        min_length=2, max_length=3, description="[x, y] or [x, y, z] in map coordinates (m)"
    )
    radius_m: Finite = Field(gt=0.0, le=1e6, description="search radius (m)")
    yaw_deg: Finite | None = Field(None, description="heading of the sensor's x axis (deg)")
    yaw_tolerance_deg: Finite = Field(
        DEFAULT_YAW_TOLERANCE_DEG, gt=0.0, le=180.0, description="allowed heading error (deg)"
    )

    def to_prior(self) -> Prior:
        return Prior(tuple(self.position), self.radius_m, self.yaw_deg, self.yaw_tolerance_deg)


class SeedBody(_In):
    """Where the sensor is believed to be, for tracking: a pose and its 1-sigma errors."""

    T_map_sensor: Array = Field(description="4x4 rigid transform, row-major: the predicted pose")
    sigma_m: Finite = Field(gt=0.0, le=1e4, description="position uncertainty, 1 sigma (m)")
    sigma_yaw_deg: Finite = Field(gt=0.0, le=180.0, description="heading uncertainty (deg)")

    def to_seed(self) -> Seed:
        with at_field("seed.T_map_sensor"):
            T = check_rigid(self.T_map_sensor, "T_map_sensor")
        return Seed(T, float(self.sigma_m), float(self.sigma_yaw_deg))


class LocalizeBody(_In):
    """``POST /v1/maps/{map}/localize``: a scan or features, and per-request options."""

    points: Array | None = Field(None, description="[P, 3|4] scan, sensor frame")
    features: FeaturesBody | None = None
    top_k: StrictInt | None = Field(
        None,
        ge=1,
        description="candidates retrieved (map default; per descriptor block when the map "
        "merges several, localizer.retrieval.combine); an integer, not '5' or true",
    )
    rerank: RerankMethod | None = Field(None, description="re-ranking method (map default)")
    refine: Literal["none", "icp"] | None = Field(None, description="ICP after RANSAC")
    prior: PriorBody | None = Field(
        None,
        description="where the sensor is believed to be (e.g. GNSS): only keyframes inside "
        "the radius are searched, an estimate outside the region is rejected",
    )
    min_confidence: Annotated[Finite, Field(ge=0.0, le=1.0)] | None = Field(
        None, description="accept when confidence >= this (map default: verdict.min_confidence)"
    )
    seed: SeedBody | None = Field(
        None,
        description="track: register the scan against the map around this pose (needs "
        "points); if the fit fails, localize globally with the seed as a prior",
    )

    @field_validator("points")
    @classmethod
    def _points(cls, v: np.ndarray | None, info: ValidationInfo) -> np.ndarray | None:
        return None if v is None else check_points(v, _limit(info, "max_points"))

    @field_validator("top_k")
    @classmethod
    def _top_k(cls, v: int | None, info: ValidationInfo) -> int | None:
        cap = _limit(info, "max_top_k")
        if v is not None and cap is not None and v > cap:
            raise ValueError(f"is {v}, the limit is {cap}")
        return v

    @model_validator(mode="after")
    def _one_source(self) -> LocalizeBody:
        if (self.points is None) == (self.features is None):
            raise ValueError("give exactly one of points or features")
        return self


class CandidateOut(BaseModel):
    """A candidate keyframe: retrieval similarity and rank, re-ranking score."""

    keyframe_id: int
    similarity: float
    retrieval_rank: int = Field(description="0-based; -1 if found only by query expansion")
    score: float


class PoseOut(BaseModel):
    """Diagnostics of the pose estimate."""

    inliers: int
    num_correspondences: int
    fitness: float
    inlier_rmse: float = Field(description="metres")
    refined: bool
    icp: dict[str, Any] = Field(
        default_factory=dict,
        description="ICP diagnostics: used, fitness, inlier_rmse (or why it was not used)",
    )


class TimingsOut(BaseModel):
    """Stage durations in milliseconds (a stage that did not run reads 0)."""

    encode: float = 0.0
    retrieve: float = 0.0
    rerank: float = 0.0
    pose: float = 0.0
    verify: float = Field(0.0, description="evidence, confidence and verdict")
    track: float = Field(0.0, description="a seeded fit: submap and registration")
    total: float = 0.0


class EstimateOut(BaseModel):
    """The best pose estimate, whether or not it was accepted."""

    T_map_sensor: Matrix4 = Field(description="query pose in the map frame")
    T_keyframe_sensor: Matrix4 = Field(description="query pose in the keyframe frame")
    translation: list[float] = Field(description="T_map_sensor translation [x, y, z]")
    quaternion_xyzw: list[float] = Field(description="rotation, [x, y, z, w] (scalar last)")


class PriorOut(BaseModel):
    """How the request's prior restricted the search."""

    used: bool
    keyframes_in_radius: int


class TrackingOut(BaseModel):
    """How a seeded fit went (``mode`` tracked or relocalized)."""

    fitness: float = Field(description="share of scan points within inlier_distance_m")
    fitness_fine: float = Field(description="share of scan points within 0.2 m")
    rmse_m: float = Field(description="RMSE of those points (-1: none)")
    conditioning: float = Field(
        description="log10 smallest/largest eigenvalue of the fit's translation information: "
        "very negative when the scan can slide along the map (a corridor)"
    )
    information: float = Field(description="log10 of the smallest such eigenvalue per inlier")
    iterations: int
    submap_keyframes: int
    submap_points: int
    scan_points: int
    seed_offset_m: float = Field(description="distance of the fit from the seed (-1: no fit)")
    seed_offset_deg: float = Field(description="rotation between the fit and the seed (deg)")
    why: str = Field(description="why the fit was (not) trusted")


class LocalizeOut(BaseModel):
    """Where the scan is in the map, with the candidates and diagnostics behind it.

    ``localized`` is the verdict to act on: ``T_map_sensor`` and friends are null unless
    it is true. ``estimate`` holds the best estimate either way (null only without one),
    ``confidence`` the calibrated probability that it is within 2 m and 5 deg."""

    map: str
    map_version: int = Field(description="the map version that answered")
    localized: bool
    verdict: str = Field(
        description="why: localized | low_confidence | pose_check | outside_prior | "
        "no_estimate | no_keyframe_in_prior | no_keyframes | tracking_failed"
    )
    reason: str
    mode: Literal["global", "tracked", "relocalized"] = Field(
        description="global search; tracked (registered around the request's seed); "
        "relocalized (the seed's fit failed, the global path answered)"
    )
    tracking: TrackingOut | None = Field(description="the seeded fit; null without a seed")
    confidence: float = Field(description="probability that the estimate is within 2 m, 5 deg")
    min_confidence: float = Field(description="the acceptance threshold applied")
    keyframe_id: int | None = Field(description="the re-ranked top-1 the pose was taken from")
    T_map_sensor: Matrix4 | None = Field(
        description="query pose in the map frame (null unless localized)"
    )
    T_keyframe_sensor: Matrix4 | None = Field(
        description="query pose in the keyframe frame (null unless localized)"
    )
    translation: list[float] | None = Field(description="T_map_sensor translation [x, y, z]")
    quaternion_xyzw: list[float] | None = Field(
        description="T_map_sensor rotation, [x, y, z, w] (scalar last)"
    )
    estimate: EstimateOut | None = Field(
        description="the best estimate, also when it was rejected (null without one)"
    )
    evidence: dict[str, Any] | None = Field(
        description="what the confidence was computed from (sgv, sgv_margin, similarity, "
        "inliers, inlier_ratio, icp_fitness, icp_rmse, icp_constraint, free_space, "
        "agreement, offset_m, planar)"
    )
    prior: PriorOut | None = Field(description="null when the request had no prior")
    pose: PoseOut | None
    retrieved: list[CandidateOut] = Field(description="retrieval order")
    reranked: list[CandidateOut] = Field(description="after re-ranking, best first")
    top1_changed: bool
    rerank_method: str
    timings_ms: TimingsOut


# -- probes -------------------------------------------------------------------------------


class Health(BaseModel):
    """``GET /healthz``."""

    status: Literal["ok"] = "ok"


class Ready(BaseModel):
    """``GET /readyz``."""

    status: Literal["ready", "loading", "degraded", "failed"] = Field(
        description="degraded (503): every map loaded except those under failed; failed "
        "(503): loading the maps failed as a whole (a store this sgvloc cannot read) and "
        "the process stops, its log saying why"
    )
    maps: int
    failed: dict[str, str] = Field(
        default_factory=dict,
        description="map folders that could not be loaded, and why: shown to a caller with "
        "a key (of those maps it may use); an open probe without one sees only failed_maps",
    )
    failed_maps: int = Field(0, description="how many map folders could not be loaded")
    store_reachable: bool | None = Field(
        None,
        description="a shared PostgreSQL store: false while it does not answer this replica "
        "(loading waits for it; writes fail with 503 store_unavailable; localizations go on "
        "from the maps in memory, so readiness does not change once loaded); null with SQLite",
    )


class LimitsOut(BaseModel):
    """The request limits and admission settings in force."""

    max_body_bytes: int = Field(description="413 above this")
    max_json_body_bytes: int = Field(description="413 above this for a JSON body")
    max_body_memory_bytes: int = Field(
        description="request bodies in memory at once, over all requests (503 above this)"
    )
    max_points: int = Field(description="points per scan (422)")
    max_keypoints: int = Field(
        description="keypoints per feature set, and a new map's encoder num_keypoints (422)"
    )
    max_batch: int = Field(description="keyframes per insert request (422)")
    max_top_k: int = Field(
        description="largest top_k of a localize request and of a map's settings (422)"
    )
    max_import_bytes: int = Field(description="largest map archive an import takes (413)")
    max_self_test_keyframes: int = Field(
        description="largest map a self-test compares encoders on (422 on encoders)"
    )
    max_inflight_localize: int = Field(description="localize requests admitted at once (429)")
    request_timeout_s: float = Field(description="longest wait for a worker thread (503)")
    retry_after_s: int = Field(description="Retry-After of 429/503 answers")
    header_timeout_s: float = Field(
        description="longest a request's headers may take to arrive (then the connection is closed)"
    )
    body_timeout_s: float = Field(description="longest a request body may take to arrive (408)")
    send_timeout_s: float = Field(
        description="longest a client may take none of an answer (then the connection is closed)"
    )
    workers: int = Field(description="threads running CPU work")
    write_workers: int = Field(
        description="of the workers, how many may run map changes and long jobs at once"
    )
    threads_per_worker: int = Field(
        description="threads each numeric library may use inside one request (as configured; "
        "OMP_NUM_THREADS and the like set by the operator take precedence)"
    )
    spare_cores: int = Field(
        description="cores that requests share while some are idle (setting spare_cores): "
        "the network forward and ICP with its fitness pass take this // busy workers threads; "
        "1 = off"
    )


class KeysReloaded(BaseModel):
    """``POST /v1/keys/reload``: the keys now in force (counts, never keys)."""

    keys: int
    by_role: dict[str, int]


class AuthOut(BaseModel):
    """How callers are authenticated (never the keys)."""

    enabled: bool = Field(description="false only in development mode")
    keys: int | None = Field(description="configured keys (null to a key limited to some maps)")
    metrics: Literal["open", "viewer"]
    readyz: Literal["open", "viewer"]


class BatchingOut(BaseModel):
    """Dynamic batching in force (settings ``batch_wait_ms``, ``batch_max``)."""

    enabled: bool
    wait_ms: float = Field(description="0 = off")
    max_size: int


class StoreOut(BaseModel):
    """Where the maps are kept."""

    kind: Literal["sqlite", "postgresql"] = Field(
        description="sqlite: one database per map on this replica's disk; postgresql: "
        "one store shared by every replica"
    )
    location: str | None = Field(
        description="the data directory, or the store URL without password (null to a key "
        "limited to some maps)"
    )
    local_features: Literal["memory", "store"]
    feature_cache: int
    follow_poll_s: float
    catch_up_wait_s: float
    caught_up_failures: int = Field(
        description="failed catch-ups with the shared store in a row (0: following it)"
    )


class ConfigOut(BaseModel):
    """``GET /v1/config``: the service's limits and access settings."""

    version: str
    limits: LimitsOut
    auth: AuthOut
    batching: BatchingOut
    store: StoreOut
    snapshot_every: int
    snapshot_delay_s: float
    shutdown_timeout_s: float = Field(
        description="on SIGTERM, longest wait for open requests and for map loading"
    )


class ErrorDetail(BaseModel):
    """What went wrong."""

    code: str
    message: str
    field: str | None = None


class ErrorOut(BaseModel):
    """The body of every 4xx/5xx answer."""

    error: ErrorDetail
