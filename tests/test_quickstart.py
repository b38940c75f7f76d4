"""The README's quick start runs as written (on a free port and a temporary data dir)."""

import re
import shutil
import socket
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.skipif(shutil.which("curl") is None, reason="needs curl")
def test_quick_start_runs_as_written(tmp_path):
    readme = (ROOT / "README.md").read_text()
    section = readme.split("## Quick start", 1)[1]
    script = re.search(r"```bash\n(.*?)```", section, re.S).group(1)
    port = str(_free_port())
    script = (
        script.replace("8470", port)
        .replace("./data", str(tmp_path / "data"))
        .replace("query.json", str(tmp_path / "query.json"))
    )
    # stop the server even if a step fails
    script = "set -e\ntrap 'kill %1 2>/dev/null || true' EXIT\n" + script
    out = subprocess.run(
        ["bash", "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert "localized: True" in out.stdout, out.stdout
    # the curl answer: localized, keyframe id, translation
    assert any(line.startswith("True ") for line in out.stdout.splitlines()), out.stdout
