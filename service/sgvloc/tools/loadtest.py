"""A bounded load test of a running service on this machine (``sgvloc loadtest``).

N client threads, each with its own connection, send a mix of localize requests and
bulk inserts to one map for D seconds. Every answer is recorded; the report gives the
requests per kind, errors (anything but a 2xx, or a 429/503 with ``Retry-After``, which
are the service refusing work on purpose and are counted apart), latency p50/p99 and
throughput. Only loopback URLs are accepted: this is not a tool to load other hosts.

Requests carry precomputed features (a map of kind ``precomputed``), so the figures are
the service's own cost (HTTP, decoding, FAISS, re-ranking, SQLite commits), not the
handcrafted encoder's.

``slow_clients`` adds connections that send a localize's headers and then trickle its
body one byte every half second (never finishing it), reconnecting when the service
closes them: the normal clients' figures show whether slow uploads hold up others.
"""

from __future__ import annotations

import logging
import select
import socket
import threading
import time
import uuid
from dataclasses import asdict, dataclass, field
from typing import Any
from urllib.parse import urlparse

import httpx
import numpy as np

from sgvloc_client import wire

log = logging.getLogger(__name__)

LOOPBACK = ("127.0.0.1", "localhost", "::1")
G, N, D = 256, 256, 32  # features per keyframe: global dim, keypoints, local dim


@dataclass
class KindStats:
    """Answers of one request kind."""

    requests: int = 0
    ok: int = 0
    refused: int = 0  # 429/503 with Retry-After: deliberate
    errors: int = 0
    p50_ms: float = 0.0
    p99_ms: float = 0.0
    latencies_ms: list[float] = field(default_factory=list, repr=False)


@dataclass
class SlowStats:
    """The slow uploads of one run."""

    clients: int = 0
    connections: int = 0
    bytes_sent: int = 0
    timed_out: int = 0  # answered 408 (the service's body_timeout_s) and closed


@dataclass
class LoadResult:
    """The figures of one run."""

    url: str
    clients: int
    duration_s: float
    kinds: dict[str, KindStats]
    error_samples: list[str]
    slow: SlowStats = field(default_factory=SlowStats)

    @property
    def errors(self) -> int:
        return sum(k.errors for k in self.kinds.values())

    @property
    def requests(self) -> int:
        return sum(k.requests for k in self.kinds.values())

    @property
    def throughput(self) -> float:
        """Successful requests per second."""
        return sum(k.ok for k in self.kinds.values()) / self.duration_s

    def as_dict(self) -> dict[str, Any]:
        kinds = {
            name: {k: v for k, v in asdict(s).items() if k != "latencies_ms"}
            for name, s in self.kinds.items()
        }
        return {
            "url": self.url,
            "clients": self.clients,
            "duration_s": round(self.duration_s, 2),
            "requests": self.requests,
            "errors": self.errors,
            "throughput_rps": round(self.throughput, 2),
            "kinds": kinds,
            "slow_uploads": asdict(self.slow),
            "error_samples": self.error_samples,
        }

    def summary(self) -> str:
        lines = [
            f"{self.clients} clients for {self.duration_s:.1f} s against {self.url}: "
            f"{self.requests} requests, {self.errors} errors, "
            f"{self.throughput:.1f} successful requests/s"
        ]
        for name, s in self.kinds.items():
            lines.append(
                f"  {name:9s} {s.requests:6d} sent, {s.ok:6d} ok, {s.refused:4d} refused "
                f"(429/503), {s.errors:3d} errors, p50 {s.p50_ms:7.1f} ms, p99 {s.p99_ms:7.1f} ms"
            )
        if self.slow.clients:
            sl = self.slow
            lines.append(
                f"  slow uploads: {sl.clients} clients, {sl.connections} connections, "
                f"{sl.bytes_sent} bytes trickled, {sl.timed_out} answered 408"
            )
        lines += [f"  error: {e}" for e in self.error_samples]
        return "\n".join(lines)


