"""Many pose subscribers in one process, for the fan-out benchmark (bench/fleet.py).

`python -m bench.fanout_clients --server URL --sessions s1,s2 --sse 1000
    --zenoh-connect EP --zenoh-subscribers 50 --out FILE.json`

Opens `--sse` browser-like streams (`GET /sessions/<id>/pose/stream`, spread round-robin over
the sessions) on raw asyncio sockets, which read and count bytes and events and nothing more,
and `--zenoh-subscribers` Zenoh sessions, each with its own subscriber to every robot's poses
(separate sessions: the service's Zenoh sends each one its own copy, as to separate
processes). Streams read once a second, subscribers keep the last pose in a Rust-side ring:
the clients share the service's cores, so they are kept cheap. Prints `ready` once every
stream has its response header and every subscriber is
declared; stops on `stop` on stdin and writes counts to `--out`.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import zenoh
from zenoh.handlers import RingChannel

from clients.keyexpr import DEFAULT_PREFIX, pose_wildcard
from clients.zenoh_config import build_zenoh_config

log = logging.getLogger(__name__)

READ_PERIOD_S = 1.0


class SseCounts:
    def __init__(self) -> None:
        self.connected = 0
        self.events = 0
        self.bytes = 0
        self.failed = 0
        self.closed_early = 0


async def _sse_client(
    host: str, port: int, path: str, counts: SseCounts, stop: asyncio.Event
) -> None:
    try:
        reader, writer = await asyncio.open_connection(host, port)
    except OSError:
        counts.failed += 1
        return
    writer.write(
        f"GET {path} HTTP/1.1\r\nHost: {host}\r\nAccept: text/event-stream\r\n\r\n".encode()
    )
    await writer.drain()
    header = await reader.readuntil(b"\r\n\r\n")
    if not header.startswith(b"HTTP/1.1 200"):
        counts.failed += 1
        writer.close()
        return
    counts.connected += 1
    try:
        while not stop.is_set():
            # A browser reads as data comes; reading what piled up once a second costs this
            # process (on the same cores as the service) a tenth of that, and the service the same.
            await asyncio.sleep(READ_PERIOD_S)
            data = await reader.read(1 << 20)
            if not data:
                counts.closed_early += 1
                break
            counts.bytes += len(data)
            counts.events += data.count(b"event: pose")
    finally:
        writer.close()


async def _run_sse(  # noqa: PLR0917
    server: str,
    sessions: Sequence[str],
    n: int,
    counts: SseCounts,
    connected: threading.Event,
    stop_thread: threading.Event,
) -> None:
    url = urlsplit(server)
    host, port = url.hostname or "127.0.0.1", url.port or 80
    stop = asyncio.Event()
    tasks = []
    for i in range(n):
        path = f"/sessions/{sessions[i % len(sessions)]}/pose/stream"
        tasks.append(asyncio.create_task(_sse_client(host, port, path, counts, stop)))
        if i % 50 == 49:
            await asyncio.sleep(0.05)  # do not flood the accept queue
    while counts.connected + counts.failed < n:
        await asyncio.sleep(0.05)
    connected.set()
    await asyncio.to_thread(stop_thread.wait)
    stop.set()
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.fanout_clients")
    parser.add_argument("--server", required=True, help="service base URL")
    parser.add_argument("--sessions", required=True, help="comma-separated session ids")
    parser.add_argument("--sse", type=int, default=0, help="SSE streams to open")
    parser.add_argument("--zenoh-connect", action="append", default=[])
    parser.add_argument("--zenoh-subscribers", type=int, default=0)
    parser.add_argument(
        "--via-router",
        default=None,
        metavar="ENDPOINT",
        help="run a Zenoh router here, listening on ENDPOINT and connected to --zenoh-connect, "
        "and connect the subscribers to it as clients (the site layout: the service then sends "
        "each pose once, the router copies it); default: subscribers connect directly",
    )
    parser.add_argument("--prefix", default=DEFAULT_PREFIX)
    parser.add_argument("--out", required=True, type=Path)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    sessions = [s for s in args.sessions.split(",") if s]
    stop = threading.Event()
    zenoh_seen = [0] * args.zenoh_subscribers
    zsessions: list[zenoh.Session] = []
    rings: list[Any] = []
    counts = SseCounts()

    def poll_rings() -> None:
        # A ring of one in Rust per subscriber: no Python callback per pose (50 subscribers
        # x 400 poses/s would cost this process a core); a poll shows each one keeps receiving.
        while not stop.wait(0.5):
            for i, ring in enumerate(rings):
                if ring.try_recv() is not None:
                    zenoh_seen[i] += 1

    try:
        connect, mode = args.zenoh_connect, "peer"
        if args.via_router and args.zenoh_subscribers:
            zsessions.append(
                zenoh.open(
                    build_zenoh_config(
                        mode="router", listen=[args.via_router], connect=args.zenoh_connect
                    )
                )
            )
            connect, mode = [args.via_router], "client"
        for _ in range(args.zenoh_subscribers):
            z = zenoh.open(build_zenoh_config(mode=mode, connect=connect))
            zsessions.append(z)
            rings.append(z.declare_subscriber(pose_wildcard(args.prefix), RingChannel(1)))
        poller = threading.Thread(target=poll_rings, daemon=True)
        poller.start()

        def wait_stdin() -> None:
            for line in sys.stdin:
                if line.strip() == "stop":
                    break
            stop.set()

        threading.Thread(target=wait_stdin, daemon=True).start()
        connected = threading.Event()
        if args.sse:

            def run_loop() -> None:
                asyncio.run(_run_sse(args.server, sessions, args.sse, counts, connected, stop))

            loop_thread = threading.Thread(target=run_loop, daemon=True)
            loop_thread.start()
            connected.wait(120)
        sys.stdout.write("ready\n")
        sys.stdout.flush()
        stop.wait()
        if args.sse:
            loop_thread.join(timeout=30)
    finally:
        for ring in rings:
            ring.undeclare()
        for z in zsessions:
            z.close()  # type: ignore[no-untyped-call]
    args.out.write_text(
        json.dumps(
            {
                "sse_requested": args.sse,
                "sse_connected": counts.connected,
                "sse_failed": counts.failed,
                "sse_closed_early": counts.closed_early,
                "sse_events": counts.events,
                "sse_bytes": counts.bytes,
                "zenoh_subscribers": args.zenoh_subscribers,
                "zenoh_via_router": bool(args.via_router),
                # Polls (every 0.5 s) at which a subscriber had a new pose: ~2 per second each.
                "zenoh_polls_with_pose_min": min(zenoh_seen) if zenoh_seen else 0,
                "zenoh_polls_with_pose_total": sum(zenoh_seen),
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
