"""``sgvloc bench --only cluster``: replicas over one PostgreSQL store.

PostgreSQL is ``--cluster-store`` (a ``postgresql://`` URL of a database the bench may
fill; its maps are named ``bench-*``) or, by default, a throwaway cluster started from the
system's ``postgresql`` package. Four measurements:

- **insert-to-visible**: two replicas (``sgvloc serve`` processes, one worker each); one
  keyframe at a time is inserted on the first, and the second is polled (``GET
  /v1/maps/{map}`` every 2 ms) until its ``version`` reaches the insert's ``map_version``:
  the time from the first replica's 201 to the second serving it;
- **catch-up**: maps of N synthetic keyframes (a 620-D global descriptor as the learned
  encoder's, ``--cluster-keypoints`` keypoints with 32-D local features, no cloud) are
  written straight into the store, then a fresh map manager (what a starting replica
  runs before it reports ready) loads the store, with the features in memory and with
  only poses and global descriptors (``local_features=store``);
- **features in memory vs fetched**: the shipped fixture's scans (every second one a
  keyframe, the learned encoder, ICP) localized in process by a manager holding the
  features and by one fetching the candidates' features and clouds from PostgreSQL, query
  by query in turn; cold = a cache of one keyframe (every candidate fetched), warm = the
  default cache;
- **one vs two replicas**: the same map, loaded by ``--cluster-clients`` threads of the SDK
  over one base URL, then over both (round robin) for ``--cluster-duration`` seconds each.
  Every process shares this machine's cores: with two cores the second replica cannot add
  more than the cores it finds idle.
"""

from __future__ import annotations

import contextlib
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from sgvloc_client import wire

from ..service_process import ServiceProcess, start_side_by_side
from .engine import _table
from .http import FIXTURE, _pct

Echo = Callable[[str], None]
GLOBAL_DIM = 620
LOCAL_DIM = 32


@contextlib.contextmanager
def _database(store: str | None) -> Iterator[str]:
    """A database URL: ``store`` as given, or a fresh one on a throwaway cluster."""
    if store:
        yield store
        return
    from ..pg_cluster import TempCluster

    with TempCluster() as cluster:
        yield cluster.new_database("bench")


#: the maps this bench makes, besides ``bench-catchup-<size>``
BENCH_MAPS = ("bench-visible", "bench-qps", "bench-fetch")


def _drop_bench_maps(url: str, sizes: list[int]) -> None:
    """Delete the maps this bench makes from the store (none other)."""
    from sgvloc.core.errors import NotFoundError
    from sgvloc.server.store.postgres import PgBackend

    ours = {*BENCH_MAPS, *(f"bench-catchup-{n}" for n in sizes)}
    backend = PgBackend(url)
    backend.start()
    try:
        for name in set(backend.catalog()) & ours:
            with contextlib.suppress(NotFoundError):
                backend.drop(backend.open(name))
    finally:
        backend.close()


@contextlib.contextmanager
def _dropping_bench_maps(url: str, sizes: list[int]) -> Iterator[None]:
    """The bench's maps removed however it ends (a given store is left as it was found,
    and a second run does not meet the first one's maps)."""
    _drop_bench_maps(url, sizes)
    try:
        yield
    finally:
        _drop_bench_maps(url, sizes)


def _features(rng: np.random.Generator, keypoints: int) -> dict[str, np.ndarray]:
    g = rng.normal(size=GLOBAL_DIM).astype(np.float32)
    return {
        "global_descriptor": g / np.linalg.norm(g),
        "keypoints": rng.uniform(-40, 40, (keypoints, 3)).astype(np.float32),
        "local_features": rng.normal(size=(keypoints, LOCAL_DIM)).astype(np.float32),
    }


def _spec() -> dict[str, Any]:
    return {
        "kind": "precomputed",
        "name": "bench",
        "global_dim": GLOBAL_DIM,
        "local_dim": LOCAL_DIM,
    }


