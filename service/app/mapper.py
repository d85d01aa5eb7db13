"""Where a session's SLAM core runs: in the service's process, or in mapper processes.

One Python process estimates on one core: the work per scan holds the GIL. With
`mapper_processes` > 0 the service starts that many worker processes and places each session's
mapper in one of them (the least loaded when the session is made). The service's
process keeps Zenoh, validation, HTTP and the fan-out.

The per-scan path of an active session runs in its mapper process under a *lease* of the
session's recording (`RemoteMapper.delegate`): the service forwards each validated scan's wire
bytes without waiting (`forward`), and the process records the scan, maps it, builds, encodes
and records the pose (`_Lease.handle`), then sends back one small `Done`; the service applies it
and publishes the recorded pose bytes. So no service thread blocks on a round trip per scan, and
the service's process does no recording or pose encoding. Every other operation on the session
(checkpoint, stop, reset, idle close) first takes the lease back (`revoke`, ordered after the
scans forwarded before it: their `Done` messages are applied when it returns).

Protocol on the pipe: service → process `("call", id, op, key, args)` and `("scan", key,
payload)`; process → service `("reply", id, status, value)` and `("done", key, Done)`. One
reader thread per process in the service receives both.

A session's mapper holds its core, `service.core.slam.SlamSession`: the class
`mapping-service map` runs (front end by name, `Engine.front_end`; back end; map). `map_scan`
runs its front half (`track`). With `Engine.loop_closure` (the default) the back half (nodes,
loop search, the map's scans) goes to a background thread of the same process
(`service.app.backend.LiveBackend`), which also draws the map at the corrected poses;
`map_scan` answers with the front end's pose and the newest correction, and never waits for
that thread. Without it, the back half (the map alone) runs on the per-scan path.

A mapper process that dies (killed, out of memory) loses the state of its sessions. The process
is started again at the next call, and each of its sessions sees `MapperLostError` once: the
session then rebuilds itself from its checkpoint and recording (`MappingSession`), as a restart
does. Mapper processes die with the service (`PR_SET_PDEATHSIG`): after a `kill -9` of the
service no orphan keeps appending to a recording that the next start replays.
"""

from __future__ import annotations

import contextlib
import ctypes
import itertools
import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final, NamedTuple, Protocol

from clients.recording import RecordingReport, RecordingWriter
from clients.wire import Pose, PoseFlag, Scan, decode_scan, encode_pose
from service.app import statecodec
from service.core.frontend.scan_matcher import warm_up
from service.core.slam import (
    DEFAULT_DRAW_PERIOD_S,
    DEFAULT_FRONT_END,
    FrontEndName,
    SlamParams,
    SlamSession,
    Tracker,
    make_frontend,
)
from service.core.types import LaserScan

if TYPE_CHECKING:
    from service.app.backend import GraphSnapshot, LiveBackend
    from service.app.ingest import IngestStats
    from service.app.mapper_ingest import IngestConfig, ProcessIngest
    from service.app.metrics import Snapshot

log = logging.getLogger(__name__)

# LocalMapper.state(): 1 = (estimator, grid), 2 = {estimator, grid, back end}, 3 = {the session
# core (`SlamSession`) with every drawn scan kept, the back-half items queued}, 4 = the same with
# the map as chunks (`maps.composed`). Only 4 is read: 1 to 3 hold the map another way.
STATE_VERSION: Final = 4


EstimatorFactory = Callable[[bool], Tracker]  # use_odometry -> front end
ScanConverter = Callable[[Scan, bool], LaserScan]  # (scan, use_odometry) -> LaserScan


def default_scan_converter(scan: Scan, use_odometry: bool) -> LaserScan:
    from service.bridge import scan_to_laser  # noqa: PLC0415

    return scan_to_laser(scan, use_odometry=use_odometry)


@dataclass(frozen=True, slots=True)
class Engine:
    """How sessions turn scans into poses and maps: the settings of each session's core
    (`SlamSession`, the one `mapping-service map` runs). Picklable by reference when its
    functions are module-level ones, as mapper processes need."""

    # The front end of new sessions by name (`service.core.slam.make_frontend`): "matcher",
    # the one live front end. A session keeps its own (`SessionMeta.front_end`): each mapper is
    # made with the session's name, this one only when none is given.
    front_end: FrontEndName = DEFAULT_FRONT_END
    # The back end (loop closure, pose graph) beside the front end, in a background thread
    # (service/app/backend.py); False: the front end and its map alone.
    loop_closure: bool = True
    # The map rule's period in scan time (`SlamSession`): as `mapping-service map`.
    draw_period_s: float = DEFAULT_DRAW_PERIOD_S
    # Tests only: a front end of their own instead of `front_end`.
    make_estimator: EstimatorFactory | None = None
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
    # The back end's view when it answered: its graph revision, the newest node's correction
    # (x, y, theta: optimised ∘ front-end⁻¹, which moves this pose onto the graph) and the
    # revision of its composed map. Zeros without a back end.
    graph_revision: int = 0
    correction: tuple[float, float, float] = (0.0, 0.0, 0.0)
    image_revision: int = 0


