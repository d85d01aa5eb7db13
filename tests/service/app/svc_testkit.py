"""The service test kit: helpers for every test that needs a mapping service (not a test module).

Tests in any folder import it as `svc_testkit` (tests/conftest.py puts this folder on the path).

- `SimRobot`: wire `Scan`s of a robot driving the synthetic building (sensor_agent.sim), with
  the ground truth, on a simulated 40 Hz clock (not the wall clock);
- `ServiceProc`: `mapping-service serve` as a real subprocess on free loopback ports;
  `shared_service`: one of them (token `SHARED_TOKEN`) for all tests of a run that only need
  a service to talk to;
- `ScanFeeder`: a thread publishing scans of a rectangular room (`room_scan`) over Zenoh;
- `agent`: a real `sensor-agent --emulate` process publishing to a service;
- `zenoh_peer`: a test-side Zenoh session connected to a service;
- `malformed_payloads`: a deterministic mix of bad scan payloads, with their expected reasons;
- `align_to_truth`, `check_against_truth`: served poses against the simulator's ground truth;
- in-process fixtures (`runtime_factory`, `runtime`, `client`) and `feed`.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import subprocess
import sys
import threading
import time
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

from clients.keyexpr import DEFAULT_PREFIX, scan_key
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
BIN = Path(sys.executable).parent  # the venv's console scripts (sensor-agent, mapctl, ...)
SHARED_TOKEN = "test-token"


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


def align_to_truth(
    stamps_ns: np.ndarray, est: np.ndarray, truth_at: Any, search_s: float = 60.0
) -> tuple[float, np.ndarray]:
    """Find the scene-time offset of the first pose; return (offset_s, relative truth poses).

    Agent stamps are host times, the emulator's scene time started a little earlier: we search
    the constant offset that best explains the estimated motion (the error that remains is the
    estimator's).
    """
    dt_s = (stamps_ns - stamps_ns[0]) / 1e9
    est_rel = relative(est[0], est)

    def truth_rel(offset_s: float) -> np.ndarray:
        poses = truth_at(offset_s + dt_s)
        return relative(poses[0], poses)

    def cost(offset_s: float) -> float:
        # Position and heading (1 rad ~ 1 m): on straight stretches only turns pin the offset.
        t = truth_rel(offset_s)
        dth = (t[:, 2] - est_rel[:, 2] + math.pi) % (2 * math.pi) - math.pi
        return float(np.mean(np.hypot(*(t[:, :2] - est_rel[:, :2]).T) + np.abs(dth)))

    coarse = np.arange(0.0, search_s, 0.1)
    best = min(coarse, key=cost)
    fine = np.arange(max(0.0, best - 0.1), best + 0.1, 0.005)
    best = min(fine, key=cost)
    return float(best), truth_rel(float(best))


def check_against_truth(poses: list[dict[str, Any]], truth_at: Any) -> dict[str, float]:
    """Served poses (the trajectory resource's dicts) against `truth_at(t_s) -> (N, 3)`, both as
    motion relative to their first pose: distances travelled, end-point error, absolute
    trajectory error (RMS and worst) and the final heading error."""
    stamps = np.array([p["stamp_ns"] for p in poses], dtype=np.int64)
    est = np.array([(p["x"], p["y"], p["theta"]) for p in poses])
    _, truth_rel = align_to_truth(stamps, est, truth_at)
    est_rel = relative(est[0], est)
    # Path lengths on ~0.5 s steps, first to last pose (per-scan jitter would inflate them).
    steps = max(2, int((stamps[-1] - stamps[0]) / 0.5e9) + 1)
    pick = np.unique(np.linspace(0, len(est_rel) - 1, steps).round().astype(int))
    distance_true = float(np.sum(np.hypot(*np.diff(truth_rel[pick, :2], axis=0).T)))
    distance_est = float(np.sum(np.hypot(*np.diff(est_rel[pick, :2], axis=0).T)))
    position_errors = np.hypot(*(truth_rel[:, :2] - est_rel[:, :2]).T)
    end_error = float(position_errors[-1])
    heading_error = abs((truth_rel[-1, 2] - est_rel[-1, 2] + math.pi) % (2 * math.pi) - math.pi)
    return {
        "distance_true_m": distance_true,
        "distance_est_m": distance_est,
        "end_error_m": end_error,
        "ate_rms_m": float(np.sqrt(np.mean(position_errors**2))),
        "ate_max_m": float(position_errors.max()),
        "heading_error_deg": math.degrees(heading_error),
    }


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
    """`mapping-service serve` in a subprocess; restartable on the same ports and data dir.

    `prefix` is passed as `--prefix` (scans on `<prefix>/<robot>/scan`); `extra_args` (and
    `args` of `start`) are appended to the command line, `env` (in `start`) to the environment.
    """

    def __init__(
        self,
        data_dir: Path,
        token: str | None = None,
        prefix: str = DEFAULT_PREFIX,
        *,
        read_token: str | None = None,
        extra_args: Sequence[str] = (),
        zenoh_endpoint: str | None = None,
        listen_flag: bool = True,
    ) -> None:
        """`extra_args` go to `serve` (e.g. --robots, --instance-id, --zenoh-config);
        `listen_flag=False` leaves listening to a `--zenoh-config` in `extra_args` (whose
        endpoint is then `zenoh_endpoint`)."""
        self.data_dir = data_dir
        self.token = token
        self.read_token = read_token
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
        if self.read_token:
            cmd += ["--read-token", self.read_token]
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
        """Stop with `sig` and return the exit code; fails the test if the service hangs."""
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


_shared: ServiceProc | None = None


def shared_service(config: pytest.Config, tmp_factory: pytest.TempPathFactory) -> ServiceProc:
    """One service (token `SHARED_TOKEN`) for all the tests of a pytest run that only need one to
    talk to: starting a service costs seconds. Tests use their own robot ids and must not
    restart it; it is stopped at the end of the run."""
    global _shared  # noqa: PLW0603 - one per pytest run, stopped at session end
    if _shared is None or _shared.proc is None or _shared.proc.poll() is not None:
        service = ServiceProc(tmp_factory.mktemp("shared-service") / "data", token=SHARED_TOKEN)
        service.start()
        config.add_cleanup(service.stop)
        _shared = service
    return _shared


def room_scan(
    robot_id: str, seq: int, *, x_m: float, y_m: float, theta_rad: float, beams: int = 541
) -> Scan:
    """A scan from inside a 12 m x 8 m room with a pillar (enough structure in x and y)."""
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
    return Scan(
        robot_id=robot_id,
        seq=seq,
        sensor_stamp_ns=seq * SCAN_PERIOD_NS,
        host_stamp_ns=time.time_ns(),
        angle_min_rad=float(angles[0]),
        angle_increment_rad=float(angles[1] - angles[0]),
        range_min_m=0.023,
        range_max_m=30.0,
        ranges_m=np.clip(ranges, 0.0, 30.0),
    )


class ScanFeeder:
    """Publishes room scans for one robot at `rate_hz` from a thread, moving slowly along x."""

    def __init__(
        self, endpoint: str, robot_id: str, rate_hz: float = 20.0, prefix: str = DEFAULT_PREFIX
    ) -> None:
        self.robot_id = robot_id
        self.period_s = 1.0 / rate_hz
        self.sent = 0
        self._stop = threading.Event()
        self._session = zenoh.open(build_zenoh_config(connect=[endpoint]))
        self._pub = self._session.declare_publisher(scan_key(robot_id, prefix))
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
    # These runtimes listen nowhere and are fed with `ingest.submit`, so their mapper processes
    # cannot take scans from Zenoh: the layout with the scans through the service's process
    # (`--no-ingest-in-mappers`), asked for explicitly. Real processes test the default one.
    if ingest.get("mapper_processes"):
        ingest.setdefault("ingest_in_mappers", False)
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
