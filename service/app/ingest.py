"""Scan ingest: the Zenoh callback, per-robot bounded queues, and a small pool of workers.

Why per-robot queues and not one `RingChannel`: a single ring shared by the fleet lets one
chatty or hostile publisher evict every other robot's scans, and a ring drops silently. Here the
Zenoh callback only reads the key, copies the payload and appends it to its robot's deque under
a lock held for microseconds; when the deque is full the oldest scan is dropped and counted. The
callback never decodes, never touches the disk and never calls Zenoh, so it cannot stall
Zenoh's receive thread.

Why a pool (one thread by default) and not a thread per robot: the work per scan is Python and
numpy under the GIL, so threads never add a core; ten busy threads instead hand the GIL back and
forth at every numpy call that releases it, which measured 1.5-2x the CPU per scan of the same
work done by one thread. Robots with queued scans wait in a ready line and the workers serve it
round-robin, one scan per turn, so every robot gets its share and each robot's scans are still
processed in order by one worker at a time.

Why newcomers share one queue: a robot's state (its queue, its metrics series, its place
under `max_robots`) is made only by a payload that decodes and validates, never by a key
alone, or junk on made-up keys would lock real robots out. Payloads of robots not tracked yet
wait in one bounded queue (drop oldest, counted) that the workers serve like a robot; the first
valid one adopts its robot. A robot without an active session that falls silent for
`robot_idle_s` is forgotten; one with a session always gets a place (sessions have their own
limit), so a created session is never starved by robots without one.

Time: each scan's host stamp must be in ROS time (`limits.in_ros_time`), and, while its robot
has a session, after the previous scan mapped in that session: a duplicate or a step back is
refused (`stamp_duplicate`, `stamp_backwards`), a jump beyond `max_stamp_gap_s` is mapped but
counted and logged (`stamp_gap`). docs/wire-format.md, "Time", is the contract.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import zenoh

from clients.keyexpr import robot_id_from_key
from clients.wire import DecodeError, Pose, Scan, decode_scan, is_valid_robot_id
from service.app.errors import ServiceError
from service.app.limits import ROS_TIME_MAX_NS, in_ros_time
from service.app.metrics import SCAN_SECONDS_BUCKETS, Labels, Metrics, labels
from service.app.publishers import PublisherStatus, source_id_of
from service.app.sessions import DEFERRED, Ingested
from service.app.settings import IngestSettings

log = logging.getLogger(__name__)

_MAX_LOGGED_PAIRS = 4096
# A (reason, robot) logged once is logged again at most this often, with how many were only
# counted meanwhile.
_LOG_AGAIN_S = 60.0
# Junk is cheap to refuse: a newcomer turn refuses up to this many before yielding its turn.
_NEWCOMER_BATCH = 32
_ANY_ROBOT = ""  # the log key of refusals of robots that are not tracked (ids are made up)

SCANS_ACCEPTED = "mapping_scans_accepted_total"
SCANS_REJECTED = "mapping_scans_rejected_total"
SCANS_UNMAPPED = "mapping_scans_unmapped_total"
SCANS_DROPPED = "mapping_scans_dropped_total"
SCAN_SECONDS = "mapping_scan_processing_seconds"
QUEUE_DEPTH = "mapping_ingest_queue_depth"
ROBOTS_SEEN = "mapping_robots_seen"
ROBOTS_TRACKED = "mapping_ingest_robots"
ROBOTS_LIMIT = "mapping_ingest_max_robots"
ROBOTS_FORGOTTEN = "mapping_ingest_robots_forgotten_total"
NEWCOMERS_QUEUED = "mapping_ingest_newcomer_queue_depth"
PAYLOADS = "mapping_ingest_payloads_total"
STAMP_ANOMALIES = "mapping_scan_stamp_anomalies_total"
# Series of a robot that go when the robot is forgotten.
_PER_ROBOT = (SCANS_UNMAPPED, SCANS_DROPPED, STAMP_ANOMALIES)


def declare_metrics(
    metrics: Metrics,
    depths: Callable[[], list[tuple[Labels, float]]],
    tracked: Callable[[], list[tuple[Labels, float]]],
    newcomers: Callable[[], list[tuple[Labels, float]]],
) -> None:
    metrics.counter(SCANS_ACCEPTED, "Scans recorded and mapped, by robot.")
    metrics.counter(SCANS_REJECTED, "Scans refused by validation, by reason.")
    metrics.counter(SCANS_UNMAPPED, "Valid scans from robots without an active session.")
    metrics.counter(
        SCANS_DROPPED,
        "Scans not processed: queue_full (oldest dropped), newcomer_queue_full (a robot not "
        "tracked yet; oldest dropped), too_many_robots, store_error, mapper_lost (its mapper "
        "process died before recording it).",
    )
    metrics.counter(
        STAMP_ANOMALIES,
        "Scans of a robot with a session whose host stamp was out of ROS time, not after the "
        "previous one (refused: stamp_out_of_range, stamp_backwards, stamp_duplicate) or beyond "
        "the gap limit after it (mapped: stamp_gap).",
    )
    metrics.counter(
        PAYLOADS,
        "Scan payloads taken in, by process: main (the service's) or mapper-<i> (mapper "
        "processes that ingest their robots' scans themselves).",
    )
    metrics.counter(ROBOTS_FORGOTTEN, "Robots without a session forgotten after falling silent.")
    metrics.gauge(ROBOTS_TRACKED, "Robots with ingest state (a queue).", tracked)
    metrics.gauge(ROBOTS_LIMIT, "Robots without a session that ingest tracks at most.")
    metrics.gauge(
        NEWCOMERS_QUEUED, "Payloads of robots not tracked yet, waiting for validation.", newcomers
    )
    metrics.histogram(
        SCAN_SECONDS,
        "Worker time per accepted scan: decode, record, estimate, map, publish.",
        SCAN_SECONDS_BUCKETS,
    )
    metrics.gauge(QUEUE_DEPTH, "Scans waiting in each robot's ingest queue.", depths)


@dataclass(eq=False)
class _RobotQueue:
    robot_id: str
    depth: int
    items: deque[bytes] = field(default_factory=deque)
    scheduled: bool = False  # in the ready line or in a worker's hands (guarded by Ingest._lock)
    busy: bool = False  # a worker holds one of its scans
    last_received_ns: int = 0  # wall clock, for /health
    last_received_mono_ns: int = 0  # for forgetting a silent robot
    # The time contract, touched only by the worker holding the robot's one scan in flight:
    stamp_session: str | None = None  # the session `last_stamp_ns` belongs to
    last_stamp_ns: int | None = None  # host stamp of the last scan mapped in that session
    stamps_refused: int = 0
    stamp_gaps: int = 0


@dataclass(eq=False)
class _Newcomers:
    """Payloads (robot id, payload, source) of robots not tracked yet, in arrival order."""

    depth: int
    items: deque[tuple[str, bytes, str | None]] = field(default_factory=deque)
    scheduled: bool = False
    busy: bool = False


@dataclass(frozen=True, slots=True)
class RobotStatus:
    robot_id: str
    queue_depth: int
    last_received_ns: int
    stamps_refused: int = 0
    stamp_gaps: int = 0


@dataclass(frozen=True, slots=True)
class IngestStats:
    """What a mapper process's ingest reports to the service now and then (with
    `ingest_in_mappers`): small, one entry per robot it tracks (at most `max_robots`)."""

    robots: tuple[RobotStatus, ...]
    newcomers_queued: int
    robots_forgotten: int
    store_errors: int
    publishers: tuple[PublisherStatus, ...] = ()  # the process's guard, for its robots


class SessionLookup(Protocol):
    """Where ingest finds a robot's active session (`SessionManager`, or a mapper process's
    table of the sessions it holds leases for)."""

    def active_for(self, robot_id: str) -> Any: ...


@dataclass(frozen=True, slots=True)
class IngestSummary:
    """Counts for /health: one entry per reason, never one per robot id."""

    robots_tracked: int
    max_robots: int
    robots_forgotten: int
    newcomers_queued: int
    scans_accepted: int
    scans_unmapped: int
    scans_rejected: dict[str, int]
    scans_dropped: dict[str, int]
    stamp_anomalies: dict[str, int]


class Ingest:
    """Routes scan payloads from Zenoh to sessions. `on_sample` is the Zenoh callback."""

    def __init__(
        self,
        prefix: str,
        sessions: SessionLookup,
        publish: Callable[[Pose, bytes | None], None],
        metrics: Metrics,
        settings: IngestSettings,
        *,
        admit: Callable[[str, str | None], bool] | None = None,
        forget: Callable[[str], None] | None = None,
        process: str = "main",
        driven: bool = False,
    ) -> None:
        """`admit(robot_id, source_id)` may refuse a scan before it is queued (it counts and
        logs that itself): `PublisherGuard.admit`, against a second publisher on a key.
        `forget(robot_id)` is told when a silent robot without a session is forgotten.
        `driven`: no worker threads; the caller serves the ready line (`serve_one`) and
        forgets silent robots (`sweep_if_due`) itself, from its own thread."""
        self._driven = driven
        self._prefix = prefix
        self._process = process
        self._admit = admit
        self._forget = forget
        self._sessions = sessions
        self._publish = publish
        self._metrics = metrics
        self._settings = settings
        self._idle_ns = int(settings.robot_idle_s * 1e9)
        self._gap_ns = int(settings.max_stamp_gap_s * 1e9)
        # Robots tracked (created by the workers only, from a valid payload); changed under
        # `_lock` so that the callback's choice between a robot's queue and the newcomers'
        # cannot race an adoption.
        self._queues: dict[str, _RobotQueue] = {}
        self._newcomers = _Newcomers(settings.newcomer_depth)
        self._pool_lock = threading.Lock()  # the start of the worker pool
        # One lock for every queue and the ready line: held for microseconds by the callback
        # and by a worker between scans, so one lock costs less than a lock per robot.
        self._lock = threading.Lock()
        self._ready: deque[_RobotQueue | _Newcomers] = deque()
        self._wakeup = threading.Condition(self._lock)
        self._workers: list[threading.Thread] = []
        self._closing = False
        self._next_sweep_ns = 0
        self._store_errors = 0
        self.robots_forgotten = 0
        # Mapper processes that ingest themselves report here (key: the process), so that
        # /health and /metrics count their robots as ours.
        self.remote: dict[str, IngestStats] = {}
        # (reason, robot) -> (monotonic ns of its last line, occurrences only counted since)
        self._logged: dict[tuple[str, str], tuple[int, int]] = {}
        self._logged_lock = threading.Lock()
        # Called with each accepted scan and its pose after publishing (the Foxglove view);
        # an observer must not block: it runs on the worker.
        self.scan_observers: list[Callable[[Scan, Pose | None], None]] = []
        declare_metrics(metrics, self._depths, self._tracked, self._queued_newcomers)
        metrics.set(ROBOTS_LIMIT, float(settings.max_robots))

    # -- Zenoh side (must never block) -----------------------------------------------------

    def on_sample(self, sample: Any) -> None:
        """Zenoh subscriber callback: copy the payload into its robot's queue, nothing more."""
        try:
            if sample.kind != zenoh.SampleKind.PUT:
                return
            key = str(sample.key_expr)
            if len(sample.payload) > self._settings.max_payload_bytes:
                robot = robot_id_from_key(key, self._prefix) or "?"
                self._reject("too_large", robot, f"{len(sample.payload)} bytes", tracked=False)
                return
            self.submit(key, sample.payload.to_bytes(), source_id_of(sample))
        except Exception:  # a callback that raises only prints; keep our own log instead
            log.exception("ingest callback failed")

    def submit(self, key: str, payload: bytes, source: str | None = None) -> None:
        """Queue one payload received on `key` from publisher `source` (its Zenoh id, if
        known); non-blocking, drops the oldest when full."""
        self._metrics.inc(PAYLOADS, process=self._process)
        robot_id = robot_id_from_key(key, self._prefix)
        if robot_id is None or not is_valid_robot_id(robot_id):
            self._reject("bad_key", "?", key[:120], tracked=False)
            return
        known = self._queues.get(robot_id)  # dict reads are atomic
        # A tracked robot's second publisher is refused before it can fill the queue; a
        # newcomer's payload is admitted once it validates (the guard keeps no state for junk).
        if known is not None and self._admit is not None and not self._admit(robot_id, source):
            return
        if not self._workers and not self._driven:
            self._start_workers()
        dropped: str | None = None
        with self._lock:
            queue = self._queues.get(robot_id)
            if queue is None:  # not tracked (yet, or forgotten meanwhile): validate first
                newcomers = self._newcomers
                if len(newcomers.items) >= newcomers.depth:
                    newcomers.items.popleft()
                    dropped = "newcomer_queue_full"
                newcomers.items.append((robot_id, payload, source))
                self._schedule(newcomers)
            else:
                if len(queue.items) >= queue.depth:
                    queue.items.popleft()
                    dropped = "queue_full"
                queue.items.append(payload)
                queue.last_received_ns = time.time_ns()
                queue.last_received_mono_ns = time.monotonic_ns()
                self._schedule(queue)
        if dropped == "queue_full":
            self._metrics.inc(SCANS_DROPPED, robot=robot_id, reason=dropped)
            self._log_once(dropped, robot_id, "ingest queue full; dropping oldest scans")
        elif dropped is not None:
            self._metrics.inc(SCANS_DROPPED, robot="", reason=dropped)
            self._log_once(
                dropped, _ANY_ROBOT, "queue of robots not tracked yet full; dropping oldest"
            )

    def _schedule(self, queue: _RobotQueue | _Newcomers) -> None:
        """Put a queue with work in the ready line (`_lock` held)."""
        if not queue.scheduled:
            queue.scheduled = True
            self._ready.append(queue)
            self._wakeup.notify()

    def _start_workers(self) -> None:
        """Start the worker pool (once, with the first payload)."""
        with self._pool_lock:
            if self._workers or self._closing:
                return
            for index in range(self._settings.worker_threads):
                thread = threading.Thread(target=self._run, name=f"ingest-{index}", daemon=True)
                self._workers.append(thread)
                thread.start()
        log.info("ingest: %d worker thread(s) started", self._settings.worker_threads)

    # -- worker side ---------------------------------------------------------------------------

    def _run(self) -> None:
        """Serve the ready line round-robin, one scan per turn, until closed and drained."""
        sweep_every_ns = int(min(self._idle_ns / 2, 5e9))
        while True:
            sweep = False
            with self._lock:
                while not self._ready:
                    if self._closing:
                        return
                    # Wake now and then to forget silent robots even when nothing arrives.
                    self._wakeup.wait(sweep_every_ns / 1e9)
                    if not self._ready and time.monotonic_ns() >= self._next_sweep_ns:
                        break
                now = time.monotonic_ns()
                if now >= self._next_sweep_ns:
                    self._next_sweep_ns = now + sweep_every_ns
                    sweep = True
                queue = self._ready.popleft() if self._ready else None
                if queue is not None:
                    queue.busy = True
            if sweep:
                self._forget_silent()
            if queue is not None:
                self._turn(queue)

    def serve_one(self) -> bool:
        """One turn of the ready line, without waiting (`driven`); False if none was ready."""
        with self._lock:
            queue = self._ready.popleft() if self._ready else None
            if queue is not None:
                queue.busy = True
        if queue is None:
            return False
        self._turn(queue)
        return True

    def sweep_if_due(self) -> None:
        """Forget silent robots when it is time (`driven`: the caller's timer)."""
        now = time.monotonic_ns()
        if now >= self._next_sweep_ns:
            self._next_sweep_ns = now + int(min(self._idle_ns / 2, 5e9))
            self._forget_silent()

    def _turn(self, queue: _RobotQueue | _Newcomers) -> None:
        """Serve one scan of `queue` (a batch of newcomers), which is marked busy."""
        if isinstance(queue, _Newcomers):
            self._serve_newcomers(queue)
            return
        with self._lock:
            if not queue.items:  # cannot happen (drop-oldest never empties); be safe
                queue.busy = queue.scheduled = False
                return
            payload = queue.items.popleft()
        deferred = False
        try:
            deferred = self._handle(queue, payload)
        except Exception:  # a worker must never die: its robots would go unmapped
            log.exception("ingest worker failed on a scan of %s", queue.robot_id)
        if not deferred:
            self._release(queue, notify=False)

    def _release(self, queue: _RobotQueue | _Newcomers, *, notify: bool) -> None:
        """The robot's scan is done: its next one may go (one in flight per robot keeps its
        scans in order)."""
        with self._lock:
            queue.busy = False
            if queue.items:
                self._ready.append(queue)  # back of the line: the next robot goes first
                if notify:
                    self._wakeup.notify()
            else:
                queue.scheduled = False

    def _serve_newcomers(self, newcomers: _Newcomers) -> None:
        """Validate newcomers' payloads in arrival order until one adopts its robot (or a
        batch was refused): junk costs a decode and a count, and creates nothing."""
        try:
            for _ in range(_NEWCOMER_BATCH):
                with self._lock:
                    if not newcomers.items:
                        break
                    robot_id, payload, source = newcomers.items.popleft()
                try:
                    if self._welcome(robot_id, payload, source):
                        break
                except Exception:
                    log.exception("ingest worker failed on a scan of new robot %s", robot_id)
        finally:
            self._release(newcomers, notify=True)

    def _welcome(self, robot_id: str, payload: bytes, source: str | None) -> bool:
        """A payload of a robot not tracked: True when it validated and adopted its robot."""
        scan = self._validate(robot_id, payload, tracked=None)
        if scan is None:
            return False
        has_session = self._sessions.active_for(robot_id) is not None
        if not has_session and len(self._queues) >= self._settings.max_robots:
            self._forget_silent()
        admitted = True
        with self._lock:
            queue = self._queues.get(robot_id)
            if queue is not None:  # adopted meanwhile (cannot happen: one worker serves these)
                queue.items.append(payload)
                self._schedule(queue)
            # A robot with a session always fits: sessions have their own limit, and a created
            # session must never meet "robot limit reached". The publisher guard is asked only
            # now, so that it keeps no state for a robot that is not tracked.
            elif has_session or len(self._queues) < self._settings.max_robots:
                admitted = self._admit is None or self._admit(robot_id, source)
                if admitted:
                    queue = self._adopt(robot_id, payload)
        if not admitted:
            return False
        if queue is None:
            self._metrics.inc(SCANS_DROPPED, robot="", reason="too_many_robots")
            self._log_once(
                "too_many_robots",
                _ANY_ROBOT,
                f"robot {robot_id}: robot limit ({self._settings.max_robots}) reached by robots "
                "without a session; dropping its scans",
            )
            return False
        log.info("robot %s: first valid scan received", robot_id)
        return True

    def _adopt(self, robot_id: str, first: bytes) -> _RobotQueue:
        """Track a robot: its queue holds its first valid payload, then its other payloads
        still waiting among the newcomers, in order (`_lock` held: the callback cannot put
        one of its scans anywhere meanwhile)."""
        queue = _RobotQueue(robot_id, self._settings.queue_depth)
        queue.items.append(first)
        rest: deque[tuple[str, bytes, str | None]] = deque()
        for item in self._newcomers.items:
            if item[0] != robot_id:
                rest.append(item)
            elif self._admit is None or self._admit(robot_id, item[2]):
                if len(queue.items) >= queue.depth:
                    queue.items.popleft()
                    self._metrics.inc(SCANS_DROPPED, robot=robot_id, reason="queue_full")
                queue.items.append(item[1])
        self._newcomers.items = rest
        queue.last_received_ns = time.time_ns()
        queue.last_received_mono_ns = time.monotonic_ns()
        self._queues[robot_id] = queue
        self._schedule(queue)
        return queue

    def _forget_silent(self) -> None:
        """Forget robots without an active session that sent nothing for `robot_idle_s`:
        their queue, their series in /metrics, their log lines' keys."""
        now = time.monotonic_ns()
        with self._lock:
            silent = [
                q
                for q in self._queues.values()
                if not q.scheduled and not q.busy and now - q.last_received_mono_ns >= self._idle_ns
            ]
        forgotten: list[str] = []
        for queue in silent:
            if self._sessions.active_for(queue.robot_id) is not None:
                continue  # a session keeps its robot, however quiet
            with self._lock:
                if self._queues.get(queue.robot_id) is queue and not queue.scheduled:
                    del self._queues[queue.robot_id]
                    forgotten.append(queue.robot_id)
        if not forgotten:
            return
        for robot_id in forgotten:
            self._metrics.forget(_PER_ROBOT, robot=robot_id)
            with self._logged_lock:
                for key in [k for k in self._logged if k[1] == robot_id]:
                    del self._logged[key]
            if self._forget is not None:
                self._forget(robot_id)
        self.robots_forgotten += len(forgotten)
        self._metrics.inc(ROBOTS_FORGOTTEN, float(len(forgotten)))
        log.info(
            "forgot %d robot(s) without a session, silent for %.0f s: %s",
            len(forgotten),
            self._settings.robot_idle_s,
            ", ".join(forgotten[:5]) + (" ..." if len(forgotten) > 5 else ""),
        )

    def _validate(self, robot_id: str, payload: bytes, tracked: _RobotQueue | None) -> Scan | None:
        """Decode and check a payload; None (counted and logged) when refused."""
        try:
            scan = decode_scan(payload, max_payload_bytes=self._settings.max_payload_bytes)
        except DecodeError as err:
            self._reject(err.reason, robot_id, err.detail, tracked=tracked is not None)
            return None
        if scan.robot_id != robot_id:
            self._reject(
                "robot_id_mismatch",
                robot_id,
                f"payload says {scan.robot_id!r}",
                tracked=tracked is not None,
            )
            return None
        if not in_ros_time(scan.host_stamp_ns):
            detail = (
                f"host_stamp_ns {scan.host_stamp_ns} is outside ROS time "
                f"(0 .. {ROS_TIME_MAX_NS}, 1970 to 2038)"
            )
            if tracked is not None:
                self._stamp_anomaly(tracked, "stamp_out_of_range", refused=True)
            self._reject("stamp_out_of_range", robot_id, detail, tracked=tracked is not None)
            return None
        return scan

    def _check_time(self, queue: _RobotQueue, scan: Scan, session: Any) -> bool:
        """The time contract against the previous scan mapped in `session`: False (counted
        and logged) to refuse the scan; a gap is counted, logged and mapped."""
        if queue.stamp_session != session.id:
            # First scan of this session seen here (a new session, or a restart): the session's
            # last pose is its previous scan's stamp.
            last = session.last_pose
            queue.stamp_session = session.id
            queue.last_stamp_ns = last.stamp_ns if last is not None else None
        previous = queue.last_stamp_ns
        if previous is None:
            return True
        stamp = scan.host_stamp_ns
        if stamp <= previous:
            reason = "stamp_duplicate" if stamp == previous else "stamp_backwards"
            self._stamp_anomaly(queue, reason, refused=True)
            self._reject(
                reason,
                queue.robot_id,
                f"host_stamp_ns {stamp} is {(previous - stamp) / 1e9:.6f} s before the previous "
                f"mapped scan's {previous} (seq {scan.seq}); not mapped",
                tracked=True,
            )
            return False
        if stamp - previous > self._gap_ns:
            self._stamp_anomaly(queue, "stamp_gap", refused=False)
            self._log_once(
                "stamp_gap",
                queue.robot_id,
                f"host_stamp_ns jumped {(stamp - previous) / 1e9:.3f} s forward (limit "
                f"{self._settings.max_stamp_gap_s:g} s) at seq {scan.seq}; mapped, counted",
            )
        return True

    def _stamp_anomaly(self, queue: _RobotQueue, reason: str, *, refused: bool) -> None:
        if refused:
            queue.stamps_refused += 1
        else:
            queue.stamp_gaps += 1
        self._metrics.inc(STAMP_ANOMALIES, robot=queue.robot_id, reason=reason)

    def _handle(self, queue: _RobotQueue, payload: bytes) -> bool:
        """Validate and hand one scan to its session; True when the session answers later
        (its mapper process records and maps it, then `_completed` runs)."""
        robot_id = queue.robot_id
        t0 = time.perf_counter()
        scan = self._validate(robot_id, payload, tracked=queue)
        if scan is None:
            return False
        session = self._sessions.active_for(robot_id)
        if session is not None and not self._check_time(queue, scan, session):
            return False
        session_id = session.id if session is not None else None
        on_done = functools.partial(self._completed, queue, session_id, scan, t0)
        try:
            result = session.ingest(payload, scan, on_done) if session is not None else None
        except (OSError, ServiceError) as err:  # disk full, I/O error: not durable, not counted
            self._store_error(robot_id, str(err))
            return False
        if result is DEFERRED:
            return True
        self._finish(queue, session_id, scan, result, t0)
        return False

    def _completed(
        self, queue: _RobotQueue, session_id: str | None, scan: Scan, t0: float, result: Ingested
    ) -> None:
        """A deferred scan's answer (on its mapper process's reader thread)."""
        try:
            self._finish(queue, session_id, scan, result, t0)
        finally:
            self._release(queue, notify=True)

    def _finish(
        self,
        queue: _RobotQueue,
        session_id: str | None,
        scan: Scan,
        result: Ingested | None,
        t0: float,
    ) -> None:
        robot_id = queue.robot_id
        if result is not None and not result.accepted and result.error is not None:
            if result.error.startswith("store"):
                self._store_error(robot_id, result.error)
            else:  # its mapper process died before recording it: never accepted
                self._metrics.inc(SCANS_DROPPED, robot=robot_id, reason="mapper_lost")
                self._log_once("mapper_lost", robot_id, f"scan not recorded: {result.error}")
            return
        if result is None or not result.accepted:
            self._metrics.inc(SCANS_UNMAPPED, robot=robot_id)
            self._log_once(
                "unmapped", robot_id, "scans arrive but no active session: not mapped", logging.INFO
            )
            return
        # The next scan of this session must come after this one (one in flight per robot).
        queue.stamp_session, queue.last_stamp_ns = session_id, scan.host_stamp_ns
        self._metrics.inc(SCANS_ACCEPTED, robot=robot_id)
        if result.pose is not None:
            try:
                self._publish(result.pose, result.pose_bytes)
            except Exception:
                log.exception("publishing a pose of %s failed", robot_id)
        for observer in self.scan_observers:
            try:
                observer(scan, result.pose)
            except Exception:
                log.exception("a scan observer failed on %s", robot_id)
        self._metrics.observe(SCAN_SECONDS, time.perf_counter() - t0)

    @property
    def store_errors(self) -> int:
        return self._store_errors + sum(r.store_errors for r in list(self.remote.values()))

    def stats(self) -> IngestStats:
        """This ingest's own counts, for the service (in a mapper process)."""
        return IngestStats(
            tuple(self._robots()),
            len(self._newcomers.items),
            self.robots_forgotten,
            self._store_errors,
        )

    def _store_error(self, robot_id: str, detail: str) -> None:
        self._store_errors += 1
        self._metrics.inc(SCANS_DROPPED, robot=robot_id, reason="store_error")
        self._log_once("store_error", robot_id, f"could not record the scan: {detail}")

    # -- bookkeeping -----------------------------------------------------------------------

    def _reject(self, reason: str, robot_id: str, detail: str, *, tracked: bool = True) -> None:
        """Count a refused scan by reason; log it once per (reason, robot) for a tracked
        robot, once per reason for others (their ids may be made up by the thousand)."""
        self._metrics.inc(SCANS_REJECTED, reason=reason)
        if tracked:
            self._log_once(reason, robot_id, f"rejected scan: {detail}")
        else:
            self._log_once(reason, _ANY_ROBOT, f"robot {robot_id}: rejected scan: {detail}")

    def _log_once(
        self, reason: str, robot_id: str, message: str, level: int = logging.WARNING
    ) -> None:
        """Log the first occurrence per (reason, robot), then at most one line per
        `_LOG_AGAIN_S` saying how many were only counted meanwhile."""
        pair = (reason, robot_id)
        now = time.monotonic_ns()
        with self._logged_lock:
            seen = self._logged.get(pair)
            if seen is None and len(self._logged) >= _MAX_LOGGED_PAIRS:
                return  # bounded; the counters still count
            if seen is not None and now - seen[0] < _LOG_AGAIN_S * 1e9:
                self._logged[pair] = (seen[0], seen[1] + 1)
                return
            self._logged[pair] = (now, 0)
        if seen is not None and seen[1]:
            message += f" ({seen[1]} more since the last such line)"
        who = f"robot {robot_id}" if robot_id else "ingest"
        log.log(level, "%s: %s [%s; further ones counted, logged again after %.0f s]",
                who, message, reason, _LOG_AGAIN_S)  # fmt: skip

    def _depths(self) -> list[tuple[Labels, float]]:
        return [(labels(robot=s.robot_id), float(s.queue_depth)) for s in self._robots()]

    def _tracked(self) -> list[tuple[Labels, float]]:
        return [((), float(len(self._queues)))]

    def _queued_newcomers(self) -> list[tuple[Labels, float]]:
        return [((), float(len(self._newcomers.items)))]

    def robots(self) -> list[RobotStatus]:
        """Every robot tracked, here and in the mapper processes that ingest."""
        out = self._robots()
        for remote in list(self.remote.values()):
            out.extend(remote.robots)
        return sorted(out, key=lambda r: r.robot_id)

    def _robots(self) -> list[RobotStatus]:
        with self._lock:
            queues = list(self._queues.values())
        return [
            RobotStatus(
                q.robot_id, len(q.items), q.last_received_ns, q.stamps_refused, q.stamp_gaps
            )
            for q in sorted(queues, key=lambda q: q.robot_id)
        ]

    def summary(self) -> IngestSummary:
        m = self._metrics

        def by(name: str, label: str) -> dict[str, int]:
            return {k: int(v) for k, v in sorted(m.by_label(name, label).items())}

        remote = list(self.remote.values())
        return IngestSummary(
            robots_tracked=len(self._queues) + sum(len(r.robots) for r in remote),
            max_robots=self._settings.max_robots,
            robots_forgotten=self.robots_forgotten + sum(r.robots_forgotten for r in remote),
            newcomers_queued=len(self._newcomers.items) + sum(r.newcomers_queued for r in remote),
            scans_accepted=int(m.total(SCANS_ACCEPTED)),
            scans_unmapped=int(m.total(SCANS_UNMAPPED)),
            scans_rejected=by(SCANS_REJECTED, "reason"),
            scans_dropped=by(SCANS_DROPPED, "reason"),
            stamp_anomalies=by(STAMP_ANOMALIES, "reason"),
        )

    def pending(self) -> int:
        """Scans queued or being processed (for orderly shutdown and tests)."""
        with self._lock:
            queues: list[_RobotQueue | _Newcomers] = [*self._queues.values(), self._newcomers]
            return sum(len(q.items) + (1 if q.busy else 0) for q in queues)

    def close(self, timeout_s: float = 10.0) -> None:
        """Stop the workers after they drain what is already queued."""
        with self._pool_lock:
            workers = list(self._workers)
            with self._lock:
                self._closing = True
                self._wakeup.notify_all()
        deadline = time.monotonic() + timeout_s
        for thread in workers:
            thread.join(max(0.0, deadline - time.monotonic()))
            if thread.is_alive():
                log.warning("ingest worker %s did not stop in time", thread.name)
