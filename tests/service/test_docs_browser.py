"""/docs and /redoc render in a real headless browser (Debian's chromium) with no network:
every script, style and font comes from the service itself."""

from __future__ import annotations

import re

import httpx
from browser import render


def test_swagger_ui_renders_the_operations_offline(server) -> None:
    html = httpx.get(f"{server.url}/docs").text
    # nothing on the page is fetched from anywhere but the service
    assert not re.search(r"""(src|href)=["']?(https?:)?//""", html), html
    dom = render(f"{server.url}/docs")
    # Swagger UI drew the operations from /openapi.json: the localize route is on the page
    assert 'class="swagger-ui' in dom, dom[:2000]
    assert "/v1/maps/{map}/localize" in dom, dom[:2000]
    assert dom.count('class="opblock ') >= 10


def test_redoc_renders_offline(server) -> None:
    html = httpx.get(f"{server.url}/redoc").text
    assert not re.search(r"""(src|href)=["']?(https?:)?//""", html), html
    dom = render(f"{server.url}/redoc")
    assert "/v1/maps/{map}/localize" in dom, dom[:2000]


def test_api_docs_can_be_switched_off(tmp_path) -> None:
    from conftest import Server

    srv = Server(tmp_path / "data", tmp_path / "server.log", env={"SGVLOC_API_DOCS": "off"})
    srv.start()
    try:
        for path in ("/openapi.json", "/docs", "/redoc", "/static-offline-docs/swagger-ui.css"):
            assert httpx.get(f"{srv.url}{path}").status_code == 404, path
        assert httpx.get(f"{srv.url}/v1/maps").status_code == 200  # the API itself is served
    finally:
        srv.stop()
