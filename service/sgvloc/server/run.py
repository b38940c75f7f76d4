"""``sgvloc serve``: one process, the app on uvicorn, library threads capped first."""

from __future__ import annotations

import contextlib
import errno
import logging
import socket
import struct
from collections.abc import Callable

from .settings import Settings
from .threads import limit_library_threads

log = logging.getLogger(__name__)


class StartupError(Exception):
    """The service cannot start (an unusable keys file, say); the message says why."""


def serve(settings: Settings) -> None:
    """Run the service until it is stopped.

    The port is checked first, so a busy one fails at once; library threads are capped
    before numpy, Open3D, FAISS and torch are loaded (by the app's modules), so this
    module imports none of them at the top. Raises :class:`StartupError` when the port
    is taken, the keys file or the store is unusable, or loading the maps failed.
    """
    check_port(settings.host, settings.port)
    # an explicit threads_per_worker wins over OMP_NUM_THREADS & co.; the default does not
    threads = limit_library_threads(
        settings.library_threads, force=settings.threads_per_worker is not None
    )
    log.info("library threads per worker: %s", threads)
    log.info("open files: at most %d (each SQLite map holds about 3)", raise_open_files_limit())

    import uvicorn

    from .api import create_app
    from .api.auth import KeysError
    from .store import StoreError

    try:
        application = create_app(settings)
    except (KeysError, StoreError) as exc:
        raise StartupError(str(exc)) from None
    json_logs = settings.log_format == "json"
    config = uvicorn.Config(
        application,
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        # JSON: uvicorn's records go through the root logger's JSON handler, and the app's
        # own access line (with the request id) replaces uvicorn's
        log_config=None if json_logs else uvicorn.config.LOGGING_CONFIG,
        workers=None,  # one process: an app object cannot be forked into workers anyway
        access_log=settings.log_level == "debug" and not json_logs,
        timeout_graceful_shutdown=settings.shutdown_timeout_s,
        http=_timed_protocol(
            settings.header_timeout_s,
            settings.send_timeout_s,
            lambda reason: application.state.metrics.connections_cut.labels(reason).inc(),
        ),
    )
    server = _graceful_server(config)

    def stop() -> None:  # loading the maps failed for good: stop as on SIGTERM
        server.should_exit = True

    application.state.on_fatal = stop
    server.run()
    why = application.state.manager.load_error
    if why is not None:
        raise StartupError(f"loading the maps failed: {why}")


