"""The localizer: encode -> retrieve top-k -> re-rank -> pose, as in the paper's Fig. 1.

A :class:`Localizer` holds one map in memory: keyframes (pose, features, optional
downsampled cloud for ICP) and a FAISS index of their global descriptors. It is safe to
use from many threads: localizations run concurrently, inserts and removals are
exclusive. Persistence is the caller's business (the service keeps SQLite as the source
of truth and feeds keyframes in with :meth:`Localizer.add_keyframe`).
"""

from __future__ import annotations

import functools
import itertools
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any

import numpy as np

from . import batching
from ._rwlock import RWLock
from .cache import BuildCache, FetchCache
from .confidence import (
    AGREEMENT_CANDIDATES,
    Calibration,
    Evidence,
    SpectralCandidate,
    assess,
    nearest_of_place,
    shipped_calibration,
    spectral_candidates,
)
from .config import LocalizerConfig
from .deadline import check as check_deadline
from .encoders import Encoder
from .errors import ConflictError, EmptyScanError, InputError, NotFoundError
from .features import Features
from .freespace import RADIUS_M, RangeImage, thin, views_near, violation
from .pose import IcpTarget, PoseResult, check_rigid, ransac_pose, refine_icp
from .prior import PositionGrid, Prior, yaw_deg
from .rerank import Candidate, RerankOutput, check_method, rerank
from .retrieval import FaissIndex, retrieve
from .tracking import (
    Seed,
    Submap,
    TrackResult,
    build_submap,
    register,
    tracked_confidence,
)

log = logging.getLogger(__name__)


