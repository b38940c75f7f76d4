"""The package's rooms import downwards only: tools -> server -> core.

Read from the source (every ``import`` statement, including those inside functions), so a
late import that only runs on some code path is caught too.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "service" / "sgvloc"

#: room -> module prefixes it must not import
FORBIDDEN = {
    "core": ("sgvloc.server", "sgvloc.tools", "sgvloc.cli", "fastapi", "uvicorn", "starlette"),
    "server": ("sgvloc.tools", "sgvloc.cli"),
}


def _imports(path: Path) -> list[tuple[int, str]]:
    """``(line, absolute module)`` of every import in ``path``."""
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    package = parts if parts[-1] == "__init__" else parts[:-1]
    package = [p for p in package if p != "__init__"]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            found.append((node.lineno, module))
            found += [(node.lineno, f"{module}.{alias.name}") for alias in node.names]
    return found


def _violations(room: str) -> list[str]:
    bad = []
    for path in sorted((PACKAGE / room).rglob("*.py")):
        for line, module in _imports(path):
            for prefix in FORBIDDEN[room]:
                if module == prefix or module.startswith(prefix + "."):
                    bad.append(f"{path.relative_to(PACKAGE)}:{line} imports {module}")
    return bad


@pytest.mark.parametrize("room", sorted(FORBIDDEN))
def test_rooms_import_downwards_only(room):
    assert (PACKAGE / room / "__init__.py").is_file()
    assert _violations(room) == []


def test_the_check_sees_relative_and_late_imports(tmp_path, monkeypatch):
    """The checker itself: a relative import and one inside a function are both found."""
    fake = tmp_path / "sgvloc"
    (fake / "core").mkdir(parents=True)
    (fake / "core" / "__init__.py").write_text("")
    (fake / "core" / "x.py").write_text(
        "from ..server import maps\n\ndef f():\n    import fastapi\n"
    )
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", fake)
    assert _violations("core") == [
        "core/x.py:1 imports sgvloc.server",
        "core/x.py:1 imports sgvloc.server.maps",
        "core/x.py:4 imports fastapi",
    ]


def test_every_room_says_what_lives_there():
    for room in ("core", "server", "tools"):
        doc = ast.get_docstring(ast.parse((PACKAGE / room / "__init__.py").read_text()))
        assert doc, f"sgvloc/{room}/__init__.py has no docstring"