def make_pose(mapped: MappedScan, session_id: str, robot_id: str, seq: int, stamp_ns: int) -> Pose:
    """The pose a session records and publishes for a mapped scan (both transports)."""
    return Pose(
        session_id=session_id,
        robot_id=robot_id,
        seq=seq,
        stamp_ns=stamp_ns,
        x_m=mapped.x_m,
        y_m=mapped.y_m,
        theta_rad=mapped.theta_rad,
        quality=min(max(mapped.quality, 0.0), 1.0),
        flags=PoseFlag(mapped.flags),
        covariance=mapped.covariance if len(mapped.covariance) == 9 else None,
    )


@dataclass(frozen=True, slots=True)
class LeaseSpec:
    """What a mapper process needs to record a session's scans and poses itself."""

    session_id: str
    robot_id: str
    path: str  # the recording segment appends go to
    end_offset: int | None  # where its intact records end (None: read the file to find out)
    next_seq: int  # the sequence of the next pose
    fsync_each: bool
    last_stamp_ns: int | None = None  # the last pose's stamp (the time contract's start)


class Done(NamedTuple):
    """A mapper process's answer for one forwarded scan (small: it crosses the pipe)."""

    recorded: bool  # the scan is in the recording (it counts as accepted)
    mapped: MappedScan | None  # None: estimator failure, store failure, or the process was lost
    pose_bytes: bytes | None  # the pose as recorded (`encode_pose`), published as it is
    seq: int  # the pose's sequence
    stamp_ns: int  # the scan's stamp
    error: str | None  # "store: ...", "estimator: ...", "lost: ..."
    busy_s: float  # the process's time on the scan: decode, record, map, encode, record


LOST: Final = Done(False, None, None, -1, 0, "lost: the mapper process died", 0.0)


def flat_done(done: Done) -> tuple[Any, ...]:
    """`done` as plain tuples for the pipe (a NamedTuple pickles its class by name: slower)."""
    mapped = done.mapped
    return (done.recorded, None if mapped is None else tuple(mapped), *done[2:])


_flat = flat_done


def _unflat(flat: tuple[Any, ...]) -> Done:
    mapped = flat[1]
    return Done(flat[0], None if mapped is None else MappedScan(*mapped), *flat[2:])


class MapperError(Exception):
    """The mapper could not map a scan (the scan stays recorded)."""


class MapperLostError(MapperError):
    """The mapper's state is gone (its process died): rebuild it, then try again."""


class Mapper(Protocol):
    """One session's core: front end, back end and map."""

    def map_scan(self, scan: Scan, payload: bytes | None = None, seq: int = -1) -> MappedScan:
        """Map `scan`; `payload` is its wire encoding when the caller has it (a mapper in
        another process is sent those bytes rather than the pickled `Scan`); `seq` is the
        sequence its pose will have (the back end's nodes are named by it)."""
        ...

    def graph(self, known_revision: int = -1) -> GraphSnapshot | None:
        """The back end's graph; None when it is still `known_revision` (or there is none)."""
        ...

    def finish(self) -> None:
        """The session's scans are over: the core's final search and batch optimisation."""
        ...

    def reset(self) -> None: ...
    def snapshot(self) -> Any: ...  # GridImage; None while the back end draws it: ask again
    def state(self, pack_path: str | None = None) -> bytes:
        """For checkpoints; with `pack_path`, frozen arrays go to that `statecodec.ArrayPack`
        once (fsynced when this returns) and the bytes refer to them."""
        ...

    def restore(self, state: bytes, pack_path: str | None = None) -> None: ...
    def close(self) -> None: ...


# (session id, use_odometry, resolution_m, front end): the session's settings (`SessionMeta`).
MapperFactory = Callable[[str, bool, float, FrontEndName], Mapper]


