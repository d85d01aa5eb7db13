"""`mapping-service serve`: settings -> runtime -> HTTP server, and an orderly shutdown."""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import signal
import socket
import sys
import threading
from collections.abc import Callable
from types import FrameType
from typing import Any

import uvicorn

from service.app.api.app import create_app
from service.app.errors import ServiceError, SettingsError
from service.app.limits import raise_nofile_limit
from service.app.runtime import MappingRuntime
from service.app.settings import ServiceSettings, build_settings

log = logging.getLogger(__name__)

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
GIL_SWITCH_INTERVAL_S = 0.001

OnReady = Callable[[str], None]
ACCEPT_BACKLOG = 128


class _Server(uvicorn.Server):
    """uvicorn's server, also ending the live pose streams when asked to exit.

    Open SSE responses would otherwise hold a graceful shutdown for its whole timeout.
    """

    def __init__(self, config: uvicorn.Config, runtime: MappingRuntime) -> None:
        super().__init__(config)
        self._runtime = runtime

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        if not self.should_exit:  # a second signal forces uvicorn's exit: said once
            log.info("%s: shutting down (HTTP first, then the sessions)", signal.Signals(sig).name)
        self._runtime.fanout.end_streams_threadsafe()
        super().handle_exit(sig, frame)


def bind_socket(host: str, port: int) -> socket.socket:
    """Bind the HTTP socket ourselves so that a busy port is a clean one-line error."""
    try:
        family, kind, proto, _, addr = socket.getaddrinfo(
            host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )[0]
        sock = socket.socket(family, kind, proto)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
    except OSError as err:
        raise SettingsError(f"cannot listen on {host}:{port}: {err.strerror or err}") from err
    sock.set_inheritable(True)
    return sock


def http_url(sock: socket.socket, host: str) -> str:
    port = sock.getsockname()[1]
    shown = host if host not in ("0.0.0.0", "::", "") else "127.0.0.1"
    if ":" in shown:
        shown = f"[{shown}]"
    return f"http://{shown}:{port}"


def serve_http(
    runtime: MappingRuntime,
    sock: socket.socket,
    *,
    on_ready: OnReady | None = None,
    duration_s: float | None = None,
) -> int:
    """Serve the API on `sock` until SIGINT/SIGTERM (or `duration_s`).

    `on_ready(url)` runs in a worker thread once the server accepts connections.
    """
    url = http_url(sock, runtime.settings.http.host)
    config = uvicorn.Config(
        create_app(runtime),
        log_config=None,  # our logging configuration, not uvicorn's
        access_log=log.isEnabledFor(logging.DEBUG),
        timeout_graceful_shutdown=3,
        lifespan="on",
        # At the descriptor limit asyncio retries accept() once per backlog slot, each failure
        # logged and rescheduled: a smaller backlog bounds that storm (and is plenty for a
        # service whose clients are a fleet's tools and browsers).
        backlog=ACCEPT_BACKLOG,
    )
    server = _Server(config, runtime)
    failed = threading.Event()

    async def main() -> None:
        task = asyncio.create_task(server.serve(sockets=[sock]))
        while not server.started and not task.done():
            await asyncio.sleep(0.02)
        if server.started:
            log.info("HTTP API on %s (OpenAPI at %s/docs)", url, url)
            if on_ready is not None:
                asyncio.get_running_loop().run_in_executor(
                    None, _ready, on_ready, url, server, failed
                )
            if duration_s is not None:
                asyncio.get_running_loop().call_later(duration_s, _stop, server, runtime)
        await task

    # uvicorn re-raises the signal it caught once it has shut down; with these handlers that
    # is a no-op and the runtime below is still closed in order (SIGTERM would kill us).
    previous = _quiet_signals()
    try:
        asyncio.run(main())
    finally:
        _restore_signals(previous)
    if not server.started:
        return EXIT_FAILURE
    return EXIT_FAILURE if failed.is_set() else EXIT_OK


def _ready(on_ready: OnReady, url: str, server: uvicorn.Server, failed: threading.Event) -> None:
    try:
        on_ready(url)
    except Exception as err:
        log.error("start-up step failed: %s", err)
        failed.set()
        server.should_exit = True


def _stop(server: uvicorn.Server, runtime: MappingRuntime) -> None:
    runtime.fanout.end_streams()
    server.should_exit = True


def _quiet_signals() -> dict[int, Any]:
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {sig: signal.signal(sig, _ignore) for sig in (signal.SIGINT, signal.SIGTERM)}


def _ignore(sig: int, frame: FrameType | None) -> None:
    """uvicorn re-raises the signal that stopped it; the shutdown is already under way."""
    log.debug("signal %d during shutdown", sig)


def _restore_signals(previous: dict[int, Any]) -> None:
    for sig, handler in previous.items():
        signal.signal(sig, handler)


def log_settings(settings: ServiceSettings) -> None:
    log.info("effective settings: %s", json.dumps(settings.describe(), sort_keys=True))


def run_runtime(
    settings: ServiceSettings,
    *,
    on_ready: OnReady | None = None,
    duration_s: float | None = None,
    runtime_factory: Callable[[ServiceSettings], MappingRuntime] = MappingRuntime,
) -> int:
    """Start the runtime, serve, close; known failures become one log line and an exit code."""
    try:
        # Bind first: a busy port fails fast, before sessions are replayed.
        sock = bind_socket(settings.http.host, settings.http.port)
        try:
            with runtime_factory(settings) as runtime:
                runtime.http_url = http_url(sock, settings.http.host)
                return serve_http(runtime, sock, on_ready=on_ready, duration_s=duration_s)
        finally:
            sock.close()
    except SettingsError as err:
        log.error("%s", err.reason)
        return EXIT_USAGE
    except ServiceError as err:
        log.error("%s", err.reason)
        return EXIT_FAILURE


def run_serve(args: argparse.Namespace) -> int:
    if getattr(args, "verbose", 0) == 0:
        # A daemon reports its start-up and lifecycle by default; -v adds more.
        logging.getLogger("service").setLevel(logging.INFO)
    before, after = raise_nofile_limit()  # before the settings: the robot limit derives from it
    if after != before:
        log.info("descriptor limit raised from %d to %d", before, after)
    try:
        settings = build_settings(args)
    except SettingsError as err:
        log.error("%s", err.reason)
        return EXIT_USAGE
    log_settings(settings)
    # The HTTP loop (pose streams, map renders) and the ingest threads share the GIL. A thread
    # that waits for it gets it only after the holder's switch interval (5 ms by default), and
    # an ingest thread takes it several times per scan: with a busy loop that made each scan
    # wait for tens of milliseconds. 1 ms bounds the wait at a small cost in switches.
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    return run_runtime(settings)
