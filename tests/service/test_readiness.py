"""Before the maps are loaded: alive, not ready, map routes 503 (in process, no lifespan)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import httpx

from sgvloc.server.api import create_app
from sgvloc.server.maps import LOCK_NAME
from sgvloc.server.settings import Settings


def test_not_ready_until_maps_are_loaded(tmp_path: Path) -> None:
    # httpx.ASGITransport does not run the lifespan, so the maps are never loaded here
    app = create_app(Settings(data_dir=tmp_path, dev=True))

    async def probe() -> list[httpx.Response]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as c:
            return [
                await c.get("/healthz"),
                await c.get("/readyz"),
                await c.get("/v1/maps"),
                await c.post("/v1/maps", json={"name": "a"}),
            ]

    health, ready, maps, create = asyncio.run(probe())
    assert health.status_code == 200 and health.json() == {"status": "ok"}
    assert ready.status_code == 503 and ready.json()["status"] == "loading"
    for r in (maps, create):
        assert r.status_code == 503
        assert r.json()["error"]["code"] == "unavailable"
    # nothing was created: the maps folder holds only the lock taken at start-up
    assert [p.name for p in (tmp_path / "maps").iterdir()] == [LOCK_NAME]


def test_a_failed_load_is_failed_not_loading(tmp_path: Path) -> None:
    """A load that failed as a whole (the process is stopping) is not 'loading'."""
    app = create_app(Settings(data_dir=tmp_path, dev=True))
    app.state.manager.load_error = "the store's schema is version 2, newer than ..."

    async def probe() -> httpx.Response:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as c:
            return await c.get("/readyz")

    ready = asyncio.run(probe())
    assert ready.status_code == 503 and ready.json()["status"] == "failed"
    app.state.manager.close()


def test_open_routes_name_the_development_caller(tmp_path: Path, caplog) -> None:
    """The access line's key_name: 'development' on every route with --dev (the probes
    said so, the status page said 'anonymous')."""
    import logging

    app = create_app(Settings(data_dir=tmp_path, dev=True))

    async def probe() -> None:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as c:
            assert (await c.get("/ui")).status_code == 200
            assert (await c.get("/healthz")).status_code == 200

    with caplog.at_level(logging.DEBUG, logger="sgvloc.access"):
        asyncio.run(probe())
    names = {r.route: r.key_name for r in caplog.records if r.name == "sgvloc.access"}
    assert names == {"/ui": "development", "/healthz": "development"}, names
    app.state.manager.close()
