"""``sgvloc serve``: one process, the app on uvicorn, library threads capped first."""

from __future__ import annotations

import logging

from .settings import Settings
from .threads import limit_library_threads

log = logging.getLogger(__name__)


class StartupError(Exception):
    """The service cannot start (an unusable keys file, say); the message says why."""


def serve(settings: Settings) -> None:
    """Run the service until it is stopped.

    Library threads are capped before numpy, Open3D, FAISS and torch are loaded (by the
    app's modules), so this module imports none of them at the top. Raises
    :class:`StartupError` when the keys file is unusable.
    """
    threads = limit_library_threads(settings.library_threads)
    log.info("library threads per worker: %s", threads)

    import uvicorn

    from .api import create_app
    from .api.auth import KeysError

    try:
        application = create_app(settings)
    except KeysError as exc:
        raise StartupError(str(exc)) from None
    uvicorn.run(
        application,
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        workers=None,  # one process: an app object cannot be forked into workers anyway
        access_log=settings.log_level == "debug",
    )
