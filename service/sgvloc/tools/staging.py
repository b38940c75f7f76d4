"""Outputs written aside and moved into place at the end, so that a run that fails or is
interrupted leaves the previous outputs as they were (``--overwrite`` included)."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def staged(out: Path, names: tuple[str, ...]) -> Iterator[Path]:
    """A new folder inside ``out`` to write ``names`` (files or folders) into; when the
    block ends without an error each of them replaces its namesake in ``out`` (a folder is
    moved aside, then removed). On an error or an interruption the staging folder is
    removed and ``out`` is unchanged."""
    out.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=".staging-", dir=out))
    try:
        yield stage
        trash = out / f".replaced-{uuid.uuid4().hex[:8]}"
        trash.mkdir()
        for name in names:
            new, old = stage / name, out / name
            if not new.exists():
                continue
            if old.is_dir() and not old.is_symlink():
                old.rename(trash / name)  # a folder cannot be replaced in one step
            os.replace(new, old)
        shutil.rmtree(trash, ignore_errors=True)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
