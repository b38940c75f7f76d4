"""A real sgvloc service in a subprocess for the SDK tests.

The sync client cannot talk to the app in-process (``httpx.ASGITransport`` is async
only), so the tests run ``sgvloc serve`` on a free local port, as a user would.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path

import httpx
import pytest

STARTUP_TIMEOUT_S = 90.0


def free_port() -> int:
    """A TCP port nobody listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def running_service(data_dir: Path, *args: str) -> Iterator[str]:
    """Run ``sgvloc serve --data-dir <data_dir>`` on a free port; yields its base URL
    once the service is ready.

    Extra ``args`` go after ``serve``; ``--host``/``--port`` are added unless given.
    """
    port = free_port()
    argv = list(args)
    if "--host" not in argv:
        argv += ["--host", "127.0.0.1"]
    if "--port" not in argv:
        argv += ["--port", str(port)]
    else:
        port = int(argv[argv.index("--port") + 1])
    cmd = [
        sys.executable,
        "-c",
        "import sys; from sgvloc.cli import main; sys.argv[0] = 'sgvloc'; sys.exit(main())",
        "serve",
        "--data-dir",
        str(data_dir),
        *argv,
    ]
    log_path = data_dir.parent / f"service-{port}.log"
    env = {**os.environ, "SGVLOC_LOG_LEVEL": "warning", "OMP_NUM_THREADS": "1"}
    if "--keys-file" not in argv and "SGVLOC_KEYS_FILE" not in os.environ:
        env["SGVLOC_DEV"] = "1"  # development mode: no API keys
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while True:
            if proc.poll() is not None:
                raise RuntimeError(
                    f"sgvloc serve exited with {proc.returncode}:\n{log_path.read_text()[-4000:]}"
                )
            try:  # up = every map loaded, or tried (degraded: some failed to load)
                r = httpx.get(f"{url}/readyz", timeout=1.0)
                if r.status_code == 200 or r.json().get("status") == "degraded":
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"sgvloc serve not up after {STARTUP_TIMEOUT_S} s")
            time.sleep(0.2)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.fixture(scope="session")
def start_service() -> Callable[..., AbstractContextManager[str]]:
    """:func:`running_service`, for tests that need a service on their own data directory."""
    return running_service


@pytest.fixture
def closed_url() -> str:
    """A local URL where nothing listens (connections are refused)."""
    return f"http://127.0.0.1:{free_port()}"


@pytest.fixture(scope="session")
def service_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """Base URL of a service shared by the client tests (each test uses its own maps)."""
    data_dir = tmp_path_factory.mktemp("sgvloc-client") / "data"
    data_dir.mkdir()
    with running_service(data_dir) as url:
        yield url