class LocalMapper:
    """One session's core (`service.core.slam.SlamSession`: front end, back end, map) in this
    process. The scan's front half runs here, at once; with `engine.loop_closure` its back
    half runs in the process's back-end thread (`LiveBackend`), else here too."""

    def __init__(
        self,
        engine: Engine,
        use_odometry: bool,
        resolution_m: float,
        front_end: FrontEndName | None = None,
    ) -> None:
        """`front_end`: the session's (None: `engine.front_end`)."""
        self._engine = engine
        self._front_end: FrontEndName = front_end if front_end is not None else engine.front_end
        self._use_odometry = use_odometry
        self._resolution_m = resolution_m
        self._session = self._new_session()
        self._backend: LiveBackend | None = None
        self._array_pack: statecodec.ArrayPack | None = None  # `state`, `restore`
        if engine.loop_closure:
            from service.app.backend import LiveBackend  # noqa: PLC0415  # gtsam: only when used

            self._backend = LiveBackend(self._session)

    def _new_session(self) -> SlamSession:
        engine = self._engine
        frontend: Tracker
        if engine.make_estimator is not None:
            frontend = engine.make_estimator(self._use_odometry)
        else:
            frontend = make_frontend(self._front_end, use_odometry=self._use_odometry)
        return SlamSession(
            SlamParams(loop_closure=engine.loop_closure),
            frontend,
            map_resolution_m=self._resolution_m,
            draw_period_s=engine.draw_period_s,
            keep_trajectory=False,  # the session records its poses itself
        )

    def map_scan(self, scan: Scan, payload: bytes | None = None, seq: int = -1) -> MappedScan:
        laser = self._engine.to_laser(scan, self._use_odometry)
        tracked = self._session.track(laser)
        estimate = tracked.estimate
        pose = estimate.pose
        covariance = tuple(float(v) for v in getattr(estimate, "covariance", ()))
        backend = self._backend
        revision, image_revision = 0, 0
        correction = (0.0, 0.0, 0.0)
        if backend is None:
            self._session.integrate(tracked, seq)
        else:
            if tracked.node or tracked.drawn:
                backend.submit(tracked, seq)
            revision, c, image_revision = backend.correction()
            correction = (c.x_m, c.y_m, c.theta_rad)
        return MappedScan(
            pose.x_m,
            pose.y_m,
            pose.theta_rad,
            float(estimate.quality),
            int(estimate.flags),
            bool(estimate.is_keyframe),
            covariance,
            revision,
            correction,
            image_revision,
        )

    def map_payload(self, payload: bytes, seq: int = -1) -> MappedScan:
        """`map_scan` of a wire payload the service already validated (mapper processes)."""
        return self.map_scan(decode_scan(payload, max_payload_bytes=len(payload)), None, seq)

    def graph(self, known_revision: int = -1) -> GraphSnapshot | None:
        if self._backend is None:
            return None
        snap = self._backend.snapshot()
        return None if snap.revision == known_revision else snap

    def wait_backend(self, timeout_s: float = 60.0) -> bool:
        """Until the back end has every node and its map drawn (tests and benchmarks)."""
        return self._backend is None or self._backend.wait_idle(timeout_s)

    def finish(self) -> None:
        """The end of the session's scans: the core's final loop search and batch
        optimisation (as `mapping-service map` ends), in the back-end thread."""
        if self._backend is not None:
            self._backend.finish()
        else:
            self._session.finish()

    def reset(self) -> None:
        self._session = self._new_session()
        self._array_pack = None  # a reset is a new recording epoch: a new pack
        if self._backend is not None:
            self._backend.reset(self._session)

    delegates = False  # records nothing itself: the session's store does

    def snapshot(self) -> Any:
        """The map (`GridImage`) at its latest revision; None while the back end draws it
        (`LiveBackend.image`): ask again."""
        if self._backend is None:
            return self._session.map_image()
        return self._backend.image()

    def _allowed_modules(self) -> tuple[str, ...]:
        """Where the checkpoint codec may find classes: the core and our own front end's."""
        return ("service.core", type(self._session.frontend).__module__)

    def _pack(self, pack_path: str | None) -> statecodec.ArrayPack | None:
        """The session's array pack (one per recording epoch: a new path is a new pack)."""
        if pack_path is None:
            return None
        if self._array_pack is None or self._array_pack.path != Path(pack_path):
            self._array_pack = statecodec.ArrayPack(Path(pack_path))
        return self._array_pack

    def state(self, pack_path: str | None = None) -> bytes:
        """The core and the back-half items still queued, as data (arrays plus JSON,
        compressed): no code, see statecodec. Version 4: `{"version", "session", "queued"}`."""
        allowed = self._allowed_modules()
        pack = self._pack(pack_path)

        def encode(queued: list[Any]) -> bytes:
            tree = {"version": STATE_VERSION, "session": self._session, "queued": queued}
            return statecodec.encode(tree, allowed, pack)

        # The back end's thread is held off the core while it is encoded.
        return self._backend.state(encode) if self._backend is not None else encode([])

    def restore(self, state: bytes, pack_path: str | None = None) -> None:
        tree = statecodec.decode(state, self._allowed_modules(), self._pack(pack_path))
        version = (
            tree.get("version")
            if isinstance(tree, dict)
            else 1
            if isinstance(tree, tuple)
            else None
        )
        if version != STATE_VERSION:
            raise statecodec.StateCodecError(
                f"mapper state version {version} is not {STATE_VERSION} (versions 1 to 3 "
                "hold the map another way: the recording is replayed instead)"
            )
        session = tree["session"]
        if not isinstance(session, SlamSession):
            raise statecodec.StateCodecError("not a session core")
        if type(session.frontend) is not type(self._session.frontend):
            raise statecodec.StateCodecError("checkpoint of another front end")
        if session.params.loop_closure != self._engine.loop_closure:
            raise statecodec.StateCodecError("checkpoint with loop closure set otherwise")
        self._session = session
        if self._backend is not None:
            self._backend.restore(session, list(tree["queued"]))

    def close(self) -> None:
        if self._backend is not None:
            self._backend.close()


