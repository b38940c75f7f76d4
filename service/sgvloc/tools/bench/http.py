"""``sgvloc bench`` sections that measure the service end to end: ``http`` and ``scaling``.

Both start the real service (``python -m sgvloc.cli serve --dev``: uvicorn, one process,
``--workers`` threads, every other setting at its default) on a free 127.0.0.1 port with a
temporary data directory, wait for ``/readyz``, and stop it with SIGTERM at the end, also
on errors and Ctrl-C (:class:`ServiceProcess`). The only changed setting is
``max_inflight_localize``, raised to the largest client count so that no localize request
is refused with 429 (refusals are still counted apart, as in ``sgvloc loadtest``).

Clients run in a second, spawned Python process (:class:`ClientProcess`), so neither the
server nor the clients share a GIL with the other: every client is a thread there with its
own ``httpx`` connection, sending MessagePack bodies (``sgvloc_client.wire``) made before
the clock starts and asking for MessagePack answers. Latency is measured by the client
(send to last byte of the answer); the service's own per-stage times come from the
``timings_ms`` of each localize answer (encode, retrieve, rerank, pose, total).

``http`` (:func:`bench_http`): a map with the default encoder (the learned BEV encoder:
620-D global descriptor, up to 256 keypoints with 64-D descriptors) holding ``keyframes``
keyframes, inserted as precomputed features through the bulk endpoint. The features are
*copies* of the real database scans of ``tests/fixtures/balm_mini`` encoded once here with
the map's encoder: each copy's keypoints are turned by a random yaw and jittered (2 cm),
its local feature rows and global descriptor get small noise, and it sits at its own place
of a 10 m grid. So every keyframe has the full size and shape of a real one (the
per-candidate costs of SGV and RANSAC are real), but the map is 12 places repeated:
retrieval and re-ranking results are not meaningful for accuracy. Queries are the
fixture's held-out query scans, densified to ``points`` points (5 cm jitter), posted raw
so the server encodes them; ``top_k`` 20, ``rerank`` sgv, ``refine`` none: keyframes
inserted as features carry no cloud, so ICP could not run against them anyway. Closed-loop
clients (send, wait, send again) run for ``duration_s`` per client count; throughput is
successful answers per second of the window. Bulk insert is timed per request (server
time: decoding, validation, encoding of raw scans, one SQLite transaction with fsync,
FAISS add): with precomputed features (the 10k map's batches) and with raw scans (a second
map of the same encoder that keeps clouds, so the server encodes and stores each scan's
preprocessed cloud).

``scaling`` (:func:`bench_scaling`): one map grown in steps (default 1k, 3k, 10k, 30k,
100k keyframes); after each step localize p50/p99/QPS (1 and 4 clients), insert
keyframes/s of the step's batches, the server's RSS and the map's size on disk (SQLite
with its WAL, FAISS snapshot); a PNG of the curves and a table. To keep 100k keyframes
fast to insert and small on disk, the map's handcrafted encoder keeps ``keypoints`` (64)
keypoints per scan instead of 512 (about 12 KB per keyframe instead of 76 KB); the
global descriptor (620-D, flat index: the part that grows with the map) is the real one,
and queries are still raw scans encoded by the server.
"""

from __future__ import annotations

import contextlib
import logging
import pickle
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from sgvloc_client import wire

from ..service_process import temporary_service

log = logging.getLogger(__name__)

REQUEST_TIMEOUT_S = 120.0
FIXTURE = Path(__file__).resolve().parents[4] / "tests/fixtures/balm_mini"

#: targets of the performance issue (2 cores, medians)
TARGET_P50_MS = 150.0
TARGET_QPS_4 = 10.0
TARGET_INSERT_KF_S = 200.0

Echo = Callable[[str], None]


def _quiet(_: str) -> None:
    pass


class ClientProcess:
    """A second Python process (``python -m sgvloc.tools.bench.http``) that runs the client
    jobs (:data:`CLIENT_JOBS`) one at a time; arguments and results travel as pickles
    over its stdin/stdout. A plain subprocess rather than ``multiprocessing``: spawn would
    re-import the caller's ``__main__``, which a script without a main guard cannot take.
    """

    def __init__(self) -> None:
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "sgvloc.tools.bench.http"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
        )

    def run(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """``fn(*args, **kwargs)`` in the client process; its exception as RuntimeError."""
        if fn.__name__ not in CLIENT_JOBS:
            raise ValueError(f"{fn.__name__} is not a client job")
        proc = self._proc
        assert proc.stdin is not None and proc.stdout is not None
        data = pickle.dumps((fn.__name__, args, kwargs), protocol=pickle.HIGHEST_PROTOCOL)
        try:
            proc.stdin.write(len(data).to_bytes(8, "little") + data)
            proc.stdin.flush()
        except BrokenPipeError:
            raise RuntimeError(f"the client process is gone (code {proc.poll()})") from None
        status, value = _read_frame(proc.stdout, f"the client process (job {fn.__name__})")
        if status != "ok":
            raise RuntimeError(f"client job {fn.__name__} failed: {value}")
        return value

    def close(self) -> None:
        proc = self._proc
        if proc.poll() is None:
            with contextlib.suppress(OSError):
                proc.stdin.close()  # type: ignore[union-attr]
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)
        with contextlib.suppress(OSError):
            proc.stdout.close()  # type: ignore[union-attr]

    def __enter__(self) -> ClientProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _read_frame(stream: Any, who: str) -> Any:
    header = stream.read(8)
    if len(header) < 8:
        raise RuntimeError(f"{who} ended without an answer")
    size = int.from_bytes(header, "little")
    data = stream.read(size)
    if len(data) < size:
        raise RuntimeError(f"{who} ended in the middle of an answer")
    return pickle.loads(data)


