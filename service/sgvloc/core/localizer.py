"""The localizer: encode -> retrieve top-k -> re-rank -> pose, as in the paper's Fig. 1.

A :class:`Localizer` holds one map in memory: keyframes (pose, features, optional
downsampled cloud for ICP) and a FAISS index of their global descriptors. It is safe to
use from many threads: localizations run concurrently, inserts and removals are
exclusive. Persistence is the caller's business (the service keeps SQLite as the source
of truth and feeds keyframes in with :meth:`Localizer.add_keyframe`).
"""

from __future__ import annotations

import itertools
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ._rwlock import RWLock
from .config import LocalizerConfig
from .encoders import Encoder
from .errors import ConflictError, InputError, NotFoundError
from .features import Features
from .pose import PoseResult, check_rigid, ransac_pose, refine_icp
from .rerank import Candidate, check_method, rerank
from .retrieval import FaissIndex

log = logging.getLogger(__name__)


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

    ``T_map_sensor`` is the query's pose in the map frame (4x4, row-major, float64),
    ``T_keyframe_sensor`` the query relative to the matched keyframe. Both are ``None``
    when ``localized`` is false; ``reason`` then says why. ``retrieved`` is the candidate
    list in retrieval order, ``reranked`` after re-ranking (best first). ``timings_ms``
    holds encode, retrieve, rerank, pose and total.
    """

    localized: bool
    reason: str
    keyframe_id: int | None
    T_map_sensor: np.ndarray | None
    T_keyframe_sensor: np.ndarray | None
    pose: PoseResult | None
    retrieved: list[Candidate]
    reranked: list[Candidate]
    rerank_method: str
    timings_ms: dict[str, float]
    map_version: int

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
    ) -> None:
        self.encoder = encoder
        self.config = config or LocalizerConfig()
        self.keep_clouds = keep_clouds
        self.index = FaissIndex(encoder.global_dim, self.config.retrieval)
        self._keyframes: dict[int, Keyframe] = {}
        self._next_id = itertools.count(1)
        self._lock = RWLock()
        self.version = 0  # changes on every insert and removal

    # -- the map ------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._keyframes)

    def keyframe(self, keyframe_id: int) -> Keyframe:
        try:
            return self._keyframes[int(keyframe_id)]
        except KeyError:
            raise NotFoundError(f"keyframe {keyframe_id} does not exist") from None

    def keyframe_ids(self) -> list[int]:
        return sorted(self._keyframes)

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
            ids = []
            for kf in keyframes:
                if kf.id < 0:
                    kf.id = self._fresh_id()
                ids.append(kf.id)
            dup = [i for i in ids if i in self._keyframes]
            if dup or len(set(ids)) != len(ids):
                raise ConflictError(f"keyframe id(s) already exist: {dup[:5] or ids}")
            if keyframes:
                descs = np.stack([kf.features.global_descriptor for kf in keyframes])
                self.index.add(np.asarray(ids, dtype=np.int64), descs)
            for kf in keyframes:
                self._keyframes[kf.id] = kf
            if keyframes:
                self.version += 1
            return ids

    def add_keyframe(self, T_map_sensor: np.ndarray, **kwargs: Any) -> int:
        """Encode (or validate) and add one keyframe; returns its id. See :meth:`make_keyframe`."""
        return self.add_keyframes([self.make_keyframe(T_map_sensor, **kwargs)])[0]

    def remove_keyframe(self, keyframe_id: int) -> None:
        with self._lock.write():
            self.keyframe(keyframe_id)
            self.index.remove(np.array([keyframe_id], dtype=np.int64))
            del self._keyframes[int(keyframe_id)]
            self.version += 1

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
        with self._lock.write():
            self.index = index
            self._keyframes = {kf.id: kf for kf in keyframes}
            self.version = int(version)

    def _fresh_id(self) -> int:
        while True:
            candidate = next(self._next_id)
            if candidate not in self._keyframes:
                return candidate

    # -- localization -------------------------------------------------------------------

    def localize(
        self,
        scan: np.ndarray | None = None,
        *,
        features: Features | None = None,
        top_k: int | None = None,
        rerank_method: str | None = None,
        refine: str | None = None,
    ) -> LocalizationResult:
        """Localize a raw scan (or precomputed features) in this map."""
        cfg = self.config
        top_k = top_k or cfg.top_k
        method = check_method(rerank_method or cfg.rerank)
        refine = refine or cfg.pose.refine
        if refine not in ("none", "icp"):
            raise InputError(f"refine must be 'none' or 'icp', got {refine!r}")
        if top_k < 1:
            raise InputError(f"top_k must be at least 1, got {top_k}")
        if (scan is None) == (features is None):
            raise InputError("give exactly one of scan or features")
        timings: dict[str, float] = {}
        t_start = time.perf_counter()

        # 1. encode the query (or check that its precomputed features fit this map)
        t = time.perf_counter()
        query_cloud = None
        if features is None:
            query_cloud = self.encoder.prepare(scan)
            query = self.encoder.encode_cloud(query_cloud)
        else:
            self.encoder.check(features)
            query = features
        timings["encode"] = _ms(t)

        with self._lock.read():
            version = self.version
            # 2. retrieve the top-k keyframes by global descriptor
            t = time.perf_counter()
            hits = self.index.search(query.global_descriptor, top_k)[0]
            retrieved = [Candidate(h.id, h.similarity, r, h.similarity) for r, h in enumerate(hits)]
            timings["retrieve"] = _ms(t)
            if not retrieved:
                timings["total"] = _ms(t_start)
                return LocalizationResult(
                    False,
                    "the map has no keyframes",
                    None,
                    None,
                    None,
                    None,
                    [],
                    [],
                    method,
                    timings,
                    version,
                )

            # 3. re-rank the candidates
            t = time.perf_counter()
            out = rerank(method, query, retrieved, self._features_of, self.index, cfg)
            timings["rerank"] = _ms(t)

            # 4. estimate the pose against the re-ranked top-1
            t = time.perf_counter()
            best = self._keyframes[out.candidates[0].keyframe_id]
            pose = out.poses.get(best.id) or ransac_pose(
                query.keypoints,
                query.local_features,
                best.features.keypoints,
                best.features.local_features,
                cfg.pose,
            )
            if refine == "icp" and pose.num_correspondences >= cfg.pose.ransac_n:
                pose = self._refine(pose, query_cloud, best)
            timings["pose"] = _ms(t)

        timings["total"] = _ms(t_start)
        if not pose.localized:
            return LocalizationResult(
                False,
                pose.reason,
                best.id,
                None,
                None,
                pose,
                retrieved,
                out.candidates,
                method,
                timings,
                version,
            )
        T_kf_sensor = pose.T_target_source
        return LocalizationResult(
            True,
            pose.reason,
            best.id,
            best.T_map_sensor @ T_kf_sensor,
            T_kf_sensor,
            pose,
            retrieved,
            out.candidates,
            method,
            timings,
            version,
        )

    def _features_of(self, keyframe_id: int) -> Features:
        return self._keyframes[keyframe_id].features

    def _refine(
        self, pose: PoseResult, query_cloud: np.ndarray | None, best: Keyframe
    ) -> PoseResult:
        if query_cloud is None or best.cloud is None:
            pose.icp = {
                "used": False,
                "why": "ICP needs the raw query scan and a map that "
                "keeps keyframe clouds (keep_clouds=True)",
            }
            return pose
        return refine_icp(pose, query_cloud, best.cloud, self.config.pose)


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3
