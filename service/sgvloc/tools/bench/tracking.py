"""``sgvloc bench --only tracking``: a seeded (tracked) localize against a global one.

The map is every ``map_every``-th scan of a KITTI-layout sequence (``--track-data``;
default the shipped fixture, every second scan), with the default encoder. Each query is
a scan of the sequence sent twice, in the same run: once plain (global: encode,
retrieve, re-rank, RANSAC, ICP) and once with a seed (its ground-truth pose moved by
0.3 m and 3 degrees, sigmas 1 m and 5 degrees), first in process through the map manager
(the code the routes call), then over HTTP with MessagePack to a started service
(``sgvloc serve --dev``, one client, sequential). Medians, and the ratio global/tracked
measured on the same scans. In process also the throughput of tracked scans from one
thread and from ``workers`` threads at once (the same scans, split between them), which
says whether concurrent tracked scans run in parallel or wait for each other.
"""

from __future__ import annotations

import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from sgvloc_client import wire

from ..eval_track import perturbed
from ..service_process import temporary_service
from .http import FIXTURE

Echo = Callable[[str], None]


def _seed(T: np.ndarray, rng: np.random.Generator) -> dict[str, Any]:
    dyaw = 3.0 * rng.choice([-1.0, 1.0])
    S = perturbed(T, 0.3 * rng.standard_normal(2) / np.sqrt(2), dyaw)
    return {"T_map_sensor": S, "sigma_m": 1.0, "sigma_yaw_deg": 5.0}


def bench_tracking(
    *,
    data: Path | None = None,
    map_every: int = 2,
    repeats: int = 3,
    workers: int = 2,
    echo: Echo = lambda _m: None,
) -> dict[str, Any]:
    """Median time of a global and of a seeded localize, in process and over HTTP."""
    from sgvloc.core.sequence import KittiSequence
    from sgvloc.core.tracking import Seed
    from sgvloc.server.maps import KeyframeIn, MapManager

    seq = KittiSequence(data or FIXTURE)
    map_ids = list(range(0, len(seq), map_every))
    queries = [i for i in range(len(seq)) if i not in set(map_ids)] or list(range(len(seq)))
    rng = np.random.default_rng(0)
    scans = {i: seq[i].scan().xyzi() for i in queries}
    seeds = {i: _seed(seq[i].T_world_sensor, rng) for i in queries}
    result: dict[str, Any] = {
        "data": str(data or FIXTURE),
        "map_keyframes": len(map_ids),
        "queries": len(queries),
        "repeats": repeats,
    }
    keyframes = [
        KeyframeIn(seq[i].T_world_sensor, points=seq[i].scan().xyzi(), key=str(i)) for i in map_ids
    ]

    # in process: the map manager, as the routes call it
    with tempfile.TemporaryDirectory(prefix="sgvloc-bench-track-") as tmp:
        manager = MapManager(Path(tmp) / "maps")
        manager.load_all()
        try:
            manager.create("track")
            manager.insert("track", keyframes)
            times: dict[str, list[float]] = {"global": [], "tracked": []}
            modes = []
            for rep in range(repeats + 1):  # the first round warms caches up, untimed
                for i in queries:
                    t0 = time.perf_counter()
                    manager.localize("track", points=scans[i])
                    t1 = time.perf_counter()
                    s = seeds[i]
                    r = manager.localize(
                        "track",
                        points=scans[i],
                        seed=Seed(s["T_map_sensor"], s["sigma_m"], s["sigma_yaw_deg"]),
                    )
                    t2 = time.perf_counter()
                    if rep:
                        times["global"].append((t1 - t0) * 1e3)
                        times["tracked"].append((t2 - t1) * 1e3)
                        modes.append(r.mode)
            jobs = [
                (scans[i], Seed(s["T_map_sensor"], s["sigma_m"], s["sigma_yaw_deg"]))
                for _ in range(repeats)
                for i, s in seeds.items()
            ]
            rates = {n: _tracked_per_s(manager, jobs, n) for n in sorted({1, workers})}
        finally:
            manager.close()
    result["in_process"] = _summary(times, modes)
    result["in_process"]["tracked_per_s"] = rates
    echo(f"  in process: {_line(result['in_process'])}")
    echo("  tracked scans/s: " + ", ".join(f"{n} thread(s) {r:.1f}" for n, r in rates.items()))

    # over HTTP, MessagePack both ways
    with temporary_service(None, "track", workers, {}) as srv:
        with httpx.Client(base_url=srv.url, timeout=120.0) as c:
            assert c.post("/v1/maps", json={"name": "track"}).status_code == 201
            body = {
                "keyframes": [
                    {"key": kf.key, "T_map_sensor": kf.T_map_sensor, "points": kf.points}
                    for kf in keyframes
                ]
            }
            r = c.post(
                "/v1/maps/track/keyframes",
                content=wire.packb(body),
                headers={"Content-Type": wire.MSGPACK},
            )
            r.raise_for_status()
            headers = {"Content-Type": wire.MSGPACK, "Accept": wire.MSGPACK}
            plain = {i: wire.packb({"points": scans[i]}) for i in queries}
            seeded = {i: wire.packb({"points": scans[i], "seed": seeds[i]}) for i in queries}
            times = {"global": [], "tracked": []}
            modes = []
            for rep in range(repeats + 1):
                for i in queries:
                    t0 = time.perf_counter()
                    c.post("/v1/maps/track/localize", content=plain[i], headers=headers)
                    t1 = time.perf_counter()
                    r = c.post("/v1/maps/track/localize", content=seeded[i], headers=headers)
                    t2 = time.perf_counter()
                    if rep:
                        times["global"].append((t1 - t0) * 1e3)
                        times["tracked"].append((t2 - t1) * 1e3)
                        modes.append(wire.unpackb(r.content)["mode"])
    result["http"] = _summary(times, modes)
    echo(f"  HTTP (MessagePack): {_line(result['http'])}")
    return result