def _client_main() -> None:
    """The client process: run the jobs read from stdin, answer on stdout."""
    out = sys.stdout.buffer
    sys.stdout = sys.stderr  # stray prints must not corrupt the answers
    while True:
        try:
            name, args, kwargs = _read_frame(sys.stdin.buffer, "the bench process")
        except RuntimeError:
            return  # stdin closed: done
        try:
            if name not in CLIENT_JOBS:
                raise ValueError(f"{name!r} is not a client job")
            answer = ("ok", globals()[name](*args, **kwargs))
        except Exception as exc:  # noqa: BLE001 - reported to the bench process
            answer = ("error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}")
        data = pickle.dumps(answer, protocol=pickle.HIGHEST_PROTOCOL)
        out.write(len(data).to_bytes(8, "little") + data)
        out.flush()


# --------------------------------------------------------------------------------------
# Inputs: real scans, their features, perturbed copies
# --------------------------------------------------------------------------------------


def source_scans(fixture: Path = FIXTURE) -> tuple[list[np.ndarray], list[np.ndarray], str]:
    """``(database scans, query scans, source)``: the real fixture's scans (``[P, 3]``),
    or procedural scenes when the fixture is not at hand (a wheel install)."""
    roles = fixture / "scans.txt"
    files = sorted((fixture / "velodyne").glob("*.bin"))
    if roles.exists() and files:
        kinds = [ln.split()[1] for ln in roles.read_text().splitlines() if ln and ln[0] != "#"]
        scans = [np.fromfile(p, dtype=np.float32).reshape(-1, 4)[:, :3] for p in files]
        db = [s for s, k in zip(scans, kinds, strict=True) if k == "database"]
        q = [s for s, k in zip(scans, kinds, strict=True) if k == "query"]
        return db, q, f"{fixture.name} ({len(db)} database scans, {len(q)} query scans, real)"
    from .engine import _procedural_scan

    rng = np.random.default_rng(7)
    db = [_procedural_scan(rng, 10_000) for _ in range(12)]
    q = [_procedural_scan(rng, 10_000) for _ in range(3)]
    return db, q, "procedural scenes (12 database, 3 query; the fixture is not installed)"


def encode_bases(scans: list[np.ndarray], spec: Any) -> tuple[list[dict[str, np.ndarray]], dict]:
    """Encode ``scans`` with the encoder of ``spec`` (here, once): the features the copies
    are made from, and the claim (encoder name, fingerprint) they are sent with."""
    from sgvloc.core.encoders import make_encoder

    enc = make_encoder(spec)
    bases = []
    for scan in scans:
        f = enc.encode(scan)
        bases.append(
            {
                "global_descriptor": f.global_descriptor,
                "keypoints": f.keypoints,
                "local_features": f.local_features,
            }
        )
    claim = {"encoder": enc.identity.name, "fingerprint": enc.identity.fingerprint}
    return bases, claim


