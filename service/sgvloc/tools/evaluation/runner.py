"""Run the evaluation protocol (docs/EVALUATION.md) over one KITTI-layout sequence.

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
from sgvloc.core.errors import EmptyScanError, InputError
from sgvloc.core.features import Features
from sgvloc.core.rerank import METHODS

from .diagnostics import score_separation, summarise_pairs
from .metrics import expected_calibration_error, first_true_rank, mrr, recall_at, rre, rte, success
from .splits import Split, make_split

log = logging.getLogger(__name__)

#: methods swept over every n_topk value (cheap); the others only at ``sweep_rir``
FULL_SWEEP_METHODS = ("none", "average-qe", "alpha-qe", "sgv")
DEFAULT_SWEEP = (1, 2, 3, 4, 5, 7, 10, 15, 20, 25, 30, 40, 50)


class EvalConfig(BaseModel):
    """Everything that defines an evaluation run (stored verbatim in the JSON report)."""

    model_config = ConfigDict(extra="forbid")

    data: str
    frames: tuple[int, int | None] | None = Field(
        None, description="use only frames [start, stop) of the sequence (by index)"
    )
    db_until: float | None = Field(None, description="time split: database = first SECONDS")
    min_gap: float | None = Field(None, description="loop split: database = scans >= SECONDS older")
    db_range: tuple[int, int | None] | None = Field(
        None, description="range split: database = frames [start, stop) (by index)"
    )
    query_range: tuple[int, int | None] | None = Field(
        None, description="range split: queries from frames [start, stop) (default: after db)"
    )
    leave_out: float | None = Field(
        None, description="self-test split: database = scans >= SECONDS away, before or after"
    )
    methods: list[str] = Field(default_factory=lambda: list(METHODS))
    topk: list[int] = Field(default_factory=lambda: [2, 20])
    thresholds: list[float] = Field(default_factory=lambda: [5.0, 20.0])
    planar_distance: bool = Field(
        False,
        description="measure the revisit thresholds (coverage, recall, the ceiling) in the "
        "plane, ignoring height: for data whose ground-truth heights disagree between "
        "passes; RTE/RRE and the verdict's correctness are unchanged",
    )
    sweep: list[int] = Field(default_factory=lambda: list(DEFAULT_SWEEP))
    sweep_rir: list[int] | None = Field(None, description="RIR sweep k values (None: topk)")
    refine: str = Field("icp", description="pose refinement after RANSAC: icp | none")
    query_stride: int = Field(1, ge=1)
    max_queries: int | None = Field(None, ge=1)
    cache_dir: str | None = None
    fov: float | None = Field(
        None,
        gt=0.0,
        le=360.0,
        description="crop every scan (database, queries, foreign) to this horizontal field "
        "of view about the sensor's forward axis (deg), emulating a forward-looking sensor; "
        "a query is then in coverage only if a database scan within the threshold also "
        "faces within half the field of view of it (their views share at least half)",
    )
    negatives: bool = Field(
        True, description="keep out-of-coverage queries as negatives for the verdict"
    )
    foreign: list[str] = Field(
        default_factory=list,
        description="sequences of other places, every scan queried against the database "
        "(all out of coverage: any accepted answer is a false accept)",
    )
    prior_noise: float | None = Field(
        None, ge=0.0, description="simulate a GNSS prior: ground truth + noise (m per axis)"
    )
    prior_radius: float = Field(20.0, gt=0.0, description="radius of the simulated prior (m)")
    prior_seed: int = 0
    calibration: str | None = Field(
        None, description="calibration file (default: the one shipped for the encoder kind)"
    )
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
    from sgvloc.core.confidence import (
        Calibration,
        assess,
        nearest_of_place,
        shipped_calibration,
        spectral_candidates,
    )
    from sgvloc.core.encoders import make_encoder
    from sgvloc.core.freespace import RADIUS_M, RangeImage, thin, views_near, violation
    from sgvloc.core.pose import ransac_pose, refine_icp
    from sgvloc.core.prior import Prior
    from sgvloc.core.rerank import rerank
    from sgvloc.core.retrieval import FaissIndex
    from sgvloc.core.sgv import sgv_rerank_scores

    from .cache import FeatureCache, default_cache_dir
    from .data import open_sequence
    from .diagnostics import MATCH_RADIUS_M, is_planar, pair_match_stats

    t_run = time.perf_counter()
    seq = open_sequence(cfg.data)
    if cfg.frames is not None:
        seq = seq.frames(*cfg.frames)
    poses = seq.poses  # [F, 4, 4] T_world_sensor
    headings = np.degrees(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))  # [F]
    max_turn = cfg.fov / 2.0 if cfg.fov and cfg.fov < 360.0 else None

    def facing(ids: Any, gt: np.ndarray) -> np.ndarray | None:
        """Which of scans ``ids`` face the query's way closely enough to share its view
        (the coverage rule of ``--fov``); None without one: every scan may count."""
        if max_turn is None:
            return None
        q_heading = np.degrees(np.arctan2(gt[1, 0], gt[0, 0]))
        diff = headings[np.asarray(ids, dtype=np.int64)] - q_heading
        return np.abs((diff + 180.0) % 360.0 - 180.0) <= max_turn

    def at(T: np.ndarray) -> np.ndarray:
        """Where poses ``[..., 4, 4]`` stand for the revisit thresholds (height zeroed
        with ``planar_distance``)."""
        return T[..., :3, 3] * (1.0, 1.0, 0.0) if cfg.planar_distance else T[..., :3, 3]

    positions = at(poses)  # [F, 3]

    split = make_split(
        seq.times,
        positions,
        db_until=cfg.db_until,
        min_gap=cfg.min_gap,
        db_range=cfg.db_range,
        query_range=cfg.query_range,
        leave_out=cfg.leave_out,
        threshold=cfg.thresholds[0],
        query_stride=cfg.query_stride,
        max_queries=cfg.max_queries,
        negatives=cfg.negatives,
        headings_deg=headings,
        max_heading_deg=max_turn,
    )
    if len(split.queries) == 0 and len(split.negatives) == 0 and not cfg.foreign:
        raise InputError(f"{cfg.data}: no query has a database scan within {split.threshold} m")
    log.info("split %s", split.summary())
    foreign = [open_sequence(f) for f in cfg.foreign]

    # 1. features of every scan the run needs (cached on disk)
    encoder = make_encoder(cfg.encoder)
    refine = cfg.refine
    for s in [seq, *foreign]:
        if s.kind == "bev-images":
            if not callable(getattr(encoder, "encode_image", None)):
                raise InputError(
                    f"{s.root} holds BEV images (imgs/*.png) and encoder kind "
                    f"{cfg.encoder.kind!r} cannot encode images; use an image encoder, "
                    """e.g. --encoder '{"kind":"bev"}'"""
                )
            refine = "none"  # no 3-D cloud for ICP
    calibration = (
        Calibration.load(cfg.calibration)
        if cfg.calibration
        else shipped_calibration(cfg.encoder.kind)
    )
    cache = FeatureCache(cfg.cache_dir or default_cache_dir(), encoder, fov_deg=cfg.fov)
    evaluated = np.union1d(split.queries, split.negatives)
    needed = sorted(set(split.database.tolist()) | set(evaluated.tolist()))
    # every query of the run: (source, index) with source 0 = this sequence, 1.. = foreign
    qkeys = [(0, int(q)) for q in evaluated] + [
        (s + 1, i) for s, f in enumerate(foreign) for i in range(len(f.paths))
    ]
    sources = [seq, *foreign]
    t0 = time.perf_counter()
    unencodable: dict[str, str] = {}  # scan file -> why the encoder refused it

    centres = cfg.localizer.retrieval.centres()  # a query's displaced descriptor centres
    as_query = set(evaluated.tolist())

    def encoded(path: str, query: bool) -> Features | None:
        """The scan's features (a query's with its global descriptor about the displaced
        centres too), or None when the encoder finds nothing to describe (a scan too
        sparse for it): such a scan stays out of the database and, as a query, is an
        answer without an estimate, as the service answers it with a 422."""
        try:
            return cache.get(path, centres if query else None)
        except EmptyScanError as exc:
            unencodable[str(path)] = str(exc)
            return None
        except InputError as exc:  # a malformed or empty file: which one
            if str(path) in str(exc):  # the scan readers name it already
                raise
            raise InputError(f"{path}: {exc}") from None

    everything = {
        i: encoded(seq.paths[i], i in as_query)
        for i in _progress(needed, progress, desc="features", unit="scan")
    }
    feats = {i: f for i, f in everything.items() if f is not None}
    qfeats = {key: everything[key[1]] for key in qkeys if key[0] == 0}
    for key in _progress([k for k in qkeys if k[0]], progress, desc="foreign", unit="scan"):
        qfeats[key] = encoded(sources[key[0]].paths[key[1]], True)
    t_features = time.perf_counter() - t0
    if not feats:
        raise InputError(f"{cfg.data}: the encoder found nothing to describe in any scan")
    planar = is_planar(*(f.keypoints for f in feats.values()))
    # BEV images: the pose is x, y and yaw, so errors are measured in the plane
    in_plane = seq.kind == "bev-images"

    plan = cfg.plan()
    kmax = max(max(ks) for ks in plan.values())
    table_ks = set(cfg.topk)
    loc_cfg = cfg.localizer
    min_confidence = loc_cfg.verdict.min_confidence
    pose_cache: dict[tuple[tuple[int, int], int], tuple[Any, np.ndarray | None]] = {}

    def pose_for(qk: tuple[int, int], kf: int) -> tuple[Any, np.ndarray | None]:
        """(PoseResult, T_kf_query or None without an estimate) against keyframe kf."""
        if (qk, kf) not in pose_cache:
            fq, fk = qfeats[qk], feats[kf]
            pose = ransac_pose(
                fq.keypoints, fq.local_features, fk.keypoints, fk.local_features, loc_cfg.pose
            )
            has_estimate = pose.num_correspondences >= loc_cfg.pose.ransac_n
            if refine == "icp" and has_estimate:
                pose = refine_icp(
                    pose,
                    cache.cloud(sources[qk[0]].paths[qk[1]]),
                    cache.cloud(seq.paths[kf]),
                    loc_cfg.pose,
                )
            pose_cache[(qk, kf)] = (pose, pose.T_target_source if has_estimate else None)
        return pose_cache[(qk, kf)]

    def spectral_for(qk: tuple[int, int], ids: list[int], known: dict[int, Any]) -> None:
        """Add the SpectralGV view of the ids not yet in ``known`` (one batch)."""
        missing = [i for i in ids if i not in known]
        if missing:
            fq = qfeats[qk]
            kps = [feats[i].keypoints for i in missing]
            res = sgv_rerank_scores(
                fq.keypoints,
                fq.local_features,
                kps,
                [feats[i].local_features for i in missing],
                loc_cfg.sgv,
            )
            known.update(spectral_candidates(missing, fq.keypoints, kps, res))

    range_images: dict[int, Any] = {}

    def free_space_for(qk: tuple[int, int], matched: int, visible: np.ndarray):
        """The free-space check of the query's estimates (as the localizer makes it,
        against the database scans the query may see)."""

        def check(T_map_query: np.ndarray) -> float | None:
            d = np.linalg.norm(poses[visible, :2, 3] - T_map_query[:2, 3], axis=1)
            ids = views_near(
                T_map_query[:3, 3], matched, visible[d <= RADIUS_M], lambda i: poses[i][:3, 3]
            )
            for i in ids:
                if i not in range_images:
                    range_images[i] = RangeImage(cache.cloud(seq.paths[i]))
            points = thin(cache.cloud(sources[qk[0]].paths[qk[1]]))
            return violation(points, T_map_query, [(poses[i], range_images[i]) for i in ids])

        return check

    def verdict_record(
        qk: tuple[int, int],
        ids: list[int],
        gt: np.ndarray,
        same_world: bool,
        spectral,
        prior,
        visible: np.ndarray,
    ) -> dict[str, Any]:
        """Pose, evidence, confidence and verdict of one answer (re-ranked ``ids``)."""
        if not ids:
            return {
                "rte": float("nan"),
                "rre": float("nan"),
                "localized": False,
                "has_estimate": False,
                "confidence": 0.0,
                "verdict": "no_keyframe_in_prior" if prior is not None else "no_keyframes",
                "accepted": False,
                "correct": False,
            }
        pose, T_kf_q = pose_for(qk, ids[0])
        spectral_for(qk, ids, spectral)
        fq = qfeats[qk]
        judged = assess(
            calibration,
            ids,
            spectral,
            lambda i: poses[i],
            query_keypoints=fq.keypoints,
            similarity=float(fq.global_descriptor @ feats[ids[0]].global_descriptor),
            pose=pose,
            T_kf_query=T_kf_q,
            min_confidence=min_confidence,
            prior=prior,
            free_space=free_space_for(qk, ids[0], visible) if refine == "icp" else None,
        )
        T_est = poses[ids[0]] @ (T_kf_q if T_kf_q is not None else np.eye(4))
        e_t, e_r = rte(T_est, gt, in_plane), rre(T_est, gt, in_plane)
        return {
            "rte": e_t if same_world else float("nan"),
            "rre": e_r if same_world else float("nan"),
            "localized": pose.localized,
            "has_estimate": T_kf_q is not None,
            "confidence": judged.confidence,
            "evidence": judged.evidence.to_dict(),
            "verdict": judged.verdict.code,
            "accepted": judged.verdict.localized,
            "correct": bool(same_world and success([e_t], [e_r])[0]),
        }

    rng_prior = np.random.default_rng(cfg.prior_seed)

    # 2. queries in time order against the database each may see
    index = FaissIndex(encoder.global_dim, loc_cfg.retrieval)
    # several descriptor blocks merged: each block's top-k, united (as the localizer does)
    blocks = encoder.blocks if loc_cfg.retrieval.combine == "merge" else (encoder.global_dim,)
    in_index: set[int] = set()
    recs: dict[tuple[str, int], list[dict[str, Any]]] = {
        (m, k): [] for m, ks in plan.items() for k in ks
    }
    k_scores = max(cfg.topk)  # SGV score statistics over this many retrieved candidates
    match_pairs: list[dict[str, Any]] = []
    score_recs: list[dict[str, Any]] = []
    in_coverage = set(split.queries.tolist())
    t_queries = time.perf_counter()
    for qk in _progress(qkeys, progress, desc="queries", unit="query"):
        src, q = qk
        visible = split.database_for(q) if src == 0 else split.database
        if unencodable:
            visible = visible[[int(i) in feats for i in visible]]
        new = [i for i in visible.tolist() if i not in in_index]
        if new:
            index.add(
                np.asarray(new, np.int64), np.stack([feats[i].global_descriptor for i in new])
            )
            in_index.update(new)
        gt = sources[src].poses[q]
        covered = src == 0 and q in in_coverage
        prior = among = None
        if split.mode == "leave-out":  # the index holds the scans near the query too
            among = visible
        if cfg.prior_noise is not None:
            noisy = gt[:2, 3] + rng_prior.normal(0.0, cfg.prior_noise, size=2)
            prior = Prior(tuple(noisy), cfg.prior_radius)
            among = visible[prior.distance(poses[visible, :3, 3]) <= cfg.prior_radius]
        fq = qfeats[qk]
        if fq is None:  # nothing to describe: no answer for any method
            for (_method, k), rs in recs.items():
                rec = {"query": q, "ms": 0.0, "ranked": [], "candidates": 0}
                rec.update({"top1_changed": False, "in_coverage": covered})
                if src:
                    rec["foreign"] = cfg.foreign[src - 1]
                rec.update({f"rank@{thr:g}m": None for thr in cfg.thresholds})
                if k in table_ks:
                    rec.update(verdict_record(qk, [], gt, src == 0, {}, None, visible))
                    rec["verdict"] = "no_features"
                rs.append(rec)
            continue
        candidates = _retrieval(index, fq, kmax, blocks, among)
        retrieved = candidates(kmax)
        spectral: dict[int, Any] = {}
        spectral_for(qk, [c.keyframe_id for c in retrieved], spectral)
        sgv_out = None
        for method, ks in plan.items():
            for k in ks:
                t = time.perf_counter()
                start = candidates(k)
                out = rerank(method, fq, start, feats.__getitem__, index, loc_cfg, among)
                ms = (time.perf_counter() - t) * 1e3
                if method == "sgv" and k == k_scores:
                    sgv_out = out
                ids = [c.keyframe_id for c in out.candidates]
                if method == "sgv":  # as the localizer: the nearest keyframe of the place
                    ids = nearest_of_place(
                        ids,
                        spectral,
                        lambda i: poses[i],
                        loc_cfg.sgv.tie_tolerance,
                        loc_cfg.sgv.tie_gain_m,
                    )
                rec: dict[str, Any] = {
                    "query": q,
                    "ms": ms,
                    "ranked": ids,
                    "candidates": len(start),
                    "top1_changed": bool(ids and start and ids[0] != start[0].keyframe_id),
                    "in_coverage": covered,
                }
                if src:
                    rec["foreign"] = cfg.foreign[src - 1]
                for thr in cfg.thresholds:
                    rec[f"rank@{thr:g}m"] = (
                        first_true_rank(positions[ids], at(gt), thr, facing(ids, gt))
                        if covered
                        else None
                    )
                # the ceiling's rank: in the candidates re-ranking started from (query
                # expansion answers from a search of its own)
                start_ids = [c.keyframe_id for c in start]
                rec["start_rank"] = (
                    first_true_rank(
                        positions[start_ids],
                        at(gt),
                        cfg.thresholds[0],
                        facing(start_ids, gt),
                    )
                    if covered
                    else None
                )
                if k in table_ks:
                    rec.update(verdict_record(qk, ids, gt, src == 0, spectral, prior, visible))
                recs[(method, k)].append(rec)
        if not covered:
            continue

        # encoder diagnostics: matches on the true pair, SGV scores of true/false candidates
        d = np.linalg.norm(positions[visible] - at(gt), axis=1)
        seen = facing(visible, gt)  # the true pair shares the query's view (--fov)
        if seen is not None and seen.any():
            d = np.where(seen, d, np.inf)
        db = int(visible[int(np.argmin(d))])
        T_db_q = np.linalg.inv(poses[db]) @ gt
        fd = feats[db]
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
            sgv_out = rerank("sgv", fq, candidates(k_scores), feats.__getitem__, index, loc_cfg)
        ids = [c.keyframe_id for c in sgv_out.candidates]
        dist = np.linalg.norm(positions[ids] - at(gt), axis=1) if ids else np.zeros(0)
        true = dist <= cfg.thresholds[0]
        if ids and (seen_ids := facing(ids, gt)) is not None:
            true &= seen_ids
        score_recs.append(
            {
                "query": q,
                "ids": ids,
                "scores": [float(c.score) for c in sgv_out.candidates],
                "true": [bool(x) for x in true],
            }
        )
    t_queries = time.perf_counter() - t_queries

    # 3. aggregate
    rows, sweep, per_query = [], {m: [] for m in plan}, {}
    for (method, k), rs in recs.items():
        agg = _aggregate(method, k, rs, cfg.thresholds, with_pose=k in table_ks)
        keep = [
            key
            for key in agg
            if key.startswith(("R@1", "ceiling", "candidates")) or key.endswith("_ms")
        ]
        sweep[method].append({"k": k, **{key: agg[key] for key in keep}})
        if k in table_ks:
            rows.append(agg)
            per_query[f"{method}@{k}"] = rs
    order = {m: i for i, m in enumerate(cfg.methods)}
    rows.sort(key=lambda r: (r["k"], order[r["method"]]))
    for m in sweep:
        sweep[m].sort(key=lambda e: e["k"])

    n_out = len(split.negatives) + sum(len(f.paths) for f in foreign)
    notes = [
        f"retrieval: top-{kmax} once per query; each (method, k) re-ranks the first k hits"
        if len(blocks) == 1
        else f"retrieval: top-{kmax} of each of the {len(blocks)} descriptor blocks once per "
        "query; each (method, k) re-ranks the merge of each block's first k hits (between k "
        "and blocks x k candidates, each keyframe once)",
        *(
            [
                f"retrieval: each query's polar block also about {len(centres)} centres "
                f"{cfg.localizer.retrieval.offset_m:g} m from its sensor, each database scan "
                "ranked by its best similarity over them (retrieval.offset_m)"
            ]
            if centres is not None
            and any(f is not None and f.global_variants is not None for f in qfeats.values())
            else []
        ),
        "pose: RANSAC on local features against the re-ranked top-1"
        + (", refined by ICP on the preprocessed clouds" if refine == "icp" else "")
        + "; the same estimator for every method",
        "recall, S and RTE/RRE: over the in-coverage queries (a database scan within "
        f"{split.threshold:g} m"
        + (" in the plane, heights ignored: --planar-distance" if cfg.planar_distance else "")
        + "); RTE/RRE are means, a query that is not localized keeps its "
        "estimate; with no estimate at all (too few correspondences) the matched keyframe's "
        "pose is used; a query with no candidate at all (nothing to describe, or none in "
        "the prior's radius) counts as a failure in S and is left out of the means",
        f"verdict: accepted = the calibrated confidence ({calibration.name}, "
        f"{calibration.fingerprint}) >= min_confidence {min_confidence:g} and the pose "
        "step's minimums hold"
        + (", and the estimate lies inside the prior's radius" if prior is not None else "")
        + "; correct = RTE <= 2 m and RRE <= 5 deg; false accepts = accepted but not correct, "
        f"over all {len(qkeys)} queries, {n_out} of them out of coverage"
        + (f" ({sum(len(f.paths) for f in foreign)} from other places)" if foreign else ""),
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
        *(
            [
                f"{len(unencodable)} scans could not be encoded (e.g. "
                f"{next(iter(unencodable.values()))}): left out of the database; as queries "
                "they count as not localized (verdict no_features)"
            ]
            if unencodable
            else []
        ),
        f"out-of-coverage queries (no database scan within {split.threshold:g} m): "
        f"{len(split.dropped)}"
        + (
            f", {len(split.negatives)} of them kept as negatives for the verdict"
            if cfg.negatives
            else ", dropped (--no-negatives)"
        ),
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
        f"SGV scores: the sgv method's score of every candidate it re-ranks at top-k "
        f"{k_scores} (the first {k_scores} of each descriptor block, merged) per query, true "
        f"= within {cfg.thresholds[0]:g} m; AUC pooled over all queries and as the mean of "
        "per-query AUCs",
    ]
    if cache.fov_deg:
        notes.insert(
            0,
            f"field of view: every scan cropped to {cache.fov_deg:g} deg about the sensor's "
            "forward axis before encoding (a forward-looking sensor emulated); in coverage "
            f"= a database scan within {split.threshold:g} m facing within "
            f"{cache.fov_deg / 2:g} deg of the query",
        )
    if cfg.prior_noise is not None:
        notes.append(
            f"prior: per query, the ground-truth x/y plus Gaussian noise of {cfg.prior_noise:g} m "
            f"per axis (seed {cfg.prior_seed}), radius {cfg.prior_radius:g} m: retrieval "
            "searches only the database scans inside it"
        )
    if seq.kind == "bev-images":
        notes.insert(
            0,
            f"data: BEV images (imgs/*.png), times from {seq.times_source}; features from "
            "the encoder's encode_image; poses estimated from planar keypoints (x, y, yaw), "
            "RTE/RRE and the verdict's correctness in the plane (x/y distance, yaw "
            "difference): height, roll and pitch are not observable in the images",
        )
    if refine != cfg.refine:
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
    config["calibration"] = {"name": calibration.name, "fingerprint": calibration.fingerprint}
    config["plan"] = plan
    split_info = split.summary()
    split_info["query_indices"] = split.queries.tolist()
    split_info["dropped_indices"] = split.dropped.tolist()
    split_info["negative_indices"] = split.negatives.tolist()
    split_info["foreign_queries"] = {
        f: len(s.paths) for f, s in zip(cfg.foreign, foreign, strict=True)
    }
    matches = summarise_pairs(match_pairs, planar, MATCH_RADIUS_M)
    matches["per_pair"] = match_pairs
    scores = score_separation(score_recs)
    scores.update(k=k_scores, threshold_m=cfg.thresholds[0], per_query=score_recs)
    return EvalResult(config, split_info, rows, sweep, per_query, timings, notes, matches, scores)


def _retrieval(index: Any, query: Features, kmax: int, blocks: tuple[int, ...], among: Any) -> Any:
    """One query's retrieval, run once with ``kmax``: returns ``candidates(k)``, the
    candidate list for any ``k <= kmax`` (the first k hits; with several descriptor
    blocks, the merge of each block's first k; with the descriptor about displaced
    centres, by the best similarity over them: as :func:`sgvloc.core.retrieval.retrieve`
    gives it)."""
    from sgvloc.core.rerank import Candidate
    from sgvloc.core.retrieval import merge_hits, retrieve

    descriptor, variants = query.global_descriptor, query.global_variants
    k = min(kmax, len(index))
    if len(blocks) > 1:
        lists = (
            index.search_blocks(descriptor, k, blocks, among=among, variants=variants) if k else []
        )

        def hits_for(n: int) -> list[Any]:
            return merge_hits(lists, n)
    else:  # one block: retrieve's own list, whose first n are its top n
        hits = retrieve(index, descriptor, k, blocks, among=among, variants=variants) if k else []

        def hits_for(n: int) -> list[Any]:
            return hits[:n]

    def candidates(n: int) -> list[Any]:
        return [Candidate(h.id, h.similarity, r, h.similarity) for r, h in enumerate(hits_for(n))]

    return candidates


def ceiling(first_true_ranks: list[int | None]) -> float:
    """Recall ceiling in percent: the share of queries with a true match anywhere in the
    candidate list that re-ranking started from (a rank, not None); NaN for none."""
    if not first_true_ranks:
        return float("nan")
    return 100.0 * sum(r is not None for r in first_true_ranks) / len(first_true_ranks)


def _mean(xs: list[float]) -> float:
    return float(np.mean(xs)) if xs else float("nan")


def _nanmean(xs: list[float]) -> float:
    finite = [x for x in xs if not np.isnan(x)]
    return float(np.mean(finite)) if finite else float("nan")


def _aggregate(
    method: str, k: int, recs: list[dict[str, Any]], thresholds: list[float], with_pose: bool
) -> dict[str, Any]:
    """Figures of one (method, k): recall and pose over the in-coverage queries, the
    verdict over all of them."""
    cov = [r for r in recs if r["in_coverage"]]
    out: dict[str, Any] = {"method": method, "k": k, "queries": len(cov)}
    for thr in thresholds:
        ranks = [r[f"rank@{thr:g}m"] for r in cov]
        out[f"R@1_{thr:g}m"] = recall_at(ranks, 1)
        out[f"R@5_{thr:g}m"] = recall_at(ranks, 5)
        out[f"MRR_{thr:g}m"] = mrr(ranks)
    # the recall ceiling: a true match among the candidates re-ranking starts from (k of
    # them, or up to k per block when descriptor blocks are merged)
    first = [r.get("start_rank", r[f"rank@{thresholds[0]:g}m"]) for r in cov]
    out[f"ceiling_{thresholds[0]:g}m"] = ceiling(first)
    out["candidates_mean"] = _mean([float(r.get("candidates", k)) for r in cov])
    ms = [r["ms"] for r in recs]
    out["rerank_median_ms"] = statistics.median(ms) if ms else float("nan")
    out["rerank_mean_ms"] = _mean(ms)
    out["top1_changed_pct"] = 100.0 * _mean([float(r["top1_changed"]) for r in cov])
    if not with_pose:
        return out
    t = [r.get("rte", float("nan")) for r in cov]
    a = [r.get("rre", float("nan")) for r in cov]
    ok = success(t, a)
    out["success_pct"] = 100.0 * float(ok.mean()) if cov else float("nan")
    # pose success where the re-ranked top-1 is a true match (the pose step alone)
    true1 = np.array([r[f"rank@{thresholds[0]:g}m"] == 1 for r in cov], dtype=bool)
    out["success_true_top1_pct"] = 100.0 * float(ok[true1].mean()) if true1.any() else float("nan")
    # over the queries with an estimate to measure (one without candidates has none; it
    # counts in no_estimate and as a failure in success_pct)
    out["mean_rte_m"] = _nanmean(t)
    out["mean_rre_deg"] = _nanmean(a)
    out["median_rte_m"] = float(np.nanmedian(t)) if t else float("nan")
    out["localized_pct"] = 100.0 * _mean([float(r.get("localized", False)) for r in cov])
    out["no_estimate"] = sum(1 for r in cov if not r.get("has_estimate", True))
    out.update(verdict_figures(recs))
    return out


def verdict_figures(recs: list[dict[str, Any]]) -> dict[str, Any]:
    """What the verdict did over every query (in and out of coverage)."""
    n = len(recs)
    acc = np.array([r["accepted"] for r in recs], dtype=bool)
    cor = np.array([r["correct"] for r in recs], dtype=bool)
    cov = np.array([r["in_coverage"] for r in recs], dtype=bool)
    conf = np.array([r["confidence"] for r in recs], dtype=np.float64)
    fa = acc & ~cor
    return {
        "all_queries": n,
        "out_of_coverage": int((~cov).sum()),
        "accepted_in_coverage_pct": 100.0 * float(acc[cov].mean()) if cov.any() else float("nan"),
        "accepted_of_correct_pct": 100.0 * float(acc[cor].mean()) if cor.any() else float("nan"),
        "false_accepts": int(fa.sum()),
        "false_accepts_out_of_coverage": int((fa & ~cov).sum()),
        "false_accept_pct": 100.0 * float(fa.mean()) if n else float("nan"),
        "ece": expected_calibration_error(conf, cor) if n else float("nan"),
    }


__all__ = ["EvalConfig", "EvalResult", "Split", "run_evaluation", "FULL_SWEEP_METHODS"]