def _timed_protocol(  # uvicorn is imported late
    header_timeout_s: float, send_timeout_s: float, on_cut: Callable[[str], None]
):
    """uvicorn's h11 protocol with two deadlines (``on_cut`` hears of each connection
    closed by one: ``"header_timeout"``, ``"unread_body"`` or ``"send_timeout"``).

    - Request headers: a connection whose next request's headers are not complete within
      ``header_timeout_s`` (from the connection or from the previous answer) is closed.
      uvicorn's keep-alive timeout stops at the first byte, so headers trickled a byte at
      a time would hold a connection forever otherwise.
    - Answers: a connection whose send buffer stays full for ``send_timeout_s`` (the
      client takes none of it, or less than about 1 KiB/s), or whose finished answer
      still waits in the buffer that long, is aborted (the buffer dropped), also when it
      is already closing (a close waits for the buffer). Without it a stalled download
      holds its answer's memory, and an export its snapshot of the store, for as long
      as the client keeps the connection open.
    """
    import h11
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class TimedProtocol(H11Protocol):
        _header_timer = None
        _send_timer = None

        def _arm_header_timer(self) -> None:
            self._disarm_header_timer()
            self._header_timer = self.loop.call_later(header_timeout_s, self._header_timeout)

        def _disarm_header_timer(self) -> None:
            if self._header_timer is not None:
                self._header_timer.cancel()
                self._header_timer = None

        def _answered_unread(self) -> bool:
            """The answer went out before the request's body was read (401, 405, 413,
            415): whatever the client still sends is of no use."""
            return self.conn.our_state is h11.DONE and self.conn.their_state is h11.SEND_BODY

        def _header_timeout(self) -> None:
            self._header_timer = None
            if self.transport.is_closing():
                return
            if self.conn.their_state is h11.IDLE:
                log.info(
                    "closing a connection whose request headers took over %g s", header_timeout_s
                )
                self.transport.close()
                on_cut("header_timeout")
            elif self._answered_unread():
                log.info(
                    "closing a connection still sending a body %g s after its answer",
                    header_timeout_s,
                )
                self.transport.close()
                on_cut("unread_body")

        def connection_made(self, transport) -> None:  # noqa: ANN001
            super().connection_made(transport)
            self._arm_header_timer()

        def handle_events(self) -> None:
            super().handle_events()
            # the headers are complete, unless the answer is out and only an unread body
            # is still arriving (its trickle must not keep the connection open)
            if self.conn.their_state is not h11.IDLE and not self._answered_unread():
                self._disarm_header_timer()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing():
                self._arm_header_timer()
            if self.transport.get_write_buffer_size() and self._send_timer is None:
                # an answer's tail waits in the buffer (below the pause mark): the same
                # deadline, also once the connection is closing (close() waits for it)
                self._send_timer = self.loop.call_later(send_timeout_s, self._send_timeout)

        def pause_writing(self) -> None:  # the client is not taking the answer
            super().pause_writing()
            if self._send_timer is None:
                self._send_timer = self.loop.call_later(send_timeout_s, self._send_timeout)

        def resume_writing(self) -> None:
            self._disarm_send_timer()
            super().resume_writing()

        def _disarm_send_timer(self) -> None:
            if self._send_timer is not None:
                self._send_timer.cancel()
                self._send_timer = None

        def _send_timeout(self) -> None:
            self._send_timer = None
            if not self.transport.get_write_buffer_size():
                return  # all of it went out: nothing stalls
            if not (
                self.flow.write_paused
                or self.transport.is_closing()
                or self.conn.our_state is h11.DONE
            ):
                return  # an answer under way whose data moves: a healthy download
            peer = self.client[0] if getattr(self, "client", None) else "?"
            log.warning(
                "closing a connection to %s that took none of its answer for %g s (send_timeout_s)",
                peer,
                send_timeout_s,
            )
            sock = self.transport.get_extra_info("socket")
            if sock is not None:  # a reset: the kernel drops its queue too (no FIN-WAIT)
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            self.transport.abort()  # close() would wait for the unsent data
            on_cut("send_timeout")

        def connection_lost(self, exc) -> None:  # noqa: ANN001
            self._disarm_header_timer()
            self._disarm_send_timer()
            super().connection_lost(exc)

    return TimedProtocol


def _graceful_server(config):  # uvicorn is imported late: after the thread caps
    """uvicorn's server, which on SIGTERM/SIGINT also stops in-flight localize work at its
    next step (:func:`sgvloc.core.deadline.abort_all`): those answers are 503 at once
    instead of the shutdown waiting for them (at most ``shutdown_timeout_s`` in all)."""
    import uvicorn

    from sgvloc.core.deadline import abort_all

    class Server(uvicorn.Server):
        def handle_exit(self, sig, frame) -> None:
            log.info("shutting down: stopping in-flight work, finishing requests")
            abort_all()
            super().handle_exit(sig, frame)

    return Server(config)


def raise_open_files_limit() -> int:
    """Raise this process's open-file limit to its hard limit (each SQLite map keeps its
    database, WAL and index files open; a default soft limit of 1024 runs out at a few
    hundred maps); returns the limit in force."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY:
        hard = max(soft, 1 << 20)
    if soft < hard:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
            soft = hard
        except (ValueError, OSError) as exc:  # a container that forbids it
            log.warning("cannot raise the open-file limit from %d: %s", soft, exc)
    return soft


def check_port(host: str, port: int) -> None:
    """Raise :class:`StartupError` unless ``host:port`` can be bound now (as uvicorn binds
    it: ``SO_REUSEADDR``, so a port in TIME_WAIT counts as free)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise StartupError(f"cannot listen on {host}:{port}: {exc.strerror}") from None
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(address)
        except OSError as exc:
            hint = " (another process listens there: stop it or pick --port)"
            raise StartupError(
                f"cannot listen on {host}:{port}: {exc.strerror}"
                + (hint if exc.errno == errno.EADDRINUSE else "")
            ) from None