def _under_way(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Count the call as a localization under way for dynamic batching, whose batches
    wait only for localizations that could still join (:mod:`sgvloc.core.batching`)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with batching.localizing():
            return fn(*args, **kwargs)

    return wrapper


#: keyframe clouds kept indexed for ICP per map (about 0.3 MB each at 5k points)
ICP_CACHED_KEYFRAMES = 64
#: keyframe range images kept for the free-space check per map (about 0.13 MB each)
RANGE_IMAGES_CACHED = 64


@dataclass
class Keyframe:
    """A map keyframe: its pose in the map, its features and optional metadata."""

    id: int
    T_map_sensor: np.ndarray  # [4, 4] float64
    features: Features
    cloud: np.ndarray | None = None  # [M, 3] preprocessed points, kept for ICP refinement
    metadata: dict[str, Any] = field(default_factory=dict)


@dataclass
class LocalizationResult:
    """Everything one localization produced.

    ``localized`` is the verdict: act on this answer. ``T_map_sensor`` is then the query's
    pose in the map frame (4x4, row-major, float64) and ``T_keyframe_sensor`` the query
    relative to the matched keyframe; both are ``None`` when ``localized`` is false.
    ``T_map_sensor_estimate`` / ``T_keyframe_sensor_estimate`` hold the best estimate
    whether or not it was accepted (``None`` only without any estimate).

    ``confidence`` is the calibrated probability that the estimate is within 2 m and
    5 degrees (:mod:`sgvloc.core.confidence`), ``evidence`` what it was computed from;
    ``verdict`` a reason code (:data:`~sgvloc.core.confidence.VERDICT_CODES`) and
    ``reason`` a sentence. ``prior``: how a prior restricted the search (None: no prior).
    ``retrieved`` is the candidate list in retrieval order, ``reranked`` after re-ranking
    (best first). ``timings_ms`` holds encode, retrieve, rerank, pose, verify and total
    (and track for a seeded request). ``mode`` says how the answer was found: ``global``
    search, ``tracked`` (registered against the map around the request's seed), or
    ``relocalized`` (the seed's fit failed and the global path answered); ``tracking``
    describes the seeded fit.
    """

    localized: bool
    reason: str
    keyframe_id: int | None
    pose: PoseResult | None
    retrieved: list[Candidate]
    reranked: list[Candidate]
    rerank_method: str
    timings_ms: dict[str, float]
    map_version: int
    verdict: str = "localized"
    confidence: float = 0.0
    min_confidence: float = 0.0
    evidence: Evidence | None = None
    T_map_sensor_estimate: np.ndarray | None = None
    T_keyframe_sensor_estimate: np.ndarray | None = None
    prior: dict[str, Any] | None = None
    mode: str = "global"  # global | tracked | relocalized (a seed's fit failed: global)
    tracking: dict[str, Any] | None = None  # the seeded fit (None without a seed)

    @property
    def T_map_sensor(self) -> np.ndarray | None:
        """The query's pose in the map, if ``localized``."""
        return self.T_map_sensor_estimate if self.localized else None

    @property
    def T_keyframe_sensor(self) -> np.ndarray | None:
        """The query's pose relative to the matched keyframe, if ``localized``."""
        return self.T_keyframe_sensor_estimate if self.localized else None

    @property
    def top1_changed(self) -> bool:
        """True when re-ranking put a different keyframe first."""
        return bool(self.retrieved and self.reranked) and (
            self.retrieved[0].keyframe_id != self.reranked[0].keyframe_id
        )


class Localizer:
    """One map and the pipeline that localizes scans in it."""

    def __init__(
        self,
        encoder: Encoder,
        config: LocalizerConfig | None = None,
        *,
        keep_clouds: bool = True,
        calibration: Calibration | None = None,
        keyframe_source: FetchCache[Keyframe] | None = None,
    ) -> None:
        self.encoder = encoder
        #: where whole keyframes (keypoints, local features, cloud) come from when the
        #: map holds only their poses and global descriptors in memory; None: in memory
        self.keyframe_source = keyframe_source
        self.config = config or LocalizerConfig()
        self.keep_clouds = keep_clouds
        #: the confidence model (default: the one shipped for the encoder's kind)
        self.calibration = calibration or shipped_calibration(_encoder_kind(encoder))
        self.index = FaissIndex(encoder.global_dim, self.config.retrieval)
        self._keyframes: dict[int, Keyframe] = {}
        self._grid = PositionGrid()  # keyframe positions, for prior-restricted retrieval
        self._next_id = itertools.count(1)
        self._lock = RWLock()
        self.version = 0  # changes on every insert and removal
        self._submaps: BuildCache[Submap | None] = BuildCache(self.config.tracking.cached_submaps)
        #: keyframe clouds indexed for ICP, by (keyframe id, id of the cloud array): the
        #: entry holds the array, so its id cannot be reused while the entry lives
        self._icp_targets: BuildCache[IcpTarget] = BuildCache(ICP_CACHED_KEYFRAMES)
        #: (cloud, range image) of keyframes for the free-space check, keyed as the ICP
        #: targets (the entry holds the cloud for the same reason)
        self._range_images: BuildCache[tuple[np.ndarray, RangeImage]] = BuildCache(
            RANGE_IMAGES_CACHED
        )

    # -- the map ------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._keyframes)

    def keyframe(self, keyframe_id: int) -> Keyframe:
        try:
            return self._keyframes[int(keyframe_id)]
        except KeyError:
            raise NotFoundError(f"keyframe {keyframe_id} does not exist") from None

    def holds(self, keyframe_id: int) -> bool:
        return int(keyframe_id) in self._keyframes

    def keyframe_ids(self) -> list[int]:
        return sorted(self._keyframes)

    def keyframe_table(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Ids ``[N]``, positions ``[N, 3]`` and timestamps ``[N]`` (``metadata.timestamp``
        in seconds; None unless every keyframe has a numeric one) of the keyframes."""
        with self._lock.read():
            kfs = list(self._keyframes.values())
        ids = np.array([k.id for k in kfs], dtype=np.int64)
        xyz = np.array([k.T_map_sensor[:3, 3] for k in kfs], dtype=np.float64).reshape(-1, 3)
        stamps = [k.metadata.get("timestamp") for k in kfs]
        numeric = all(
            isinstance(t, (int, float)) and not isinstance(t, bool) and np.isfinite(t)
            for t in stamps
        )
        return ids, xyz, np.array(stamps, dtype=np.float64) if numeric and kfs else None

    def localize_keyframe(
        self, keyframe_id: int, among: np.ndarray
    ) -> tuple[Keyframe, LocalizationResult]:
        """Localize keyframe ``keyframe_id``'s stored features and cloud against the
        keyframes ``among`` (the leave-out self-test); returns the keyframe and the
        :class:`LocalizationResult`. As a live query of its scan would, it searches with
        its descriptor about the displaced centres too, computed again from its cloud
        (``retrieval.offset_m``; a keyframe stored without a cloud searches without)."""
        with self._lock.read():
            if int(keyframe_id) not in self._keyframes:
                raise ConflictError(f"keyframe {keyframe_id} was removed during the self-test")
            kf = self._whole([int(keyframe_id)])[int(keyframe_id)]
        features, centres = kf.features, self.config.retrieval.centres()
        if centres is not None and kf.cloud is not None and self.encoder.describes_displaced:
            variants = self.encoder.encode_query(kf.cloud, centres).global_variants
            features = replace(features, global_variants=variants)
        return kf, self.localize(features=features, cloud=kf.cloud, among=among)

    def whole_keyframes(self, ids: list[int]) -> dict[int, Keyframe]:
        """The keyframes ``ids`` that exist, with their features and clouds (from memory
        or the keyframe source)."""
        with self._lock.read():
            held = [int(i) for i in ids if int(i) in self._keyframes]
            return self._whole(held, gone_ok=True)

    def encode(self, scan: np.ndarray) -> Features:
        """Features of a raw scan ``[P, 3+]`` with this map's encoder."""
        return self.encoder.encode(scan)

    def make_keyframe(
        self,
        T_map_sensor: np.ndarray,
        *,
        scan: np.ndarray | None = None,
        features: Features | None = None,
        keyframe_id: int | None = None,
        metadata: dict[str, Any] | None = None,
    ) -> Keyframe:
        """Validate and encode a keyframe without adding it (for all-or-nothing batches)."""
        T = check_rigid(T_map_sensor, "T_map_sensor")
        if (scan is None) == (features is None):
            raise InputError("give exactly one of scan or features")
        cloud = None
        if features is None:
            cloud = self.encoder.prepare(scan)
            features = self.encoder.encode_cloud(cloud)
            if not self.keep_clouds:
                cloud = None
        else:
            self.encoder.check(features)
        kf_id = int(keyframe_id) if keyframe_id is not None else -1
        return Keyframe(kf_id, T, features, cloud, dict(metadata or {}))

    def add_keyframes(self, keyframes: list[Keyframe]) -> list[int]:
        """Add prepared keyframes atomically: all are added or none. Returns their ids.

        A keyframe with ``id < 0`` gets the next free id.
        """
        with self._lock.write():
            given = {kf.id for kf in keyframes if kf.id >= 0}
            ids = [kf.id if kf.id >= 0 else self._fresh_id(given) for kf in keyframes]
            dup = [i for i in ids if i in self._keyframes]
            if dup or len(set(ids)) != len(ids):
                raise ConflictError(f"keyframe id(s) already exist: {dup[:5] or ids}")
            for kf, i in zip(keyframes, ids, strict=True):
                kf.id = i
            self._put(keyframes)
            if keyframes:
                self.version += 1
            return ids

    def add_keyframe(self, T_map_sensor: np.ndarray, **kwargs: Any) -> int:
        """Encode (or validate) and add one keyframe; returns its id. See :meth:`make_keyframe`."""
        return self.add_keyframes([self.make_keyframe(T_map_sensor, **kwargs)])[0]

    def remove_keyframe(self, keyframe_id: int) -> None:
        self.remove_keyframes([keyframe_id])

    def remove_keyframes(self, keyframe_ids: list[int]) -> None:
        """Remove keyframes in one step (one version change); an unknown id raises
        :class:`NotFoundError` and removes nothing."""
        ids = list(dict.fromkeys(int(i) for i in keyframe_ids))  # each once, in order
        if not ids:
            return
        with self._lock.write():
            for i in ids:
                self.keyframe(i)
            self._drop(ids)
            self.version += 1

    def apply_changes(self, add: list[Keyframe], remove: list[int], version: int) -> None:
        """Apply writes another process made to the map's store, in one step: remove
        the ``remove`` ids held, add the ``add`` keyframes not held (ids kept), and take
        ``version``. Ids already in the wanted state are skipped, so a change applied
        twice changes nothing."""
        with self._lock.write():
            gone = dict.fromkeys(int(i) for i in remove if int(i) in self._keyframes)
            self._drop(list(gone))
            new = {kf.id: kf for kf in add if kf.id not in self._keyframes}  # each id once
            self._put(list(new.values()))
            self.version = int(version)

    def _put(self, keyframes: list[Keyframe]) -> None:
        """Add keyframes with new ids to the index, the table and the grid (write lock)."""
        if not keyframes:
            return
        descs = np.stack([kf.features.global_descriptor for kf in keyframes])
        self.index.add(np.asarray([kf.id for kf in keyframes], dtype=np.int64), descs)
        for kf in keyframes:
            self._keyframes[kf.id] = kf
            self._grid.add(kf.id, kf.T_map_sensor[:3, 3])

    def _drop(self, ids: list[int]) -> None:
        """Take held keyframe ids out of the index, the table and the grid (write lock)."""
        if not ids:
            return
        self.index.remove(np.asarray(ids, dtype=np.int64))
        for i in ids:
            del self._keyframes[i]
            self._grid.remove(i)

    def memory_bytes(self) -> int:
        """Bytes held by the keyframes' arrays (features, clouds, poses) and the index's
        vectors: the map's share of the process's memory, roughly."""
        with self._lock.read():
            total = self.index.memory_bytes()
            for kf in self._keyframes.values():
                f = kf.features
                total += kf.T_map_sensor.nbytes + f.global_descriptor.nbytes
                total += f.keypoints.nbytes + f.local_features.nbytes
                total += 0 if kf.cloud is None else kf.cloud.nbytes
        return total

    def restore(
        self, keyframes: list[Keyframe], version: int, index: FaissIndex | None = None
    ) -> None:
        """Replace the map's content with persisted keyframes (their ids kept) and version.

        ``index``: a loaded snapshot holding exactly these ids, used as is (no rebuild);
        without it the index is built from the keyframes' descriptors. For start-up from
        the service's store.
        """
        ids = [kf.id for kf in keyframes]
        if len(set(ids)) != len(ids) or any(i < 0 for i in ids):
            raise InputError("restored keyframes need distinct non-negative ids")
        if index is None:
            index = FaissIndex(self.encoder.global_dim, self.config.retrieval)
            if keyframes:
                descs = np.stack([kf.features.global_descriptor for kf in keyframes])
                index.add(np.asarray(ids, dtype=np.int64), descs)
        elif index.dim != self.encoder.global_dim or index.ids().tolist() != sorted(ids):
            raise ConflictError("the index snapshot does not hold exactly these keyframes")
        grid = PositionGrid()
        for kf in keyframes:
            grid.add(kf.id, kf.T_map_sensor[:3, 3])
        with self._lock.write():
            self.index = index
            self._keyframes = {kf.id: kf for kf in keyframes}
            self._grid = grid
            self.version = int(version)

    def update_settings(self, config: LocalizerConfig, calibration: Calibration) -> None:
        """Swap in new settings and calibration between localizations (the index's
        retrieval settings must stay as they are: it was built with them)."""
        if config.retrieval.index_settings() != self.config.retrieval.index_settings():
            raise InputError("the index's retrieval settings cannot change on a built index")
        with self._lock.write():
            self.config = config
            self.calibration = calibration
            self._submaps = BuildCache(config.tracking.cached_submaps)

    def _fresh_id(self, taken: set[int]) -> int:
        """The next id that no keyframe has, ``taken`` does not hold and the index does
        not keep (a removed id an HNSW index still holds until it compacts)."""
        while True:
            candidate = next(self._next_id)
            if candidate not in self._keyframes and candidate not in taken:
                if not self.index.retired(candidate):
                    return candidate

    # -- localization -------------------------------------------------------------------

    @_under_way
    def localize(
        self,
        scan: np.ndarray | None = None,
        *,
        features: Features | None = None,
        top_k: int | None = None,
        rerank_method: str | None = None,
        refine: str | None = None,
        prior: Prior | None = None,
        min_confidence: float | None = None,
        seed: Seed | None = None,
        cloud: np.ndarray | None = None,
        among: np.ndarray | None = None,
    ) -> LocalizationResult:
        """Localize a raw scan (or precomputed features) in this map.

        ``prior``: search only the keyframes inside its radius and reject an estimate
        outside its region; ``min_confidence``: this request's acceptance threshold
        (default: the map's ``verdict.min_confidence``). ``seed``: track: register the
        scan against the map around this pose first (:mod:`sgvloc.core.tracking`); if
        the fit fails, localize globally with the seed as a prior (``tracking.fallback``).
        ``cloud``: with ``features``, the query's prepared cloud (``encoder.prepare``), so
        that ICP can refine; ``among``: search only these keyframe ids (the map's leave-out
        self-test, :mod:`sgvloc.core.leave_out`).
        """
        if seed is not None:
            if scan is None:
                raise InputError("seed: tracking needs the raw scan (points), not features")
            t_start = time.perf_counter()
            threshold = self.config.verdict.min_confidence
            if min_confidence is not None:
                if not 0.0 <= min_confidence <= 1.0:
                    raise InputError(f"min_confidence must be in [0, 1], got {min_confidence}")
                threshold = min_confidence
            tracked = self._track(scan, seed)
            if tracked.ok:  # a fit that failed a check keeps confidence 0
                tracked.confidence = tracked_confidence(tracked)
            if tracked.ok and tracked.confidence < threshold:
                tracked.ok = False  # a fit the confidence does not trust: as a failed one
                shown = math.floor(tracked.confidence * 1e4) / 1e4  # 0.99998 is not "1.00"
                tracked.why = (
                    f"the fit's confidence {shown:.4f} is below min_confidence {threshold:g}"
                )
            code = None  # of a fit not accepted: tracking_failed unless said otherwise
            if tracked.ok and prior is not None:  # the request's prior bounds the fit too
                outside = prior.rejects(tracked.T_map_sensor)
                if outside:
                    tracked.ok, tracked.why = False, f"outside the prior region: {outside}"
                    code = "outside_prior"
            if tracked.ok:
                return self._tracked_answer(tracked, t_start, threshold, prior)
            tcfg = self.config.tracking
            if tcfg.fallback == "none":
                return self._tracked_answer(tracked, t_start, threshold, prior, code)
            if prior is None:
                k = tcfg.seed_sigmas
                prior = Prior(
                    tuple(seed.T_map_sensor[:3, 3]),
                    max(k * seed.sigma_m, tcfg.fallback_min_radius_m),
                    yaw_deg=yaw_deg(seed.T_map_sensor),
                    yaw_tolerance_deg=min(180.0, max(k * seed.sigma_yaw_deg, 30.0)),
                )
            check_deadline("the global fallback")  # the fit may have used the time up
            try:
                result = self.localize(
                    scan,
                    top_k=top_k,
                    rerank_method=rerank_method,
                    refine=refine,
                    prior=prior,
                    min_confidence=min_confidence,
                )
            except EmptyScanError as exc:  # the fit's answer stands, with why no fallback
                tracked.why += f"; no global fallback: {exc}"
                return self._tracked_answer(tracked, t_start, threshold, prior, code)
            result.mode, result.tracking = "relocalized", tracked.to_dict()
            result.timings_ms["track"] = tracked.timings_ms["track"]
            result.timings_ms["total"] = _ms(t_start)
            return result
        with self._lock.read():  # one settings change's config and calibration, not a mix
            cfg, calibration = self.config, self.calibration
        top_k = cfg.top_k if top_k is None else top_k
        method = check_method(rerank_method or cfg.rerank)
        refine = refine or cfg.pose.refine
        if refine not in ("none", "icp"):
            raise InputError(f"refine must be 'none' or 'icp', got {refine!r}")
        if top_k < 1:
            raise InputError(f"top_k must be at least 1, got {top_k}")
        if min_confidence is None:
            min_confidence = cfg.verdict.min_confidence
        elif not 0.0 <= min_confidence <= 1.0:
            raise InputError(f"min_confidence must be in [0, 1], got {min_confidence}")
        if (scan is None) == (features is None):
            raise InputError("give exactly one of scan or features")
        if cloud is not None and features is None:
            raise InputError("cloud goes with features (a raw scan brings its own)")
        timings: dict[str, float] = {}
        t_start = time.perf_counter()
        answer = partial(
            LocalizationResult,
            rerank_method=method,
            timings_ms=timings,
            min_confidence=min_confidence,
        )

        # 1. encode the query (or check that its precomputed features fit this map)
        t = time.perf_counter()
        query_cloud = cloud
        if features is None:
            check_deadline("encoding")
            query_cloud = self.encoder.prepare(scan)
            query = self.encoder.encode_query(query_cloud, cfg.retrieval.centres())
        else:
            self.encoder.check(features)
            query = features
        timings["encode"] = _ms(t)

        check_deadline("retrieval")
        searched = among  # the keyframes this answer may use, before a prior narrows them
        with self._lock.read():
            version = self.version
            # 2. retrieve the top-k keyframes by global descriptor (inside the prior's radius)
            t = time.perf_counter()
            prior_info = None
            if prior is not None:
                inside = self._grid.within(prior)
                prior_info = {"used": True, "keyframes_in_radius": int(len(inside))}
                among = inside if among is None else np.intersect1d(inside, among)
            hits = retrieve(
                self.index,
                query.global_descriptor,
                top_k,
                self.encoder.blocks,
                cfg.retrieval.combine,
                among=among,
                variants=query.global_variants,
            )
            retrieved = [Candidate(h.id, h.similarity, r, h.similarity) for r, h in enumerate(hits)]
            timings["retrieve"] = _ms(t)
            if not retrieved:
                timings["total"] = _ms(t_start)
                code = "no_keyframes" if prior is None else "no_keyframe_in_prior"
                why = (
                    "the map has no keyframes" + ("" if among is None else " to search")
                    if prior is None
                    else f"no keyframe within {prior.radius_m:g} m of the prior position"
                )
                return answer(
                    False,
                    why,
                    None,
                    None,
                    [],
                    [],
                    map_version=version,
                    verdict=code,
                    prior=prior_info,
                )

            # 3. re-rank the candidates
            check_deadline("re-ranking")
            t = time.perf_counter()
            whole = self._whole([c.keyframe_id for c in retrieved], gone_ok=True)
            if self.keyframe_source is not None:
                timings["fetch"] = _ms(t)
                # candidates deleted in the store meanwhile are not answers any more
                retrieved = [c for c in retrieved if c.keyframe_id in whole]
                if not retrieved:
                    raise ConflictError(
                        "every candidate keyframe is gone from the store; the map is "
                        "catching up, retry"
                    )

            def features_of(i: int) -> Features:
                if i not in whole:  # a candidate query expansion found
                    whole.update(self._whole([i]))
                return whole[i].features

            out = rerank(method, query, retrieved, features_of, self.index, cfg, among)
            whole.update(
                self._whole([c.keyframe_id for c in out.candidates if c.keyframe_id not in whole])
            )
            ranked = [c.keyframe_id for c in out.candidates]
            spectral = None
            if out.sgv is not None and cfg.sgv.tie_tolerance > 0:
                spectral = self._spectral(query, retrieved, out, ranked, whole, cfg)
                order = nearest_of_place(
                    ranked,
                    spectral,
                    lambda i: self._keyframes[i].T_map_sensor,
                    cfg.sgv.tie_tolerance,
                    cfg.sgv.tie_gain_m,
                )
                if order != ranked:
                    by_id = {c.keyframe_id: c for c in out.candidates}
                    out.candidates = [by_id[i] for i in order]
                    ranked = order
            timings["rerank"] = _ms(t)

            # 4. estimate the pose against the re-ranked top-1
            check_deadline("the pose")
            t = time.perf_counter()
            best = whole[out.candidates[0].keyframe_id]
            pose = out.poses.get(best.id) or ransac_pose(
                query.keypoints,
                query.local_features,
                best.features.keypoints,
                best.features.local_features,
                cfg.pose,
            )
            has_estimate = pose.num_correspondences >= cfg.pose.ransac_n
            if refine == "icp" and has_estimate:
                check_deadline("ICP")
                pose = self._refine(pose, query_cloud, best, cfg)
            timings["pose"] = _ms(t)

            # 5. the evidence, its calibrated confidence and the verdict
            check_deadline("the verdict")
            t = time.perf_counter()
            T_kf = pose.T_target_source if has_estimate else None
            T_map = best.T_map_sensor @ T_kf if T_kf is not None else None
            judged = assess(
                calibration,
                ranked,
                spectral
                if spectral is not None
                else self._spectral(query, retrieved, out, ranked, whole, cfg),
                lambda i: self._keyframes[i].T_map_sensor,
                query_keypoints=query.keypoints,
                similarity=float(query.global_descriptor @ best.features.global_descriptor),
                pose=pose,
                T_kf_query=T_kf,
                min_confidence=min_confidence,
                prior=prior,
                free_space=lambda T: self._free_space(query_cloud, T, best.id, searched, whole),
            )
            timings["verify"] = _ms(t)

        timings["total"] = _ms(t_start)
        return answer(
            judged.verdict.localized,
            judged.verdict.reason,
            best.id,
            pose,
            retrieved,
            out.candidates,
            map_version=version,
            verdict=judged.verdict.code,
            confidence=judged.confidence,
            evidence=judged.evidence,
            T_map_sensor_estimate=T_map,
            T_keyframe_sensor_estimate=T_kf,
            prior=prior_info,
        )

    def _track(self, scan: np.ndarray, seed: Seed) -> TrackResult:
        """Register ``scan`` against the submap around ``seed`` (built once per map cell
        and version, then cached)."""
        t = time.perf_counter()
        with self._lock.read():
            cfg = self.config.tracking  # as the submap is built: settings swap under the lock
            x, y = seed.T_map_sensor[:2, 3]
            cell = (int(np.floor(x / cfg.submap_cell_m)), int(np.floor(y / cfg.submap_cell_m)))
            version = self.version
            key = (version, cell)

            def build():  # noqa: ANN202 - the cache's builder
                centre = ((cell[0] + 0.5) * cfg.submap_cell_m, (cell[1] + 0.5) * cfg.submap_cell_m)
                reach = cfg.submap_radius_m + cfg.submap_cell_m * 0.7072  # + half a diagonal
                ids = self._grid.within(Prior(centre, reach))
                whole = self._whole([int(i) for i in ids], gone_ok=True)
                clouds = [
                    (int(i), kf.T_map_sensor, kf.cloud)
                    for i in ids
                    if (kf := whole.get(int(i))) is not None and kf.cloud is not None
                ]
                return build_submap(clouds, cfg)

            submap = self._submaps.get(key, build)
            poses = (
                {i: self._keyframes[i].T_map_sensor for i in submap.keyframe_ids}
                if submap is not None
                else {}
            )
        if submap is None:
            out = TrackResult(
                False,
                f"no keyframe cloud within {cfg.submap_radius_m:g} m of the seed (the map "
                "keeps no clouds, or the seed lies outside it)",
            )
        else:
            check_deadline("tracking")
            out = register(scan, seed, submap, cfg)
            if out.T_map_sensor is not None:
                pos = out.T_map_sensor[:3, 3]
                nearest = min(poses, key=lambda i: float(np.linalg.norm(poses[i][:3, 3] - pos)))
                out.nearest_keyframe, out.T_map_nearest = nearest, poses[nearest]
        out.map_version = version
        out.timings_ms["track"] = _ms(t)
        return out

    def _tracked_answer(
        self,
        tracked: TrackResult,
        t_start: float,
        min_confidence: float,
        prior: Prior | None = None,
        code: str | None = None,
    ) -> LocalizationResult:
        """The answer of a seeded fit: accepted (``tracked.ok``, its confidence at least
        ``min_confidence``, inside the request's ``prior`` region) or, with ``fallback:
        none`` or a scan the global fallback cannot describe, not (verdict ``code``,
        default ``tracking_failed``)."""
        T = tracked.T_map_sensor
        T_kf = None
        if T is not None and tracked.T_map_nearest is not None:
            T_kf = np.linalg.inv(tracked.T_map_nearest) @ T
        localized, reason, confidence = tracked.ok, tracked.why, tracked.confidence
        timings = {"track": tracked.timings_ms["track"], "total": _ms(t_start)}
        prior_info = None
        if prior is not None:
            with self._lock.read():
                inside = len(self._grid.within(prior))
            prior_info = {"used": True, "keyframes_in_radius": int(inside)}
        return LocalizationResult(
            localized,
            reason,
            tracked.nearest_keyframe,
            None,
            [],
            [],
            "none",
            timings,
            tracked.map_version,
            verdict="localized" if localized else code or "tracking_failed",
            confidence=confidence,
            min_confidence=min_confidence,
            T_map_sensor_estimate=T,
            T_keyframe_sensor_estimate=T_kf,
            prior=prior_info,
            mode="tracked",
            tracking=tracked.to_dict(),
        )

    def _spectral(
        self,
        query: Features,
        retrieved: list[Candidate],
        out: RerankOutput,
        ranked: list[int],
        whole: dict[int, Keyframe],
        cfg: LocalizerConfig,
    ) -> dict[int, SpectralCandidate]:
        """SpectralGV's view of the re-ranked candidates: from the re-ranking when it was
        SGV (its scores are in retrieval order), else scored now in one batch with the
        request's settings ``cfg``."""
        if out.sgv is not None:
            res, scored = out.sgv, [c.keyframe_id for c in retrieved]
        else:
            from .sgv import sgv_rerank_scores

            feats = [whole[i].features for i in ranked]
            res = sgv_rerank_scores(
                query.keypoints,
                query.local_features,
                [f.keypoints for f in feats],
                [f.local_features for f in feats],
                cfg.sgv,
            )
            scored = ranked
        kps = [whole[i].features.keypoints for i in scored]
        # the top-1 may give way to one of the next candidates (nearest_of_place), whose
        # agreement is then checked against one more
        wanted = set(ranked[: 2 + AGREEMENT_CANDIDATES])
        return spectral_candidates(scored, query.keypoints, kps, res, poses_for=wanted)

    def _whole(self, ids: list[int], gone_ok: bool = False) -> dict[int, Keyframe]:
        """The keyframes ``ids`` with their features and clouds: from memory, or from
        the keyframe source (its cache, then one fetch for the rest). A keyframe deleted
        in the store that this copy still lists (another replica's delete, not yet caught
        up) is left out with ``gone_ok``, else a ConflictError. Call under the read lock."""
        if self.keyframe_source is None:
            return {int(i): self._keyframes[int(i)] for i in ids}
        got = self.keyframe_source.get_many([int(i) for i in ids])
        missing = [int(i) for i in ids if int(i) not in got]
        if missing and not gone_ok:
            raise ConflictError(
                f"keyframes {missing[:5]} are gone from the store; the map is catching up, retry"
            )
        return got

    def _free_space(
        self,
        query_cloud: np.ndarray | None,
        T_map_query: np.ndarray,
        matched: int,
        among: np.ndarray | None,
        whole: dict[int, Keyframe],
    ) -> float | None:
        """The free-space violation of the estimate ``T_map_query`` against the matched
        keyframe and its nearest neighbours (:mod:`sgvloc.core.freespace`), only among
        ``among`` when given. Call under the read lock."""
        if query_cloud is None:
            return None
        near = self._grid.within(Prior(tuple(T_map_query[:2, 3]), RADIUS_M))
        if among is not None:
            near = np.intersect1d(near, among)
        ids = views_near(
            T_map_query[:3, 3], matched, near, lambda i: self._keyframes[i].T_map_sensor[:3, 3]
        )
        missing = [i for i in ids if i not in whole]
        if missing:
            whole.update(self._whole(missing, gone_ok=True))
            ids = [i for i in ids if i in whole]
        views = []
        for kf in (whole[i] for i in ids):
            if kf.cloud is not None and len(kf.cloud):
                cloud = kf.cloud  # held by the entry, so that its id() is not reused
                _, image = self._range_images.get(
                    (kf.id, id(cloud)), lambda c=cloud: (c, RangeImage(c))
                )
                views.append((kf.T_map_sensor, image))
        return violation(thin(query_cloud), T_map_query, views)

    def _refine(
        self,
        pose: PoseResult,
        query_cloud: np.ndarray | None,
        best: Keyframe,
        settings: LocalizerConfig,
    ) -> PoseResult:
        if query_cloud is None or best.cloud is None:
            pose.icp = {
                "used": False,
                "why": "ICP needs the raw query scan and a map that "
                "keeps keyframe clouds (keep_clouds=True)",
            }
            return pose
        cfg = settings.pose
        target = None
        if cfg.icp_backend != "open3d" and len(best.cloud) >= 3:
            cloud, backend = best.cloud, cfg.icp_backend
            target = self._icp_targets.get(
                (best.id, id(cloud), backend), lambda: IcpTarget(cloud, backend)
            )
        return refine_icp(pose, query_cloud, best.cloud, cfg, target)


def _encoder_kind(encoder: Encoder) -> str:
    """The encoder's kind as EncoderSpec names it (its identity name up to a colon)."""
    return encoder.identity.name.split(":", 1)[0]


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3
