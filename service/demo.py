"""`mapping-service demo`: the service plus simulated robots through the real agent path.

The service opens a Zenoh peer listening on a loopback endpoint; each robot is a separate
`sensor-agent --emulate` process (emulated UTM-30LX on a pty, the real SCIP driver, the real
publisher) connecting to it. One session per robot is started, and the live map URL printed.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Mapping
from pathlib import Path

from service.app.errors import ConflictError
from service.app.main import EXIT_USAGE, log_settings, run_runtime
from service.app.runtime import MappingRuntime
from service.app.sessions import MappingSession
from service.app.settings import (
    HttpSettings,
    IngestSettings,
    ServiceSettings,
    StorageSettings,
    ZenohSettings,
    is_loopback_host,
)

log = logging.getLogger(__name__)

_STOP_TIMEOUT_S = 5.0


def _free_loopback_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def default_demo_dir(env: Mapping[str, str] | None = None) -> Path:
    """`$XDG_DATA_HOME/manhattan-mapper/demo` (default `~/.local/share/...`): a named folder
    that outlives the demo, so that maps saved in it are not lost on exit."""
    env = os.environ if env is None else env
    base = env.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "manhattan-mapper" / "demo"


def agent_command(robot_id: str, world_seed: int, endpoint: str, prefix: str) -> list[str]:
    """The agent as a real subprocess (module form: works without the venv on PATH)."""
    return [
        sys.executable,
        "-m",
        "sensor_agent.cli",
        "--robot-id",
        robot_id,
        "--emulate",
        "--world-seed",
        str(world_seed),
        "--zenoh-connect",
        endpoint,
        "--prefix",
        prefix,
    ]


class Fleet:
    """The demo's simulated robots: one agent process each, and their sessions."""

    def __init__(
        self, robots: int, world_seed: int, endpoint: str, data_dir: Path | None = None
    ) -> None:
        self._data_dir = data_dir
        self.robot_ids = [f"robot-{i + 1}" for i in range(robots)]
        self._world_seed = world_seed
        self._endpoint = endpoint
        self._children: list[subprocess.Popen[bytes]] = []
        self._lock = threading.Lock()
        self._stopping = False

    def start(self, runtime: MappingRuntime, url: str) -> None:
        prefix = runtime.settings.zenoh.prefix
        session_ids = []
        for index, robot_id in enumerate(self.robot_ids):
            previous = runtime.sessions.active_for(robot_id)
            if previous is not None:
                # A kept data folder: the simulated robot starts again where it started, so
                # it gets a new map; the previous session stays (stopped) with its map.
                runtime.sessions.stop(previous.id)
            session: MappingSession | None
            try:
                session = runtime.sessions.create(robot_id, 0.05, True)
            except ConflictError:
                session = runtime.sessions.active_for(robot_id)
            if session is not None:
                session_ids.append(session.id)
            with self._lock:
                if self._stopping:
                    return
                child = subprocess.Popen(
                    # One building per robot (the agent has no start-position option), so
                    # several robots give visibly different maps.
                    agent_command(robot_id, self._world_seed + index, self._endpoint, prefix),
                    stdin=subprocess.DEVNULL,
                    # Own process group: Ctrl-C reaches the demo, which then stops them in order.
                    start_new_session=True,
                )
                self._children.append(child)
            log.info("robot %s: sensor-agent pid %d", robot_id, child.pid)
            threading.Thread(
                target=self._watch, args=(robot_id, child), name=f"watch-{robot_id}", daemon=True
            ).start()
        first = f"?session={session_ids[0]}" if session_ids else ""
        # The lines of output the demo exists for (the CLI's result, hence stdout).
        lines = [f"Live map: {url}/{first}   (API docs: {url}/docs; Ctrl-C to stop)"]
        if runtime.foxglove is not None:
            lines.append(
                f"Foxglove: {runtime.foxglove.url}   (Foxglove: Open connection > "
                "Foxglove WebSocket; topics /<robot>/map, /scan, /pose, /trajectory, /tf)"
            )
        if self._data_dir is not None:
            lines.append(f"Data: {self._data_dir}   (sessions and saved maps are kept here)")
        print("\n".join(lines), flush=True)  # noqa: T201

    def _watch(self, robot_id: str, child: subprocess.Popen[bytes]) -> None:
        code = child.wait()
        if not self._stopping:
            log.warning("robot %s: sensor-agent exited with code %d", robot_id, code)

    def stop(self) -> None:
        with self._lock:
            self._stopping = True
            children = list(self._children)
        for child in children:
            if child.poll() is None:
                child.send_signal(signal.SIGTERM)
        for child in children:
            try:
                child.wait(timeout=_STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                log.warning("sensor-agent pid %d ignored SIGTERM; killing it", child.pid)
                child.kill()
                child.wait()


def run_demo(args: argparse.Namespace) -> int:
    if args.robots < 1 or args.robots > 16:
        log.error("--robots must be between 1 and 16")
        return EXIT_USAGE
    if not is_loopback_host(args.http_host):
        log.error("the demo has no token: it serves on loopback only")
        return EXIT_USAGE
    data_dir = (Path(args.data_dir) if args.data_dir else default_demo_dir()).absolute()
    # Printed at start (stderr) and beside the address (stdout): saved maps live there.
    log.warning("demo data (sessions, saved maps) in %s; it is kept after the demo", data_dir)
    endpoint = f"tcp/127.0.0.1:{_free_loopback_port()}"
    settings = ServiceSettings(
        http=HttpSettings(
            host=args.http_host, port=args.http_port, foxglove_port=args.foxglove_port
        ),
        zenoh=ZenohSettings(listen=(endpoint,)),
        storage=StorageSettings(data_dir=data_dir),
        ingest=IngestSettings(loop_closure=not getattr(args, "no_loop_closure", False)),
    )
    log_settings(settings)
    fleet = Fleet(args.robots, args.world_seed, endpoint, data_dir)
    runtime_box: list[MappingRuntime] = []

    def make_runtime(s: ServiceSettings) -> MappingRuntime:
        runtime = MappingRuntime(s)
        runtime_box.append(runtime)
        return runtime

    def on_ready(url: str) -> None:
        fleet.start(runtime_box[0], url)

    try:
        return run_runtime(
            settings, on_ready=on_ready, duration_s=args.duration, runtime_factory=make_runtime
        )
    finally:
        fleet.stop()


__all__ = ["Fleet", "agent_command", "default_demo_dir", "run_demo"]
