"""``sgvloc serve``: one process, the app on uvicorn, library threads capped first."""

from __future__ import annotations

import logging

from .settings import Settings
from .threads import limit_library_threads

log = logging.getLogger(__name__)


def serve(settings: Settings) -> None:
    """Run the service until it is stopped.

    Library threads are capped before numpy, Open3D, FAISS and torch are loaded (by the
    app's modules). Raises :class:`~sgvloc.server.api.auth.KeysError` when the keys file
    is unusable.
    """
    threads = limit_library_threads(settings.library_threads)
    log.info("library threads per worker: %s", threads)

    import uvicorn

    from .api import create_app

    application = create_app(settings)
    uvicorn.run(
        application,
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        workers=None,  # one process: an app object cannot be forked into workers anyway
        access_log=settings.log_level == "debug",
    )
