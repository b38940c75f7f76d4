"""Admission and timeouts: a full localize queue is a 429 at once, a request that waits
too long for a worker is a 503, both with Retry-After; the limits in force are reported
by ``GET /v1/config``. (Body size, points, batch and top_k: test_bad_input.py.)"""

from __future__ import annotations

import asyncio
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from conftest import Server
from svc_helpers import (
    MAX_BATCH,
    MAX_BODY_BYTES,
    MAX_POINTS,
    MAX_TOP_K,
    PRECOMPUTED,
    answer_head,
    error_of,
    post_msgpack,
    random_features,
)

from sgvloc.core.encoders import EncoderSpec
from sgvloc.server.api import create_app
from sgvloc.server.api.deps import make_pools
from sgvloc.server.settings import Settings
from sgvloc.server.threads import usable_cpus
from sgvloc_client import wire

SPEC = EncoderSpec.model_validate(PRECOMPUTED)
_MSGPACK = {"Content-Type": wire.MSGPACK}


def test_config_reports_the_limits(client: httpx.Client) -> None:
    r = client.get("/v1/config")
    assert r.status_code == 200
    cfg = r.json()
    assert cfg["limits"] == {
        "max_body_bytes": MAX_BODY_BYTES,
        "max_json_body_bytes": 8 * 1024 * 1024,
        "max_body_memory_bytes": 4 * MAX_BODY_BYTES,
        "max_points": MAX_POINTS,
        "max_keypoints": 4096,
        "max_batch": MAX_BATCH,
        "max_top_k": MAX_TOP_K,
        "max_import_bytes": 64 * 1024**3,
        "max_self_test_keyframes": 1000,
        "max_inflight_localize": 8,  # 4 x 2 workers
        "request_timeout_s": 30.0,
        "retry_after_s": 1,
        "header_timeout_s": 10.0,
        "body_timeout_s": 30.0,
        "send_timeout_s": 60.0,
        "workers": 2,
        "write_workers": 1,  # workers - 1: one is always free of map changes
        "threads_per_worker": max(1, usable_cpus() // 2),
        "spare_cores": usable_cpus(),  # a request alone may use them all
    }
    assert cfg["auth"]["enabled"] is False  # the shared test server is in development mode
    # dynamic batching is off by default on CPU
    assert cfg["batching"] == {"enabled": False, "wait_ms": 0.0, "max_size": 16}


def test_library_threads_follow_workers_and_cores() -> None:
    cpus = usable_cpus()
    assert Settings(workers=1).library_threads == cpus
    assert Settings(workers=cpus * 2).library_threads == 1  # never 0
    assert Settings(workers=8, threads_per_worker=3).library_threads == 3
    with pytest.raises(ValueError):
        Settings(threads_per_worker=0)


def test_write_workers_leave_workers_to_localize() -> None:
    assert Settings(workers=1).write_limit == 1  # nothing to keep back
    assert Settings(workers=2).write_limit == 1
    assert Settings(workers=6).write_limit == 5
    assert Settings(workers=6, write_workers=2).write_limit == 2
    with pytest.raises(ValueError, match="write_workers"):
        Settings(workers=2, write_workers=3)


def test_body_memory_holds_at_least_one_body() -> None:
    assert Settings(max_body_bytes=1 << 20).body_memory_limit == 4 << 20
    with pytest.raises(ValueError, match="max_body_memory_bytes"):
        Settings(max_body_bytes=1 << 20, max_body_memory_bytes=1 << 19)


def test_inflight_default_follows_workers() -> None:
    assert Settings(workers=3).inflight_limit == 12
    assert Settings(workers=3, max_inflight_localize=5).inflight_limit == 5
    with pytest.raises(ValueError):
        Settings(max_inflight_localize=0)


# -- in process: the admission counter and the worker pool, held by the test -------------


def _app(tmp_path: Path, **settings: object):
    app = create_app(Settings(data_dir=tmp_path, dev=True, **settings))
    # no lifespan under ASGITransport: load the (empty) data dir and make the pools here
    app.state.manager.load_all()
    make_pools(app.state, app.state.settings)
    return app


def _localize_body() -> bytes:
    return wire.packb({"features": random_features(np.random.default_rng(0))})


def test_full_localize_queue_is_429_at_once(tmp_path: Path) -> None:
    app = _app(tmp_path, max_inflight_localize=3, retry_after_s=2)
    app.state.manager.create("m", SPEC)

    async def go() -> list[httpx.Response]:
        transport = httpx.ASGITransport(app=app)
        headers = {"Content-Type": wire.MSGPACK}
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            app.state.admission.inflight = 3  # three localizations in flight
            full = await c.post("/v1/maps/m/localize", content=_localize_body(), headers=headers)
            app.state.admission.inflight = 2  # one finished
            ok = await c.post("/v1/maps/m/localize", content=_localize_body(), headers=headers)
            return [full, ok]

    full, ok = asyncio.run(go())
    assert full.status_code == 429 and full.headers["retry-after"] == "2"
    err = error_of(full)
    assert err["code"] == "overloaded" and "max_inflight_localize=3" in err["message"]
    assert ok.status_code == 200, ok.text
    assert app.state.admission.inflight == 2  # the admitted request gave its slot back


def test_waiting_too_long_for_a_worker_is_503(tmp_path: Path) -> None:
    app = _app(tmp_path, workers=1, request_timeout_s=0.2)
    app.state.manager.create("m", SPEC)

    async def go() -> list[httpx.Response]:
        transport = httpx.ASGITransport(app=app)
        headers = {"Content-Type": wire.MSGPACK}
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            busy = object()
            await app.state.cpu_limiter.acquire_on_behalf_of(busy)  # the one worker is busy
            try:
                loc = await c.post("/v1/maps/m/localize", content=_localize_body(), headers=headers)
                kf = await c.get("/v1/maps/m/keyframes/1")
            finally:
                app.state.cpu_limiter.release_on_behalf_of(busy)
            after = await c.get("/v1/maps/m/keyframes/1")
            return [loc, kf, after]

    loc, kf, after = asyncio.run(go())
    for r in (loc, kf):
        assert r.status_code == 503 and r.headers["retry-after"] == "1"
        err = error_of(r)
        assert err["code"] == "queue_timeout" and "request_timeout_s=0.2" in err["message"]
    assert after.status_code == 404  # a free worker again: the request runs
    assert app.state.admission.inflight == 0


def test_map_changes_never_take_every_worker(tmp_path: Path) -> None:
    """With two workers, map changes and long jobs run on at most one (write_workers):
    while one holds it, a localization and a read still run at once, and the next
    changes wait for it instead of taking the second worker."""
    app = _app(tmp_path, workers=2)
    app.state.manager.create("m", SPEC)
    rng = np.random.default_rng(1)
    kfs = wire.packb({"keyframes": [{"T_map_sensor": np.eye(4), "features": random_features(rng)}]})

    async def go() -> dict[str, httpx.Response]:
        transport = httpx.ASGITransport(app=app)
        out = {}
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            assert (await c.post("/v1/maps/m/keyframes", content=kfs, headers=_MSGPACK)).is_success
            job = object()  # a long map job holds the one write worker (and a worker)
            await app.state.write_limiter.acquire_on_behalf_of(job)
            await app.state.cpu_limiter.acquire_on_behalf_of(job)
            insert = asyncio.create_task(
                c.post("/v1/maps/m/keyframes", content=kfs, headers=_MSGPACK)
            )
            delete = asyncio.create_task(c.delete("/v1/maps/m/keyframes/1"))
            try:
                out["localize"] = await c.post(
                    "/v1/maps/m/localize", content=_localize_body(), headers=_MSGPACK
                )
                out["read"] = await c.get("/v1/maps/m/keyframes/1")
                await asyncio.sleep(0.2)
                out["changes_waited"] = not insert.done() and not delete.done()
            finally:
                app.state.cpu_limiter.release_on_behalf_of(job)
                app.state.write_limiter.release_on_behalf_of(job)
            out["insert"], out["delete"] = await insert, await delete
        return out

    out = asyncio.run(go())
    assert out["localize"].status_code == 200, out["localize"].text
    assert out["read"].status_code == 200, out["read"].text
    assert out["changes_waited"] is True
    assert out["insert"].status_code == 201, out["insert"].text  # the job ended: they ran
    assert out["delete"].status_code == 200, out["delete"].text
    assert app.state.write_limiter.borrowed_tokens == 0
    assert app.state.cpu_limiter.borrowed_tokens == 0


# -- a real server: a slow upload does not hold the only localize slot -------------------


@pytest.fixture(scope="module")
def one_slot_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    root = tmp_path_factory.mktemp("limits")
    srv = Server(
        data_dir=root / "data",
        log_path=root / "server.log",
        env={"SGVLOC_MAX_INFLIGHT_LOCALIZE": "1"},
    )
    srv.start()
    try:
        yield srv
    finally:
        srv.stop()


def test_a_slow_body_holds_no_slot(one_slot_server: Server) -> None:
    url = one_slot_server.url
    with httpx.Client(base_url=url, timeout=60) as c:
        assert c.post("/v1/maps", json={"name": "one", "encoder": PRECOMPUTED}).status_code == 201
        feats = random_features(np.random.default_rng(0))
        kfs = {"keyframes": [{"T_map_sensor": np.eye(4), "features": feats}]}
        assert post_msgpack(c, "/v1/maps/one/keyframes", kfs).status_code == 201
    body = _localize_body()
    release, sent = threading.Event(), threading.Event()
    slow: dict[str, httpx.Response] = {}

    def chunks() -> Iterator[bytes]:  # a client that sends its body slowly
        yield body[:10]
        sent.set()
        release.wait(60)
        yield body[10:]

    def send_slowly() -> None:
        with httpx.Client(base_url=url, timeout=120) as c:
            for _ in range(100):  # 429 if a probe below held the slot when it arrived
                slow["r"] = c.post(
                    "/v1/maps/one/localize",
                    content=chunks(),
                    headers={"Content-Type": wire.MSGPACK, "Content-Length": str(len(body))},
                )
                if slow["r"].status_code != 429:
                    return

    thread = threading.Thread(target=send_slowly)
    thread.start()
    seen = []
    try:
        assert sent.wait(60)
        with httpx.Client(base_url=url, timeout=60) as c:
            for _ in range(5):  # the slow upload holds no slot: every probe is served
                r = c.post("/v1/maps/one/localize", content=body, headers=_MSGPACK)
                seen.append(r.status_code)
    finally:
        release.set()
        thread.join(120)
    assert seen == [200] * 5, seen
    assert slow["r"].status_code == 200, slow["r"].text
    with httpx.Client(base_url=url, timeout=60) as c:  # the slot is free again
        assert c.post("/v1/maps/one/localize", content=body, headers=_MSGPACK).status_code == 200


def test_waiting_for_a_map_version_holds_no_slot(one_slot_server: Server) -> None:
    """A localize waiting for a map version this replica has not reached (up to
    catch_up_wait_s) holds no localize slot: a garbage body asking for a version far
    ahead on every connection must not lock honest vehicles out with 429s."""
    url = one_slot_server.url
    with httpx.Client(base_url=url, timeout=60) as c:
        if c.get("/v1/maps/one").status_code == 404:
            assert (
                c.post("/v1/maps", json={"name": "one", "encoder": PRECOMPUTED}).status_code == 201
            )
            feats = random_features(np.random.default_rng(0))
            kfs = {"keyframes": [{"T_map_sensor": np.eye(4), "features": feats}]}
            assert post_msgpack(c, "/v1/maps/one/keyframes", kfs).status_code == 201
    stale: list[int] = []

    def ask_the_future() -> None:
        with httpx.Client(base_url=url, timeout=60) as c:
            r = c.post(
                "/v1/maps/one/localize?min_map_version=999999999",
                content=b"x",
                headers=_MSGPACK,
            )
            stale.append(r.status_code)

    waiting = [threading.Thread(target=ask_the_future) for _ in range(3)]
    for t in waiting:
        t.start()
    try:
        seen = []
        with httpx.Client(base_url=url, timeout=60) as c:
            for _ in range(5):
                r = c.post("/v1/maps/one/localize", content=_localize_body(), headers=_MSGPACK)
                seen.append(r.status_code)
    finally:
        for t in waiting:
            t.join(60)
    assert seen == [200] * 5, seen
    assert stale == [503] * 3, stale


# -- a real server: the bodies of all requests together are bounded ---------------------


def _hold_body(port: int, length: int) -> socket.socket:
    """A client that declares a body of ``length`` bytes, sends its first bytes and waits."""
    sock = socket.create_connection(("127.0.0.1", port))
    sock.sendall(
        b"POST /v1/maps/one/localize HTTP/1.1\r\nHost: x\r\nContent-Type: application/msgpack\r\n"
        + f"Content-Length: {length}\r\n\r\n".encode()
        + b"\x80" * 10
    )
    return sock


def test_bodies_in_memory_are_bounded_over_all_requests(tmp_path: Path) -> None:
    """max_body_memory_bytes = 2 MiB with bodies of at most 1 MiB: two uploads that
    declared 1 MiB and 1 MiB - 1000 bytes leave no room, so a third body is 503 ``overloaded`` at
    once (declared) or as soon as it passes the room left (streamed without a length,
    and the connection is closed); once the holders go away, bodies are served again and
    the gauge is back to 0."""
    mib = 1 << 20
    srv = Server(
        tmp_path / "data",
        tmp_path / "server.log",
        env={
            "SGVLOC_MAX_BODY_BYTES": str(mib),
            "SGVLOC_MAX_BODY_MEMORY_BYTES": str(2 * mib),
            "SGVLOC_BODY_TIMEOUT_S": "60",
        },
    )
    srv.start()
    holders: list[socket.socket] = []
    try:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            assert c.post("/v1/maps", json={"name": "one", "encoder": PRECOMPUTED}).is_success
            feats = random_features(np.random.default_rng(0))
            kfs = {"keyframes": [{"T_map_sensor": np.eye(4), "features": feats}]}
            assert post_msgpack(c, "/v1/maps/one/keyframes", kfs).status_code == 201
            assert c.get("/v1/config").json()["limits"]["max_body_memory_bytes"] == 2 * mib
            holders = [_hold_body(srv.port, mib), _hold_body(srv.port, mib - 1000)]
            gauge = ""
            for _ in range(100):  # until the server has both requests' headers
                gauge = next(
                    line for line in c.get("/metrics").text.splitlines()
                    if line.startswith("sgvloc_body_bytes ")
                )  # fmt: skip
                if float(gauge.split()[1]) == 2 * mib - 1000:
                    break
                time.sleep(0.1)
            assert float(gauge.split()[1]) == 2 * mib - 1000, gauge
            r = c.post("/v1/maps/one/localize", content=_localize_body(), headers=_MSGPACK)
            assert r.status_code == 503 and r.headers["retry-after"] == "1", r.text
            err = error_of(r)
            assert err["code"] == "overloaded" and "max_body_memory_bytes=2097152" in err["message"]
            streamed = socket.create_connection(("127.0.0.1", srv.port))
            holders.append(streamed)
            chunk = b"\x80" * 200_000
            streamed.sendall(
                b"POST /v1/maps/one/localize HTTP/1.1\r\nHost: x\r\n"
                b"Content-Type: application/msgpack\r\nTransfer-Encoding: chunked\r\n\r\n"
                + f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n"
            )  # fmt: skip
            head = answer_head(streamed)
            assert head.startswith("http/1.1 503") and "connection: close" in head, head
            for sock in holders:
                sock.close()
            codes = []
            for _ in range(100):  # the server sees the holders go and gives their room back
                r = c.post("/v1/maps/one/localize", content=_localize_body(), headers=_MSGPACK)
                codes.append(r.status_code)
                if r.status_code == 200:
                    break
                time.sleep(0.1)
            assert codes[-1] == 200, codes
            assert "sgvloc_body_bytes 0.0" in c.get("/metrics").text
    finally:
        for sock in holders:
            sock.close()
        srv.stop()
