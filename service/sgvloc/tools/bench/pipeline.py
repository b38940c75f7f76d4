"""``sgvloc bench --only pipeline``: what one localization costs in process, stage by
stage, in wall time and in CPU time, for the default path and (``--compare``) the
earlier one, in the same run.

The map is every ``map_every``-th scan of a KITTI-layout sequence (``--pipeline-data``;
default the shipped fixture, every second scan), encoded once with the default encoder;
the same keyframes (features and clouds) back every path. The queries are the other
scans. Paths:

- ``default``: the defaults (network in ONNX Runtime when installed, ICP with small_gicp);
- ``default, no ICP``: the same with ``refine="none"``;
- ``earlier`` (``--compare``): the network in torch, RANSAC in batches of 1000 hypotheses
  and Open3D's point-to-point ICP over every point (:data:`EARLIER_POSE`), everything
  else equal: the path before these changes.

Each round sends every query once through every path, interleaved (query by query), so
that a busy moment of a shared machine falls on all paths alike; the first round is an
untimed warm-up. CPU time is the process's (``time.process_time``: every thread,
including a library's own pool) over the localize call. Reported: medians, the ratio to
the default path, and whether the paths agree (verdict, keyframe, pose within 5 cm and
0.1 degree).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..evaluation.metrics import rre, rte
from .engine import _table
from .http import FIXTURE

Echo = Callable[[str], None]
STAGES = ("encode", "retrieve", "rerank", "pose", "verify")
#: the pose settings of the earlier path: RANSAC in batches of 1000, Open3D's
#: point-to-point ICP over every point of the query cloud
EARLIER_POSE = {
    "ransac_first_batch": 1000,
    "icp_backend": "open3d",
    "icp_method": "point_to_point",
    "icp_source_voxel_m": 0.0,
    "icp_coarse_m": 0.0,  # one ICP stage, as then (the coarse stage came later)
}


def bench_pipeline(
    *,
    data: Path | None = None,
    map_every: int = 2,
    rounds: int = 3,
    compare: bool = True,
    echo: Echo = lambda _m: None,
) -> dict[str, Any]:
    """Per-stage medians of each path over the queries (see the module docstring)."""
    from sgvloc.core.config import LocalizerConfig, PoseConfig
    from sgvloc.core.encoders import EncoderSpec, make_encoder
    from sgvloc.core.localizer import Localizer
    from sgvloc.core.sequence import KittiSequence

    if map_every < 2 or rounds < 1:
        raise ValueError("map_every must be >= 2 and rounds >= 1")
    seq = KittiSequence(data or FIXTURE)
    map_ids = list(range(0, len(seq), map_every))
    queries = [i for i in range(len(seq)) if i % map_every]
    new_enc = make_encoder(EncoderSpec())
    base = Localizer(new_enc, LocalizerConfig())
    keyframes = [
        base.make_keyframe(seq[i].T_world_sensor, scan=seq[i].scan().points) for i in map_ids
    ]
    base.add_keyframes(keyframes)
    scans = {i: seq[i].scan().points for i in queries}

    paths: dict[str, tuple[Localizer, dict[str, Any]]] = {
        "default": (base, {}),
        "default, no ICP": (base, {"refine": "none"}),
    }
    if compare:
        old = Localizer(
            make_encoder(EncoderSpec(runtime="torch")),
            LocalizerConfig(pose=PoseConfig(**EARLIER_POSE)),
        )
        old.add_keyframes(keyframes)
        paths["earlier"] = (old, {})
    runtime = getattr(new_enc, "runtime", "-")
    echo(
        f"  {len(map_ids)} keyframes, {len(queries)} queries x {rounds} rounds, paths: "
        f"{', '.join(paths)} (default network runtime: {runtime})"
    )
    samples: dict[str, dict[str, list[float]]] = {p: {} for p in paths}
    answers: dict[str, dict[int, Any]] = {p: {} for p in paths}
    for rnd in range(rounds + 1):  # round 0 warms up (ONNX sessions, numba, caches)
        for i in queries:
            for name, (loc, kwargs) in paths.items():
                c0, w0 = time.process_time(), time.perf_counter()
                res = loc.localize(scans[i], **kwargs)
                wall, cpu = (time.perf_counter() - w0) * 1e3, (time.process_time() - c0) * 1e3
                answers[name][i] = res
                if rnd:
                    s = samples[name]
                    s.setdefault("wall", []).append(wall)
                    s.setdefault("cpu", []).append(cpu)
                    for stage in STAGES:
                        s.setdefault(stage, []).append(res.timings_ms.get(stage, 0.0))
    rows = []
    ref = samples["default"]
    for name in paths:
        s = samples[name]
        med = {k: float(np.median(v)) for k, v in s.items()}
        rows.append(
            {
                "path": name,
                "wall_p50_ms": med["wall"],
                "cpu_p50_ms": med["cpu"],
                "cpu_mean_ms": float(np.mean(s["cpu"])),
                "stages_p50_ms": {k: med[k] for k in STAGES},
                "cpu_vs_default": med["cpu"] / float(np.median(ref["cpu"])),
                "wall_vs_default": med["wall"] / float(np.median(ref["wall"])),
                "agreement": _agreement(answers["default"], answers[name]),
            }
        )
    return {
        "data": str(data or FIXTURE),
        "map_keyframes": len(map_ids),
        "queries": len(queries),
        "rounds": rounds,
        "default_runtime": runtime,
        "paths": rows,
    }


def _agreement(ref: dict[int, Any], other: dict[int, Any]) -> dict[str, Any]:
    """How often ``other``'s answers match ``ref``'s: verdict, keyframe and pose."""
    same_verdict = same_kf = close = 0
    worst_m = 0.0
    for i, a in ref.items():
        b = other[i]
        same_verdict += a.localized == b.localized
        same_kf += a.keyframe_id == b.keyframe_id
        if a.T_map_sensor is not None and b.T_map_sensor is not None:
            dt, dr = rte(b.T_map_sensor, a.T_map_sensor), rre(b.T_map_sensor, a.T_map_sensor)
            worst_m = max(worst_m, dt)
            close += dt <= 0.05 and dr <= 0.1
    return {
        "queries": len(ref),
        "same_verdict": same_verdict,
        "same_keyframe": same_kf,
        "pose_within_5cm_0.1deg": close,
        "largest_position_difference_m": worst_m,
    }


def format_pipeline(res: dict[str, Any]) -> str:
    """The section's table."""
    header = ["path", "wall p50 (ms)", "CPU p50 (ms)", "CPU / default", "encode", "rerank"]
    header += ["pose", "verify", "same verdict", "pose within 5 cm"]
    rows = []
    for r in res["paths"]:
        st, ag = r["stages_p50_ms"], r["agreement"]
        n = ag["queries"]
        rows.append(
            [r["path"], f"{r['wall_p50_ms']:.1f}", f"{r['cpu_p50_ms']:.1f}"]
            + [f"{r['cpu_vs_default']:.2f}x"]
            + [f"{st[k]:.1f}" for k in ("encode", "rerank", "pose", "verify")]
            + [f"{ag['same_verdict']}/{n}", f"{ag['pose_within_5cm_0.1deg']}/{n}"]
        )
    return (
        f"{_table(header, rows)}\n\n{res['queries']} query scans x {res['rounds']} rounds, "
        f"map of {res['map_keyframes']} keyframes ({res['data']}); stages are wall-time "
        "medians"
    )


FORMATTERS = {"pipeline": format_pipeline}
