"""Run the evaluation protocol (SPEC section 4) over one KITTI-layout sequence.

The sequence is 3-D scans (``velodyne/``, ``poses.txt``, ``times.txt``) or kitti-bev BEV
images (``imgs/*.png``, ``pose.txt``; :mod:`.data`). Images need an encoder with
``encode_image``; they have no 3-D cloud, so refinement is forced to ``none``.

Per query, in time order:

1. features come from the on-disk cache (:mod:`.cache`), extracted once per encoder;
2. the database visible to the query (its split) is in a FAISS index; retrieval runs
   once with the largest k needed, and every (method, k) re-ranks the first k hits
   (``rerank`` is timed; QE methods search the same index again, as the service does);
3. for the table's top-k values, the pose is estimated against the re-ranked top-1
   with RANSAC on local features, refined by ICP on the preprocessed clouds (the same
   estimator for every method, so the figures isolate the effect of re-ranking; RANSAC
   and ICP results are cached per (query, keyframe) pair as they are deterministic).

The n_topk sweep (for the plot) runs the cheap methods (``none``, QE, ``sgv``) at every
sweep k, and the per-candidate registration methods (``*-rir``) only at ``sweep_rir``
k values (default: the table's top-k values), since each of their candidates costs one
registration.

Pose of a query that is not localized: the estimate is used anyway (RTE/RRE count over
all queries). When RANSAC has no estimate at all (fewer correspondences than its sample
size), the estimate is the matched keyframe's pose, as if the query were at the keyframe;
such queries are counted in ``no_estimate``.

Encoder diagnostics (:mod:`.diagnostics`), per query:

- local matches on the true pair (the query and the visible database scan nearest to it
  in position): share of nearest-neighbour feature matches within 1 m after the
  ground-truth pose;
- SGV scores (the ``sgv`` method's score) of the first ``max(topk)`` retrieved
  candidates, split into true (within the first threshold) and false; taken from the
  ``sgv`` run at that k when ``sgv`` is among the methods, else computed once.
"""

from __future__ import annotations

import logging
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from sgvloc.core.config import LocalizerConfig
from sgvloc.core.encoders import EncoderSpec
from sgvloc.core.errors import InputError
from sgvloc.core.rerank import METHODS

from .diagnostics import score_separation, summarise_pairs
from .metrics import first_true_rank, mrr, recall_at, rre, rte, success
from .splits import Split, make_split

log = logging.getLogger(__name__)

#: methods swept over every n_topk value (cheap); the others only at ``sweep_rir``
FULL_SWEEP_METHODS = ("none", "average-qe", "alpha-qe", "sgv")
DEFAULT_SWEEP = (1, 2, 3, 4, 5, 7, 10, 15, 20, 25, 30, 40, 50)


