"""The FastAPI application: ``create_app(settings)``.

One process, threads for CPU work (see ``sgvloc serve --help``). At start-up the maps
are loaded in a background thread: ``/healthz`` answers at once, ``/readyz`` and the map
routes answer 503 until every map is loaded. At shutdown every changed map's FAISS
snapshot is saved.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import logging
import signal
import threading
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager

import anyio
import anyio.to_thread
from fastapi import FastAPI
from fastapi.routing import APIRoute
from fastapi_offline import FastAPIOffline
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from sgvloc.about import __version__
from sgvloc.core import batching, cores

from ..maps import MapManager
from ..metrics import Metrics
from ..recent import RecentLocalizations
from ..settings import Settings
from ..store import SharedBackend, open_backend
from ..threads import usable_cpus
from .auth import KeyRing, KeysError, reload_keys
from .body import BodyBudget
from .deps import Admission, make_pools
from .errors import install_error_handlers
from .openapi import install_openapi
from .request_id import RequestIdMiddleware
from .routes import archives, config, keyframes, localizations, localize, maps, probes, ui

log = logging.getLogger(__name__)


class MetricsMiddleware:
    """Counts requests and times them, labelled by route template (not raw path)."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500

        async def send_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            route = getattr(scope.get("route"), "path", None) or "unmatched"
            # a client may send any token as a method: only the known ones are labels
            method = scope["method"] if scope["method"] in HTTP_METHODS else "other"
            self.metrics.http_requests.labels(route, method, str(status)).inc()
            self.metrics.http_duration.labels(route, method).observe(time.perf_counter() - start)


#: the methods counted under their own label in the HTTP metrics (others: "other")
HTTP_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})


def _warm_up() -> None:
    """Import the engine libraries and compile its kernels now, not in the first requests."""
    for module in ("sgvloc.core.sgv", "open3d"):  # torch for SGV; Open3D for FPFH and RANSAC
        t0 = time.perf_counter()
        try:
            importlib.import_module(module)
        except ImportError as exc:
            log.warning("cannot import %s: %s", module, exc)
            continue
        log.debug("imported %s in %.1f s", module, time.perf_counter() - t0)
    # compile (or load from numba's cache) the CPU SGV, ICP and tracking (GICP) kernels:
    # ~10 s each on first use
    from sgvloc.core import gicp_numba, icp_numba, sgv

    log.debug("SGV kernels ready in %.1f s", sgv.warm_up())
    for name, module in (("ICP", icp_numba), ("GICP", gicp_numba)):
        t0 = time.perf_counter()
        module.warm_up()
        log.debug("%s kernels ready in %.1f s", name, time.perf_counter() - t0)


def _load_maps(manager: MapManager, on_fatal: Callable[[], None] | None = None) -> None:
    """Load every map (the start-up's thread). A failure of the whole load (a store this
    sgvloc cannot read, say) leaves the process unfit to serve: it is recorded in
    ``manager.load_error`` (``/readyz`` answers ``failed``) and ``on_fatal`` is called
    (``sgvloc serve`` stops and exits with status 2, saying why)."""
    try:
        _warm_up()
        manager.load_all()
        if not manager.loaded.is_set():  # stopped first (the store may never have answered)
            log.info("stopping: not ready (%d map(s) loaded)", len(manager.list()))
            return
        manager.start_snapshotter()
        log.info("ready: %d map(s) loaded", len(manager.list()))
    except Exception as exc:
        log.exception("loading the maps failed")
        manager.load_error = str(exc) or type(exc).__name__
        if on_fatal is not None:
            on_fatal()