def local_mapper_factory(engine: Engine) -> MapperFactory:
    def make(
        session_id: str, use_odometry: bool, resolution_m: float, front_end: FrontEndName
    ) -> Mapper:
        return LocalMapper(engine, use_odometry, resolution_m, front_end)

    return make


# -- mapper processes ---------------------------------------------------------------------------


class _Lease:
    """A session's per-scan path inside a mapper process, while it holds the recording."""

    def __init__(self, spec: LeaseSpec, mapper: LocalMapper) -> None:
        self.spec = spec
        self.mapper = mapper
        self.next_seq = spec.next_seq
        end = spec.end_offset
        report = RecordingReport(valid_end=end, size_bytes=end) if end is not None else None
        self.writer = RecordingWriter(
            spec.path, fsync_every=1 if spec.fsync_each else 0, report=report
        )

    def handle(self, payload: bytes, scan: Scan | None = None) -> Done:
        """The per-scan path: record the scan, map it, record its pose (in this order: a scan
        is durable before it counts, its pose before anyone is told). `scan` is the payload
        decoded, when the caller validated it here."""
        t0 = time.perf_counter()
        if scan is None:  # validated by the service
            scan = decode_scan(payload, max_payload_bytes=len(payload))
        seq = self.next_seq
        try:
            self.writer.append(payload)
        except Exception as err:  # disk full, I/O error: not recorded, not accepted
            return Done(False, None, None, seq, scan.stamp_ns, f"store: {err}", 0.0)
        try:
            mapped = self.mapper.map_scan(scan, payload, seq)
        except Exception as err:  # recorded; a replay meets the same failure
            log.debug("estimator failed", exc_info=True)
            busy = time.perf_counter() - t0
            return Done(True, None, None, seq, scan.stamp_ns, f"estimator: {err!r}", busy)
        pose = make_pose(mapped, self.spec.session_id, self.spec.robot_id, seq, scan.stamp_ns)
        encoded = encode_pose(pose)
        try:
            self.writer.append(encoded)
        except Exception as err:
            return Done(True, None, None, seq, scan.stamp_ns, f"store: {err}", 0.0)
        self.next_seq = seq + 1
        return Done(True, mapped, encoded, seq, scan.stamp_ns, None, time.perf_counter() - t0)

    def close(self) -> int:
        """fsync and close the recording (a checkpoint may follow); its end offset."""
        self.writer.sync()
        self.writer.close()
        return self.writer.end_offset


def _die_with_parent() -> None:
    """SIGKILL this process when the service dies (Linux): an orphan must not append to a
    recording that the next start replays."""
    if not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(Exception):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() == 1:  # the service died before the line above
        os._exit(1)


