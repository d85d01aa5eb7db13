"""Helpers for the client tests that need a running service (not a test module itself).

`LiveService` runs `mapping-service serve` as a real subprocess on free loopback ports;
`ScanFeeder` publishes synthetic scans of a rectangular room over Zenoh so the service has
something to map without depending on the sensor agent.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import zenoh
from conftest import REPO_ROOT, free_port, wait_for

from clients.keyexpr import scan_key
from clients.wire import Scan, encode_scan
from clients.zenoh_config import build_zenoh_config

BIN = Path(sys.executable).parent


def service_available() -> bool:
    try:
        from service.app import main  # noqa: F401
    except ImportError:
        return False
    return True


def require_service() -> None:
    if not service_available():
        pytest.skip("service.app.main is not available yet")


class LiveService:
    """`mapping-service serve` in a subprocess. Restartable on the same ports and data dir."""

    def __init__(
        self, data_dir: Path, token: str | None = None, read_token: str | None = None
    ) -> None:
        self.data_dir = data_dir
        self.token = token
        self.read_token = read_token
        self.http_port = free_port()
        self.zenoh_endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.url = f"http://127.0.0.1:{self.http_port}"
        self.log_path = data_dir.parent / f"service-{self.http_port}.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self, timeout_s: float = 30.0) -> None:
        cmd = [
            str(BIN / "mapping-service"),
            "serve",
            "--http-port",
            str(self.http_port),
            "--data-dir",
            str(self.data_dir),
            "--zenoh-listen",
            self.zenoh_endpoint,
        ]
        if self.token:
            cmd += ["--token", self.token]
        if self.read_token:
            cmd += ["--read-token", self.read_token]
        env = {k: v for k, v in os.environ.items() if not k.startswith("MAPPING_")}
        log = self.log_path.open("ab")
        self.proc = subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, cwd=REPO_ROOT, env=env
        )
        log.close()

        def healthy() -> bool:
            assert self.proc is not None
            if self.proc.poll() is not None:
                pytest.fail(f"service exited with {self.proc.returncode}:\n{self.log_tail()}")
            return httpx.get(self.url + "/health", timeout=1.0).status_code == 200

        wait_for(healthy, timeout_s, "the service to answer /health")

    def stop(self) -> None:
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        self.proc = None

    def log_tail(self, lines: int = 40) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"


SHARED_TOKEN = "test-token"
_shared: LiveService | None = None


def shared_service(config: pytest.Config, tmp_factory: pytest.TempPathFactory) -> LiveService:
    """One service (token `SHARED_TOKEN`) for all client test modules of a pytest run: starting
    a service costs seconds. Tests use their own robot ids and must not restart it."""
    global _shared  # noqa: PLW0603 - one per pytest run, stopped at session end
    require_service()
    if _shared is None or _shared.proc is None or _shared.proc.poll() is not None:
        service = LiveService(tmp_factory.mktemp("shared-service") / "data", token=SHARED_TOKEN)
        service.start()
        config.add_cleanup(service.stop)
        _shared = service
    return _shared


def room_scan(
    robot_id: str, seq: int, *, x_m: float, y_m: float, theta_rad: float, beams: int = 541
) -> Scan:
    """A scan from inside an L-free rectangular room with a pillar (enough structure in x and y)."""
    width_m, height_m = 12.0, 8.0
    angles = np.linspace(-3 * math.pi / 4, 3 * math.pi / 4, beams)
    world = theta_rad + angles
    c, s = np.cos(world), np.sin(world)
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = np.where(c > 0, (width_m - x_m) / c, np.where(c < 0, -x_m / c, np.inf))
        ty = np.where(s > 0, (height_m - y_m) / s, np.where(s < 0, -y_m / s, np.inf))
    ranges = np.minimum(tx, ty)
    # A 1 m square pillar at (8..9, 5..6) gives corners to match against.
    for x0, x1, y0, y1 in [(8.0, 9.0, 5.0, 6.0)]:
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (np.array([x0, x1])[:, None] - x_m) / c
            t2 = (np.array([y0, y1])[:, None] - y_m) / s
        tmin = np.maximum(np.minimum(t1[0], t1[1]), np.minimum(t2[0], t2[1]))
        tmax = np.minimum(np.maximum(t1[0], t1[1]), np.maximum(t2[0], t2[1]))
        hit = (tmax >= tmin) & (tmin > 0)
        ranges = np.where(hit, np.minimum(ranges, tmin), ranges)
    now_ns = time.time_ns()
    return Scan(
        robot_id=robot_id,
        seq=seq,
        sensor_stamp_ns=seq * 25_000_000,
        host_stamp_ns=now_ns,
        angle_min_rad=float(angles[0]),
        angle_increment_rad=float(angles[1] - angles[0]),
        range_min_m=0.023,
        range_max_m=30.0,
        ranges_m=np.clip(ranges, 0.0, 30.0),
    )


class ScanFeeder:
    """Publishes room scans for one robot at `rate_hz` from a thread, moving slowly along x."""

    def __init__(self, endpoint: str, robot_id: str, rate_hz: float = 20.0) -> None:
        self.robot_id = robot_id
        self.period_s = 1.0 / rate_hz
        self.sent = 0
        self._stop = threading.Event()
        self._session = zenoh.open(build_zenoh_config(connect=[endpoint]))
        self._pub = self._session.declare_publisher(scan_key(robot_id))
        self._thread = threading.Thread(target=self._run, name=f"feeder-{robot_id}", daemon=True)

    def __enter__(self) -> ScanFeeder:
        self._thread.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            step = self.sent
            x = 3.0 + 0.01 * (step % 400)  # 1 cm per scan, back to the start every 400 scans
            scan = room_scan(self.robot_id, step, x_m=x, y_m=3.0, theta_rad=0.0)
            self._pub.put(encode_scan(scan))
            self.sent += 1
            self._stop.wait(self.period_s)

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5)
        self._pub.undeclare()  # type: ignore[no-untyped-call]
        self._session.close()  # type: ignore[no-untyped-call]