def synthetic_keyframe(
    bases: list[dict[str, np.ndarray]], rng: np.random.Generator, index: int, claim: dict
) -> dict[str, Any]:
    """Keyframe ``index``: a perturbed copy of ``bases[index % len(bases)]``.

    Keypoints turned by a random yaw (FPFH and the polar-grid descriptor do not change
    with yaw) plus 2 cm noise; FPFH rows plus small non-negative noise, re-normalised;
    the global descriptor plus 2 % noise. Pose: the same yaw, at place ``index`` of a
    10 m grid, 100 places a row.
    """
    b = bases[index % len(bases)]
    yaw = rng.uniform(0.0, 2.0 * np.pi)
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=np.float32)
    kp, lf, g = b["keypoints"], b["local_features"], b["global_descriptor"]
    f32 = np.float32
    kp = kp @ rot.T + f32(0.02) * rng.standard_normal(kp.shape, dtype=f32)
    lf = lf + np.abs(f32(0.02) * rng.standard_normal(lf.shape, dtype=f32))
    lf /= np.maximum(np.linalg.norm(lf, axis=1, keepdims=True), f32(1e-12))
    g = g + f32(0.02 * float(np.abs(g).mean())) * rng.standard_normal(g.shape, dtype=f32)
    T = np.eye(4)
    T[:3, :3] = rot
    T[:2, 3] = (10.0 * (index % 100), 10.0 * (index // 100))
    return {
        "key": f"kf{index}",
        "T_map_sensor": T,
        "features": {"global_descriptor": g, "keypoints": kp, "local_features": lf, **claim},
    }


def query_bodies(
    scans: list[np.ndarray],
    points: int,
    count: int,
    top_k: int,
    seed: int = 1,
    refine: str = "none",
) -> list[bytes]:
    """``count`` localize bodies (MessagePack): the query scans in turn, densified to
    ``points`` points with 5 cm jitter, raw, SGV re-ranking of ``top_k``, ``refine``."""
    from .engine import densify

    rng = np.random.default_rng(seed)
    return [
        wire.packb(
            {
                "points": densify(scans[i % len(scans)], points, rng),
                "top_k": top_k,
                "rerank": "sgv",
                "refine": refine,
            }
        )
        for i in range(count)
    ]


# --------------------------------------------------------------------------------------
# Client jobs (run in the spawned client process)
# --------------------------------------------------------------------------------------

_MSGPACK_HEADERS = {"Content-Type": wire.MSGPACK, "Accept": wire.MSGPACK}


def _localize_load(
    url: str,
    map_name: str,
    bodies: list[bytes],
    clients: int,
    duration_s: float,
    warmup_requests: int = 1,
    timeout_s: float = REQUEST_TIMEOUT_S,
) -> dict[str, Any]:
    """``clients`` closed-loop threads, each on its own connection, for ``duration_s``.

    Every thread first sends ``warmup_requests`` untimed requests (connection set-up,
    first-touch), then all start together; requests sent before the deadline are waited
    for. Returns raw per-request records; summarised by :func:`_summarise_load`.
    """
    path = f"/v1/maps/{map_name}/localize"
    records: list[dict[str, Any]] = []
    samples: list[str] = []
    lock = threading.Lock()
    clock: dict[str, float] = {}
    barrier = threading.Barrier(
        clients, action=lambda: clock.__setitem__("start", time.perf_counter())
    )

    def one(c: httpx.Client, body: bytes) -> dict[str, Any]:
        t0 = time.perf_counter()
        try:
            r = c.post(path, content=body, headers=_MSGPACK_HEADERS)
            status, retry = r.status_code, "retry-after" in r.headers
            content = r.content
        except httpx.TransportError as exc:
            status, retry, content = 0, False, repr(exc).encode()
        rec: dict[str, Any] = {"ms": (time.perf_counter() - t0) * 1e3, "status": status}
        if 200 <= status < 300:
            ans = wire.unpackb(content)
            rec["server_ms"] = {k: float(v) for k, v in ans["timings_ms"].items()}
            rec["localized"] = bool(ans["localized"])
        elif status in (429, 503) and retry:
            rec["refused"] = True
        else:
            rec["error"] = f"{status}: {content[:300]!r}"
        return rec

    def client(i: int) -> None:
        n = i
        with httpx.Client(base_url=url, timeout=timeout_s) as c:
            for _ in range(warmup_requests):
                rec = one(c, bodies[n % len(bodies)])
                if "error" in rec:
                    with lock:
                        samples.append(f"warm-up {rec['error']}")
            barrier.wait()
            deadline = clock["start"] + duration_s
            while time.perf_counter() < deadline:
                rec = one(c, bodies[n % len(bodies)])
                rec["end"] = time.perf_counter()
                n += clients
                with lock:
                    records.append(rec)
                    if "error" in rec and len(samples) < 5:
                        samples.append(rec["error"])
                if rec.get("refused"):
                    time.sleep(0.05)

    threads = [threading.Thread(target=client, args=(i,), daemon=True) for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    start = clock.get("start", time.perf_counter())
    end = max((r["end"] for r in records), default=start)
    for r in records:
        r.pop("end", None)
    return {"clients": clients, "elapsed_s": end - start, "records": records, "samples": samples}


def _insert_features(
    url: str,
    map_name: str,
    bases: list[dict[str, np.ndarray]],
    claim: dict,
    first: int,
    count: int,
    batch: int,
    seed: int,
    timeout_s: float = REQUEST_TIMEOUT_S,
) -> dict[str, Any]:
    """Insert keyframes ``first .. first + count - 1`` (:func:`synthetic_keyframe`) in
    batches of ``batch``; times each request (the body is made before its clock starts)."""
    rng = np.random.default_rng(seed)
    rows, gen_s = [], 0.0
    with httpx.Client(base_url=url, timeout=timeout_s) as c:
        for b0 in range(first, first + count, batch):
            n = min(batch, first + count - b0)
            t0 = time.perf_counter()
            kfs = [synthetic_keyframe(bases, rng, b0 + j, claim) for j in range(n)]
            body = wire.packb({"keyframes": kfs})
            gen_s += time.perf_counter() - t0
            rows.append(_post_insert(c, map_name, body, n))
    return {"batches": rows, "generate_s": gen_s}


def _insert_scans(
    url: str,
    map_name: str,
    scans: list[np.ndarray],
    batch: int,
    timeout_s: float = REQUEST_TIMEOUT_S,
) -> dict[str, Any]:
    """Insert raw ``scans`` (the server encodes them) in batches of ``batch``."""
    rows, gen_s = [], 0.0
    with httpx.Client(base_url=url, timeout=timeout_s) as c:
        for b0 in range(0, len(scans), batch):
            t0 = time.perf_counter()
            part = scans[b0 : b0 + batch]
            kfs = [
                {"key": f"raw{b0 + j}", "T_map_sensor": np.eye(4), "points": s}
                for j, s in enumerate(part)
            ]
            body = wire.packb({"keyframes": kfs})
            gen_s += time.perf_counter() - t0
            rows.append(_post_insert(c, map_name, body, len(part)))
    return {"batches": rows, "generate_s": gen_s}


def _post_insert(c: httpx.Client, map_name: str, body: bytes, n: int) -> dict[str, Any]:
    t0 = time.perf_counter()
    r = c.post(f"/v1/maps/{map_name}/keyframes", content=body, headers=_MSGPACK_HEADERS)
    ms = (time.perf_counter() - t0) * 1e3
    if r.status_code != 201:
        raise RuntimeError(f"insert into {map_name!r}: {r.status_code} {r.text[:500]}")
    created = wire.unpackb(r.content)["created"]
    if not all(created) or len(created) != n:
        raise RuntimeError(f"insert into {map_name!r}: {sum(created)} of {n} keyframes created")
    return {"keyframes": n, "ms": ms, "bytes": len(body)}


# --------------------------------------------------------------------------------------
# Summaries
# --------------------------------------------------------------------------------------


def _pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def _summarise_load(raw: dict[str, Any]) -> dict[str, Any]:
    """p50/p99/mean latency, QPS, refusals, errors and the service's stage medians."""
    recs = raw["records"]
    ok = [r for r in recs if "server_ms" in r]
    lat = [r["ms"] for r in ok]
    out: dict[str, Any] = {
        "clients": raw["clients"],
        "elapsed_s": raw["elapsed_s"],
        "requests": len(recs),
        "ok": len(ok),
        "refused": sum(1 for r in recs if r.get("refused")),
        "errors": sum(1 for r in recs if "error" in r),
        "error_samples": raw["samples"],
        "p50_ms": _pct(lat, 50),
        "p99_ms": _pct(lat, 99),
        "mean_ms": float(np.mean(lat)) if lat else None,
        "qps": len(ok) / raw["elapsed_s"] if raw["elapsed_s"] > 0 else 0.0,
        "localized_share": float(np.mean([r["localized"] for r in ok])) if ok else None,
    }
    stages: dict[str, float] = {}
    for stage in ("encode", "retrieve", "rerank", "pose", "total"):
        vals = [r["server_ms"][stage] for r in ok if stage in r["server_ms"]]
        if vals:
            stages[stage] = float(np.median(vals))
    out["server_median_ms"] = stages
    # what the service's stages do not account for: HTTP, body decoding, queueing for a
    # worker thread, answer encoding, the client's own work
    if ok:
        out["outside_stages_median_ms"] = float(
            np.median([r["ms"] - r["server_ms"]["total"] for r in ok])
        )
    return out


def _summarise_inserts(raw: dict[str, Any]) -> dict[str, Any]:
    """Keyframes/s per request (median, min, max), overall, and MiB/s of bodies."""
    rows = raw["batches"]
    rates = [r["keyframes"] / (r["ms"] / 1e3) for r in rows]
    total_kf = sum(r["keyframes"] for r in rows)
    total_s = sum(r["ms"] for r in rows) / 1e3
    return {
        "batches": len(rows),
        "batch": rows[0]["keyframes"] if rows else 0,
        "keyframes": total_kf,
        "median_kf_s": float(np.median(rates)) if rates else None,
        "min_kf_s": float(np.min(rates)) if rates else None,
        "max_kf_s": float(np.max(rates)) if rates else None,
        "overall_kf_s": total_kf / total_s if total_s > 0 else None,
        "request_s": total_s,
        "body_mib_per_s": sum(r["bytes"] for r in rows) / 2**20 / total_s if total_s else None,
        "kib_per_keyframe": sum(r["bytes"] for r in rows) / 1024 / total_kf if total_kf else None,
        "client_generate_s": raw["generate_s"],
    }


def _target(name: str, measured: float | None, target: float, unit: str, higher: bool) -> dict:
    """A target row: ratio = measured / target (met when <= 1 for ``<=`` targets)."""
    ratio = None if measured is None else measured / target
    met = None if ratio is None else (ratio >= 1.0 if higher else ratio <= 1.0)
    return {
        "name": name,
        "target": f"{'>=' if higher else '<='} {target:g} {unit}",
        "measured": measured,
        "unit": unit,
        "ratio": ratio,
        "met": met,
    }


def _create_map(url: str, body: dict[str, Any]) -> dict[str, Any]:
    r = httpx.post(f"{url}/v1/maps", json=body, timeout=REQUEST_TIMEOUT_S)
    if r.status_code != 201:
        raise RuntimeError(f"cannot create map {body['name']!r}: {r.status_code} {r.text}")
    return r.json()


def _map_info(url: str, name: str) -> dict[str, Any]:
    r = httpx.get(f"{url}/v1/maps/{name}", timeout=REQUEST_TIMEOUT_S)
    r.raise_for_status()
    return r.json()


def _check_clients(clients: list[int]) -> list[int]:
    if not clients or any(c < 1 for c in clients):
        raise ValueError(f"client counts must be >= 1, got {clients}")
    return sorted(set(clients))


# --------------------------------------------------------------------------------------
# Section: http
# --------------------------------------------------------------------------------------


def bench_http(
    *,
    keyframes: int = 10_000,
    clients: list[int] | None = None,
    duration_s: float = 8.0,
    batch: int = 250,
    raw_scans: int = 24,
    raw_batch: int = 8,
    points: int = 25_000,
    top_k: int = 20,
    workers: int = 2,
    compare: bool = False,
    batch_wait_ms: float = 0.0,
    work_dir: Path | None = None,
    echo: Echo = _quiet,
) -> dict[str, Any]:
    """Localize p50/p99/QPS at each client count on a ``keyframes`` map; bulk insert
    keyframes/s with precomputed features and with raw scans; on the raw-scan map,
    localize with ICP (the default) and without, and with ``compare`` on a second map of
    the same scans with the earlier path's settings. With ``batch_wait_ms`` > 0, a second
    service with dynamic batching on (that wait) is started beside the first and both are
    loaded in turn (raw-scan map, ICP) at every client count. See the module docstring."""
    from sgvloc.core.encoders import EncoderSpec

    clients = _check_clients(clients or [1, 4, 16])
    if keyframes < 1 or batch < 1 or raw_batch < 1 or raw_scans < 0 or duration_s <= 0:
        raise ValueError("keyframes, batch, raw_batch and duration_s must be positive")
    db, queries, source = source_scans()
    spec = EncoderSpec()
    t0 = time.perf_counter()
    bases, claim = encode_bases(db, spec)
    encode_s = time.perf_counter() - t0
    bodies = query_bodies(queries, points, max(6, len(queries)), top_k)
    # batching off in this service, also where CUDA would turn it on: the baseline of the
    # batching comparison below
    env = {
        "SGVLOC_MAX_INFLIGHT_LOCALIZE": str(max(4 * workers, max(clients))),
        "SGVLOC_BATCH_WAIT_MS": "0",
    }
    result: dict[str, Any] = {"source": source, "keyframes": keyframes, "top_k": top_k}
    with temporary_service(work_dir, "http", workers, env) as srv, ClientProcess() as cp:
        result["server"] = {"workers": workers, "env": env, "pids": srv.pids}
        name = "bench-http"
        info = _create_map(
            srv.url,
            {"name": name, "encoder": spec.model_dump(mode="json"), "localizer": {"top_k": top_k}},
        )
        enc = info["encoder"]
        result["map"] = {
            "name": name,
            "encoder": enc["name"],
            "global_dim": enc["global_dim"],
            "local_dim": enc["local_dim"],
            "keypoints_per_keyframe": int(np.median([len(b["keypoints"]) for b in bases])),
            "bases": len(bases),
            "bases_encode_s": encode_s,
        }
        echo(f"  inserting {keyframes} keyframes (precomputed features, batches of {batch}) ...")
        t0 = time.perf_counter()
        raw = cp.run(_insert_features, srv.url, name, bases, claim, 0, keyframes, batch, 0)
        ins = _summarise_inserts(raw)
        ins["wall_s"] = time.perf_counter() - t0
        result["insert_features"] = ins
        echo(
            f"  insert, precomputed features: median {ins['median_kf_s']:.0f} keyframes/s per "
            f"request of {ins['batch']} ({ins['kib_per_keyframe']:.0f} KiB each), overall "
            f"{ins['overall_kf_s']:.0f}/s, {ins['wall_s']:.0f} s wall"
        )
        stored = _map_info(srv.url, name)["keyframes"]
        if stored != keyframes:
            raise RuntimeError(f"map {name!r} holds {stored} keyframes, expected {keyframes}")
        result["map"]["store_mib"] = srv.map_disk_mib(name)
        rows = []
        for n in clients:
            load = _summarise_load(
                cp.run(_localize_load, srv.url, name, bodies, n, duration_s, 2 if n == 1 else 1)
            )
            rows.append(load)
            echo("  " + _load_line(load))
        result["localize"] = rows
        result["server"]["memory_after_localize"] = srv.memory_mib()

        if raw_scans:
            from .engine import densify

            rng = np.random.default_rng(2)
            scans = [densify(db[i % len(db)], points, rng) for i in range(raw_scans)]
            _create_map(srv.url, {"name": "bench-raw", "encoder": spec.model_dump(mode="json")})
            echo(f"  inserting {raw_scans} raw {points}-point scans (batches of {raw_batch}) ...")
            ins_raw = _summarise_inserts(
                cp.run(_insert_scans, srv.url, "bench-raw", scans, raw_batch)
            )
            ins_raw["store_mib"] = srv.map_disk_mib("bench-raw")
            result["insert_raw"] = ins_raw
            echo(
                f"  insert, raw scans: median {ins_raw['median_kf_s']:.1f} keyframes/s per "
                f"request of {ins_raw['batch']}, overall {ins_raw['overall_kf_s']:.1f}/s"
            )
            raw_load = RawScanLoad(scans, queries, points, top_k, clients, duration_s, raw_batch)
            result["icp"] = _icp_rows(srv.url, cp, raw_load, compare, echo)
            if batch_wait_ms > 0:
                result["batching"] = _batching_rows(
                    srv.url, cp, raw_load, work_dir, workers, env, batch_wait_ms, echo
                )
        result["server"]["memory_end"] = srv.memory_mib()

    by_clients = {r["clients"]: r for r in rows}
    icp_targets = _icp_targets(result.get("icp", []), compare)
    result["targets"] = [
        _target(
            f"localize p50, {min(clients)} client(s) ({points}-point scan, {keyframes} keyframes, "
            f"top_k {top_k}, sgv)",
            by_clients[min(clients)]["p50_ms"],
            TARGET_P50_MS,
            "ms",
            higher=False,
        ),
        _target(
            "bulk insert, precomputed features",
            result["insert_features"]["median_kf_s"],
            TARGET_INSERT_KF_S,
            "keyframes/s",
            higher=True,
        ),
    ]
    if 4 in by_clients:
        result["targets"].insert(
            1, _target("localize QPS, 4 clients", by_clients[4]["qps"], TARGET_QPS_4, "QPS", True)
        )
    result["targets"] += icp_targets
    result["notes"] = [
        f"service: 'sgvloc serve --dev', {workers} worker threads, default settings except "
        f"max_inflight_localize={env['SGVLOC_MAX_INFLIGHT_LOCALIZE']} (no 429 by design); "
        "clients: threads of one spawned process, one connection each, MessagePack both ways",
        f"map: the default encoder ({spec.kind}); {keyframes} keyframes inserted as "
        "precomputed features = perturbed copies (random yaw, 2 cm keypoint jitter, "
        f"feature noise) of {len(bases)} encoded scans of {source}: real per-keyframe "
        "size and cost, but 12 places repeated, so retrieval/re-ranking results say "
        "nothing about accuracy",
        f"queries: {len(bodies)} bodies cycling over the held-out query scans densified to "
        f"{points} points (5 cm jitter), raw (the server encodes them); top_k {top_k}, "
        "rerank sgv, refine none (feature keyframes carry no cloud, so no ICP)",
        f"localize: closed loop for {duration_s:g} s per client count after an untimed "
        "warm-up; latency = client send to answer read; QPS = answers / window; 'server' "
        "columns = medians of the answer's timings_ms; 'outside' = latency minus the "
        "service's total (HTTP, decoding, waiting for one of the worker threads)",
        "ICP rows: the raw-scan map (real scans, each keeps its cloud), the same queries "
        "with refine icp (the default) and none; 'earlier' (--compare) = a second map of "
        "the same scans whose encoder runs the network in torch and whose pose step has "
        "the earlier settings (RANSAC batches of 1000, Open3D point-to-point ICP over every "
        "point), loaded in turn with the default map in the same service",
        "insert: keyframes/s per request (median over requests; bodies made before the "
        "clock starts), overall = all keyframes / all request time; raw scans go to a "
        "second map of the same encoder that keeps clouds (server-side encoding + cloud "
        "storage)",
    ]
    return result


@dataclass
class RawScanLoad:
    """The raw-scan map's scans (inserted in batches of ``batch``) and the localize load
    put on it: the query scans densified to ``points``, ``top_k``, closed loop for
    ``duration_s`` at each of ``clients``."""

    scans: list[np.ndarray]
    queries: list[np.ndarray]
    points: int
    top_k: int
    clients: list[int]
    duration_s: float
    batch: int

    def bodies(self, refine: str) -> list[bytes]:
        n = max(6, len(self.queries))
        return query_bodies(self.queries, self.points, n, self.top_k, refine=refine)


def _icp_rows(
    url: str, cp: ClientProcess, load: RawScanLoad, compare: bool, echo: Echo
) -> list[dict[str, Any]]:
    """Localize load on the raw-scan map with ICP and without (and on the earlier path's
    map with ICP when ``compare``), at the fewest clients and at 4 if measured; each in
    two rounds of half the duration, the paths taking turns."""
    from sgvloc.core.encoders import EncoderSpec

    from .pipeline import EARLIER_POSE

    maps = {"default": "bench-raw"}
    if compare:
        maps["earlier"] = "bench-raw-earlier"
        spec = EncoderSpec(runtime="torch").model_dump(mode="json")
        _create_map(
            url,
            {"name": maps["earlier"], "encoder": spec, "localizer": {"pose": EARLIER_POSE}},
        )
        cp.run(_insert_scans, url, maps["earlier"], load.scans, load.batch)
    bodies = {refine: load.bodies(refine) for refine in ("icp", "none")}
    runs = [
        (path, name, refine)
        for path, name in maps.items()
        for refine in (("icp", "none") if path == "default" else ("icp",))
    ]
    rows = []
    for n in sorted({min(load.clients), *(c for c in load.clients if c == 4)}):
        # two rounds of half the duration each, the paths in turn: a slow spell of a
        # shared machine falls on every path
        raws: dict[tuple[str, str], dict[str, Any]] = {}
        for _ in range(2):
            for path, name, refine in runs:
                raw = cp.run(_localize_load, url, name, bodies[refine], n, load.duration_s / 2, 2)
                if (path, refine) in raws:
                    acc = raws[(path, refine)]
                    acc["records"] += raw["records"]
                    acc["samples"] += raw["samples"]
                    acc["elapsed_s"] += raw["elapsed_s"]
                else:
                    raws[(path, refine)] = raw
        for (path, refine), raw in raws.items():
            row = _summarise_load(raw)
            row.update(path=path, refine=refine)
            rows.append(row)
            echo(f"  {path}, refine {refine}: " + _load_line(row))
    return rows


def _batching_rows(
    url: str,
    cp: ClientProcess,
    load: RawScanLoad,
    work_dir: Path | None,
    workers: int,
    env: dict[str, str],
    wait_ms: float,
    echo: Echo,
) -> list[dict[str, Any]]:
    """At every client count, localize load (raw-scan map, ICP) on the running service
    (batching off) and then on a second one with dynamic batching on, started beside it
    with the same scans: pairs measured one right after the other. The batched rows
    carry the batches' mean size from that service's metrics."""
    env = {**env, "SGVLOC_BATCH_WAIT_MS": str(wait_ms)}
    bodies = load.bodies("icp")
    rows = []
    with temporary_service(work_dir, "batch", workers, env) as srv:
        _create_map(srv.url, {"name": "bench-raw"})
        cp.run(_insert_scans, srv.url, "bench-raw", load.scans, load.batch)
        for n in load.clients:
            for label, base in (("batching off", url), (f"batching {wait_ms:g} ms", srv.url)):
                before = httpx.get(f"{base}/metrics").text
                row = _summarise_load(
                    cp.run(_localize_load, base, "bench-raw", bodies, n, load.duration_s, 2)
                )
                after = httpx.get(f"{base}/metrics").text
                for stage in ("forward", "sgv"):
                    count, items = (
                        _metric_sum(after, f'sgvloc_batch_size_{w}{{stage="{stage}"}}')
                        - _metric_sum(before, f'sgvloc_batch_size_{w}{{stage="{stage}"}}')
                        for w in ("count", "sum")
                    )
                    row[f"mean_batch_{stage}"] = items / count if count else None
                row.update(path=label, refine="icp")
                rows.append(row)
                echo(f"  {label}: " + _load_line(row))
    return rows


def _metric_sum(text: str, name: str) -> float:
    """The sum of the samples of ``name`` (with its labels) in a /metrics text."""
    return sum(float(ln.split()[-1]) for ln in text.splitlines() if ln.startswith(name + " "))


def _icp_targets(rows: list[dict[str, Any]], compare: bool) -> list[dict[str, Any]]:
    """p50 at one client with ICP, and with ``compare`` the QPS ratio at 4 clients."""
    by = {(r["path"], r["refine"], r["clients"]): r for r in rows}
    out = []
    one = by.get(("default", "icp", 1))
    if one:
        out.append(_target("localize p50 with ICP, 1 client", one["p50_ms"], 35.0, "ms", False))
    new, old = by.get(("default", "icp", 4)), by.get(("earlier", "icp", 4))
    if compare and new and old and old["qps"]:
        out.append(
            _target(
                "QPS with ICP, 4 clients, default / earlier path (same run)",
                new["qps"] / old["qps"],
                1.8,
                "x",
                True,
            )
        )
    return out


def _load_line(r: dict[str, Any]) -> str:
    s = r["server_median_ms"]
    return (
        f"{r['clients']:3d} clients: {r['ok']} ok, {r['errors']} errors, {r['refused']} refused; "
        f"p50 {_f(r['p50_ms'])} ms, p99 {_f(r['p99_ms'])} ms, {r['qps']:.1f} QPS; server "
        f"encode {_f(s.get('encode'))} retrieve {_f(s.get('retrieve'), 2)} rerank "
        f"{_f(s.get('rerank'))} pose {_f(s.get('pose'))} total {_f(s.get('total'))} ms"
    )


def _f(x: float | None, digits: int = 1) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


# --------------------------------------------------------------------------------------
# Section: scaling
# --------------------------------------------------------------------------------------


def bench_scaling(
    *,
    sizes: list[int] | None = None,
    clients: list[int] | None = None,
    duration_s: float = 3.0,
    batch: int = 1000,
    keypoints: int = 64,
    points: int = 25_000,
    top_k: int = 20,
    workers: int = 2,
    reload: bool = True,
    plot: Path | None = None,
    work_dir: Path | None = None,
    echo: Echo = _quiet,
) -> dict[str, Any]:
    """Grow one map through ``sizes`` keyframes; after each step measure localize (each
    client count), the step's insert rate, server RSS and disk size. ``reload``: restart
    the service on the largest map and time until it is ready. ``plot``: write a PNG."""
    from sgvloc.core.encoders import EncoderSpec

    sizes = sorted(set(sizes or [1000, 3000, 10_000, 30_000, 100_000]))
    clients = _check_clients(clients or [1, 4])
    if sizes[0] < 1 or batch < 1 or keypoints < 1 or duration_s <= 0:
        raise ValueError("sizes, batch, keypoints and duration_s must be positive")
    db, queries, source = source_scans()
    spec = EncoderSpec.model_validate(
        {"kind": "handcrafted", "handcrafted": {"num_keypoints": keypoints}}
    )
    bases, claim = encode_bases(db, spec)
    bodies = query_bodies(queries, points, max(6, len(queries)), top_k)
    env = {"SGVLOC_MAX_INFLIGHT_LOCALIZE": str(max(4 * workers, max(clients)))}
    name = "bench-scaling"
    rows: list[dict[str, Any]] = []
    result: dict[str, Any] = {"source": source, "sizes": sizes, "top_k": top_k, "rows": rows}
    with temporary_service(work_dir, "scaling", workers, env) as srv, ClientProcess() as cp:
        info = _create_map(
            srv.url,
            {
                "name": name,
                "encoder": spec.model_dump(mode="json"),
                "localizer": {"top_k": top_k},
                "keep_clouds": False,
            },
        )
        result["map"] = {
            "name": name,
            "encoder": info["encoder"]["name"],
            "global_dim": info["encoder"]["global_dim"],
            "local_dim": info["encoder"]["local_dim"],
            "num_keypoints": keypoints,
            "index": info["index_kind"],
        }
        result["server"] = {"workers": workers, "env": env, "pids": srv.pids}
        have = 0
        for size in sizes:
            t0 = time.perf_counter()
            raw = cp.run(
                _insert_features, srv.url, name, bases, claim, have, size - have, batch, size
            )
            ins = _summarise_inserts(raw)
            ins["wall_s"] = time.perf_counter() - t0
            have = size
            row: dict[str, Any] = {"keyframes": size, "insert": ins, "localize": {}}
            for n in clients:
                load = _summarise_load(
                    cp.run(_localize_load, srv.url, name, bodies, n, duration_s, 1)
                )
                row["localize"][str(n)] = load
            row.update(srv.memory_mib())
            row["disk_mib"] = srv.map_disk_mib(name)
            rows.append(row)
            echo("  " + _scaling_line(row, clients))
        if reload:
            # graceful stop saves the snapshot; the start-up loads every keyframe from SQLite
            result["reload_s"] = srv.restart()
            result["reload_rss_mib"] = srv.memory_mib().get("rss_mib")
            echo(
                f"  restart on {sizes[-1]} keyframes: ready in {result['reload_s']:.1f} s, "
                f"RSS {_f(result['reload_rss_mib'], 0)} MiB"
            )
    result["notes"] = [
        f"one map grown through {sizes} keyframes (precomputed-feature inserts in batches "
        f"of {batch}); handcrafted encoder with num_keypoints={keypoints} (not 512) so "
        "100k keyframes stay small and fast to insert; 620-D global descriptor, flat "
        "(exact) FAISS index: the part of localize that grows with the map",
        "keyframes: perturbed copies of encoded real scans, as in the http section; "
        f"queries: raw {points}-point scans encoded by the server, top_k {top_k}, sgv, "
        f"refine none; {duration_s:g} s per client count at each size",
        "insert kf/s: the requests of the step that reached this size (median per "
        "request); RSS: the server process (VmRSS; peak = VmHWM); disk: the map folder "
        "(SQLite + WAL + FAISS snapshot); 'x first' = ratio to the smallest size",
        "service snapshots the FAISS index every 1000 keyframe changes (default "
        "snapshot_every): its cost grows with the map and is part of the insert times",
    ]
    if plot is not None:
        result["plot"] = str(plot_scaling(result, plot))
        echo(f"  wrote {plot}")
    return result


def _scaling_line(row: dict[str, Any], clients: list[int]) -> str:
    parts = [f"{row['keyframes']:>7d} keyframes:"]
    for n in clients:
        r = row["localize"][str(n)]
        parts.append(
            f"{n} cl p50 {_f(r['p50_ms'], 0)} p99 {_f(r['p99_ms'], 0)} ms {r['qps']:.1f} QPS"
            f" (retrieve {_f(r['server_median_ms'].get('retrieve'), 2)} ms, {r['errors']} err);"
        )
    parts.append(
        f"insert {_f(row['insert']['median_kf_s'], 0)} kf/s; RSS {_f(row.get('rss_mib'), 0)} "
        f"MiB; disk {row['disk_mib']:.0f} MiB"
    )
    return " ".join(parts)


def plot_scaling(res: dict[str, Any], path: Path) -> Path:
    """Four panels against map size (log x): latency, QPS, insert rate, memory/disk."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = res["rows"]
    x = [r["keyframes"] for r in rows]
    clients = list(rows[0]["localize"]) if rows else []
    fig, axes = plt.subplots(2, 2, figsize=(11, 8), constrained_layout=True)
    ax = axes[0][0]
    for n in clients:
        for key, style in (("p50_ms", "-o"), ("p99_ms", "--x")):
            ax.plot(x, [r["localize"][n][key] for r in rows], style, label=f"{n} cl {key[:3]}")
    n0 = clients[0] if clients else None
    if n0 is not None:
        retrieve = [r["localize"][n0]["server_median_ms"].get("retrieve") for r in rows]
        ax.plot(x, retrieve, ":^", label=f"{n0} cl server retrieve (median)")
    ax.set(title="localize latency (client)", ylabel="ms")
    ax = axes[0][1]
    for n in clients:
        ax.plot(x, [r["localize"][n]["qps"] for r in rows], "-o", label=f"{n} client(s)")
    ax.set(title="localize throughput", ylabel="QPS")
    ax = axes[1][0]
    ax.plot(x, [r["insert"]["median_kf_s"] for r in rows], "-o", label="median per request")
    ax.set(title="bulk insert (precomputed features)", ylabel="keyframes/s")
    ax = axes[1][1]
    ax.plot(x, [r.get("rss_mib") for r in rows], "-o", label="server RSS")
    ax.plot(x, [r["disk_mib"] for r in rows], "-s", label="map on disk")
    ax.set(title="memory and disk", ylabel="MiB")
    for ax in axes.flat:
        ax.set_ylim(bottom=0)
        ax.set_xscale("log")
        ax.set_xlabel("keyframes in the map")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    m = res.get("map", {})
    fig.suptitle(
        f"sgvloc scaling: {m.get('encoder', '?')} ({m.get('num_keypoints', '?')} keypoints, "
        f"{m.get('global_dim', '?')}-D global, {m.get('index', '?')} index), top_k {res['top_k']}"
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------


def format_http(res: dict[str, Any]) -> str:
    """Localize table (QPS also as a ratio to the fewest clients), insert table and the
    targets with their ratios (measured / target)."""
    qps0 = res["localize"][0]["qps"] if res["localize"] else 0.0
    loc = _table(
        [
            "clients",
            "requests",
            "errors",
            "p50 ms",
            "p99 ms",
            "QPS",
            "QPS x first",
            "server encode",
            "retrieve",
            "rerank",
            "pose",
            "server total",
            "outside",
        ],
        [
            [
                str(r["clients"]),
                str(r["requests"]),
                str(r["errors"] + r["refused"]),
                _f(r["p50_ms"]),
                _f(r["p99_ms"]),
                f"{r['qps']:.1f}",
                f"{r['qps'] / qps0:.2f}x" if qps0 else "-",
                _f(r["server_median_ms"].get("encode")),
                _f(r["server_median_ms"].get("retrieve"), 2),
                _f(r["server_median_ms"].get("rerank")),
                _f(r["server_median_ms"].get("pose")),
                _f(r["server_median_ms"].get("total")),
                _f(r.get("outside_stages_median_ms")),
            ]
            for r in res["localize"]
        ],
    )
    ins_rows = []
    for label, key in (("precomputed features", "insert_features"), ("raw scans", "insert_raw")):
        r = res.get(key)
        if r:
            ins_rows.append(
                [
                    label,
                    f"{r['batches']} x {r['batch']}",
                    f"{r['kib_per_keyframe']:.0f}",
                    _f(r["median_kf_s"]),
                    _f(r["min_kf_s"]),
                    _f(r["overall_kf_s"]),
                    _f(r["body_mib_per_s"]),
                ]
            )
    ins = _table(
        ["insert", "requests", "KiB/keyframe", "kf/s median", "kf/s min", "kf/s overall", "MiB/s"],
        ins_rows,
    )
    icp = _table(
        ["map (path)", "refine", "clients", "errors", "p50 ms", "p99 ms", "QPS", "server pose"],
        [
            [
                r["path"],
                r["refine"],
                str(r["clients"]),
                str(r["errors"] + r["refused"]),
                _f(r["p50_ms"]),
                _f(r["p99_ms"]),
                f"{r['qps']:.1f}",
                _f(r["server_median_ms"].get("pose")),
            ]
            for r in res.get("icp", [])
        ],
    )
    batched = _table(
        [
            "service",
            "clients",
            "p50 ms",
            "p99 ms",
            "QPS",
            "mean batch (forward)",
            "mean batch (sgv)",
        ],
        [
            [
                r["path"],
                str(r["clients"]),
                _f(r["p50_ms"]),
                _f(r["p99_ms"]),
                f"{r['qps']:.1f}",
                _f(r.get("mean_batch_forward"), 2),
                _f(r.get("mean_batch_sgv"), 2),
            ]
            for r in res.get("batching", [])
        ],
    )
    parts = [loc, ins, icp] + ([batched] if res.get("batching") else [])
    return "\n\n".join([*parts, format_targets(res.get("targets", []))])


def format_targets(targets: list[dict[str, Any]]) -> str:
    return _table(
        ["target", "goal", "measured", "ratio", "met"],
        [
            [
                t["name"],
                t["target"],
                f"{_f(t['measured'])} {t['unit']}",
                "-" if t["ratio"] is None else f"{t['ratio']:.2f}",
                {True: "yes", False: "NO", None: "-"}[t["met"]],
            ]
            for t in targets
        ],
    )


def _table(header: list[str], rows: list[list[str]]) -> str:
    """:func:`.engine._table` (imported late: ``engine`` may import this module)."""
    from .engine import _table as table

    return table(header, rows)


def format_scaling(res: dict[str, Any]) -> str:
    """One row per map size, with ratios to the smallest size."""
    rows = res["rows"]
    if not rows:
        return "(no sizes)"
    clients = list(rows[0]["localize"])
    first = rows[0]
    header = ["keyframes"]
    for n in clients:
        header += [f"{n} cl p50 ms", f"{n} cl p99 ms", f"{n} cl QPS"]
    header += ["retrieve ms", "insert kf/s", "RSS MiB", "disk MiB", "p50 x first", "disk x first"]
    c0 = clients[0]
    p50_0 = first["localize"][c0]["p50_ms"]
    table_rows = []
    for r in rows:
        cells = [str(r["keyframes"])]
        for n in clients:
            lo = r["localize"][n]
            cells += [_f(lo["p50_ms"]), _f(lo["p99_ms"]), f"{lo['qps']:.1f}"]
        p50 = r["localize"][c0]["p50_ms"]
        cells += [
            _f(r["localize"][c0]["server_median_ms"].get("retrieve"), 2),
            _f(r["insert"]["median_kf_s"], 0),
            _f(r.get("rss_mib"), 0),
            f"{r['disk_mib']:.0f}",
            "-" if not (p50 and p50_0) else f"{p50 / p50_0:.2f}x",
            f"{r['disk_mib'] / first['disk_mib']:.1f}x" if first["disk_mib"] else "-",
        ]
        table_rows.append(cells)
    out = [_table(header, table_rows)]
    if "reload_s" in res:
        out.append(
            f"restart on {rows[-1]['keyframes']} keyframes: ready in {res['reload_s']:.1f} s "
            f"(RSS {_f(res.get('reload_rss_mib'), 0)} MiB)"
        )
    errors = sum(lo["errors"] for r in rows for lo in r["localize"].values())
    out.append(f"localize errors over all sizes: {errors}")
    return "\n\n".join(out)


FORMATTERS = {"http": format_http, "scaling": format_scaling}

#: functions the client process may run, by name
CLIENT_JOBS = frozenset({"_localize_load", "_insert_features", "_insert_scans"})


if __name__ == "__main__":
    _client_main()