def _reload_keys_on_sighup(app: FastAPI) -> Callable[[], None]:
    """SIGHUP re-reads the keys file (:func:`~sgvloc.server.api.auth.reload_keys`);
    returns the function that removes the handler. Nothing where signals cannot be
    handled (not the main thread, not Unix)."""
    loop = asyncio.get_running_loop()

    def reload() -> None:
        if app.state.settings.dev:
            return
        with contextlib.suppress(KeysError):  # logged; the previous keys stay
            reload_keys(app)

    try:
        loop.add_signal_handler(signal.SIGHUP, reload)
    except (NotImplementedError, RuntimeError, ValueError, AttributeError):
        return lambda: None
    return lambda: loop.remove_signal_handler(signal.SIGHUP)


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    settings: Settings = app.state.settings
    manager: MapManager = app.state.manager
    make_pools(app.state, settings)
    log.info(
        "sgvloc %s: data dir %s, store %s, %d worker thread(s) (map changes on at most %d), "
        "at most %d localize request(s) in flight, %g s queue timeout",
        __version__,
        settings.data_dir.resolve(),
        manager.backend.describe() if manager.shared else "SQLite",  # type: ignore[union-attr]
        settings.workers,
        settings.write_limit,
        settings.inflight_limit,
        settings.request_timeout_s,
    )
    cores.set_cores(usable_cpus() if settings.spare_cores else 1)
    log.info("spare cores: a request running alone may use %d thread(s)", cores.cores())
    batcher = batching.configure(
        settings.batch_wait_ms, settings.batch_max, observe=app.state.metrics.observe_batch
    )
    log.info(
        "dynamic batching: %s",
        f"wait {batcher.wait_ms:g} ms, at most {batcher.max_size}" if batcher.enabled else "off",
    )
    loader = threading.Thread(
        target=_load_maps,
        args=(manager, getattr(app.state, "on_fatal", None)),
        name="sgvloc-load",
        daemon=True,
    )
    loader.start()
    hup = _reload_keys_on_sighup(app)
    try:
        yield
    finally:
        hup()
        manager.stop_loading()  # a start-up still loading maps ends after the current one
        await anyio.to_thread.run_sync(loader.join, settings.shutdown_timeout_s)
        await anyio.to_thread.run_sync(manager.close)
        batching.reset()
        log.info("shut down: snapshots saved, stores closed")


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the service for ``settings`` (read from ``SGVLOC_*`` when not given).

    Raises :class:`~sgvloc.server.api.auth.KeysError` when the keys file is unusable, or when no
    keys are configured outside development mode.
    """
    settings = settings or Settings()
    keyring = KeyRing.from_settings(settings)
    metrics = Metrics()
    recent = RecentLocalizations()  # for the status page; a deleted map's is dropped

    def on_change(name: str, keyframes: int | None) -> None:
        metrics.set_map_keyframes(name, keyframes)
        recent.on_change(name, keyframes)

    backend = open_backend(
        settings.store_url,
        pool_size=settings.store_pool_size,
        password_file=settings.store_password_file,
    )
    if isinstance(backend, SharedBackend):  # a refusal for good ends the start-up
        backend.check_access()
    manager = MapManager(
        settings.maps_dir,
        snapshot_every=settings.snapshot_every,
        snapshot_delay_s=settings.snapshot_delay_s,
        on_change=on_change,
        backend=backend,
        follow_poll_s=settings.follow_poll_s,
        features_in_memory=settings.local_features == "memory",
        feature_cache=settings.feature_cache,
    )
    about = dict(
        title="sgvloc",
        version=__version__,
        description="LiDAR localization in prior maps: FAISS retrieval, SpectralGV "
        "re-ranking, RANSAC pose. See docs/API.md.",
        lifespan=_lifespan,
    )
    if settings.api_docs == "open":
        # /docs (Swagger UI) and /redoc with their scripts, styles and favicon served from
        # this process (the fastapi-offline package ships them), not a CDN: they work offline
        app = FastAPIOffline(**about)
    else:  # api_docs = "off": no /openapi.json, /docs or /redoc at all
        app = FastAPI(**about, openapi_url=None, docs_url=None, redoc_url=None)
    app.state.settings = settings
    app.state.metrics = metrics
    app.state.manager = manager
    app.state.recent = recent
    app.state.keyring = keyring
    app.state.admission = Admission(settings.inflight_limit)
    metrics.localize_inflight.set_function(lambda: app.state.admission.inflight)
    app.state.body_budget = BodyBudget(settings.body_memory_limit)
    metrics.body_bytes.set_function(lambda: app.state.body_budget.used)
    metrics.maps_failed.set_function(lambda: len(manager.failed))
    metrics.store_up.set_function(lambda: float(manager.store_reachable is not False))
    metrics.watch_maps(lambda: [(h.name, h.num_keyframes, h.version) for h in manager.list()])
    routers = (maps, archives, keyframes, localize, localizations, probes, config, ui)
    for module in routers:
        app.include_router(module.router)
    # for the Allow header of 405 answers: every route's path and methods
    app.state.route_methods = [
        (route.path_regex, set(route.methods) - {"HEAD"})
        for module in routers
        for route in module.router.routes
        if isinstance(route, APIRoute)
    ]
    install_error_handlers(app)
    install_openapi(app)
    app.add_middleware(MetricsMiddleware, metrics=metrics)
    app.add_middleware(RequestIdMiddleware)  # outermost: every log record names its request
    return app
