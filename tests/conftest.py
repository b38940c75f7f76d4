"""Shared pytest fixtures."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

FIXTURES = Path(__file__).parent / "fixtures"


@pytest.fixture(scope="session")
def balm_mini_dir() -> Path:
    """KITTI-layout real LiDAR fixture (15 scans, see tests/fixtures/balm_mini/README.md)."""
    return FIXTURES / "balm_mini"


@pytest.fixture(scope="session")
def balm_mini_roles(balm_mini_dir: Path) -> list[tuple[int, str]]:
    """Per fixture file, in order: ``(original_index, role)``, role "database" or "query"."""
    rows = []
    for line in (balm_mini_dir / "scans.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            idx, role = line.split()
            rows.append((int(idx), role))
    return rows


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded random generator (deterministic tests)."""
    return np.random.default_rng(0)