def _visibility(a: str, b: str, n: int, keypoints: int) -> dict[str, Any]:
    """Insert on ``a`` one keyframe at a time; time until ``b`` serves each."""
    rng = np.random.default_rng(1)
    with httpx.Client(timeout=60.0) as h:
        r = h.post(f"{a}/v1/maps", json={"name": "bench-visible", "encoder": _spec()})
        r.raise_for_status()
        deadline = time.monotonic() + 30
        while h.get(f"{b}/v1/maps/bench-visible").status_code != 200:
            if time.monotonic() > deadline:
                raise RuntimeError("the second replica never saw the map")
            time.sleep(0.01)
        latencies = []
        for i in range(n):
            body = {"keyframes": [{"T_map_sensor": np.eye(4), "key": f"k{i}",
                                   "features": _features(rng, keypoints)}]}  # fmt: skip
            r = h.post(
                f"{a}/v1/maps/bench-visible/keyframes",
                content=wire.packb(body),
                headers={"Content-Type": wire.MSGPACK},
            )
            r.raise_for_status()
            acked, version = time.perf_counter(), r.json()["map_version"]
            while h.get(f"{b}/v1/maps/bench-visible").json()["version"] < version:
                if time.perf_counter() - acked > 30:
                    raise RuntimeError(f"version {version} never reached the second replica")
                time.sleep(0.002)
            latencies.append((time.perf_counter() - acked) * 1000)
    return {
        "inserts": n,
        "p50_ms": _pct(latencies, 50),
        "p99_ms": _pct(latencies, 99),
        "max_ms": max(latencies),
    }