class EvalConfig(BaseModel):
    """Everything that defines an evaluation run (stored verbatim in the JSON report)."""

    model_config = ConfigDict(extra="forbid")

    data: str
    db_until: float | None = Field(None, description="time split: database = first SECONDS")
    min_gap: float | None = Field(None, description="loop split: database = scans >= SECONDS older")
    methods: list[str] = Field(default_factory=lambda: list(METHODS))
    topk: list[int] = Field(default_factory=lambda: [2, 20])
    thresholds: list[float] = Field(default_factory=lambda: [5.0, 20.0])
    sweep: list[int] = Field(default_factory=lambda: list(DEFAULT_SWEEP))
    sweep_rir: list[int] | None = Field(None, description="RIR sweep k values (None: topk)")
    refine: str = Field("icp", description="pose refinement after RANSAC: icp | none")
    query_stride: int = Field(1, ge=1)
    max_queries: int | None = Field(None, ge=1)
    cache_dir: str | None = None
    encoder: EncoderSpec = EncoderSpec()
    localizer: LocalizerConfig = LocalizerConfig()

    @field_validator("methods")
    @classmethod
    def _known_methods(cls, v: list[str]) -> list[str]:
        bad = [m for m in v if m not in METHODS]
        if bad or not v:
            raise ValueError(f"unknown re-ranking method(s) {bad}; choose from {list(METHODS)}")
        return list(dict.fromkeys(v))

    @field_validator("topk", "sweep", "sweep_rir")
    @classmethod
    def _positive(cls, v: list[int] | None) -> list[int] | None:
        if v is not None and (not v or min(v) < 1):
            raise ValueError("top-k values must be positive integers")
        return None if v is None else sorted(set(v))

    @field_validator("thresholds")
    @classmethod
    def _thr(cls, v: list[float]) -> list[float]:
        if not v or min(v) <= 0:
            raise ValueError("revisit thresholds must be positive")
        return sorted(v)

    @field_validator("refine")
    @classmethod
    def _refine(cls, v: str) -> str:
        if v not in ("icp", "none"):
            raise ValueError("refine must be 'icp' or 'none'")
        return v

    def plan(self) -> dict[str, list[int]]:
        """Per method, the k values to run (table top-k plus its sweep values)."""
        rir_sweep = self.sweep_rir if self.sweep_rir is not None else self.topk
        return {
            m: sorted(set(self.topk) | set(self.sweep if m in FULL_SWEEP_METHODS else rir_sweep))
            for m in self.methods
        }


@dataclass
class EvalResult:
    """Everything a run measured. ``rows``: one per (method, table k); ``sweep``: per
    method, one entry per swept k; ``per_query``: per (method, k) row, per query."""

    config: dict[str, Any]
    split: dict[str, Any]
    rows: list[dict[str, Any]]
    sweep: dict[str, list[dict[str, Any]]]
    per_query: dict[str, list[dict[str, Any]]]
    timings: dict[str, Any]
    notes: list[str] = field(default_factory=list)
    matches: dict[str, Any] = field(default_factory=dict)
    sgv_scores: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "config": self.config,
            "split": self.split,
            "rows": self.rows,
            "sweep": self.sweep,
            "per_query": self.per_query,
            "timings": self.timings,
            "notes": self.notes,
            "matches": self.matches,
            "sgv_scores": self.sgv_scores,
        }


def _progress(it, enabled: bool, **kw):
    if not enabled:
        return it
    from tqdm import tqdm

    return tqdm(it, **kw)


