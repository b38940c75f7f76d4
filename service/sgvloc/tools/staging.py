"""Outputs written aside and moved into place at the end, so that a run that fails or is
interrupted leaves the previous outputs as they were (``--overwrite`` included)."""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

log = logging.getLogger(__name__)


@contextlib.contextmanager
def staged(out: Path, names: tuple[str, ...]) -> Iterator[Path]:
    """A new folder inside ``out`` to write ``names`` (files or folders) into. When the
    block ends without an error the previous ``names`` of ``out`` are moved aside, the new
    ones moved in (renames in one file system), and the old ones removed; if a move fails
    the old ones are put back. On an error or an interruption in the block the staging
    folder is removed and ``out`` is unchanged. A name in ``out`` that is a link is
    replaced by the new folder or file (what it pointed to is left as it was)."""
    out.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=".staging-", dir=out))
    try:
        yield stage
        trash = out / f".replaced-{uuid.uuid4().hex[:8]}"
        trash.mkdir()
        moved: list[str] = []
        placed: list[str] = []
        try:
            for name in names:
                old = out / name
                if old.is_symlink() or old.exists():
                    if old.is_symlink():
                        log.warning(
                            "%s was a link to %s: the new output replaces the link",
                            old,
                            os.readlink(old),
                        )
                    old.rename(trash / name)
                    moved.append(name)
            for name in names:
                if (stage / name).exists():
                    (stage / name).rename(out / name)
                    placed.append(name)
        except BaseException:
            for name in placed:  # undo: the new ones out, the old ones back
                with contextlib.suppress(OSError):
                    (out / name).rename(stage / name)
            for name in moved:
                with contextlib.suppress(OSError):
                    (trash / name).rename(out / name)
            raise
        finally:
            shutil.rmtree(trash, ignore_errors=True)  # links in it are unlinked, not followed
    finally:
        shutil.rmtree(stage, ignore_errors=True)
