"""``sgvloc bench``: how fast each stage is and how its cost grows.

Sections (each selectable):

- ``rerank``: SpectralGV (fused numba kernel and batched torch) against RANSAC-RIR and
  FGR-RIR (:mod:`sgvloc.core.pose`) on identical inputs: the same query keypoints and
  features, the same k candidates and the same correspondences (SGV's nearest
  neighbour per query keypoint, which RANSAC and FGR take as given). SGV alone at
  large n with the process's peak memory (RSS high-water mark of a fresh subprocess,
  ``resource.getrusage``).
- ``retrieval``: FAISS search latency for exact (flat) and approximate (IVF, optionally
  HNSW) indexes through :class:`~sgvloc.core.retrieval.FaissIndex`, with recall@k of the
  approximate index against exact search.
- ``encoding``: the handcrafted encoder per stage on a dense scan.

Every comparison runs in one process on the same inputs, after a warm-up call (numba
compile/load, first-touch allocations), and reports the median of the repeats (and the
minimum: the machine may be shared). Results are plain dicts, written to JSON by the CLI.
"""

from __future__ import annotations

import json
import logging
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)


Echo = Callable[[str], None]


def _quiet(_: str) -> None:
    pass


def timed(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> dict[str, float]:
    """Median and minimum wall time (ms) of ``fn()`` over ``repeats`` runs after warm-up."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return {"median_ms": float(np.median(times)), "min_ms": float(np.min(times)), "n": repeats}


def _settle(seconds: float = 0.25) -> None:
    """Pause between methods so that idle worker threads of the previous one (OpenBLAS
    spins ~0.1 s after a call, OpenMP pools a little) are parked before the next is timed:
    on 2 cores a spinning pool steals a core from the next method's threads."""
    time.sleep(seconds)


def machine_info() -> dict[str, Any]:
    """CPU count, platform and library versions (recorded with every result)."""
    import os

    info: dict[str, Any] = {
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "numpy": np.__version__,
    }
    try:
        info["load_avg"] = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        pass
    for mod in ("torch", "numba", "faiss", "open3d"):
        try:
            info[mod] = __import__(mod).__version__
        except Exception:  # noqa: BLE001 - optional, reporting only
            info[mod] = None
    try:
        import torch

        if torch.cuda.is_available():
            info["cuda_device"] = torch.cuda.get_device_name(0)
    except Exception:  # noqa: BLE001
        pass
    return info


# --------------------------------------------------------------------------------------
# Re-ranking
# --------------------------------------------------------------------------------------


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def rerank_inputs(
    rng: np.random.Generator, n: int, k: int, dim: int = 33
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """A query (``n`` keypoints, ``dim``-D features) and ``k`` candidates of ``n`` keypoints.

    The first candidate is a revisit (40 % of its points are the query's keypoints moved
    rigidly, with matching features), the others share 0-10 % of the points; the rest are
    random points with random features. LiDAR-like extent: 60 m across, flat in z.
    """
    qk = rng.uniform(-30, 30, size=(n, 3))
    qk[:, 2] *= 0.1
    qf = np.abs(rng.normal(size=(n, dim)))  # FPFH-like: non-negative histograms
    kps, fts = [], []
    for c in range(k):
        ratio = 0.4 if c == 0 else rng.uniform(0.0, 0.1)
        m = int(round(ratio * n))
        perm = rng.permutation(n)
        kp = rng.uniform(-30, 30, size=(n, 3))
        kp[:, 2] *= 0.1
        ft = np.abs(rng.normal(size=(n, dim)))
        rot, t = _rotation(rng), rng.uniform(-5, 5, size=3)
        kp[:m] = qk[perm[:m]] @ rot.T + t + rng.normal(scale=0.03, size=(m, 3))
        ft[:m] = qf[perm[:m]] + np.abs(rng.normal(scale=0.05, size=(m, dim)))
        kps.append(kp.astype(np.float32))
        fts.append(ft.astype(np.float32))
    return qk.astype(np.float32), qf.astype(np.float32), kps, fts


def bench_rerank(
    ks: list[int],
    ns: list[int],
    *,
    repeats: int = 7,
    rir_max_k: int = 20,
    rir_repeats: int = 3,
    rir: bool = True,
    large_ns: list[int] | None = None,
    echo: Echo = _quiet,
) -> dict[str, Any]:
    """SGV (numba, torch) vs RANSAC-RIR and FGR-RIR on identical inputs; SGV at large n."""
    import torch

    from sgvloc.core.config import PoseConfig, SGVConfig
    from sgvloc.core.sgv import numba_available, warm_up

    backends = (["numba"] if numba_available() else []) + ["torch"]
    cfgs = {b: SGVConfig(device="cpu", backend=b) for b in backends}
    compile_s = warm_up(cfgs["numba"]) if "numba" in cfgs else 0.0
    pose_cfg = PoseConfig(refine="none")
    rows = []
    for n in ns:
        for k in ks:
            row = _rerank_case(n, k, cfgs, pose_cfg, repeats, rir and k <= rir_max_k, rir_repeats)
            base = row[f"sgv_{backends[0]}"]["median_ms"]
            for other in ("sgv_torch", "ransac_rir", "fgr_rir"):
                if other in row and other != f"sgv_{backends[0]}":
                    row[f"ratio_{other}"] = row[other]["median_ms"] / base
            rows.append(row)
            echo(_rerank_line(row, backends[0]))
    # k = 2 -> k = max: how much slower a bigger batch is
    growth = {}
    for n in ns:
        by_k = {r["k"]: r for r in rows if r["n"] == n}
        if len(by_k) > 1 and 2 in by_k:
            for b in backends:
                hi = max(by_k)
                growth[f"n{n}_{b}_k2_to_k{hi}"] = (
                    by_k[hi][f"sgv_{b}"]["median_ms"] / by_k[2][f"sgv_{b}"]["median_ms"]
                )
                if 20 in by_k:
                    growth[f"n{n}_{b}_k2_to_k20"] = (
                        by_k[20][f"sgv_{b}"]["median_ms"] / by_k[2][f"sgv_{b}"]["median_ms"]
                    )
    large = []
    for n in large_ns or []:
        for b in backends:
            res = sgv_memory_probe(n, 1, b)
            large.append(res)
            if "error" in res:
                echo(f"  SGV alone n={n} k=1 {b}: failed: {res['error']}")
                continue
            echo(
                f"  SGV alone n={n} k=1 {b}: {res['time_ms']:.0f} ms, peak RSS "
                f"{res['peak_rss_mib']:.0f} MiB ({res['delta_rss_mib']:+.0f} MiB over the "
                f"process after imports), path {res['path']}"
            )
    return {
        "backends": backends,
        "numba_warm_up_s": compile_s,
        "torch_threads": torch.get_num_threads(),
        "rows": rows,
        "growth": growth,
        "large_n": large,
        "notes": [
            "identical correspondences: SGV's nearest-neighbour matches; 'SGV' columns and "
            "RIR columns score those pairs (matching not included); 'NN' is the matching "
            "alone and 'SGV total' matching + numba kernel (sgv_rerank_scores)",
            f"RIR only up to k={rir_max_k}, {rir_repeats} repeats: one registration per "
            "candidate, slow by design (refine=none: no ICP)",
            "large-n memory: RSS high-water mark (VmHWM, reset just before the call) of a "
            "fresh subprocess: peak = the whole process (interpreter, torch, numba, inputs), "
            "delta = peak minus the RSS just before the call",
        ],
    }


def _rerank_case(
    n: int, k: int, cfgs: dict, pose_cfg: Any, repeats: int, rir: bool, rir_repeats: int
) -> dict[str, Any]:
    """One (n, k) point: every method on the same generated query and candidates.

    The correspondences are SGV's (nearest neighbour in feature space per query keypoint,
    :func:`~sgvloc.core.sgv.nn_correspondences`); SGV scores them, and RANSAC/FGR register
    exactly the same pairs (Open3D ``*_based_on_correspondence``, as in
    :mod:`sgvloc.core.pose`) and score the inlier ratio. Matching is timed on its own
    (``nn``) and end to end with SGV (``sgv_total``).
    """
    from sgvloc.core import pose
    from sgvloc.core.sgv import nn_correspondences, sgv_rerank_scores, sgv_scores

    rng = np.random.default_rng(1000 * n + k)
    qk, qf, kps, fts = rerank_inputs(rng, n, k)
    ft_pad = np.stack(fts)  # [k, n, D]: all candidates have n keypoints here
    idx = nn_correspondences(qf, ft_pad).numpy()  # [k, n]
    src = np.ascontiguousarray(np.broadcast_to(qk[None], (k, n, 3)))  # [k, n, 3]
    dst = np.stack([kp[i] for kp, i in zip(kps, idx, strict=True)])  # [k, n, 3]
    row: dict[str, Any] = {"n": n, "k": k}
    for b, cfg in cfgs.items():
        _settle()
        row[f"sgv_{b}"] = timed(lambda cfg=cfg: sgv_scores(src, dst, None, cfg), repeats)
    _settle()
    row["nn"] = timed(lambda: nn_correspondences(qf, ft_pad), repeats)
    first = next(iter(cfgs.values()))
    _settle()
    row["sgv_total"] = timed(lambda: sgv_rerank_scores(qk, qf, kps, fts, first), repeats)
    # sanity: the revisit (candidate 0) ranks first
    row["sgv_top1_is_revisit"] = bool(sgv_scores(src, dst, None, first).order()[0] == 0)
    if rir:
        pairs = np.stack([np.arange(n), np.zeros(n, dtype=np.int64)], axis=1)  # [n, 2]
        qk64, dst64 = qk.astype(np.float64), dst.astype(np.float64)
        for name, estimate in (("ransac_rir", pose._ransac), ("fgr_rir", pose._fgr)):

            def run_rir(estimate=estimate) -> list[float]:
                ratios = []
                for b in range(k):
                    pairs[:, 1] = idx[b]
                    kp = kps[b].astype(np.float64)
                    T = estimate(qk64, kp, pairs, pose_cfg)
                    dist = pose_cfg.max_correspondence_distance
                    ratios.append(pose.inlier_ratio(qk64, dst64[b], T, dist)[1])
                return ratios

            _settle()
            row[name] = timed(run_rir, rir_repeats)
            row[f"{name}_top1_is_revisit"] = bool(np.argmax(run_rir()) == 0)
    return row


def _rerank_line(row: dict[str, Any], main: str) -> str:
    parts = [f"  n={row['n']:5d} k={row['k']:3d}"]
    for key in ("sgv_numba", "sgv_torch", "nn", "sgv_total", "ransac_rir", "fgr_rir"):
        if key in row:
            parts.append(f"{key} {row[key]['median_ms']:8.2f} ms")
    return "  ".join(parts)


def bench_sgv_cuda(
    ks: list[int], ns: list[int], *, large_ns: list[int] | None = None, repeats: int = 20
) -> dict[str, Any]:
    """SGV with the torch backend on CUDA (needs only torch, numpy and pydantic).

    Times are wall clock per call, inputs and outputs on the host (numpy), so they include
    the transfers and the final synchronisation; medians after warm-up. Large n reports
    ``torch.cuda.max_memory_allocated`` of the call.
    """
    import torch

    from sgvloc.core.config import SGVConfig
    from sgvloc.core.sgv import sgv_rerank_scores, sgv_scores

    if not torch.cuda.is_available():
        return {"skipped": "CUDA is not available"}
    cfg = SGVConfig(device="cuda", backend="torch")
    rows = []
    for n in ns:
        for k in ks:
            qk, qf, kps, fts = rerank_inputs(np.random.default_rng(1000 * n + k), n, k)
            args = (qk, qf, kps, fts, cfg)
            res = timed(lambda args=args: sgv_rerank_scores(*args), repeats, warmup=3)
            rows.append({"n": n, "k": k, "sgv_cuda": res})
    large = []
    for n in large_ns or []:
        rng = np.random.default_rng(n)
        src = rng.uniform(-30, 30, size=(1, n, 3)).astype(np.float32)
        dst = src + rng.normal(scale=0.03, size=src.shape).astype(np.float32)
        sgv_scores(src, dst, None, cfg)
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        res = timed(lambda src=src, dst=dst: sgv_scores(src, dst, None, cfg), 3, warmup=0)
        out = sgv_scores(src, dst, None, cfg)
        large.append(
            {
                "n": n,
                "k": 1,
                "sgv_cuda": res,
                "path": out.path,
                "max_memory_allocated_mib": torch.cuda.max_memory_allocated() / 2**20,
            }
        )
    return {"device": torch.cuda.get_device_name(0), "rows": rows, "large_n": large}


def format_cuda(res: dict[str, Any]) -> str:
    """Markdown table of :func:`bench_sgv_cuda`."""
    if "skipped" in res:
        return f"(CUDA skipped: {res['skipped']})"
    out = [
        _table(
            ["n", "k", "SGV CUDA ms (median)", "min ms"],
            [
                [str(r["n"]), str(r["k"]), _ms(r["sgv_cuda"]), f"{r['sgv_cuda']['min_ms']:.2f}"]
                for r in res["rows"]
            ],
        )
    ]
    if res["large_n"]:
        out.append(
            _table(
                ["n", "k", "SGV CUDA ms", "path", "GPU peak MiB"],
                [
                    [
                        str(x["n"]),
                        "1",
                        _ms(x["sgv_cuda"]),
                        x["path"],
                        f"{x['max_memory_allocated_mib']:.0f}",
                    ]
                    for x in res["large_n"]
                ],
            )
        )
    return "\n\n".join(out)


_PROBE = """
import json, resource, sys, time
import numpy as np
from sgvloc.tools.bench.engine import rerank_inputs
from sgvloc.core.config import SGVConfig
from sgvloc.core.sgv import sgv_scores, warm_up
n, k, backend = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
cfg = SGVConfig(device="cpu", backend=backend)
warm_up(cfg)
rng = np.random.default_rng(n)
src = rng.uniform(-30, 30, size=(k, n, 3)).astype(np.float32)
src[..., 2] *= 0.1
dst = src + rng.normal(scale=0.03, size=src.shape).astype(np.float32)
m = int(0.7 * n)
dst[:, m:] = rng.uniform(-30, 30, size=(k, n - m, 3))
def status(key):  # KiB from /proc/self/status (Linux), None elsewhere
    try:
        for line in open("/proc/self/status"):
            if line.startswith(key + ":"):
                return int(line.split()[1])
    except OSError:
        return None
try:  # reset the high-water mark (VmHWM) to the current RSS: Linux >= 4.0
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    source = "VmHWM after clear_refs"
except OSError:
    source = "ru_maxrss"
before = status("VmRSS") or resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t0 = time.perf_counter()
out = sgv_scores(src, dst, None, cfg)
took = time.perf_counter() - t0
hwm = status("VmHWM") if source != "ru_maxrss" else None
peak = hwm or resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"n": n, "k": k, "backend": backend, "time_ms": took * 1e3,
                  "peak_rss_mib": peak / 1024, "delta_rss_mib": (peak - before) / 1024,
                  "rss_source": source, "path": out.path, "score": float(out.score[0])}))
"""


def sgv_memory_probe(n: int, k: int, backend: str) -> dict[str, Any]:
    """Time and peak RSS of one ``sgv_scores`` call at ``[k, n]`` in a fresh subprocess.

    The inputs are built before the mark is read, so the delta is the kernel's own memory
    (plus anything it first touches). Linux reports ``ru_maxrss`` in KiB.
    """
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, str(n), str(k), backend],
        capture_output=True,
        text=True,
        check=False,
    )
    if out.returncode != 0:
        return {"n": n, "k": k, "backend": backend, "error": out.stderr.strip()[-500:]}
    return json.loads(out.stdout.strip().splitlines()[-1])


