"""The status page: ``/ui`` and its script and style, shipped in the package.

The files hold no data and need no key: the page asks the operator for one, keeps it in
the browser's session storage and calls the JSON API with it (viewer role). Every file
is sent with a strict Content-Security-Policy: scripts, styles and requests only from
this service, no inline script, no framing.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

from fastapi import APIRouter, Response
from fastapi.responses import RedirectResponse

from ..errors import ApiError

UI_DIR = Path(__file__).resolve().parents[2] / "ui"

#: the files served under /ui, with their media types
FILES = {
    "index.html": "text/html; charset=utf-8",
    "ui.js": "text/javascript; charset=utf-8",
    "ui.css": "text/css; charset=utf-8",
    "favicon.svg": "image/svg+xml",
}

CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
    "connect-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; "
    "frame-ancestors 'none'"
)
HEADERS = {
    "Content-Security-Policy": CSP,
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "X-Frame-Options": "DENY",
    "Cache-Control": "no-cache",
}

router = APIRouter(tags=["ui"], include_in_schema=False)


@cache
def _read(name: str) -> bytes:
    return (UI_DIR / name).read_bytes()


def _file(name: str) -> Response:
    if name not in FILES:
        raise ApiError(404, "not_found", f"no file {name!r} in the status page")
    return Response(_read(name), media_type=FILES[name], headers=HEADERS)


@router.get("/ui")
async def ui_page() -> Response:
    """The status page (no key needed: it holds no data)."""
    return _file("index.html")


@router.get("/ui/{name}")
async def ui_asset(name: str) -> Response:
    """The page's script and style sheet (the page itself lives at ``/ui``, where its
    relative links resolve)."""
    if name == "index.html":
        return RedirectResponse("/ui", status_code=308)
    return _file(name)