def _fill(url: str, name: str, n: int, keypoints: int, echo: Echo) -> dict[str, Any]:
    """A map of ``n`` synthetic keyframes written straight into the store."""
    from sgvloc.core.confidence import shipped_calibration
    from sgvloc.core.config import LocalizerConfig
    from sgvloc.core.encoders import EncoderSpec, make_encoder
    from sgvloc.server.store import KeyframeRow, MapRecord, utc_now
    from sgvloc.server.store.postgres import PgBackend

    spec = EncoderSpec(**_spec())
    backend = PgBackend(url)
    backend.start()
    try:
        record = MapRecord(
            name=name,
            encoder_spec=spec,
            localizer_config=LocalizerConfig(),
            encoder_fingerprint=make_encoder(spec).identity.fingerprint,
            keep_clouds=False,
            created_at=utc_now(),
            calibration=shipped_calibration("precomputed"),
        )
        store = backend.create(name, record)
        rng = np.random.default_rng(2)
        t0 = time.perf_counter()
        batch = 1000
        for start in range(0, n, batch):
            rows = []
            for i in range(start, min(n, start + batch)):
                f = _features(rng, keypoints)
                T = np.eye(4)
                T[:2, 3] = [i % 1000, i // 1000]
                rows.append(KeyframeRow(T, f["global_descriptor"], f["keypoints"],
                                        f["local_features"], key=f"k{i}"))  # fmt: skip
            store.insert(rows)
            if start and start % 20000 == 0:
                echo(f"  {name}: {start} keyframes written")
        return {"write_s": time.perf_counter() - t0, "disk_mib": store.disk_bytes() / 2**20}
    finally:
        backend.close()


def _load(url: str, name: str, in_memory: bool) -> dict[str, Any]:
    """Seconds for a fresh map manager to load the store (a starting replica's catch-up)."""
    import gc

    from sgvloc.server.maps import MapManager
    from sgvloc.server.store.postgres import PgBackend

    with tempfile.TemporaryDirectory(prefix="sgvloc-bench-cluster-") as tmp:
        manager = MapManager(Path(tmp), backend=PgBackend(url), features_in_memory=in_memory)
        t0 = time.perf_counter()
        manager.load_all()
        took = time.perf_counter() - t0
        handle = manager.get(name)
        out = {
            "load_s": took,
            "keyframes": handle.num_keyframes,
            "memory_mib": handle.localizer.memory_bytes() / 2**20,
        }
        manager.close()
    gc.collect()
    return out


def _fetch_cost(url: str, data: Path, rounds: int) -> dict[str, Any]:
    """Localize medians in process: features in memory, fetched cold, fetched warm."""
    from sgvloc.core.sequence import KittiSequence
    from sgvloc.server.maps import KeyframeIn, MapManager
    from sgvloc.server.store.postgres import PgBackend

    seq = KittiSequence(data)
    map_ids = list(range(0, len(seq), 2))
    queries = [i for i in range(len(seq)) if i % 2]
    scans = {i: seq[i].scan().xyzi() for i in queries}
    paths = {"memory": (True, 4096), "fetched, cold": (False, 1), "fetched, warm": (False, 4096)}
    with tempfile.TemporaryDirectory(prefix="sgvloc-bench-cluster-") as tmp:
        writer = MapManager(Path(tmp), backend=PgBackend(url))
        writer.load_all()
        writer.create("bench-fetch")
        writer.insert(
            "bench-fetch",
            [KeyframeIn(seq[i].T_world_sensor, points=seq[i].scan().xyzi(), key=str(i))
             for i in map_ids],
        )  # fmt: skip
        managers = {}
        for path, (in_memory, cache) in paths.items():
            m = MapManager(
                Path(tmp), backend=PgBackend(url), features_in_memory=in_memory,
                feature_cache=cache,
            )  # fmt: skip
            m.load_all()
            managers[path] = m
        times: dict[str, list[float]] = {p: [] for p in paths}
        fetch: dict[str, list[float]] = {p: [] for p in paths}
        same = 0
        for rnd in range(rounds + 1):  # the first round warms up, untimed
            for i in queries:
                answers = {}
                for path, m in managers.items():
                    t0 = time.perf_counter()
                    res = m.localize("bench-fetch", points=scans[i])
                    took = (time.perf_counter() - t0) * 1000
                    answers[path] = (res.keyframe_id, res.localized)
                    if rnd:
                        times[path].append(took)
                        fetch[path].append(res.timings_ms.get("fetch", 0.0))
                same += len(set(answers.values())) == 1
        for m in (*managers.values(), writer):
            m.close()
    base = float(np.median(times["memory"]))
    return {
        "queries": len(queries),
        "rounds": rounds,
        "same_answers": f"{same}/{len(queries) * (rounds + 1)}",
        "paths": {
            p: {
                "p50_ms": float(np.median(t)),
                "fetch_p50_ms": float(np.median(fetch[p])),
                "ratio": float(np.median(t)) / base,
            }
            for p, t in times.items()
        },
    }


def _qps(urls: list[str], points: np.ndarray, clients: int, duration_s: float) -> float:
    from sgvloc_client import Client

    done = [0]
    stop = threading.Event()
    lock = threading.Lock()

    def run() -> None:
        with Client(urls, timeout=120.0) as c:
            while not stop.is_set():
                c.localize("bench-qps", points)
                with lock:
                    done[0] += 1

    threads = [threading.Thread(target=run) for _ in range(clients)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    time.sleep(duration_s)
    stop.set()
    for t in threads:
        t.join()
    return done[0] / (time.perf_counter() - t0)


def bench_cluster(
    *,
    store: str | None = None,
    sizes: list[int] | None = None,
    visible: int = 50,
    keypoints: int = 64,
    clients: int = 4,
    duration_s: float = 8.0,
    rounds: int = 3,
    data: Path | None = None,
    echo: Echo = lambda _m: None,
) -> dict[str, Any]:
    """Every figure of the module docstring."""
    from sgvloc.core.sequence import KittiSequence

    sizes = [10000, 100000] if sizes is None else sizes
    data = data or FIXTURE
    result: dict[str, Any] = {"keypoints": keypoints, "global_dim": GLOBAL_DIM}
    with (
        _database(store) as url,
        tempfile.TemporaryDirectory(prefix="sgvloc-bench-") as tmp,
        _dropping_bench_maps(url, sizes),
    ):
        echo("starting two replicas on the store ...")
        env = {"SGVLOC_STORE_URL": url, "SGVLOC_FOLLOW_POLL_S": "1.0"}
        replicas = [
            ServiceProcess(Path(tmp) / n, Path(tmp) / f"{n}.log", workers=1, env=env) for n in "ab"
        ]
        try:
            result["replica_start_s"] = start_side_by_side(replicas)
            a, b = (r.url for r in replicas)
            echo(f"insert-to-visible ({visible} inserts) ...")
            result["visible"] = _visibility(a, b, visible, keypoints)

            echo(f"one vs two replicas ({clients} clients, {duration_s:g} s each) ...")
            seq = KittiSequence(data)
            with httpx.Client(timeout=300.0) as h:
                h.post(f"{a}/v1/maps", json={"name": "bench-qps"}).raise_for_status()
                body = {"keyframes": [{"T_map_sensor": seq[i].T_world_sensor,
                                       "points": seq[i].scan().xyzi()}
                                      for i in range(0, len(seq), 2)]}  # fmt: skip
                r = h.post(
                    f"{a}/v1/maps/bench-qps/keyframes",
                    content=wire.packb(body),
                    headers={"Content-Type": wire.MSGPACK},
                )
                r.raise_for_status()
                version = r.json()["map_version"]
                q = seq[1].scan().xyzi()
                for u in (a, b):  # both serve the map (and are warm) before the clock runs
                    h.post(
                        f"{u}/v1/maps/bench-qps/localize?min_map_version={version}",
                        content=wire.packb({"points": q}),
                        headers={"Content-Type": wire.MSGPACK},
                    ).raise_for_status()
            one = _qps([a], q, clients, duration_s)
            two = _qps([a, b], q, clients, duration_s)
            result["qps"] = {"clients": clients, "one": one, "two": two, "ratio": two / one}
        finally:
            for r in replicas:
                r.stop()

        echo("features in memory vs fetched from PostgreSQL ...")
        result["fetch"] = _fetch_cost(url, data, rounds)

        result["catch_up"] = []
        _drop_bench_maps(url, sizes)  # each catch-up loads its own map alone
        for n in sizes:
            echo(f"catch-up at {n} keyframes: writing ...")
            name = f"bench-catchup-{n}"
            filled = _fill(url, name, n, keypoints, echo)
            row = {"keyframes": n, **filled}
            for in_memory in (True, False):
                key = "memory" if in_memory else "slim"
                row[key] = _load(url, name, in_memory)
            result["catch_up"].append(row)
            _drop_bench_maps(url, sizes)
            echo(
                f"  loaded in {row['memory']['load_s']:.1f} s (features in memory), "
                f"{row['slim']['load_s']:.1f} s (fetched per query)"
            )
    result["cores_note"] = (
        "every replica and the clients share this machine's cores: two replicas can only "
        "add the cores one leaves idle"
    )
    return result


def format_cluster(res: dict[str, Any]) -> str:
    v, q, f = res["visible"], res["qps"], res["fetch"]
    starts = " / ".join(f"{s:.1f}" for s in res["replica_start_s"])
    lines = [
        _table(
            ["measure", "value"],
            [
                [
                    "replica start to ready, side by side (s)",
                    starts,
                ],
                [
                    f"insert-to-visible p50 / p99 / max (ms, {v['inserts']} inserts)",
                    f"{v['p50_ms']:.1f} / {v['p99_ms']:.1f} / {v['max_ms']:.1f}",
                ],
                [
                    f"localize QPS, {q['clients']} clients: one replica / two",
                    f"{q['one']:.1f} / {q['two']:.1f} ({q['ratio']:.2f}x)",
                ],
            ],
        ),  # fmt: skip
        "",
        _table(
            ["local features", "localize p50 (ms)", "fetch p50 (ms)", "ratio to memory"],
            [
                [p, f"{x['p50_ms']:.1f}", f"{x['fetch_p50_ms']:.1f}", f"{x['ratio']:.2f}x"]
                for p, x in f["paths"].items()
            ],
        ),
        f"same keyframe and verdict on every path: {f['same_answers']}",
        "",
        _table(
            [
                "keyframes",
                "write (s)",
                "store (MiB)",
                "catch-up, in memory (s)",
                "memory (MiB)",
                "catch-up, fetched (s)",
                "memory (MiB)",
            ],
            [
                [
                    str(r["keyframes"]),
                    f"{r['write_s']:.1f}",
                    f"{r['disk_mib']:.0f}",
                    f"{r['memory']['load_s']:.1f}",
                    f"{r['memory']['memory_mib']:.0f}",
                    f"{r['slim']['load_s']:.1f}",
                    f"{r['slim']['memory_mib']:.0f}",
                ]
                for r in res["catch_up"]
            ],
        ),  # fmt: skip
        f"- {res['cores_note']}",
    ]
    return "\n".join(lines)


FORMATTERS = {"cluster": format_cluster}
