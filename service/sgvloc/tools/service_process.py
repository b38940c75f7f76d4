"""A local ``sgvloc serve --dev`` as a subprocess, for the commands that load a service
(``sgvloc bench`` http/scaling sections, ``sgvloc loadtest``)."""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx

log = logging.getLogger(__name__)


def exit_on_sigterm() -> None:
    """SIGTERM (``timeout``, a CI cancel, ``kill``) ends the command as Ctrl-C does, through
    its ``finally`` blocks: a service, database cluster or folder it started is removed
    (the default action ends Python at once and leaves them behind)."""

    def stop(signum: int, _frame: object) -> None:
        raise SystemExit(128 + signum)

    with contextlib.suppress(ValueError):  # not the main thread: leave the default
        signal.signal(signal.SIGTERM, stop)


STARTUP_TIMEOUT_S = 300.0


def free_port() -> int:
    """A TCP port of 127.0.0.1 that nobody listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServiceProcess:
    """``python -m sgvloc.cli serve --dev`` on 127.0.0.1 as a subprocess (a context manager).

    ``SGVLOC_*`` variables of the caller's environment are dropped, so the service runs
    with its defaults plus ``env`` (with ``dev=False``, ``env`` names the keys file).
    Output goes to ``log_path``. :meth:`stop` sends SIGTERM (graceful: snapshots saved)
    and waits; SIGKILL if it does not exit in ``stop_timeout_s``.
    """

    def __init__(
        self,
        data_dir: Path,
        log_path: Path,
        *,
        workers: int = 2,
        env: dict[str, str] | None = None,
        stop_timeout_s: float = 120.0,
        dev: bool = True,
    ) -> None:
        self.data_dir = Path(data_dir)
        self.log_path = Path(log_path)
        self.workers = workers
        self.env = dict(env or {})
        self.stop_timeout_s = stop_timeout_s
        self.dev = dev
        self.port = free_port()
        self.proc: subprocess.Popen | None = None
        self.pids: list[int] = []  # every process started (a restart starts a new one)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def pid(self) -> int | None:
        return None if self.proc is None else self.proc.pid

    def start(self, timeout_s: float = STARTUP_TIMEOUT_S) -> float:
        """Start and wait until ``/readyz`` answers 200; returns the seconds that took."""
        env = {k: v for k, v in os.environ.items() if not k.startswith("SGVLOC_")}
        env.update({"SGVLOC_LOG_LEVEL": "warning", **self.env})
        cmd = [sys.executable, "-m", "sgvloc.cli", "serve", "--host", "127.0.0.1"]
        cmd += ["--dev"] if self.dev else []
        cmd += ["--port", str(self.port), "--data-dir", str(self.data_dir)]
        cmd += ["--workers", str(self.workers)]
        t0 = time.monotonic()
        with self.log_path.open("ab") as out:
            self.proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env)
        self.pids.append(self.proc.pid)
        try:
            while True:
                if self.proc.poll() is not None:
                    raise RuntimeError(
                        f"the service exited at start-up (code {self.proc.returncode}):\n"
                        + self.log_tail()
                    )
                try:
                    if httpx.get(f"{self.url}/readyz", timeout=2.0).status_code == 200:
                        return time.monotonic() - t0
                except httpx.TransportError:
                    pass
                if time.monotonic() - t0 > timeout_s:
                    raise RuntimeError(
                        f"the service was not ready within {timeout_s:.0f} s:\n" + self.log_tail()
                    )
                time.sleep(0.2)
        except BaseException:
            self.stop()
            raise

    def stop(self) -> int | None:
        """SIGTERM, wait, SIGKILL past the timeout; returns the exit code (None if never run)."""
        proc = self.proc
        if proc is None:
            return None
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=self.stop_timeout_s)
            except subprocess.TimeoutExpired:
                log.warning("the service did not stop within %.0f s: killed", self.stop_timeout_s)
                proc.kill()
                proc.wait(timeout=30)
        return proc.returncode

    def restart(self) -> float:
        """Stop, then start again on the same data directory and port; seconds to ready."""
        self.stop()
        return self.start()

    def memory_mib(self) -> dict[str, float]:
        """Resident set size now and its high-water mark (``/proc``; Linux), MiB."""
        out: dict[str, float] = {}
        if self.proc is None:
            return out
        try:
            for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
                key, _, value = line.partition(":")
                if key in ("VmRSS", "VmHWM"):
                    out["rss_mib" if key == "VmRSS" else "peak_rss_mib"] = (
                        int(value.split()[0]) / 1024
                    )
        except OSError:
            pass
        return out

    def map_disk_mib(self, name: str) -> float:
        """Size of a map's folder (SQLite database, WAL, FAISS snapshot), MiB."""
        folder = self.data_dir / "maps" / name
        return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) / 2**20

    def log_tail(self, chars: int = 4000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-chars:]
        except OSError:
            return "(no log)"

    def __enter__(self) -> ServiceProcess:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


@contextlib.contextmanager
def temporary_service(
    work_dir: Path | None, prefix: str, workers: int, env: dict[str, str]
) -> Iterator[ServiceProcess]:
    """A started service on a fresh data directory, removed afterwards."""
    root = Path(tempfile.mkdtemp(prefix=f"sgvloc-{prefix}-", dir=work_dir))
    srv = ServiceProcess(root / "data", root / "server.log", workers=workers, env=env)
    try:
        srv.start()
        yield srv
    finally:
        srv.stop()
        shutil.rmtree(root, ignore_errors=True)


def start_side_by_side(servers: list) -> list[float]:
    """Start several services at once (each ``start()`` waits for its ``/readyz``);
    the seconds each took. The first failure is raised once all have returned."""
    took: list[float] = [0.0] * len(servers)
    errors: list[BaseException] = []

    def start(k: int) -> None:
        try:
            took[k] = servers[k].start() or 0.0
        except BaseException as exc:  # re-raised below
            errors.append(exc)

    threads = [threading.Thread(target=start, args=(k,)) for k in range(len(servers))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]
    return took
