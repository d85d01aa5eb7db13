"""Where a session's estimator and grid run: in the service's process, or in mapper processes.

One Python process estimates on one core: the work per scan holds the GIL. With
`mapper_processes` > 0 the service starts that many worker processes and places each session's
estimator and grid in one of them (the least loaded when the session is made). The service's
process keeps everything else: Zenoh, decoding, the recording, poses, HTTP. An ingest thread
sends a scan (~5 KiB pickled) and waits for ~100 bytes back, without holding the GIL, so K
processes estimate K robots at once.

A mapper process that dies (killed, out of memory) loses the state of its sessions. The process
is started again at the next call, and each of its sessions sees `MapperLostError` once: the session
then rebuilds its mapper from its checkpoint and recording (`MappingSession`), as a restart does.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import multiprocessing.connection
import signal
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

from clients.wire import Scan, decode_scan
from service.app import statecodec
from service.core.types import LaserScan, Pose2D, PoseEstimate

log = logging.getLogger(__name__)


class Estimator(Protocol):
    def process(self, scan: LaserScan) -> PoseEstimate: ...
    def reset(self) -> None: ...


class Grid(Protocol):
    def integrate(self, scan: LaserScan, pose: Pose2D) -> None: ...
    def snapshot(self) -> Any: ...


EstimatorFactory = Callable[[bool], Estimator]  # use_odometry -> estimator
GridFactory = Callable[[float], Grid]  # resolution_m -> grid
ScanConverter = Callable[[Scan, bool], LaserScan]  # (scan, use_odometry) -> LaserScan


def default_estimator_factory(use_odometry: bool) -> Estimator:
    from service.core.frontend.estimator import ManhattanEstimator  # noqa: PLC0415
    from service.core.frontend.params import EstimatorParams  # noqa: PLC0415

    return ManhattanEstimator(EstimatorParams(use_odometry=use_odometry))


def default_grid_factory(resolution_m: float) -> Grid:
    from service.core.maps.grid import OccupancyGrid  # noqa: PLC0415

    return OccupancyGrid(resolution_m=resolution_m)


def default_scan_converter(scan: Scan, use_odometry: bool) -> LaserScan:
    from service.bridge import scan_to_laser  # noqa: PLC0415

    return scan_to_laser(scan, use_odometry=use_odometry)


@dataclass(frozen=True, slots=True)
class Engine:
    """How sessions turn scans into poses and maps (swappable in tests; picklable by reference
    when its factories are module-level functions, as mapper processes need)."""

    make_estimator: EstimatorFactory = default_estimator_factory
    make_grid: GridFactory = default_grid_factory
    to_laser: ScanConverter = default_scan_converter


class MappedScan(NamedTuple):
    """The estimator's answer for one scan, in the session's map frame."""

    x_m: float
    y_m: float
    theta_rad: float
    quality: float
    flags: int
    is_keyframe: bool  # the grid took this scan in
    covariance: tuple[float, ...] = ()  # row-major 3×3 (x, y, θ); () when the estimator has none


class MapperError(Exception):
    """The mapper could not map a scan (the scan stays recorded)."""


class MapperLostError(MapperError):
    """The mapper's state is gone (its process died): rebuild it, then try again."""


class Mapper(Protocol):
    """One session's estimator and grid."""

    def map_scan(self, scan: Scan, payload: bytes | None = None) -> MappedScan:
        """Map `scan`; `payload` is its wire encoding when the caller has it (a mapper in
        another process is sent those bytes rather than the pickled `Scan`)."""
        ...

    def reset(self) -> None: ...
    def snapshot(self) -> Any: ...  # service.core.maps.grid.GridImage
    def state(self) -> bytes: ...  # for checkpoints
    def restore(self, state: bytes) -> None: ...
    def close(self) -> None: ...


MapperFactory = Callable[[str, bool, float], Mapper]  # (session id, use_odometry, resolution_m)