def _serve(
    conn: multiprocessing.connection.Connection,
    engine: Engine,
    ingest_cfg: IngestConfig | None = None,
    log_level: int = logging.WARNING,
) -> None:
    """A mapper process: answer calls and map forwarded scans, in the order they come, until
    the pipe closes. With `ingest_cfg` it also ingests its share of the robots' scans from
    Zenoh itself (service/app/mapper_ingest.py)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the service stops us by closing the pipe
    _die_with_parent()
    # A spawned process starts without the service's logging: the same lines, with its name.
    logging.basicConfig(
        level=log_level,
        format=f"%(asctime)s %(levelname)-7s [mapper-{os.getpid()}] %(name)s: %(message)s",
        stream=sys.stderr,
    )
    # The matcher's compiled kernels load (or compile) now, not on a robot's first scan.
    threading.Thread(target=warm_up, name="warm-up", daemon=True).start()
    mappers: dict[str, LocalMapper] = {}
    leases: dict[str, _Lease] = {}
    # The pipe loop and the ingest worker both use mappers and leases: one at a time.
    work_lock = threading.Lock()
    send_lock = threading.Lock()

    def send(message: tuple[Any, ...]) -> None:
        with send_lock:
            conn.send(message)

    host = None
    if ingest_cfg is not None:
        from service.app.mapper_ingest import ProcessIngest  # noqa: PLC0415  # imports sessions

        host = ProcessIngest(ingest_cfg, work_lock, leases, send)
        host.start()
    try:
        _serve_loop(
            conn,
            engine,
            mappers=mappers,
            leases=leases,
            work_lock=work_lock,
            send=send,
            host=host,
        )
    finally:
        if host is not None:
            host.close()


def _serve_loop(
    conn: multiprocessing.connection.Connection,
    engine: Engine,
    *,
    mappers: dict[str, LocalMapper],
    leases: dict[str, _Lease],
    work_lock: threading.Lock,
    send: Callable[[tuple[Any, ...]], None],
    host: ProcessIngest | None,
) -> None:
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        out: tuple[Any, ...]
        if message[0] == "exit":
            return
        if message[0] == "scan":
            _, key, payload = message
            with work_lock:
                lease = leases.get(key)
                if lease is None:  # cannot happen: the service forwards only under a lease
                    done = Done(False, None, None, -1, 0, "lost: no lease", 0.0)
                else:
                    try:
                        done = lease.handle(payload)
                    except Exception as err:
                        done = Done(False, None, None, -1, 0, f"store: {err}", 0.0)
            out = ("done", key, _flat(done))
        else:
            _, req, op, key, args = message
            try:
                with work_lock:
                    try:
                        value = _call(
                            op, key, args, engine=engine, mappers=mappers, leases=leases, host=host
                        )
                    finally:
                        if host is not None:
                            host.flush()  # the scans mapped before this reply go first
                out = ("reply", req, "ok", value)
            except Exception as err:  # reported to the caller, which logs it
                out = ("reply", req, "error", f"{type(err).__name__}: {err}")
        try:
            send(out)
        except (BrokenPipeError, OSError):
            return


def _call(
    op: str,
    key: str,
    args: tuple[Any, ...],
    *,
    engine: Engine,
    mappers: dict[str, LocalMapper],
    leases: dict[str, _Lease],
    host: ProcessIngest | None,
) -> Any:
    """One call of the service on mapper `key` (work lock held)."""
    value: Any = None
    if op == "assign":
        if host is not None:
            host.assign(key, args[0])
    elif op == "activate":
        if host is not None:
            host.activate(args[0], key)
    elif op == "deactivate":
        if host is not None:
            host.deactivate(args[0], key)
    elif op == "create":
        mappers[key] = LocalMapper(engine, *args)
    elif op == "drop":
        mappers.pop(key, None)
        lease = leases.pop(key, None)
        if lease is not None:
            lease.close()
    elif key not in mappers:
        raise KeyError(f"no mapper {key!r} in this process")
    elif op == "delegate":
        old = leases.pop(key, None)
        if old is not None:
            old.close()
        leases[key] = _Lease(args[0], mappers[key])
        if host is not None:
            host.delegated(args[0])
    elif op == "revoke":
        lease = leases.pop(key, None)
        value = lease.close() if lease is not None else None
    else:
        value = getattr(mappers[key], op)(*args)
    return value


OnDone = Callable[[Done], None]
# (process label, generation, its metrics, its ingest's counts): mapper processes that ingest.
OnStats = Callable[[str, int, "Snapshot", "IngestStats"], None]


class MapperProcess:
    """One worker process and its pipe. Any thread may call or forward; one reader thread per
    started process receives every answer, in the order the process sent them."""

    def __init__(
        self,
        index: int,
        engine: Engine,
        spawner: ThreadPoolExecutor | None = None,
        *,
        ingest: IngestConfig | None = None,
        tasks: ThreadPoolExecutor | None = None,
        activations: Callable[[int], list[tuple[str, str, str]]] | None = None,
        on_stats: OnStats | None = None,
    ) -> None:
        self.index = index
        self._engine = engine
        # With `ingest`, the process subscribes to its robots' scans itself; the messages it
        # sends unasked (`pushed`, `want`, `stats`) go to the session's mapper here (`remotes`)
        # and the runtime (`on_stats`); work that takes a session's lock runs on `tasks`.
        self.ingest = ingest
        self._tasks = tasks
        self._activations = activations
        self._on_stats = on_stats
        self.remotes: dict[str, RemoteMapper] = {}
        # Processes are started from one long-lived thread: the parent-death signal fires when
        # the *thread* that started a process ends, and ingest threads come and go.
        self._spawner = spawner
        self._lock = threading.Lock()  # process lifecycle, pending calls, in-flight scans
        self._send_lock = threading.Lock()
        self._process: multiprocessing.process.BaseProcess | None = None
        self._conn: multiprocessing.connection.Connection | None = None
        self._calls: dict[int, Future[Any]] = {}
        self._inflight: dict[str, deque[OnDone]] = {}
        self._ids = itertools.count()
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
            target=_serve,
            args=(child, self._engine, self.ingest, logging.getLogger().getEffectiveLevel()),
            name=f"mapper-{self.index}",
            daemon=True,
        )
        if self._spawner is not None:
            self._spawner.submit(process.start).result()
        else:
            process.start()
        child.close()
        self._process, self._conn = process, parent
        self.generation += 1
        reader = threading.Thread(
            target=self._read,
            args=(parent, self.generation),
            name=f"mapper-{self.index}-reader",
            daemon=True,
        )
        reader.start()
        if self._activations is not None:
            # A new process knows no session: tell it which of its robots have one (their
            # scans are held until the lease comes). Replies are not waited for.
            with self._send_lock:
                for op, key, arg in self._activations(self.index):
                    parent.send(("call", -1, op, key, (arg,)))
        log.info("mapper process %d started (pid %s)", self.index, process.pid)

    def _read(self, conn: multiprocessing.connection.Connection, generation: int) -> None:
        """Deliver replies and `Done`s until the pipe ends; then fail whatever waited."""
        while True:
            try:
                message = conn.recv()
            except (EOFError, OSError):
                break
            kind = message[0]
            if kind == "pushed":
                for key, flat in message[1]:
                    self._pushed(key, _unflat(flat))
            elif kind == "want":
                self._task(message[1], "on_want")
            elif kind == "stats":
                if self._on_stats is not None:
                    with contextlib.suppress(Exception):
                        self._on_stats(f"mapper-{self.index}", generation, *message[1:])
            elif kind == "done":
                _, key, flat = message
                done = _unflat(flat)
                with self._lock:
                    waiting = self._inflight.get(key)
                    on_done = waiting.popleft() if waiting else None
                if on_done is not None:
                    try:
                        on_done(done)
                    except Exception:  # the reader must go on: other sessions wait on it
                        log.exception("applying a mapped scan of %s failed", key)
            else:
                _, req, status, value = message
                with self._lock:
                    future = self._calls.pop(req, None)
                if future is not None:
                    if status == "ok":
                        future.set_result(value)
                    else:
                        future.set_exception(MapperError(str(value)))
        self._lost(generation)

    def _pushed(self, key: str, done: Done) -> None:
        """A scan the process ingested itself, recorded and mapped under `key`'s lease."""
        remote = self.remotes.get(key)
        handler = remote.on_pushed if remote is not None else None
        if handler is not None:
            try:
                handler(done)
            except Exception:  # the reader must go on: other sessions wait on it
                log.exception("applying a mapped scan of %s failed", key)

    def _task(self, key: str | None, name: str) -> None:
        """Run a session's handler `name` on the task thread (it takes the session's lock,
        which may wait for a reply this reader delivers)."""
        remotes = list(self.remotes.values()) if key is None else [self.remotes.get(key)]
        for remote in remotes:
            handler = getattr(remote, name, None) if remote is not None else None
            if handler is not None and self._tasks is not None:
                with contextlib.suppress(RuntimeError):  # shut down
                    self._tasks.submit(handler)

    def _lost(self, generation: int) -> None:
        with self._lock:
            if generation != self.generation:
                return
            calls, self._calls = self._calls, {}
            inflight, self._inflight = self._inflight, {}
        if self.ingest is not None and not self._closed:
            self._task(None, "on_lost")  # nothing else would rebuild its sessions
        for future in calls.values():
            future.set_exception(MapperLostError(f"mapper process {self.index} died"))
        for waiting in inflight.values():
            for on_done in waiting:
                with contextlib.suppress(Exception):
                    on_done(LOST)

    def _alive_conn(self, generation: int, op: str) -> multiprocessing.connection.Connection:
        """The pipe of the running process, started again if it died (`_lock` held)."""
        if self._closed:
            raise MapperError("the service is shutting down")
        if self._conn is None or self._process is None or not self._process.is_alive():
            self._restart()
        if op != "create" and generation != self.generation:
            raise MapperLostError(f"mapper process {self.index} was restarted")
        assert self._conn is not None
        return self._conn

    def call(self, generation: int, op: str, key: str, *args: Any) -> Any:
        """Run `op` on mapper `key`; `MapperLostError` if the process restarted since then."""
        future: Future[Any] = Future()
        with self._lock:
            conn = self._alive_conn(generation, op)
            req = next(self._ids)
            self._calls[req] = future
        try:
            with self._send_lock:
                conn.send(("call", req, op, key, args))
        except (OSError, ValueError) as err:
            with self._lock:
                self._calls.pop(req, None)
            raise MapperLostError(f"mapper process {self.index} died: {err}") from err
        return future.result()

    def notify(self, op: str, key: str, *args: Any) -> None:
        """Send a call nobody waits for (the process applies it in order); nothing when the
        process is not running: a start tells it the activations anyway."""
        with self._lock:
            alive = self._process is not None and self._process.is_alive()
            conn = self._conn if alive else None
        if conn is None:
            return
        with contextlib.suppress(OSError, ValueError), self._send_lock:
            conn.send(("call", -1, op, key, args))

    def forward(self, generation: int, key: str, payload: bytes, on_done: OnDone) -> None:
        """Send a scan to mapper `key`'s lease; `on_done(Done)` runs on the reader thread
        (with `LOST` if the process dies first)."""
        with self._lock:
            conn = self._alive_conn(generation, "scan")
            self._inflight.setdefault(key, deque()).append(on_done)
        try:
            with self._send_lock:
                conn.send_bytes(_pickled_scan(key, payload))
        except (OSError, ValueError) as err:
            with self._lock:
                waiting = self._inflight.get(key)
                if waiting and on_done in waiting:
                    waiting.remove(on_done)
            raise MapperLostError(f"mapper process {self.index} died: {err}") from err

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
        calls, self._calls = self._calls, {}
        inflight, self._inflight = self._inflight, {}
        for future in calls.values():
            future.set_exception(MapperLostError(f"mapper process {self.index} was restarted"))
        for waiting in inflight.values():
            for on_done in waiting:
                with contextlib.suppress(Exception):
                    on_done(LOST)

    @property
    def pid(self) -> int | None:
        return self._process.pid if self._process is not None else None

    def close(self) -> None:
        with self._lock:
            self._closed = True
            conn, process = self._conn, self._process
            self._conn, self._process = None, None
        if conn is not None:
            # A close alone is not seen while our reader thread still blocks on the pipe.
            with contextlib.suppress(OSError, ValueError), self._send_lock:
                conn.send(("exit",))
            conn.close()
        if process is not None:
            process.join(timeout=10)
            if process.is_alive():
                log.warning("mapper process %d did not stop; killing it", self.index)
                process.kill()
                process.join(timeout=5)