# --------------------------------------------------------------------------------------
# Retrieval
# --------------------------------------------------------------------------------------


def descriptors(
    rng: np.random.Generator, size: int, dim: int, queries: int, noise: float = 0.35
) -> tuple[np.ndarray, np.ndarray]:
    """``size`` database descriptors of places along a route and ``queries`` revisits.

    Real global descriptors vary smoothly with the place: keyframes are points on a 2-D
    manifold (the mapped area) in descriptor space, plus sensor noise, not isotropic
    random vectors (the worst case for any approximate index) nor tight clusters (the
    easiest). Places are uniform in a square of ``sqrt(size)`` x ``sqrt(size)`` length
    units; the descriptor is a random Fourier feature map of the place (a smooth field
    with a correlation length of about 3 units, so ~30 keyframes look alike) plus
    Gaussian noise (``noise`` per dimension; the field's own spread is ~0.7).
    Queries revisit a random mapped place, 0.5 units off, with fresh noise. Built in
    blocks to keep the peak memory near the output's size.
    """
    side = float(np.sqrt(size))
    freq = rng.normal(scale=1.0 / 3.0, size=(2, dim)).astype(np.float32)
    phase = rng.uniform(0, 2 * np.pi, size=dim).astype(np.float32)

    def embed(places: np.ndarray) -> np.ndarray:
        x = np.cos(places.astype(np.float32) @ freq + phase)  # [m, dim]
        return x + noise * rng.standard_normal(x.shape, dtype=np.float32)

    places = rng.uniform(0, side, size=(size, 2))
    db = np.empty((size, dim), dtype=np.float32)
    for r0 in range(0, size, 100_000):
        db[r0 : r0 + 100_000] = embed(places[r0 : r0 + 100_000])
    pick = rng.integers(0, size, size=queries)
    q = embed(places[pick] + rng.normal(scale=0.5, size=(queries, 2)))
    return db, q