class LocalMapper:
    """Estimator and grid in this process."""

    def __init__(self, engine: Engine, use_odometry: bool, resolution_m: float) -> None:
        self._engine = engine
        self._use_odometry = use_odometry
        self._resolution_m = resolution_m
        self._estimator = engine.make_estimator(use_odometry)
        self._grid = engine.make_grid(resolution_m)

    def map_scan(self, scan: Scan, payload: bytes | None = None) -> MappedScan:
        laser = self._engine.to_laser(scan, self._use_odometry)
        estimate = self._estimator.process(laser)
        if estimate.is_keyframe:
            self._grid.integrate(laser, estimate.pose)
        pose = estimate.pose
        return MappedScan(
            pose.x_m,
            pose.y_m,
            pose.theta_rad,
            float(estimate.quality),
            int(estimate.flags),
            bool(estimate.is_keyframe),
            tuple(float(v) for v in getattr(estimate, "covariance", ())),
        )

    def map_payload(self, payload: bytes) -> MappedScan:
        """`map_scan` of a wire payload the service already validated (mapper processes)."""
        return self.map_scan(decode_scan(payload, max_payload_bytes=len(payload)))

    def reset(self) -> None:
        self._estimator.reset()
        self._grid = self._engine.make_grid(self._resolution_m)

    def snapshot(self) -> Any:
        return self._grid.snapshot()

    def _allowed_modules(self) -> tuple[str, ...]:
        """Where the checkpoint codec may find classes: the core and our own factories'."""
        return ("service.core", type(self._estimator).__module__, type(self._grid).__module__)

    def state(self) -> bytes:
        """Estimator and grid as data (arrays plus JSON, compressed): no code, see statecodec."""
        return statecodec.encode((self._estimator, self._grid), self._allowed_modules())

    def restore(self, state: bytes) -> None:
        estimator, grid = statecodec.decode(state, self._allowed_modules())
        if type(estimator) is not type(self._estimator) or type(grid) is not type(self._grid):
            raise statecodec.StateCodecError("checkpoint of another estimator or grid type")
        self._estimator, self._grid = estimator, grid

    def close(self) -> None:
        pass


def local_mapper_factory(engine: Engine) -> MapperFactory:
    def make(session_id: str, use_odometry: bool, resolution_m: float) -> Mapper:
        return LocalMapper(engine, use_odometry, resolution_m)

    return make


# -- mapper processes ---------------------------------------------------------------------------


