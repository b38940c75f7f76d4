"""The README's Python example runs as written (from the repository root)."""

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_python_api_example_runs():
    readme = (ROOT / "README.md").read_text()
    section = readme.split("## Python API", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("NUMBA_", "PYTHONWARN"))}
    out = subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    assert "Warning" not in out.stderr, out.stderr  # no library noise on a plain run
    assert out.stdout.startswith("True"), out.stdout
    error_m = float(re.search(r"error \(m\): ([0-9.]+)", out.stdout).group(1))
    assert error_m < 2.0
