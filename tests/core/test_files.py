"""Result files are written whole: the previous file or the new one, never a part."""

from __future__ import annotations

from pathlib import Path

import pytest

from sgvloc.core.files import write_text_whole, write_whole


def test_a_failed_write_leaves_the_previous_file_and_no_part(tmp_path: Path) -> None:
    path = tmp_path / "result.json"
    write_text_whole(path, '{"a": 1}')
    assert path.read_text() == '{"a": 1}'

    def half(part: Path) -> None:
        part.write_text('{"a": ')
        raise KeyboardInterrupt  # Ctrl-C in the middle of the write

    with pytest.raises(KeyboardInterrupt):
        write_whole(path, half)
    assert path.read_text() == '{"a": 1}'
    assert [p.name for p in tmp_path.iterdir()] == ["result.json"]
    write_text_whole(path, '{"a": 2}')
    assert path.read_text() == '{"a": 2}' and len(list(tmp_path.iterdir())) == 1
