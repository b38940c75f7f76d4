"""The service under test: a real ``sgvloc serve`` process (uvicorn) on 127.0.0.1.

One server is shared by the whole session (start-up imports torch and Open3D, which
takes seconds); ``test_restart`` restarts it on the same data directory and port. Limits
are lowered through ``SGVLOC_*`` variables so the limit tests send small bodies. The
shared server runs in development mode (``SGVLOC_DEV=1``: no keys); tests about access
control and admission start their own :class:`Server` with a keys file or other ``env``.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest
from svc_helpers import (
    MAX_BATCH,
    MAX_BODY_BYTES,
    MAX_POINTS,
    MAX_TOP_K,
    BalmMap,
    post_msgpack,
)

from sgvloc.core.sequence import KittiSequence

STARTUP_TIMEOUT_S = 120.0


def free_port() -> int:
    """A TCP port nobody listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Server:
    """A ``python -m sgvloc.cli serve`` subprocess; its output goes to ``log_path``."""

    data_dir: Path
    log_path: Path
    port: int = field(default_factory=free_port)
    proc: subprocess.Popen | None = None
    #: extra SGVLOC_* variables; without SGVLOC_KEYS_FILE the server runs with SGVLOC_DEV=1
    env: dict[str, str] = field(default_factory=dict)
    workers: int = 2

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> None:
        env = dict(
            os.environ,
            SGVLOC_MAX_BODY_BYTES=str(MAX_BODY_BYTES),
            SGVLOC_MAX_POINTS=str(MAX_POINTS),
            SGVLOC_MAX_BATCH=str(MAX_BATCH),
            SGVLOC_MAX_TOP_K=str(MAX_TOP_K),
        )
        env.pop("SGVLOC_KEYS_FILE", None)
        env.pop("SGVLOC_DEV", None)
        if "SGVLOC_KEYS_FILE" not in self.env:
            env["SGVLOC_DEV"] = "1"
        env.update(self.env)
        cmd = [
            sys.executable,
            "-m",
            "sgvloc.cli",
            "serve",
            "--host",
            "127.0.0.1",
            "--port",
            str(self.port),
            "--data-dir",
            str(self.data_dir),
            "--workers",
            str(self.workers),
        ]
        with self.log_path.open("a") as log:
            self.proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"the service exited at start-up:\n{self.log()}")
            try:  # /readyz is open unless SGVLOC_READYZ_AUTH=viewer (then 401 = up);
                # "degraded" (503): up, with map folders that failed to load
                r = httpx.get(f"{self.url}/readyz", timeout=2.0)
                if r.status_code in (200, 401) or r.json().get("status") == "degraded":
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        self.stop()
        raise RuntimeError(f"the service was not ready in {STARTUP_TIMEOUT_S} s:\n{self.log()}")

    def stop(self) -> int | None:
        """Stop with SIGTERM (graceful: snapshots are saved); returns the exit code."""
        if self.proc is None or self.proc.poll() is not None:
            return None if self.proc is None else self.proc.returncode
        self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait(timeout=10)

    def kill(self) -> None:
        """SIGKILL: no shutdown code runs (no snapshot saved, nothing flushed)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(timeout=30)

    def restart(self) -> None:
        self.stop()
        self.start()

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """The shared service process, with a temporary data directory."""
    root = tmp_path_factory.mktemp("service")
    srv = Server(data_dir=root / "data", log_path=root / "server.log")
    srv.start()
    try:
        yield srv
    finally:
        srv.stop()


@pytest.fixture
def client(server: Server) -> Iterator[httpx.Client]:
    """An HTTP client for the shared service (JSON by default)."""
    with httpx.Client(base_url=server.url, timeout=120.0) as c:
        yield c


# -- maps shared by several test modules ---------------------------------------------------


@pytest.fixture(scope="session")
def balm_map(server: Server, balm_mini_dir: Path, balm_mini_roles: list) -> BalmMap:
    """Create map ``balm`` (handcrafted encoder) and bulk-insert the database scans as
    MessagePack; each keyframe carries a key and metadata."""
    seq = KittiSequence(balm_mini_dir)
    db = [i for i, (_, role) in enumerate(balm_mini_roles) if role == "database"]
    queries = [i for i, (_, role) in enumerate(balm_mini_roles) if role == "query"]
    with httpx.Client(base_url=server.url, timeout=300.0) as c:
        r = c.post("/v1/maps", json={"name": "balm", "encoder": {"kind": "handcrafted"}})
        assert r.status_code == 201, r.text
        keyframes = []
        for i in db:
            frame = seq[i]
            keyframes.append(
                {
                    "key": f"balm/{balm_mini_roles[i][0]}",
                    "T_map_sensor": frame.T_world_sensor,
                    "points": frame.scan().xyzi(),
                    "metadata": {"timestamp": frame.time, "sequence": "balm_mini"},
                }
            )
        r = post_msgpack(c, "/v1/maps/balm/keyframes", {"keyframes": keyframes})
        assert r.status_code == 201, r.text
        body = r.json()
    assert body["created"] == [True] * len(db)
    return BalmMap(
        "balm", dict(zip(db, body["ids"], strict=True)), body["map_version"], queries, seq
    )
