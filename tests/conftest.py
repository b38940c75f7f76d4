"""Shared pytest fixtures."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

FIXTURES = Path(__file__).parent / "fixtures"


class PgServer:
    """A PostgreSQL server for the tests: :meth:`new_database` gives a fresh database's
    URL; ``cluster`` is the throwaway cluster (None when SGVLOC_TEST_PG_URL names one,
    then stop/start tests skip)."""

    def __init__(self, cluster=None, url: str | None = None) -> None:
        self.cluster = cluster
        self._url = url

    def new_database(self) -> str:
        if self.cluster is not None:
            return self.cluster.new_database()
        import uuid
        from urllib.parse import urlsplit, urlunsplit

        import psycopg

        name = f"t_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(self._url, autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return urlunsplit(urlsplit(self._url)._replace(path=f"/{name}"))


@pytest.fixture(scope="session")
def postgres() -> Iterator[PgServer]:
    """A real PostgreSQL server: SGVLOC_TEST_PG_URL if set, else a throwaway cluster
    (initdb + pg_ctl on a free loopback port) from the system's postgresql package.
    Without either the test skips, saying which package to install; with
    SGVLOC_REQUIRE_PG=1 (CI) it fails instead."""
    url = os.environ.get("SGVLOC_TEST_PG_URL")
    if url:
        yield PgServer(url=url)
        return
    from sgvloc.tools.pg_cluster import PACKAGE_HINT, ClusterError, TempCluster, find_bindir

    if find_bindir() is None:
        if os.environ.get("SGVLOC_REQUIRE_PG") == "1":
            pytest.fail(f"PostgreSQL is required here: {PACKAGE_HINT}")
        pytest.skip(f"no PostgreSQL server binaries: {PACKAGE_HINT}, or set SGVLOC_TEST_PG_URL")
    try:
        cluster = TempCluster().__enter__()
    except ClusterError as exc:
        if os.environ.get("SGVLOC_REQUIRE_PG") == "1":
            raise
        pytest.skip(str(exc))
    try:
        yield PgServer(cluster)
    finally:
        cluster.__exit__(None, None, None)


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