def _pickled_scan(key: str, payload: bytes) -> bytes:
    from multiprocessing.reduction import ForkingPickler  # noqa: PLC0415

    return bytes(ForkingPickler.dumps(("scan", key, payload)))


class RemoteMapper:
    """A session's mapper living in a `MapperProcess`."""

    delegates = True  # can record the session's scans and poses itself (a lease)

    def __init__(
        self,
        proc: MapperProcess,
        key: str,
        use_odometry: bool,
        resolution_m: float,
        front_end: FrontEndName,
    ) -> None:
        self._proc = proc
        self._key = key
        # With a process that ingests (its session sets these): a scan it recorded and mapped
        # itself (on the reader thread), a scan held for want of the lease, the process died
        # (both on the task thread).
        self.on_pushed: OnDone | None = None
        self.on_want: Callable[[], None] | None = None
        self.on_lost: Callable[[], None] | None = None
        proc.call(0, "create", key, use_odometry, resolution_m, front_end)
        self._generation = proc.generation
        proc.remotes[key] = self

    def later(self, fn: Callable[[], None]) -> None:
        """Run `fn` on the pool's task thread (it may take a session's lock)."""
        tasks = self._proc._tasks
        if tasks is not None:
            with contextlib.suppress(RuntimeError):  # shut down
                tasks.submit(fn)

    @property
    def pushes(self) -> bool:
        """Its process ingests the robot's scans itself: the session leases its recording
        there whenever it is active, and is told of each scan (`on_pushed`)."""
        return self._proc.ingest is not None

    def _call(self, op: str, *args: Any) -> Any:
        return self._proc.call(self._generation, op, self._key, *args)

    def map_scan(self, scan: Scan, payload: bytes | None = None, seq: int = -1) -> MappedScan:
        # The wire bytes (~2.4 KiB) cross the pipe as they are: pickling the decoded `Scan`
        # (dataclass and numpy array, ~8.7 KiB) cost the service's process ~15 us a scan more.
        if payload is not None:
            return MappedScan(*self._call("map_payload", payload, seq))
        return MappedScan(*self._call("map_scan", scan, None, seq))

    def graph(self, known_revision: int = -1) -> GraphSnapshot | None:
        snap: GraphSnapshot | None = self._call("graph", known_revision)
        return snap

    def wait_backend(self, timeout_s: float = 60.0) -> bool:
        return bool(self._call("wait_backend", timeout_s))

    def delegate(self, spec: LeaseSpec) -> None:
        """Hand the session's recording to the process: it records and maps what `forward`
        sends until `revoke`."""
        self._call("delegate", spec)

    def forward(self, payload: bytes, on_done: OnDone) -> None:
        self._proc.forward(self._generation, self._key, payload, on_done)

    def revoke(self) -> int | None:
        """Take the recording back (fsynced and closed); where its intact records end."""
        end: int | None = self._call("revoke")
        return end

    def finish(self) -> None:
        self._call("finish")

    def reset(self) -> None:
        self._call("reset")

    def snapshot(self) -> Any:
        return self._call("snapshot")

    def state(self, pack_path: str | None = None) -> bytes:
        state: bytes = self._call("state", pack_path)  # the pack is written by the process
        return state

    def restore(self, state: bytes, pack_path: str | None = None) -> None:
        self._call("restore", state, pack_path)

    def close(self) -> None:
        if self._proc.remotes.get(self._key) is self:
            del self._proc.remotes[self._key]
        with contextlib.suppress(MapperError):  # a process gone or going took the state along
            self._proc.call(self._generation, "drop", self._key)
        self._proc.mappers -= 1


