"""Result files written whole: a reader (or the next run) sees the previous file or the
new one, never a part, whatever stops the writer (Ctrl-C, SIGTERM, a full disk)."""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable
from pathlib import Path


def write_whole(path: str | os.PathLike[str], write: Callable[[Path], object]) -> Path:
    """``write(part)`` a file beside ``path`` (named for this process, opened with the
    umask's mode: results are read by others), then rename it onto ``path``; the part is
    removed if anything fails. Returns ``path``."""
    p = Path(path)
    part = p.with_name(f".{p.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp")
    try:
        write(part)
        os.replace(part, p)
    except BaseException:
        part.unlink(missing_ok=True)
        raise
    return p


def write_text_whole(path: str | os.PathLike[str], text: str) -> Path:
    """:func:`write_whole` of a text file."""

    def write(part: Path) -> None:
        with open(part, "x") as fh:
            fh.write(text)

    return write_whole(path, write)