def run_evaluation(cfg: EvalConfig, *, progress: bool = True) -> EvalResult:
    """Evaluate every method of ``cfg`` at every k of its plan. See the module docstring."""
    from sgvloc.core.encoders import make_encoder
    from sgvloc.core.pose import ransac_pose, refine_icp
    from sgvloc.core.rerank import Candidate, rerank
    from sgvloc.core.retrieval import FaissIndex

    from .cache import FeatureCache, default_cache_dir
    from .data import open_sequence
    from .diagnostics import MATCH_RADIUS_M, is_planar, pair_match_stats

    t_run = time.perf_counter()
    seq = open_sequence(cfg.data)
    poses = seq.poses  # [F, 4, 4] T_world_sensor
    split = make_split(
        seq.times,
        poses[:, :3, 3],
        db_until=cfg.db_until,
        min_gap=cfg.min_gap,
        threshold=cfg.thresholds[0],
        query_stride=cfg.query_stride,
        max_queries=cfg.max_queries,
    )
    if len(split.queries) == 0:
        raise InputError(f"{cfg.data}: no query has a database scan within {split.threshold} m")
    log.info("split %s", split.summary())

    # 1. features of every scan the run needs (cached on disk)
    encoder = make_encoder(cfg.encoder)
    refine = cfg.refine
    if seq.kind == "bev-images":
        if not callable(getattr(encoder, "encode_image", None)):
            raise InputError(
                f"{cfg.data} holds BEV images (imgs/*.png) and encoder kind "
                f"{cfg.encoder.kind!r} cannot encode images; use an image encoder, "
                """e.g. --encoder '{"kind":"bev"}'"""
            )
        refine = "none"  # no 3-D cloud for ICP
    cache = FeatureCache(cfg.cache_dir or default_cache_dir(), encoder)
    needed = sorted(set(split.database.tolist()) | set(split.queries.tolist()))
    t0 = time.perf_counter()
    feats = {
        i: cache.get(seq.paths[i])
        for i in _progress(needed, progress, desc="features", unit="scan")
    }
    t_features = time.perf_counter() - t0
    planar = is_planar(*(f.keypoints for f in feats.values()))

    plan = cfg.plan()
    kmax = max(max(ks) for ks in plan.values())
    table_ks = set(cfg.topk)
    loc_cfg = cfg.localizer
    pose_cache: dict[tuple[int, int], tuple[np.ndarray, bool, bool]] = {}

    def pose_for(q: int, kf: int) -> tuple[np.ndarray, bool, bool]:
        """(T_world_query estimate, localized, had an estimate) against keyframe kf."""
        if (q, kf) not in pose_cache:
            fq, fk = feats[q], feats[kf]
            pose = ransac_pose(
                fq.keypoints, fq.local_features, fk.keypoints, fk.local_features, loc_cfg.pose
            )
            has_estimate = pose.num_correspondences >= loc_cfg.pose.ransac_n
            if refine == "icp" and has_estimate:
                pose = refine_icp(
                    pose, cache.cloud(seq.paths[q]), cache.cloud(seq.paths[kf]), loc_cfg.pose
                )
            T_kf_q = pose.T_target_source if has_estimate else np.eye(4)
            pose_cache[(q, kf)] = (poses[kf] @ T_kf_q, pose.localized, has_estimate)
        return pose_cache[(q, kf)]

    # 2. queries in time order against the database each may see
    index = FaissIndex(encoder.global_dim, loc_cfg.retrieval)
    in_index: set[int] = set()
    recs: dict[tuple[str, int], list[dict[str, Any]]] = {
        (m, k): [] for m, ks in plan.items() for k in ks
    }
    k_scores = max(cfg.topk)  # SGV score statistics over this many retrieved candidates
    match_pairs: list[dict[str, Any]] = []
    score_recs: list[dict[str, Any]] = []
    t_queries = time.perf_counter()
    for q in _progress(split.queries.tolist(), progress, desc="queries", unit="query"):
        visible = split.database_for(q)
        new = [i for i in visible.tolist() if i not in in_index]
        if new:
            index.add(
                np.asarray(new, np.int64), np.stack([feats[i].global_descriptor for i in new])
            )
            in_index.update(new)
        hits = index.search(feats[q].global_descriptor, min(kmax, len(index)))[0]
        retrieved = [Candidate(h.id, h.similarity, r, h.similarity) for r, h in enumerate(hits)]
        gt = poses[q]
        sgv_out = None
        for method, ks in plan.items():
            for k in ks:
                t = time.perf_counter()
                out = rerank(method, feats[q], retrieved[:k], feats.__getitem__, index, loc_cfg)
                ms = (time.perf_counter() - t) * 1e3
                if method == "sgv" and k == k_scores:
                    sgv_out = out
                ids = [c.keyframe_id for c in out.candidates]
                rec: dict[str, Any] = {
                    "query": q,
                    "ms": ms,
                    "ranked": ids,
                    "top1_changed": bool(ids and retrieved and ids[0] != retrieved[0].keyframe_id),
                }
                for thr in cfg.thresholds:
                    rec[f"rank@{thr:g}m"] = first_true_rank(poses[ids, :3, 3], gt[:3, 3], thr)
                if k in table_ks and ids:
                    T_est, localized, has_est = pose_for(q, ids[0])
                    rec.update(
                        rte=rte(T_est, gt),
                        rre=rre(T_est, gt),
                        localized=localized,
                        has_estimate=has_est,
                    )
                recs[(method, k)].append(rec)

        # encoder diagnostics: matches on the true pair, SGV scores of true/false candidates
        d = np.linalg.norm(poses[visible, :3, 3] - gt[:3, 3], axis=1)
        db = int(visible[int(np.argmin(d))])
        T_db_q = np.linalg.inv(poses[db]) @ gt
        fq, fd = feats[q], feats[db]
        stats = pair_match_stats(
            fq.keypoints,
            fq.local_features,
            fd.keypoints,
            fd.local_features,
            T_db_q,
            MATCH_RADIUS_M,
            planar,
        )
        match_pairs.append({"query": q, "db": db, "distance_m": float(d.min()), **stats})
        if sgv_out is None:
            sgv_out = rerank(
                "sgv", feats[q], retrieved[:k_scores], feats.__getitem__, index, loc_cfg
            )
        ids = [c.keyframe_id for c in sgv_out.candidates]
        dist = np.linalg.norm(poses[ids, :3, 3] - gt[:3, 3], axis=1) if ids else np.zeros(0)
        score_recs.append(
            {
                "query": q,
                "ids": ids,
                "scores": [float(c.score) for c in sgv_out.candidates],
                "true": [bool(x) for x in dist <= cfg.thresholds[0]],
            }
        )
    t_queries = time.perf_counter() - t_queries

    # 3. aggregate
    rows, sweep, per_query = [], {m: [] for m in plan}, {}
    for (method, k), rs in recs.items():
        agg = _aggregate(method, k, rs, cfg.thresholds, with_pose=k in table_ks)
        keep = [key for key in agg if key.startswith("R@1") or key.endswith("_ms")]
        sweep[method].append({"k": k, **{key: agg[key] for key in keep}})
        if k in table_ks:
            rows.append(agg)
            per_query[f"{method}@{k}"] = rs
    order = {m: i for i, m in enumerate(cfg.methods)}
    rows.sort(key=lambda r: (r["k"], order[r["method"]]))
    for m in sweep:
        sweep[m].sort(key=lambda e: e["k"])

    notes = [
        f"retrieval: top-{kmax} once per query; each (method, k) re-ranks the first k hits",
        "pose: RANSAC on local features against the re-ranked top-1"
        + (", refined by ICP on the preprocessed clouds" if refine == "icp" else "")
        + "; the same estimator for every method",
        "RTE/RRE: means over all queries; a query that is not localized keeps its estimate; "
        "with no estimate at all (too few correspondences) the matched keyframe's pose is used",
        f"n_topk sweep: {', '.join(m for m in plan if m in FULL_SWEEP_METHODS)} at k = "
        f"{', '.join(map(str, cfg.sweep))}; "
        + (
            f"{', '.join(m for m in plan if m not in FULL_SWEEP_METHODS)} (one registration per "
            f"candidate) only at k = {', '.join(map(str, cfg.sweep_rir or cfg.topk))}"
            if any(m not in FULL_SWEEP_METHODS for m in plan)
            else "no registration-based methods selected"
        ),
        "R@5 with top-k < 5 counts the k candidates there are; k is capped by the database "
        "size visible to a query",
        f"queries dropped (no database scan within {split.threshold:g} m): {len(split.dropped)}",
        f"local matches: per query, its true pair (the visible database scan nearest in "
        f"position); each query keypoint's nearest neighbour (L2) in feature space among the "
        f"pair's keypoints is correct within {MATCH_RADIUS_M:g} m after the ground-truth pose"
        + (
            " (every keypoint has z = 0: distances in x/y only)"
            if planar
            else " (distances in 3-D)"
        )
        + "; repeatability = share of query keypoints with any keypoint that close, "
        "chance = expected ratio of random matching",
        f"SGV scores: the sgv method's score of the first {k_scores} retrieved candidates per "
        f"query, true = within {cfg.thresholds[0]:g} m; AUC pooled over all queries and as "
        "the mean of per-query AUCs",
    ]
    if seq.kind == "bev-images":
        notes.insert(
            0,
            f"data: BEV images (imgs/*.png), times from {seq.times_source}; features from "
            "the encoder's encode_image; poses estimated from planar keypoints (x, y, yaw), "
            "RTE/RRE against the full ground-truth pose",
        )
        if cfg.refine != "none":
            notes.insert(1, "refine: forced to 'none' (BEV images have no 3-D cloud for ICP)")
    import torch

    timings = {
        "features_s": round(t_features, 3),
        "queries_s": round(t_queries, 3),
        "total_s": round(time.perf_counter() - t_run, 3),
        "feature_cache": {"hits": cache.hits, "misses": cache.misses, "dir": str(cache.dir)},
        "torch_threads": torch.get_num_threads(),
    }
    config = cfg.model_dump(mode="json")
    config["data"] = str(Path(cfg.data).resolve())
    config["data_kind"] = seq.kind
    config["refine_effective"] = refine
    config["encoder_identity"] = encoder.identity.to_dict()
    config["encoder_fingerprint"] = encoder.identity.fingerprint
    config["plan"] = plan
    split_info = split.summary()
    split_info["query_indices"] = split.queries.tolist()
    split_info["dropped_indices"] = split.dropped.tolist()
    matches = summarise_pairs(match_pairs, planar, MATCH_RADIUS_M)
    matches["per_pair"] = match_pairs
    scores = score_separation(score_recs)
    scores.update(k=k_scores, threshold_m=cfg.thresholds[0], per_query=score_recs)
    return EvalResult(config, split_info, rows, sweep, per_query, timings, notes, matches, scores)