class MapperPool:
    """K mapper processes; each new session goes to the process with the fewest sessions, or,
    when the processes ingest (`ingest`), to the process that owns its robot's scans."""

    def __init__(
        self,
        processes: int,
        engine: Engine,
        ingest: Callable[[int], IngestConfig] | None = None,
        on_stats: OnStats | None = None,
    ) -> None:
        self._spawner = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mapper-spawn")
        # Leases asked for, rebuilds after a process died: one at a time, off the readers.
        self._tasks = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mapper-tasks")
        self._lock = threading.Lock()
        self._active: dict[str, str] = {}  # robot id -> its active session's id (ingest)
        # Robot id -> the process that takes its scans while it has an active session: the
        # least busy when the session starts (a hash alone put 8 of 10 robots in one of two
        # processes); robots without one go by `owner` (a stable hash). Every process knows
        # every assignment, so that exactly one takes each scan.
        self._assigned: dict[str, int] = {}
        self._robot_of: dict[str, str] = {}  # session id -> robot id (placement)
        self.ingests = ingest is not None
        self._procs = [
            MapperProcess(
                i,
                engine,
                self._spawner,
                ingest=ingest(i) if ingest is not None else None,
                tasks=self._tasks,
                activations=self._activations if ingest is not None else None,
                on_stats=on_stats,
            )
            for i in range(processes)
        ]

    def _owner(self, robot_id: str) -> MapperProcess:
        from service.app.mapper_ingest import owner  # noqa: PLC0415  # imports sessions

        index = self._assigned.get(robot_id)
        return self._procs[owner(robot_id, len(self._procs)) if index is None else index]

    def _activations(self, index: int) -> list[tuple[str, str, str]]:
        """What a (re)started process must be told: every assignment, its active sessions."""
        with self._lock:
            assigned = list(self._assigned.items())
            active = [(r, s) for r, s in self._active.items() if self._owner(r).index == index]
        return [("assign", r, str(i)) for r, i in assigned] + [
            ("activate", s, r) for r, s in active
        ]

    def activate(self, robot_id: str, session_id: str) -> None:
        """`robot_id`'s scans belong to `session_id` (its owning process holds them until the
        session leases its recording there)."""
        if not self.ingests:
            return
        with self._lock:
            self._active[robot_id] = session_id
            self._robot_of[session_id] = robot_id
            index = self._assigned.get(robot_id)
            if index is None:
                load = [0] * len(self._procs)
                for i in self._assigned.values():
                    load[i] += 1
                index = self._assigned[robot_id] = min(range(len(load)), key=load.__getitem__)
        for proc in self._procs:
            proc.notify("assign", robot_id, str(index))
        self._procs[index].notify("activate", session_id, robot_id)

    def deactivate(self, robot_id: str, session_id: str) -> None:
        if not self.ingests:
            return
        with self._lock:
            proc = self._owner(robot_id)
            if self._active.get(robot_id) != session_id:
                return
            del self._active[robot_id]
            self._assigned.pop(robot_id, None)
        proc.notify("deactivate", session_id, robot_id)
        for other in self._procs:
            other.notify("assign", robot_id, "")

    def place(self, session_id: str, robot_id: str) -> None:
        """Where `session_id`'s mapper goes when it is made (a stopped session's too)."""
        with self._lock:
            self._robot_of[session_id] = robot_id

    def start(self) -> None:
        for proc in self._procs:
            proc.start()

    def new_mapper(
        self, session_id: str, use_odometry: bool, resolution_m: float, front_end: FrontEndName
    ) -> Mapper:
        with self._lock:
            robot_id = self._robot_of.get(session_id) if self.ingests else None
            if robot_id is not None:
                proc = self._owner(robot_id)
            else:
                proc = min(self._procs, key=lambda p: p.mappers)
            proc.mappers += 1
        try:
            return RemoteMapper(proc, session_id, use_odometry, resolution_m, front_end)
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
        self._tasks.shutdown(wait=False, cancel_futures=True)
        self._spawner.shutdown(wait=False)
