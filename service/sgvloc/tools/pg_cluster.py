"""A throwaway PostgreSQL cluster on a loopback port, from the server binaries of the
system's ``postgresql`` package (Debian: ``apt-get install postgresql``).

For the tests and ``sgvloc bench --only cluster``: ``initdb`` in a temporary folder
(trust authentication, no password), ``pg_ctl`` start and stop, a fresh database per
caller. ``initdb`` refuses to run as root: as root the cluster runs as the ``postgres``
user the package creates.
"""

from __future__ import annotations

import os
import pwd
import shutil
import signal
import socket
import subprocess
import tempfile
import time
import uuid
from pathlib import Path

PACKAGE_HINT = "install Debian's postgresql package (apt-get install -y postgresql)"


class ClusterError(RuntimeError):
    """The cluster could not be made, started or stopped."""


def find_bindir() -> Path | None:
    """The folder holding ``initdb`` and ``pg_ctl`` (newest version first), or None."""
    found = shutil.which("pg_ctl")
    if found and Path(found).with_name("initdb").exists():
        return Path(found).parent
    root = Path("/usr/lib/postgresql")
    if root.is_dir():
        for version in sorted(root.iterdir(), key=lambda p: p.name, reverse=True):
            if (version / "bin" / "initdb").exists():
                return version / "bin"
    return None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class TempCluster:
    """``with TempCluster() as pg: pg.new_database()`` gives a ``postgresql://`` URL.

    :meth:`stop` and :meth:`start` take the server down and up on the same port (for
    fault tests); the folder is removed on exit.
    """

    def __init__(self, bindir: Path | None = None) -> None:
        bindir = bindir or find_bindir()
        if bindir is None:
            raise ClusterError(f"PostgreSQL server binaries not found: {PACKAGE_HINT}")
        self.bindir = bindir
        self.port = _free_port()
        self.root = Path(tempfile.mkdtemp(prefix="sgvloc-pg-"))
        self.data = self.root / "data"
        self.log = self.root / "server.log"
        self._user: str | None = None
        if os.geteuid() == 0:  # initdb refuses root: run the server as the package's user
            try:
                pwd.getpwnam("postgres")
            except KeyError:
                raise ClusterError(
                    f"running as root needs the 'postgres' user: {PACKAGE_HINT}"
                ) from None
            self._user = "postgres"
            shutil.chown(self.root, "postgres")
            os.chmod(self.root, 0o755)

    def _run(self, *args: str, timeout: float = 60.0) -> None:
        cmd = [str(self.bindir / args[0]), *args[1:]]
        if self._user is not None:
            cmd = ["runuser", "-u", self._user, "--", *cmd]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        if done.returncode != 0:
            tail = (done.stderr or done.stdout).strip()[-2000:]
            raise ClusterError(f"{args[0]} failed ({done.returncode}): {tail}")

    def init(self) -> None:
        self._run("initdb", "-D", str(self.data), "-A", "trust", "-U", "postgres", "-E", "UTF8")
        conf = self.data / "postgresql.conf"
        with conf.open("a") as f:
            f.write(
                f"\nport = {self.port}\nlisten_addresses = '127.0.0.1'\n"
                f"unix_socket_directories = '{self.root}'\n"
                "fsync = off\nfull_page_writes = off\nmax_connections = 200\n"
            )

    def start(self) -> None:
        self._run("pg_ctl", "-D", str(self.data), "-l", str(self.log), "-w", "-t", "60", "start")

    def stop(self, mode: str = "fast") -> None:
        self._run("pg_ctl", "-D", str(self.data), "-m", mode, "-w", "-t", "60", "stop")

    def _processes(self) -> list[int]:
        """The server's process ids: the postmaster (``postmaster.pid``) and its children."""
        pid = int((self.data / "postmaster.pid").read_text().split()[0])
        pids = [pid]
        for entry in Path("/proc").iterdir():
            if entry.name.isdigit():
                try:
                    stat = (entry / "stat").read_text()
                except OSError:
                    continue
                if int(stat.rsplit(")", 1)[1].split()[1]) == pid:  # its parent
                    pids.append(int(entry.name))
        return pids

    def pause(self) -> None:
        """Freeze the server (SIGSTOP to every process of it): connections stay open and
        the kernel still takes what clients send, but nothing answers (Linux only)."""
        self._signal(signal.SIGSTOP)

    def resume(self) -> None:
        """Let a paused server go on (SIGCONT)."""
        self._signal(signal.SIGCONT)

    def _signal(self, sig: signal.Signals) -> None:
        for pid in self._processes():
            try:
                os.kill(pid, sig)
            except ProcessLookupError:  # a backend that exited since it was listed
                continue

    @property
    def url(self) -> str:
        """The cluster's ``postgres`` database."""
        return f"postgresql://postgres@127.0.0.1:{self.port}/postgres"

    def new_database(self, name: str | None = None) -> str:
        """Create an empty database; returns its URL."""
        import psycopg

        name = name or f"t_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(self.url, autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return f"postgresql://postgres@127.0.0.1:{self.port}/{name}"

    def __enter__(self) -> TempCluster:
        try:
            self.init()
            self.start()
        except BaseException:
            shutil.rmtree(self.root, ignore_errors=True)
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.stop("immediate")
        except (ClusterError, subprocess.TimeoutExpired):
            pass
        for _ in range(20):  # the server's files go with the folder
            shutil.rmtree(self.root, ignore_errors=True)
            if not self.root.exists():
                break
            time.sleep(0.1)