def _mean(xs: list[float]) -> float:
    return float(np.mean(xs)) if xs else float("nan")


def _aggregate(
    method: str, k: int, recs: list[dict[str, Any]], thresholds: list[float], with_pose: bool
) -> dict[str, Any]:
    """Figures of one (method, k) over its queries."""
    out: dict[str, Any] = {"method": method, "k": k, "queries": len(recs)}
    for thr in thresholds:
        ranks = [r[f"rank@{thr:g}m"] for r in recs]
        out[f"R@1_{thr:g}m"] = recall_at(ranks, 1)
        out[f"R@5_{thr:g}m"] = recall_at(ranks, 5)
        out[f"MRR_{thr:g}m"] = mrr(ranks)
    ms = [r["ms"] for r in recs]
    out["rerank_median_ms"] = statistics.median(ms) if ms else float("nan")
    out["rerank_mean_ms"] = _mean(ms)
    out["top1_changed_pct"] = 100.0 * _mean([float(r["top1_changed"]) for r in recs])
    if with_pose:
        t = [r.get("rte", float("nan")) for r in recs]
        a = [r.get("rre", float("nan")) for r in recs]
        ok = success(t, a)
        out["success_pct"] = 100.0 * float(ok.mean()) if recs else float("nan")
        # pose success where the re-ranked top-1 is a true match (the pose step alone)
        true1 = np.array([r[f"rank@{thresholds[0]:g}m"] == 1 for r in recs], dtype=bool)
        out["success_true_top1_pct"] = (
            100.0 * float(ok[true1].mean()) if true1.any() else float("nan")
        )
        out["mean_rte_m"] = _mean(t)
        out["mean_rre_deg"] = _mean(a)
        out["median_rte_m"] = float(np.median(t)) if t else float("nan")
        out["localized_pct"] = 100.0 * _mean([float(r.get("localized", False)) for r in recs])
        out["no_estimate"] = sum(1 for r in recs if not r.get("has_estimate", True))
    return out


__all__ = ["EvalConfig", "EvalResult", "Split", "run_evaluation", "FULL_SWEEP_METHODS"]
