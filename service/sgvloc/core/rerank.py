"""Re-ranking of retrieved candidates, selectable by name.

- ``none``: keep the retrieval order.
- ``average-qe`` / ``alpha-qe``: query expansion on global descriptors only. The query
  descriptor is replaced by the (weighted) mean of itself and its top ``qe_k`` neighbours
  (alpha-QE weights each neighbour by ``similarity ** qe_alpha``) and the index is
  searched again.
- ``ransac-rir`` / ``fgr-rir``: register the query to every candidate (the seeded RANSAC
  of :mod:`sgvloc.core.pose`, or Open3D's Fast Global Registration, on feature
  correspondences) and score by the registered inlier ratio. Slow by design: one
  registration per candidate.
- ``sgv``: Spectral Geometric Verification, a registration-free score computed for all
  candidates in one batch (:mod:`sgvloc.core.sgv`).

TEASER++ (``teaser-rir`` in the paper) is not offered: no installable wheel exists for
this platform.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, get_args

import numpy as np

from .config import LocalizerConfig, RerankMethod
from .deadline import check as check_deadline
from .errors import InputError
from .features import Features
from .pose import PoseResult, fgr_pose, ransac_pose
from .retrieval import FaissIndex

METHODS: tuple[str, ...] = get_args(RerankMethod)


@dataclass(frozen=True)
class Candidate:
    """A keyframe proposed for a query.

    ``similarity`` is the retrieval inner product, ``retrieval_rank`` the 0-based rank
    before re-ranking (-1 if the candidate was found only by query expansion), and
    ``score`` the re-ranking method's score (the similarity for ``none``).
    """

    keyframe_id: int
    similarity: float
    retrieval_rank: int
    score: float


@dataclass
class RerankOutput:
    """Re-ranked candidates (best first) and method-specific by-products."""

    method: str
    candidates: list[Candidate]
    poses: dict[int, PoseResult] = field(default_factory=dict)  # RIR: per-candidate registration
    info: dict = field(default_factory=dict)
    sgv: Any = None  # sgv: the SGVScores of the candidates in retrieval order


FeaturesOf = Callable[[int], Features]


def check_method(method: str) -> str:
    if method not in METHODS:
        raise InputError(f"unknown re-ranking method {method!r}; choose one of {list(METHODS)}")
    return method


def rerank(
    method: str,
    query: Features,
    retrieved: list[Candidate],
    features_of: FeaturesOf,
    index: FaissIndex,
    cfg: LocalizerConfig,
    among: np.ndarray | None = None,
) -> RerankOutput:
    """Re-order ``retrieved`` (in retrieval order) with ``method``. ``among``: the
    keyframe ids retrieval was restricted to (a prior's region, a leave-out's visible
    scans), which query expansion's second search keeps to as well."""
    check_method(method)
    if not retrieved or method == "none":
        return RerankOutput(method, list(retrieved))
    if method in ("average-qe", "alpha-qe"):
        return _query_expansion(method, query, retrieved, features_of, index, cfg, among)
    if method == "sgv":
        return _sgv(query, retrieved, features_of, cfg)
    return _rir(method, query, retrieved, features_of, cfg)


def _sorted(cands: list[Candidate], scores: np.ndarray) -> list[Candidate]:
    rescored = [replace(c, score=float(s)) for c, s in zip(cands, scores, strict=True)]
    # stable sort: ties keep the retrieval order
    order = np.argsort(-np.asarray(scores, dtype=np.float64), kind="stable")
    return [rescored[i] for i in order]


def _sgv(
    query: Features, retrieved: list[Candidate], features_of: FeaturesOf, cfg: LocalizerConfig
) -> RerankOutput:
    from .sgv import sgv_rerank_scores

    feats = [features_of(c.keyframe_id) for c in retrieved]
    res = sgv_rerank_scores(
        query.keypoints,
        query.local_features,
        [f.keypoints for f in feats],
        [f.local_features for f in feats],
        cfg.sgv,
    )
    scores = res.score  # cfg.sgv.normalise already chose v^T M v / n or v^T M v
    return RerankOutput("sgv", _sorted(retrieved, scores), info={"n": res.n.tolist()}, sgv=res)


def _query_expansion(
    method: str,
    query: Features,
    retrieved: list[Candidate],
    features_of: FeaturesOf,
    index: FaissIndex,
    cfg: LocalizerConfig,
    among: np.ndarray | None = None,
) -> RerankOutput:
    top = retrieved[: cfg.qe_k]
    descs = np.stack(
        [query.global_descriptor] + [features_of(c.keyframe_id).global_descriptor for c in top]
    )  # [1+q, G]
    if method == "alpha-qe":
        sims = np.array([1.0] + [max(c.similarity, 0.0) for c in top])
        weights = sims**cfg.qe_alpha
    else:
        weights = np.ones(len(descs))
    expanded = (weights[:, None] * descs).sum(axis=0)
    if not np.linalg.norm(expanded) > 0:
        return RerankOutput(method, list(retrieved), info={"expanded": False})
    hits = index.search(expanded / np.linalg.norm(expanded), len(retrieved), among=among)[0]
    rank_of = {c.keyframe_id: c.retrieval_rank for c in retrieved}
    sim_of = {c.keyframe_id: c.similarity for c in retrieved}

    def similarity(i: int) -> float:  # a keyframe only the expanded search found: its cosine
        if i in sim_of:
            return sim_of[i]
        return float(query.global_descriptor @ features_of(i).global_descriptor)

    cands = [Candidate(h.id, similarity(h.id), rank_of.get(h.id, -1), h.similarity) for h in hits]
    return RerankOutput(method, cands, info={"expanded": True, "weights": weights.tolist()})


def _rir(
    method: str,
    query: Features,
    retrieved: list[Candidate],
    features_of: FeaturesOf,
    cfg: LocalizerConfig,
) -> RerankOutput:
    poses: dict[int, PoseResult] = {}
    scores = np.zeros(len(retrieved))
    for i, c in enumerate(retrieved):
        check_deadline(f"{method} candidate {i + 1} of {len(retrieved)}")
        cand = features_of(c.keyframe_id)
        if method == "ransac-rir":
            pose = ransac_pose(
                query.keypoints, query.local_features, cand.keypoints, cand.local_features, cfg.pose
            )
        else:
            pose = fgr_pose(
                query.keypoints, query.local_features, cand.keypoints, cand.local_features, cfg.pose
            )
        poses[c.keyframe_id] = pose
        scores[i] = pose.fitness
    return RerankOutput(method, _sorted(retrieved, scores), poses=poses)