def _tracked_per_s(manager: Any, jobs: list[tuple[np.ndarray, Any]], threads: int) -> float:
    """Tracked scans per second with ``threads`` threads sharing ``jobs`` (scan, seed)."""

    def work(share: list[tuple[np.ndarray, Any]]) -> None:
        for scan, seed in share:
            manager.localize("track", points=scan, seed=seed)

    pool = [threading.Thread(target=work, args=(jobs[k::threads],)) for k in range(threads)]
    t0 = time.perf_counter()
    for t in pool:
        t.start()
    for t in pool:
        t.join()
    return len(jobs) / (time.perf_counter() - t0)


def _summary(times: dict[str, list[float]], modes: list[str]) -> dict[str, Any]:
    g, t = float(np.median(times["global"])), float(np.median(times["tracked"]))
    return {
        "global_p50_ms": g,
        "tracked_p50_ms": t,
        "tracked_p90_ms": float(np.percentile(times["tracked"], 90)),
        "ratio": g / t if t else None,
        "tracked_share": modes.count("tracked") / len(modes) if modes else 0.0,
        "samples": len(modes),
    }


def _line(s: dict[str, Any]) -> str:
    return (
        f"global p50 {s['global_p50_ms']:.1f} ms, tracked p50 {s['tracked_p50_ms']:.1f} ms "
        f"(p90 {s['tracked_p90_ms']:.1f}), {s['ratio']:.1f}x; {s['tracked_share']:.0%} of "
        f"the seeded answers tracked ({s['samples']} pairs)"
    )


def format_tracking(res: dict[str, Any]) -> str:
    """The section's table."""
    rows = [
        "| path | global p50 (ms) | tracked p50 (ms) | tracked p90 (ms) | global / tracked |",
        "|---|---:|---:|---:|---:|",
    ]
    for key, name in (("in_process", "in process"), ("http", "HTTP, MessagePack")):
        s = res[key]
        rows.append(
            f"| {name} | {s['global_p50_ms']:.1f} | {s['tracked_p50_ms']:.1f} | "
            f"{s['tracked_p90_ms']:.1f} | {s['ratio']:.1f}x |"
        )
    rates = res["in_process"]["tracked_per_s"]
    one = rates.get(1) or rates.get("1")
    rows.append(
        "\ntracked scans per second in process: "
        + ", ".join(
            f"{n} thread(s) {r:.1f}" + (f" ({r / one:.2f}x)" if one and str(n) != "1" else "")
            for n, r in rates.items()
        )
    )
    rows.append(
        f"\n{res['queries']} query scans x {res['repeats']} rounds, map of "
        f"{res['map_keyframes']} keyframes ({res['data']})"
    )
    return "\n".join(rows)


FORMATTERS = {"tracking": format_tracking}