def _recall(approx: list[list[Any]], exact: list[list[Any]], k: int) -> float:
    hits = [
        len({h.id for h in a[:k]} & {h.id for h in e[:k]}) / k
        for a, e in zip(approx, exact, strict=True)
    ]
    return float(np.mean(hits))


def _search_each(index: Any, q: np.ndarray, k: int) -> tuple[list[list[Any]], list[float]]:
    """One query at a time (as the service does): results and per-query ms."""
    hits, times = [], []
    for row in q:
        t0 = time.perf_counter()
        hits.append(index.search(row[None], k)[0])
        times.append((time.perf_counter() - t0) * 1e3)
    return hits, times


def bench_retrieval(
    sizes: list[int],
    *,
    dim: int = 620,
    large_dim: int = 256,
    large_from: int = 500_000,
    queries: int = 200,
    flat_queries: int = 50,
    k: int = 20,
    nprobes: tuple[int, ...] = (4, 8, 16, 32, 48, 64, 96, 128),
    hnsw_max: int = 100_000,
    max_nlist: int = 2048,
    target_recall: float = 0.95,
    echo: Echo = _quiet,
) -> dict[str, Any]:
    """Flat vs IVF (and HNSW up to ``hnsw_max``) search latency and recall@k per size."""
    import faiss

    from sgvloc.core.config import RetrievalConfig
    from sgvloc.core.retrieval import FaissIndex

    rows = []
    for size in sizes:
        d = large_dim if size >= large_from else dim
        rng = np.random.default_rng(size)
        t0 = time.perf_counter()
        db, q = descriptors(rng, size, d, queries)
        ids = np.arange(size, dtype=np.int64)
        gen_s = time.perf_counter() - t0
        row: dict[str, Any] = {"size": size, "dim": d, "queries": queries, "k": k}

        flat = FaissIndex(d, RetrievalConfig(index="flat"))
        t0 = time.perf_counter()
        flat.add(ids, db)
        row["flat_build_s"] = time.perf_counter() - t0
        exact = flat.search(q, k)  # ground truth, one batched call
        flat.search(q[:2], k)  # warm-up
        _, times = _search_each(flat, q[:flat_queries], k)
        row["flat"] = {"median_ms": float(np.median(times)), "p99_ms": _p99(times)}
        del flat

        # IVF: nlist ~ 4 sqrt(size), capped so the index trains (39 vectors per cell) and
        # so that k-means stays within about a minute on 2 cores (2048 cells at 1M: 77 s;
        # 1024 cells need nprobe 64 for recall 0.95 at 1M, twice the scan).
        nlist = int(min(max_nlist, size // 39, 2 ** round(np.log2(4 * np.sqrt(size)))))
        ivf = FaissIndex(d, RetrievalConfig(index="ivf", nlist=nlist, nprobe=nprobes[0]))
        t0 = time.perf_counter()
        ivf.add(ids, db)
        row["ivf_build_s"] = time.perf_counter() - t0
        inner = faiss.extract_index_ivf(ivf._index)  # nprobe is index state: swept here only
        sweep = []
        for nprobe in nprobes:
            if nprobe > nlist:
                break
            inner.nprobe = nprobe
            ivf.search(q[:2], k)
            hits, times = _search_each(ivf, q, k)
            sweep.append(
                {
                    "nprobe": nprobe,
                    "median_ms": float(np.median(times)),
                    "p99_ms": _p99(times),
                    "recall": _recall(hits, exact, k),
                }
            )
        row["ivf"] = {"nlist": nlist, "sweep": sweep}
        ok = [s for s in sweep if s["recall"] >= target_recall]
        row["ivf_best"] = ok[0] if ok else max(sweep, key=lambda s: s["recall"])
        del ivf

        if size <= hnsw_max:
            hn = FaissIndex(d, RetrievalConfig(index="hnsw", hnsw_m=32, ef_search=64))
            t0 = time.perf_counter()
            hn.add(ids, db)
            row["hnsw_build_s"] = time.perf_counter() - t0
            hsweep = []
            inner_h = faiss.downcast_index(hn._index.index)
            for ef in (32, 64, 128, 256):
                inner_h.hnsw.efSearch = ef
                hn.search(q[:2], k)
                hits, times = _search_each(hn, q, k)
                hsweep.append(
                    {
                        "ef_search": ef,
                        "median_ms": float(np.median(times)),
                        "p99_ms": _p99(times),
                        "recall": _recall(hits, exact, k),
                    }
                )
            row["hnsw"] = {"m": 32, "sweep": hsweep}
            del hn
        del db
        row["data_gen_s"] = gen_s
        rows.append(row)
        best = row["ivf_best"]
        echo(
            f"  {size:>8d} x {d}: flat {row['flat']['median_ms']:.2f} ms; IVF nlist={nlist} "
            f"nprobe={best['nprobe']} {best['median_ms']:.3f} ms recall@{k} "
            f"{best['recall']:.3f} (build {row['ivf_build_s']:.0f} s)"
        )
    return {
        "rows": rows,
        "notes": [
            "synthetic descriptors: a smooth random field over a 2-D mapped area plus noise "
            "(see bench.descriptors); queries revisit mapped places",
            f"one query per search call (as the service does): {queries} queries for the "
            f"approximate indexes, {flat_queries} for flat (exact results for recall come "
            "from one batched flat search)",
            f"dimension {dim} (the learned and handcrafted encoders' global_dim) below "
            f"{large_from} descriptors, {large_dim} from there on (build time and memory on "
            "2 cores)",
            f"recall@{k} of the approximate index against exact (flat) search",
        ],
    }


def _p99(times: list[float]) -> float:
    return float(np.percentile(times, 99))


# --------------------------------------------------------------------------------------
# Encoding
# --------------------------------------------------------------------------------------


def _default_scan() -> np.ndarray | None:
    path = Path(__file__).resolve().parents[4] / "tests/fixtures/balm_mini/velodyne/000000.bin"
    if not path.exists():
        return None
    return np.fromfile(path, dtype=np.float32).reshape(-1, 4)[:, :3]


def _procedural_scan(rng: np.random.Generator, points: int) -> np.ndarray:
    """Ground, walls and poles around a sensor: a stand-in when no scan file is at hand."""
    ang = rng.uniform(0, 2 * np.pi, points)
    r = rng.uniform(2, 50, points)
    xyz = np.stack([r * np.cos(ang), r * np.sin(ang), np.full(points, -1.7)], axis=1)
    wall = rng.random(points) < 0.4
    xyz[wall, 0] = np.where(xyz[wall, 0] > 0, 12.0, -9.0) + rng.normal(0, 0.02, wall.sum())
    xyz[wall, 2] = rng.uniform(-1.7, 4.0, wall.sum())
    return xyz.astype(np.float32)


def densify(scan: np.ndarray, points: int, rng: np.random.Generator, jitter: float = 0.05):
    """``points`` points: copies of ``scan`` with Gaussian jitter (a denser sensor)."""
    reps = int(np.ceil(points / len(scan)))
    out = np.concatenate([scan + rng.normal(scale=jitter, size=scan.shape) for _ in range(reps)])
    return out[rng.permutation(len(out))[:points]].astype(np.float32)


def bench_encoding(
    sizes: list[int],
    *,
    repeats: int = 5,
    scan: np.ndarray | None = None,
    image_encoders: tuple[str, ...] = ("bev", "learned"),
    echo: Echo = _quiet,
) -> dict[str, Any]:
    """Handcrafted encoder time per stage for scans of ``sizes`` points, then the BEV
    image encoders (``image_encoders``) per stage on the same scans."""
    from sgvloc.core.encoders.handcrafted import (
        KEYPOINT_NMS_VOXEL,
        HandcraftedEncoder,
        _l2_rows,
        fpfh_at,
        normals_and_saliency,
        polar_grid,
        select_keypoints,
        yaw_invariant_descriptor,
    )

    rng = np.random.default_rng(0)
    source = "tests/fixtures/balm_mini/velodyne/000000.bin (densified with 5 cm jitter)"
    base = _default_scan() if scan is None else scan
    if base is None:
        base, source = _procedural_scan(rng, 30_000), "procedural scene (no scan file)"
    enc = HandcraftedEncoder()
    c = enc.config
    rows = []
    for size in sizes:
        raw = densify(base, size, rng)
        stages: dict[str, list[float]] = {
            k: [] for k in ("preprocess", "global", "normals", "keypoints", "fpfh", "total")
        }
        cloud = enc.prepare(raw)
        for rep in range(repeats + 1):
            t = [time.perf_counter()]
            cloud = enc.prepare(raw)
            t.append(time.perf_counter())
            yaw_invariant_descriptor(polar_grid(cloud, c.rings, c.sectors, c.max_radius))
            t.append(time.perf_counter())
            normals, sal = normals_and_saliency(cloud, c.normal_radius)
            t.append(time.perf_counter())
            kp = select_keypoints(cloud, sal, c.num_keypoints, KEYPOINT_NMS_VOXEL)
            t.append(time.perf_counter())
            _l2_rows(fpfh_at(cloud, normals, kp, c.fpfh_radius))
            t.append(time.perf_counter())
            if rep == 0:
                continue  # warm-up
            for name, a, b in zip(stages, t[:-1], t[1:], strict=False):
                stages[name].append((b - a) * 1e3)
            stages["total"].append((t[-1] - t[0]) * 1e3)
        t0 = time.perf_counter()
        enc.encode(raw)
        encode_ms = (time.perf_counter() - t0) * 1e3
        row = {
            "points": size,
            "after_preprocess": len(cloud),
            "keypoints": int(len(kp)),
            **{f"{k}_ms": float(np.median(v)) for k, v in stages.items()},
            "encode_call_ms": encode_ms,
        }
        rows.append(row)
        echo(
            f"  {size:>7d} points ({len(cloud)} after preprocess): total "
            f"{row['total_ms']:.0f} ms = preprocess {row['preprocess_ms']:.0f} + global "
            f"{row['global_ms']:.1f} + normals {row['normals_ms']:.0f} + keypoints "
            f"{row['keypoints_ms']:.1f} + FPFH {row['fpfh_ms']:.0f}"
        )
    image_rows = []
    for kind in image_encoders:
        for size in sizes:
            image_rows.append(_bench_image_encoder(kind, densify(base, size, rng), repeats))
            r = image_rows[-1]
            echo(
                f"  {kind:>8s} {size:>7d} points: total {r['total_ms']:.0f} ms = prepare "
                f"{r['prepare_ms']:.0f} + raster {r['raster_ms']:.1f} + describe "
                f"{r['describe_ms']:.0f} ({r['keypoints']} keypoints)"
            )
    return {
        "source": source,
        "rows": rows,
        "encoder": c.model_dump(),
        "image_encoders": image_rows,
    }


def _bench_image_encoder(kind: str, raw: np.ndarray, repeats: int) -> dict[str, Any]:
    """Stages of a BEV image encoder (``bev``, ``learned``) on one scan: prepare (box crop,
    0.4 m voxels), raster (density image of the prepared cloud) and describe (the rest of
    ``encode_query`` as a new map's query runs it: for the learned encoder its levelling,
    then keypoints, local and global descriptors of the image, the polar block about the
    displaced centres too)."""
    from sgvloc.core.bev import rasterize_cloud
    from sgvloc.core.config import RetrievalConfig
    from sgvloc.core.encoders import EncoderSpec, make_encoder

    enc = make_encoder(EncoderSpec(kind=kind))
    centres = RetrievalConfig().centres()
    stages: dict[str, list[float]] = {k: [] for k in ("prepare", "raster", "describe", "total")}
    feats = None
    for rep in range(repeats + 1):
        t0 = time.perf_counter()
        cloud = enc.prepare(raw)
        t1 = time.perf_counter()
        rasterize_cloud(cloud)
        t2 = time.perf_counter()
        feats = enc.encode_query(cloud, centres)  # rasterises again, then describes
        t3 = time.perf_counter()
        if rep == 0:
            continue  # warm-up
        stages["prepare"].append((t1 - t0) * 1e3)
        stages["raster"].append((t2 - t1) * 1e3)
        stages["describe"].append((t3 - t2 - (t2 - t1)) * 1e3)
        stages["total"].append((t3 - t2 + t1 - t0) * 1e3)
    assert feats is not None
    return {
        "encoder": kind,
        "identity": enc.identity.name,
        "points": len(raw),
        "keypoints": int(feats.num_keypoints),
        **{f"{k}_ms": float(np.median(v)) for k, v in stages.items()},
    }


# --------------------------------------------------------------------------------------
# Tables and the whole run
# --------------------------------------------------------------------------------------


def bench_prior(
    sizes: list[int],
    *,
    radius_m: float = 20.0,
    noise_m: float = 5.0,
    queries: int = 50,
    dim: int = 620,
    echo: Callable[[str], None] = _quiet,
) -> dict[str, Any]:
    """Localize with and without a prior on maps of ``sizes`` keyframes (in process).

    Keyframes lie on a 1 m lattice over a square (a dense map of a large area), each with
    a random global descriptor of ``dim`` and 64 keypoints with 16-D features (small, so
    that 100k keyframes fit in memory; the re-ranking and pose cost per query do not
    depend on the map size). A query is a keyframe's features with noise; its prior is the
    keyframe's position plus Gaussian noise of ``noise_m`` per axis with ``radius_m``.
    Localize runs SGV re-ranking at top-20, RANSAC pose, no ICP, one thread; both runs
    answer the same queries, alternating, so that load on the machine hits both alike.
    """
    from sgvloc.core.config import LocalizerConfig
    from sgvloc.core.encoders import PrecomputedEncoder
    from sgvloc.core.localizer import Localizer
    from sgvloc.core.prior import Prior

    rows = []
    for size in sizes:
        rng = np.random.default_rng(size)
        enc = PrecomputedEncoder("bench", dim, 16)
        loc = Localizer(enc, LocalizerConfig(top_k=20))
        side = int(np.ceil(np.sqrt(size)))
        t0 = time.perf_counter()
        feats = []
        for start in range(0, size, 5000):
            batch = []
            for i in range(start, min(size, start + 5000)):
                T = np.eye(4)
                T[:2, 3] = i % side, i // side
                f = enc.from_arrays(
                    rng.normal(size=dim),
                    rng.uniform(-20, 20, size=(64, 3)),
                    rng.normal(size=(64, 16)),
                )
                batch.append(loc.make_keyframe(T, features=f))
                if i % max(1, size // queries) == 0 and len(feats) < queries:
                    feats.append((T, f))
            loc.add_keyframes(batch)
        build_s = time.perf_counter() - t0
        times: dict[str, list[float]] = {"none": [], "prior": []}
        stage: dict[str, list[float]] = {"none": [], "prior": []}
        same, inside = 0, []
        for T, f in feats:
            q = enc.from_arrays(
                f.global_descriptor + rng.normal(scale=0.02, size=dim),
                f.keypoints + rng.normal(scale=0.05, size=f.keypoints.shape),
                f.local_features + rng.normal(scale=0.05, size=f.local_features.shape),
            )
            prior = Prior(tuple(T[:2, 3] + rng.normal(0.0, noise_m, size=2)), radius_m)
            answers = {}
            for name, kw in (("none", {}), ("prior", {"prior": prior})):
                t = time.perf_counter()
                answers[name] = loc.localize(features=q, refine="none", **kw)
                times[name].append((time.perf_counter() - t) * 1e3)
                stage[name].append(answers[name].timings_ms["retrieve"])
            same += answers["none"].keyframe_id == answers["prior"].keyframe_id
            inside.append(answers["prior"].prior["keyframes_in_radius"])
        row = {
            "size": size,
            "build_s": round(build_s, 1),
            "queries": len(feats),
            "keyframes_in_radius_median": float(np.median(inside)),
            "same_top1": same,
        }
        for name in ("none", "prior"):
            row[name] = {
                "localize_median_ms": float(np.median(times[name])),
                "retrieve_median_ms": float(np.median(stage[name])),
            }
        row["speedup"] = row["none"]["localize_median_ms"] / row["prior"]["localize_median_ms"]
        rows.append(row)
        echo(f"prior: {size} keyframes done")
        del loc
    return {
        "rows": rows,
        "radius_m": radius_m,
        "noise_m": noise_m,
        "notes": [
            f"prior radius {radius_m:g} m, position noise {noise_m:g} m per axis; keyframes "
            "on a 1 m lattice; SGV top-20, RANSAC, no ICP; medians over the queries",
            "same top-1: queries whose answer is the same keyframe with and without the prior",
        ],
    }


def format_prior(res: dict[str, Any]) -> str:
    """Markdown table of the prior section."""
    rows = [
        [
            str(r["size"]),
            f"{r['keyframes_in_radius_median']:.0f}",
            f"{r['none']['retrieve_median_ms']:.2f}",
            f"{r['prior']['retrieve_median_ms']:.2f}",
            f"{r['none']['localize_median_ms']:.2f}",
            f"{r['prior']['localize_median_ms']:.2f}",
            f"{r['speedup']:.2f}x",
            f"{r['same_top1']}/{r['queries']}",
        ]
        for r in res["rows"]
    ]
    return _table(
        [
            "keyframes",
            "in radius",
            "retrieve ms",
            "retrieve ms (prior)",
            "localize ms",
            "localize ms (prior)",
            "speed-up",
            "same top-1",
        ],
        rows,
    )


def _table(header: list[str], rows: list[list[str]]) -> str:
    widths = [
        max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(header)
    ]

    def line(cells: list[str]) -> str:
        return "| " + " | ".join(c.rjust(w) for c, w in zip(cells, widths, strict=True)) + " |"

    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([line(header), sep, *(line(r) for r in rows)])


def _ms(d: dict[str, Any] | None) -> str:
    return f"{d['median_ms']:.2f}" if d else "-"


def format_rerank(res: dict[str, Any]) -> str:
    """Markdown table of the re-ranking section."""
    header = [
        "n",
        "k",
        "SGV numba ms",
        "SGV torch ms",
        "NN ms",
        "SGV total ms",
        "RANSAC-RIR ms",
        "FGR-RIR ms",
        "RANSAC/SGV",
        "FGR/SGV",
        "torch/numba",
    ]
    rows = []
    for r in res["rows"]:
        rows.append(
            [
                str(r["n"]),
                str(r["k"]),
                _ms(r.get("sgv_numba")),
                _ms(r.get("sgv_torch")),
                _ms(r.get("nn")),
                _ms(r.get("sgv_total")),
                _ms(r.get("ransac_rir")),
                _ms(r.get("fgr_rir")),
                f"{r['ratio_ransac_rir']:.0f}x" if "ratio_ransac_rir" in r else "-",
                f"{r['ratio_fgr_rir']:.0f}x" if "ratio_fgr_rir" in r else "-",
                f"{r['ratio_sgv_torch']:.1f}x" if "ratio_sgv_torch" in r else "-",
            ]
        )
    out = [_table(header, rows)]
    if res.get("growth"):
        out.append(
            "k=2 -> k growth: " + ", ".join(f"{k} {v:.1f}x" for k, v in res["growth"].items())
        )
    if res.get("large_n"):
        out.append(
            _table(
                ["n", "k", "backend", "time ms", "peak RSS MiB", "delta MiB", "path"],
                [
                    [
                        str(x["n"]),
                        str(x["k"]),
                        x["backend"],
                        f"{x.get('time_ms', float('nan')):.0f}",
                        f"{x.get('peak_rss_mib', float('nan')):.0f}",
                        f"{x.get('delta_rss_mib', float('nan')):.0f}",
                        x.get("path", x.get("error", "?")),
                    ]
                    for x in res["large_n"]
                ],
            )
        )
    return "\n\n".join(out)


def format_retrieval(res: dict[str, Any]) -> str:
    """Markdown table of the retrieval section."""
    rows = []
    for r in res["rows"]:
        b = r["ivf_best"]
        h = None
        if "hnsw" in r:
            ok = [s for s in r["hnsw"]["sweep"] if s["recall"] >= 0.95]
            h = ok[0] if ok else max(r["hnsw"]["sweep"], key=lambda s: s["recall"])
        rows.append(
            [
                str(r["size"]),
                str(r["dim"]),
                f"{r['flat']['median_ms']:.2f}",
                f"{r['ivf']['nlist']}/{b['nprobe']}",
                f"{b['median_ms']:.3f}",
                f"{b['recall']:.3f}",
                f"{r['flat']['median_ms'] / b['median_ms']:.0f}x",
                f"{r['ivf_build_s']:.0f}",
                f"ef={h['ef_search']}: {h['median_ms']:.3f} ms, recall {h['recall']:.3f}"
                if h
                else "-",
            ]
        )
    return _table(
        [
            "size",
            "dim",
            "flat ms",
            "IVF nlist/nprobe",
            "IVF ms",
            "IVF recall@20",
            "flat/IVF",
            "IVF build s",
            "HNSW (M=32)",
        ],
        rows,
    )


def format_encoding(res: dict[str, Any]) -> str:
    """Markdown table of the encoding section."""
    rows = [
        [
            str(r["points"]),
            str(r["after_preprocess"]),
            f"{r['preprocess_ms']:.1f}",
            f"{r['global_ms']:.1f}",
            f"{r['normals_ms']:.1f}",
            f"{r['keypoints_ms']:.1f}",
            f"{r['fpfh_ms']:.1f}",
            f"{r['total_ms']:.1f}",
        ]
        for r in res["rows"]
    ]
    table = _table(
        [
            "points",
            "after preprocess",
            "preprocess ms",
            "global ms",
            "normals ms",
            "keypoints ms",
            "FPFH ms",
            "total ms",
        ],
        rows,
    )
    images = res.get("image_encoders") or []
    if not images:
        return table
    image_table = _table(
        ["encoder", "points", "prepare ms", "raster ms", "describe ms", "total ms", "keypoints"],
        [
            [
                r["encoder"],
                str(r["points"]),
                f"{r['prepare_ms']:.1f}",
                f"{r['raster_ms']:.1f}",
                f"{r['describe_ms']:.1f}",
                f"{r['total_ms']:.1f}",
                str(r["keypoints"]),
            ]
            for r in images
        ],
    )
    return f"{table}\n\n{image_table}"


FORMATTERS = {
    "prior": format_prior,
    "rerank": format_rerank,
    "cuda": format_cuda,
    "retrieval": format_retrieval,
    "encoding": format_encoding,
}
