"""Headless chromium (Debian's package) for the tests of pages a person looks at."""

from __future__ import annotations

import shutil
import subprocess
import tempfile

import pytest

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def chromium(url: str, *args: str, timeout: float = 180) -> str:
    """Run headless chromium on ``url`` with ``args`` (``--dump-dom``, ``--screenshot``),
    letting scripts run for 20 s of virtual time; it can reach 127.0.0.1 and nothing else
    (every other host name resolves to nothing). Returns its standard output."""
    if CHROMIUM is None:
        pytest.fail("Debian's chromium is not installed (README, Install)")
    with tempfile.TemporaryDirectory() as profile:
        run = subprocess.run(
            [
                CHROMIUM,
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-quic",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                f"--user-data-dir={profile}",
                "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
                "--virtual-time-budget=20000",
                *args,
                url,
            ],
            capture_output=True,
            text=True,
            timeout=timeout,
        )
    assert run.returncode == 0, run.stderr[-2000:]
    return run.stdout


def render(url: str) -> str:
    """The DOM of ``url`` after its scripts ran."""
    return chromium(url, "--dump-dom")
