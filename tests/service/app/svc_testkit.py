"""Helpers for the mapping-service tests (not a test module).

- `SimRobot`: wire `Scan`s of a robot driving the synthetic building (sensor_agent.sim), with
  the ground truth, on a simulated 40 Hz clock (not the wall clock);
- `ServiceProc`: `mapping-service serve` as a real subprocess on free loopback ports;
- `agent`: a real `sensor-agent --emulate` process publishing to a service;
- `zenoh_peer`: a test-side Zenoh session connected to a service;
- `malformed_payloads`: a deterministic mix of bad scan payloads, with their expected reasons.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

import httpx
import msgpack
import numpy as np
import pytest
import zenoh
from conftest import REPO_ROOT, free_port, wait_for
from fastapi.testclient import TestClient

from clients.wire import Scan, encode_scan
from clients.zenoh_config import build_zenoh_config
from sensor_agent.sim import LaserModel, RobotMotion, World, generate_building, simulate_scan
from service.app.api.app import create_app
from service.app.runtime import MappingRuntime
from service.app.settings import (
    HttpSettings,
    IngestSettings,
    SecuritySettings,
    ServiceSettings,
    StorageSettings,
)

SCAN_PERIOD_NS = 25_000_000
_TOKEN_VARIABLES = frozenset(
    ("MAPPING_TOKEN", "MAPPING_TOKEN_FILE", "MAPPING_READ_TOKEN", "MAPPING_READ_TOKEN_FILE")
)


@lru_cache(maxsize=4)
def building(seed: int, size: str = "small") -> World:
    return generate_building(seed, size)  # type: ignore[arg-type]


class SimRobot:
    """Scans of one robot on the corridor loop of a synthetic building, 25 ms apart."""

    def __init__(self, robot_id: str, seed: int = 1, size: str = "small") -> None:
        self.robot_id = robot_id
        self.world = building(seed, size)
        self.motion = RobotMotion(self.world, seed)
        self.model = LaserModel.utm30lx()
        self.seq = 0
        self._rng = np.random.default_rng(seed)
        self._t0_ns = 1_700_000_000_000_000_000

    def truth(self, seq: int) -> tuple[float, float, float]:
        return self.motion.pose_at(seq * SCAN_PERIOD_NS / 1e9)

    def next_scan(self) -> Scan:
        seq = self.seq
        self.seq += 1
        sample = simulate_scan(self.world, self.truth(seq), self.model, self._rng)
        return Scan(
            robot_id=self.robot_id,
            seq=seq,
            sensor_stamp_ns=seq * SCAN_PERIOD_NS,
            host_stamp_ns=self._t0_ns + seq * SCAN_PERIOD_NS,
            angle_min_rad=self.model.angle_min_rad,
            angle_increment_rad=self.model.angle_increment_rad,
            range_min_m=self.model.range_min_m,
            range_max_m=self.model.range_max_m,
            ranges_m=np.nan_to_num(sample.ranges_m, nan=0.0),
        )

    def next_payload(self) -> bytes:
        return encode_scan(self.next_scan())


def relative(a: Any, b: Any) -> np.ndarray:
    """`inverse(a) ∘ b` as (x, y, theta); `b` may be (3,) or (N, 3)."""
    b = np.asarray(b, dtype=np.float64)
    dx, dy = b[..., 0] - a[0], b[..., 1] - a[1]
    c, s = math.cos(a[2]), math.sin(a[2])
    dth = (b[..., 2] - a[2] + math.pi) % (2 * math.pi) - math.pi
    return np.stack([c * dx + s * dy, -s * dx + c * dy, dth], axis=-1)


def malformed_payloads(robot_id: str, count: int) -> Iterator[tuple[bytes, str]]:
    """`count` bad scan payloads cycling through kinds of damage, with the expected reason."""
    good = encode_scan(SimRobot(robot_id).next_scan())
    body = msgpack.unpackb(good, raw=False)

    def variant(**changes: object) -> bytes:
        d = dict(body)
        for k, v in changes.items():
            if v is None:
                d.pop(k, None)
            else:
                d[k] = v
        packed = msgpack.packb(d, use_bin_type=True)
        assert isinstance(packed, bytes)
        return packed

    kinds: list[tuple[bytes, str]] = [
        (b"\xc1garbage", "malformed_msgpack"),
        (msgpack.packb([1, 2, 3]), "not_a_map"),
        (variant(v=99), "unsupported_version"),
        (variant(seq=None), "missing_field"),
        (variant(angle_increment_rad=-0.1), "bad_geometry"),
        (variant(ranges=b"\x00\x01\x02"), "beam_count_mismatch"),
        (variant(robot_id="someone-else"), "robot_id_mismatch"),
        (good[: len(good) // 2], "malformed_msgpack"),
    ]
    for i in range(count):
        yield kinds[i % len(kinds)]


class ServiceProc:
    """`mapping-service serve` in a subprocess; restartable on the same ports and data dir."""

    def __init__(
        self,
        data_dir: Path,
        token: str | None = None,
        prefix: str = "robots",
        *,
        extra_args: Sequence[str] = (),
        zenoh_endpoint: str | None = None,
        listen_flag: bool = True,
    ) -> None:
        """`extra_args` go to `serve` (e.g. --robots, --instance-id, --zenoh-config);
        `listen_flag=False` leaves listening to a `--zenoh-config` in `extra_args` (whose
        endpoint is then `zenoh_endpoint`)."""
        self.data_dir = data_dir
        self.token = token
        self.prefix = prefix
        self.extra_args = list(extra_args)
        self.listen_flag = listen_flag
        self.http_port = free_port()
        self.zenoh_endpoint = zenoh_endpoint or f"tcp/127.0.0.1:{free_port()}"
        self.url = f"http://127.0.0.1:{self.http_port}"
        self.log_path = data_dir.parent / f"service-{self.http_port}.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(
        self,
        timeout_s: float = 30.0,
        env: dict[str, str] | None = None,
        args: list[str] | None = None,
        *,
        wait_restored: bool = True,
        preexec_fn: Callable[[], None] | None = None,
    ) -> None:
        """Start and wait for `/health`; with `wait_restored`, until no session restores."""
        cmd = [
            sys.executable,
            "-m",
            "service.cli",
            "serve",
            "--http-port",
            str(self.http_port),
            "--data-dir",
            str(self.data_dir),
            "--prefix",
            self.prefix,
            *self.extra_args,
        ]
        if self.listen_flag:
            cmd += ["--zenoh-listen", self.zenoh_endpoint]
        if self.token:
            cmd += ["--token", self.token]
        cmd += args or []
        full_env = {k: v for k, v in os.environ.items() if k not in _TOKEN_VARIABLES}
        full_env.update(env or {})
        with self.log_path.open("ab") as log:
            self.proc = subprocess.Popen(
                cmd,
                stdout=log,
                stderr=subprocess.STDOUT,
                cwd=REPO_ROOT,
                env=full_env,
                preexec_fn=preexec_fn,  # noqa: PLW1509  # only setrlimit, in tests
            )

        def healthy() -> bool:
            assert self.proc is not None
            if self.proc.poll() is not None:
                pytest.fail(f"service exited with {self.proc.returncode}:\n{self.log_tail()}")
            r = httpx.get(self.url + "/health", timeout=2.0)
            if r.status_code != 200:
                return False
            return not wait_restored or r.json().get("sessions_restoring", 0) == 0

        wait_for(healthy, timeout_s, "the service to answer /health (and restore)")

    def headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"} if self.token else {}

    def create_session(self, robot_id: str, **params: object) -> dict[str, object]:
        r = httpx.post(
            self.url + "/sessions", json={"robot_id": robot_id, **params}, headers=self.headers()
        )
        assert r.status_code == 201, r.text
        data = r.json()
        assert isinstance(data, dict)
        return data

    def get(self, path: str) -> httpx.Response:
        return httpx.get(self.url + path, timeout=10.0, headers=self.headers())

    def json(self, path: str) -> dict[str, object]:
        r = self.get(path)
        assert r.status_code == 200, f"{path}: {r.status_code} {r.text}"
        data = r.json()
        assert isinstance(data, dict)
        return data

    def metrics(self) -> dict[str, float]:
        from service.app.metrics import parse_text

        return parse_text(self.get("/metrics").text)

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 20.0) -> int:
        if self.proc is None:
            return 0
        proc, self.proc = self.proc, None
        if proc.poll() is None:
            proc.send_signal(sig)
            try:
                return proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=5)
                pytest.fail(f"service ignored signal {sig}:\n{self.log_tail()}")
        return proc.returncode

    def kill9(self) -> None:
        assert self.proc is not None
        self.proc.kill()  # SIGKILL: no cleanup at all
        self.proc.wait(timeout=10)
        self.proc = None

    def log_tail(self, lines: int = 40) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"


@contextlib.contextmanager
def agent(
    svc: ServiceProc,
    robot_id: str,
    world_seed: int,
    log: Path,
    zenoh_args: Sequence[str] | None = None,
) -> Iterator[None]:
    """A real `sensor-agent --emulate` connected to `svc` (or configured by `zenoh_args`)."""
    with log.open("wb") as out:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "sensor_agent.cli",
                "--robot-id",
                robot_id,
                "--emulate",
                "--world-seed",
                str(world_seed),
                *(["--zenoh-connect", svc.zenoh_endpoint] if zenoh_args is None else zenoh_args),
                "--stats-interval",
                "0",
            ],
            stdout=out,
            stderr=subprocess.STDOUT,
            cwd=REPO_ROOT,
        )
    try:
        yield
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@contextlib.contextmanager
def zenoh_peer(endpoint: str) -> Iterator[zenoh.Session]:
    """A test-side Zenoh session connected to the service, always closed."""
    session = zenoh.open(build_zenoh_config(connect=[endpoint]))
    try:
        yield session
    finally:
        session.close()  # type: ignore[no-untyped-call]


@contextlib.contextmanager
def zenoh_router(endpoint: str) -> Iterator[zenoh.Session]:
    """A Zenoh router in the test process, listening on `endpoint`; always closed."""
    session = zenoh.open(build_zenoh_config(mode="router", listen=[endpoint]))
    try:
        yield session
    finally:
        session.close()  # type: ignore[no-untyped-call]


class ScanPublisher:
    """Lightweight emulated robots: one thread publishing `SimRobot` scans of several robots on
    one Zenoh client session at `rate_hz` each (instead of one sensor-agent process per robot).

    Client mode: behind a router, peers only reach each other over direct links (found by
    gossip, which our configs turn off), so whatever connects to a router is a client."""

    def __init__(self, endpoint: str, robot_ids: Sequence[str], rate_hz: float = 10.0) -> None:
        self._endpoint = endpoint
        self._robots = [SimRobot(r, seed=1 + i % 3) for i, r in enumerate(robot_ids)]
        self._period_s = 1.0 / rate_hz
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.published = 0

    def __enter__(self) -> ScanPublisher:
        from clients.keyexpr import scan_key

        session = zenoh.open(build_zenoh_config(mode="client", connect=[self._endpoint]))
        pubs = [session.declare_publisher(scan_key(r.robot_id)) for r in self._robots]

        def run() -> None:
            try:
                while not self._stop.wait(self._period_s):
                    for robot, pub in zip(self._robots, pubs, strict=True):
                        pub.put(robot.next_payload())
                        self.published += 1
            finally:
                for pub in pubs:
                    pub.undeclare()  # type: ignore[no-untyped-call]
                session.close()  # type: ignore[no-untyped-call]

        self._thread = threading.Thread(target=run, name="scan-publisher", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)


def metric_sum(metrics: dict[str, float], name: str, **label_filter: str) -> float:
    """Sum of the series of `name` whose labels include `label_filter`."""
    total = 0.0
    for series, value in metrics.items():
        if series != name and not series.startswith(name + "{"):
            continue
        if all(f'{k}="{v}"' in series for k, v in label_filter.items()):
            total += value
    return total


# ---------------------------------------------------------------------------------------------
# In-process fixtures (imported by the test modules: a conftest.py here would shadow the root one)

RuntimeFactory = Callable[..., MappingRuntime]


def make_settings(
    data_dir: Path, token: str | None = None, read_token: str | None = None, **ingest: int
) -> ServiceSettings:
    return ServiceSettings(
        http=HttpSettings(max_body_bytes=64 * 1024),
        storage=StorageSettings(data_dir=data_dir, fsync_interval_s=0.2),
        ingest=IngestSettings(**ingest),
        security=SecuritySettings(token=token, read_token=read_token),  # type: ignore[arg-type]
    )


@pytest.fixture(name="runtime_factory")
def runtime_factory_fixture(tmp_path: Path) -> Iterator[RuntimeFactory]:
    """Start runtimes on an isolated Zenoh session (listens nowhere); all closed at the end."""
    started: list[MappingRuntime] = []

    def make(
        data_dir: Path | None = None,
        token: str | None = None,
        read_token: str | None = None,
        **ingest: int,
    ) -> MappingRuntime:
        settings = make_settings(data_dir or tmp_path / "data", token, read_token, **ingest)
        runtime = MappingRuntime(settings, zenoh_config=build_zenoh_config())
        runtime.start()
        started.append(runtime)
        wait = getattr(runtime.sessions, "wait_restored", None)  # also runs against older mains
        assert wait is None or wait(60), "sessions did not restore in 60 s"
        return runtime

    yield make
    for runtime in started:
        runtime.close()  # idempotent


@pytest.fixture(name="runtime")
def runtime_fixture(runtime_factory: RuntimeFactory) -> MappingRuntime:
    return runtime_factory()


@pytest.fixture(name="client")
def client_fixture(runtime: MappingRuntime) -> Iterator[TestClient]:
    with TestClient(create_app(runtime)) as c:
        yield c


def feed(runtime: Any, robot: SimRobot, count: int) -> None:
    """Submit `count` scans as the Zenoh callback would, and wait until they are processed.

    Submits only while the robot's queue has room, so a slow (loaded) worker never makes the
    queue drop scans, which would make the counts below depend on the machine's speed.
    """
    from clients.keyexpr import scan_key

    for _ in range(count):
        wait_for(lambda: runtime.ingest.pending() < 8, 60, "room in the ingest queue", 0.005)
        runtime.ingest.submit(scan_key(robot.robot_id), robot.next_payload())
    wait_for(lambda: runtime.ingest.pending() == 0, 60, "the ingest queue to drain")