def _serve(conn: multiprocessing.connection.Connection, engine: Engine) -> None:
    """A mapper process: answer requests `(op, key, *args)` with `("ok", value)` or
    `("error", text)` until the pipe closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the service stops us by closing the pipe
    mappers: dict[str, LocalMapper] = {}
    while True:
        try:
            op, key, *args = conn.recv()
        except (EOFError, OSError):
            return
        try:
            value: Any = None
            if op == "create":
                mappers[key] = LocalMapper(engine, *args)
            elif op == "drop":
                mappers.pop(key, None)
            elif key not in mappers:
                raise KeyError(f"no mapper {key!r} in this process")
            else:
                value = getattr(mappers[key], op)(*args)
            reply: tuple[str, Any] = ("ok", value)
        except Exception as err:  # reported to the caller, which logs it
            reply = ("error", f"{type(err).__name__}: {err}")
        try:
            conn.send(reply)
        except (BrokenPipeError, OSError):
            return


class MapperProcess:
    """One worker process and its pipe; one request at a time (callers queue on a lock)."""

    def __init__(self, index: int, engine: Engine) -> None:
        self.index = index
        self._engine = engine
        self._lock = threading.Lock()
        self._process: multiprocessing.process.BaseProcess | None = None
        self._conn: multiprocessing.connection.Connection | None = None
        self.generation = 0  # bumped at every (re)start: state made before it is gone
        self.mappers = 0  # sessions placed here (for placement only)
        self.restarts = 0
        self._closed = False

    def start(self) -> None:
        with self._lock:
            self._start()

    def _start(self) -> None:
        ctx = multiprocessing.get_context("spawn")  # no fork of a process with Zenoh threads
        parent, child = ctx.Pipe()
        process = ctx.Process(
            target=_serve, args=(child, self._engine), name=f"mapper-{self.index}", daemon=True
        )
        process.start()
        child.close()
        self._process, self._conn = process, parent
        self.generation += 1
        log.info("mapper process %d started (pid %s)", self.index, process.pid)

    def call(self, generation: int, op: str, key: str, *args: Any) -> Any:
        """Run `op` on mapper `key`; `MapperLostError` if the process restarted since then."""
        with self._lock:
            if self._closed:
                raise MapperError("the service is shutting down")
            if self._conn is None or self._process is None or not self._process.is_alive():
                self._restart()
            if op != "create" and generation != self.generation:
                raise MapperLostError(f"mapper process {self.index} was restarted")
            assert self._conn is not None
            try:
                self._conn.send((op, key, *args))
                status, value = self._conn.recv()
            except (EOFError, OSError) as err:
                self._discard()
                detail = err or "pipe closed"
                raise MapperLostError(f"mapper process {self.index} died: {detail}") from err
        if status != "ok":
            raise MapperError(str(value))
        return value

    def _restart(self) -> None:
        if self._process is not None:
            self.restarts += 1
            log.error(
                "mapper process %d (pid %s) is gone (exit code %s); starting it again",
                self.index,
                self._process.pid,
                self._process.exitcode,
            )
        self._discard()
        self._start()

    def _discard(self) -> None:
        if self._conn is not None:
            self._conn.close()
        if self._process is not None:
            if self._process.is_alive():
                self._process.kill()
            self._process.join(timeout=5)
        self._conn, self._process = None, None

    @property
    def pid(self) -> int | None:
        return self._process.pid if self._process is not None else None

    def close(self) -> None:
        with self._lock:
            self._closed = True
            if self._conn is not None:
                self._conn.close()  # the process sees EOF and returns
            if self._process is not None:
                self._process.join(timeout=10)
                if self._process.is_alive():
                    log.warning("mapper process %d did not stop; killing it", self.index)
                    self._process.kill()
                    self._process.join(timeout=5)
            self._conn, self._process = None, None


class RemoteMapper:
    """A session's mapper living in a `MapperProcess`."""

    def __init__(
        self, proc: MapperProcess, key: str, use_odometry: bool, resolution_m: float
    ) -> None:
        self._proc = proc
        self._key = key
        proc.call(0, "create", key, use_odometry, resolution_m)
        self._generation = proc.generation

    def _call(self, op: str, *args: Any) -> Any:
        return self._proc.call(self._generation, op, self._key, *args)

    def map_scan(self, scan: Scan, payload: bytes | None = None) -> MappedScan:
        # The wire bytes (~2.4 KiB) cross the pipe as they are: pickling the decoded `Scan`
        # (dataclass and numpy array, ~8.7 KiB) cost the service's process ~15 us a scan more.
        if payload is not None:
            return MappedScan(*self._call("map_payload", payload))
        return MappedScan(*self._call("map_scan", scan))

    def reset(self) -> None:
        self._call("reset")

    def snapshot(self) -> Any:
        return self._call("snapshot")

    def state(self) -> bytes:
        state: bytes = self._call("state")
        return state

    def restore(self, state: bytes) -> None:
        self._call("restore", state)

    def close(self) -> None:
        with contextlib.suppress(MapperError):  # a process gone or going took the state along
            self._proc.call(self._generation, "drop", self._key)
        self._proc.mappers -= 1


class MapperPool:
    """K mapper processes; each new session goes to the process with the fewest sessions."""

    def __init__(self, processes: int, engine: Engine) -> None:
        self._procs = [MapperProcess(i, engine) for i in range(processes)]
        self._lock = threading.Lock()

    def start(self) -> None:
        for proc in self._procs:
            proc.start()

    def new_mapper(self, session_id: str, use_odometry: bool, resolution_m: float) -> Mapper:
        with self._lock:
            proc = min(self._procs, key=lambda p: p.mappers)
            proc.mappers += 1
        try:
            return RemoteMapper(proc, session_id, use_odometry, resolution_m)
        except BaseException:
            proc.mappers -= 1
            raise

    @property
    def pids(self) -> list[int | None]:
        return [p.pid for p in self._procs]

    @property
    def restarts(self) -> int:
        return sum(p.restarts for p in self._procs)

    def close(self) -> None:
        for proc in self._procs:
            proc.close()
