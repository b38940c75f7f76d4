"""The SDK over several base URLs: failover on refused connections and 503 answers, with
the idempotency rules of single-URL retries. The good replica is a real service; the
"busy" one is a real HTTP server on loopback that answers every request with 503."""

from __future__ import annotations

import asyncio
import itertools
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest

from sgvloc_client import AsyncClient, Client, TransportError
from sgvloc_client._errors import APIError


class _Busy(BaseHTTPRequestHandler):
    hits = 0

    def _answer(self) -> None:
        type(self).hits += 1
        length = int(self.headers.get("Content-Length") or 0)
        self.rfile.read(length)
        body = b'{"error": {"code": "stale", "message": "behind", "field": null}}'
        self.send_response(503)
        self.send_header("Content-Type", "application/json")
        self.send_header("Retry-After", "1")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    do_GET = do_POST = do_DELETE = _answer

    def log_message(self, *args: object) -> None:
        pass


@pytest.fixture
def busy_url() -> Iterator[str]:
    _Busy.hits = 0
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Busy)
    t = threading.Thread(target=server.serve_forever, daemon=True)
    t.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


def test_a_503_moves_a_safe_call_to_the_next_replica(service_url: str, busy_url: str) -> None:
    with Client([busy_url, service_url], retries=2) as c:
        for _ in range(4):  # whichever replica a call starts on, it ends on the good one
            assert c.health() == {"status": "ok"}
    assert 1 <= _Busy.hits <= 4


def test_a_503_is_not_resent_for_an_unsafe_call(service_url: str, busy_url: str) -> None:
    with Client([busy_url, service_url], retries=2) as c:
        c._turn = iter([0])  # start on the busy replica  # type: ignore[assignment]
        with pytest.raises(APIError) as err:
            c.create_map("never")  # not safe to resend: the 503 is the answer
    assert err.value.status == 503 and _Busy.hits == 1


def test_a_refused_connection_moves_any_call(service_url: str, closed_url: str) -> None:
    with Client([closed_url, service_url], retries=1) as c:
        c._turn = itertools.count(0)  # start on the closed one
        info = c.create_map("failover-created")  # nothing was sent to the closed one
        assert info.name == "failover-created"
        # the failed URL is skipped by the next calls for a while, even on its turn
        c._turn = itertools.count(0)
        assert c._pick() == 1
        c.delete_map("failover-created")


def test_a_refused_connection_moves_an_export_and_an_import(
    service_url: str, closed_url: str, tmp_path: Path
) -> None:
    """Streamed calls fail over too when nothing was sent: the export lands whole, and
    the import's file is read again from its start on the next replica."""
    feats = {
        "global_descriptor": np.ones(16, np.float32),
        "keypoints": np.random.default_rng(0).uniform(-5, 5, (20, 3)).astype(np.float32),
        "local_features": np.ones((20, 8), np.float32),
    }
    spec = {"kind": "precomputed", "name": "egonn", "global_dim": 16, "local_dim": 8}
    with Client(service_url) as c:
        c.create_map("moved-archive", encoder=spec)
        c.insert_keyframes("moved-archive", [{"T_map_sensor": np.eye(4), "features": feats}])
    archive = tmp_path / "m.tar"
    with Client([closed_url, service_url], retries=1) as c:
        c._turn = itertools.count(0)  # start on the closed one
        size = c.export_map("moved-archive", archive)
        assert size == archive.stat().st_size > 0
        c._down_until = [0.0, 0.0]  # forget the failure: start on the closed one again
        c._turn = itertools.count(0)
        info = c.import_map(archive, "moved-archive-2")
        assert info.keyframes == 1
        c.delete_map("moved-archive")
        c.delete_map("moved-archive-2")

    async def run() -> int:
        async with AsyncClient([closed_url, service_url], retries=1) as c:
            c._turn = itertools.count(0)
            return await c.export_map("moved-archive-async", tmp_path / "a.tar")

    with Client(service_url) as c:
        c.import_map(archive, "moved-archive-async")
    assert asyncio.run(run()) == (tmp_path / "a.tar").stat().st_size
    with Client(closed_url, retries=0) as c, pytest.raises(TransportError):
        c.export_map("moved-archive-async", tmp_path / "b.tar")
    assert not (tmp_path / "b.tar").exists()


def test_no_retries_left_raises(closed_url: str) -> None:
    with Client([closed_url, closed_url], retries=0) as c, pytest.raises(TransportError):
        c.health()


def test_async_client_fails_over(service_url: str, busy_url: str, closed_url: str) -> None:
    async def run() -> None:
        async with AsyncClient([closed_url, busy_url, service_url], retries=3) as c:
            for _ in range(3):
                assert await c.health() == {"status": "ok"}

    asyncio.run(run())


def test_total_timeout_bounds_a_call_over_its_tries() -> None:
    """A server that takes connections and never answers: with timeout=1 each try ends
    after a second, and retries=10 would make it eleven; total_timeout=2.5 stops the
    call after the tries that fit (at most three) with an error naming it."""
    import socket

    silent = socket.socket()
    silent.bind(("127.0.0.1", 0))
    silent.listen(32)
    accepted: list[socket.socket] = []

    def take() -> None:
        while True:
            try:
                conn, _ = silent.accept()
            except OSError:
                return
            accepted.append(conn)  # held open, never answered

    threading.Thread(target=take, daemon=True).start()
    url = f"http://127.0.0.1:{silent.getsockname()[1]}"
    try:
        with Client(url, timeout=1.0, retries=10, backoff=0.2, total_timeout=2.5) as c:
            with pytest.raises(TransportError, match="total_timeout=2.5 s") as info:
                c.get_map("m")
        assert info.value.request_id
        assert 1 <= len(accepted) <= 3, len(accepted)

        async def run() -> None:
            async with AsyncClient(url, timeout=1.0, retries=10, total_timeout=1.5) as c:
                await c.get_map("m")

        before = len(accepted)
        with pytest.raises(TransportError, match="total_timeout=1.5 s"):
            asyncio.run(run())
        assert 1 <= len(accepted) - before <= 2
    finally:
        silent.close()
        for conn in accepted:
            conn.close()
    with pytest.raises(ValueError, match="total_timeout"):
        Client(url, total_timeout=0)