def _features(rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {
        "global_descriptor": rng.normal(size=G).astype(np.float32),
        "keypoints": rng.uniform(-30, 30, size=(N, 3)).astype(np.float32),
        "local_features": rng.normal(size=(N, D)).astype(np.float32),
    }


def check_loopback(url: str) -> None:
    """Refuse URLs that are not on this machine."""
    host = urlparse(url).hostname
    if host not in LOOPBACK:
        raise ValueError(f"the load test only runs against this machine (127.0.0.1), not {host!r}")


def run_loadtest(
    url: str,
    *,
    clients: int = 16,
    duration_s: float = 60.0,
    insert_fraction: float = 0.2,
    batch: int = 4,
    seed_keyframes: int = 200,
    api_key: str | None = None,
    map_name: str | None = None,
    timeout_s: float = 60.0,
    slow_clients: int = 0,
) -> LoadResult:
    """Load ``url`` with ``clients`` threads for ``duration_s`` seconds.

    A fresh map (``precomputed``, flat index) is created and seeded with
    ``seed_keyframes`` keyframes; then each client sends, at random, a bulk insert of
    ``batch`` keyframes (fraction ``insert_fraction``) or a localize (SGV re-ranking, no
    ICP). ``slow_clients`` (at most 64) trickle bodies meanwhile (see the module
    docstring). The map is deleted at the end.
    """
    check_loopback(url)
    if clients < 1 or duration_s <= 0:
        raise ValueError("clients must be >= 1 and duration_s > 0")
    if not 0 <= slow_clients <= 64:
        raise ValueError("slow_clients must be between 0 and 64")
    headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
    name = map_name or f"loadtest-{uuid.uuid4().hex[:8]}"
    spec = {"kind": "precomputed", "name": "loadtest", "global_dim": G, "local_dim": D}
    rng = np.random.default_rng(0)
    with httpx.Client(base_url=url, headers=headers, timeout=timeout_s) as c:
        r = c.post("/v1/maps", json={"name": name, "encoder": spec})
        if r.status_code != 201:
            raise RuntimeError(f"cannot create map {name!r}: {r.status_code} {r.text}")
    # the map is deleted however the run ends (a failed seeding, an error, Ctrl-C)
    try:
        with httpx.Client(base_url=url, headers=headers, timeout=timeout_s) as c:
            eye = np.eye(4)
            for start in range(0, seed_keyframes, 10):
                kfs = [
                    {"T_map_sensor": eye, "features": _features(rng)}
                    for _ in range(min(10, seed_keyframes - start))
                ]
                r = c.post(
                    f"/v1/maps/{name}/keyframes",
                    content=wire.packb({"keyframes": kfs}),
                    headers={"Content-Type": wire.MSGPACK},
                )
                if r.status_code != 201:
                    raise RuntimeError(f"cannot seed map {name!r}: {r.status_code} {r.text}")

        kinds = {"localize": KindStats(), "insert": KindStats()}
        samples: list[str] = []
        lock = threading.Lock()
        start = time.monotonic()
        deadline = start + duration_s

        def client(i: int) -> None:
            crng = np.random.default_rng(1000 + i)
            # bodies made ahead, so the clients measure the service, not numpy
            loc_bodies = [
                wire.packb({"features": _features(crng), "refine": "none"}) for _ in range(8)
            ]
            with httpx.Client(base_url=url, headers=headers, timeout=timeout_s) as c:
                n = 0
                while time.monotonic() < deadline:
                    n += 1
                    if crng.random() < insert_fraction:
                        kind, path = "insert", f"/v1/maps/{name}/keyframes"
                        kfs = [
                            {"key": f"c{i}-{n}-{j}", "T_map_sensor": np.eye(4), "features": f}
                            for j, f in enumerate(_features(crng) for _ in range(batch))
                        ]
                        body = wire.packb({"keyframes": kfs})
                    else:
                        kind, path = "localize", f"/v1/maps/{name}/localize"
                        body = loc_bodies[n % len(loc_bodies)]
                    t0 = time.perf_counter()
                    try:
                        r = c.post(path, content=body, headers={"Content-Type": wire.MSGPACK})
                        retry = "retry-after" in r.headers
                        status, text = r.status_code, r.text[:200]
                    except httpx.TransportError as exc:
                        status, text, retry = 0, repr(exc), False
                    ms = (time.perf_counter() - t0) * 1e3
                    with lock:
                        s = kinds[kind]
                        s.requests += 1
                        if 200 <= status < 300:
                            s.ok += 1
                            s.latencies_ms.append(ms)
                        elif status in (429, 503) and retry:
                            s.refused += 1
                        else:
                            s.errors += 1
                            if len(samples) < 5:
                                samples.append(f"{kind} {status}: {text}")
                    if status in (429, 503):
                        time.sleep(0.05)

        slow = SlowStats(clients=slow_clients)
        parsed = urlparse(url)
        auth = f"Authorization: Bearer {api_key}\r\n" if api_key else ""
        slow_head = (
            f"POST /v1/maps/{name}/localize HTTP/1.1\r\nHost: {parsed.hostname}\r\n{auth}"
            "Content-Type: application/json\r\nContent-Length: 100000\r\n\r\n"
        ).encode()

        def slow_client() -> None:
            while time.monotonic() < deadline:
                try:
                    with socket.create_connection((parsed.hostname, parsed.port or 80), 5) as sock:
                        sock.sendall(slow_head)
                        with lock:
                            slow.connections += 1
                        while time.monotonic() < deadline:
                            readable, _, _ = select.select([sock], [], [], 0.5)
                            if readable:  # the service answered (408) or closed
                                if sock.recv(4096).startswith(b"HTTP/1.1 408"):
                                    with lock:
                                        slow.timed_out += 1
                                break
                            sock.sendall(b" ")
                            with lock:
                                slow.bytes_sent += 1
                except OSError:
                    time.sleep(0.5)

        threads = [threading.Thread(target=client, args=(i,), daemon=True) for i in range(clients)]
        threads += [threading.Thread(target=slow_client, daemon=True) for _ in range(slow_clients)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(duration_s + timeout_s + 30)
        elapsed = time.monotonic() - start
        for s in kinds.values():
            if s.latencies_ms:
                s.p50_ms = round(float(np.percentile(s.latencies_ms, 50)), 1)
                s.p99_ms = round(float(np.percentile(s.latencies_ms, 99)), 1)
        return LoadResult(url, clients, elapsed, kinds, samples, slow)
    finally:
        try:
            with httpx.Client(base_url=url, headers=headers, timeout=timeout_s) as c:
                r = c.delete(f"/v1/maps/{name}")
            left = None if r.status_code in (204, 404) else f"HTTP {r.status_code}"
        except httpx.HTTPError as exc:
            left = type(exc).__name__
        if left is not None:  # deleting a map takes an admin key; say what is left behind
            log.warning(
                "the load test's map %r is left on the service (%s deleting it): delete it "
                "with an admin key (DELETE /v1/maps/%s)",
                name,
                left,
                name,
            )


def run_loadtest_local(*, workers: int = 2, **kwargs: Any) -> LoadResult:
    """:func:`run_loadtest` against a service started for the run (``serve --dev`` on
    127.0.0.1, a temporary data directory, ``workers`` threads), stopped afterwards."""
    from .service_process import temporary_service

    with temporary_service(None, "loadtest", workers, {}) as srv:
        return run_loadtest(srv.url, **kwargs)
