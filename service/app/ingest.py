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
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from clients.keyexpr import robot_id_from_key
from clients.wire import DecodeError, Pose, Scan, decode_scan, is_valid_robot_id
from service.app.errors import ServiceError
from service.app.metrics import SCAN_SECONDS_BUCKETS, Labels, Metrics, labels
from service.app.publishers import source_id_of
from service.app.sessions import DEFERRED, Ingested, SessionManager
from service.app.settings import IngestSettings

log = logging.getLogger(__name__)

_MAX_LOGGED_PAIRS = 4096

SCANS_ACCEPTED = "mapping_scans_accepted_total"
SCANS_REJECTED = "mapping_scans_rejected_total"
SCANS_UNMAPPED = "mapping_scans_unmapped_total"
SCANS_DROPPED = "mapping_scans_dropped_total"
SCAN_SECONDS = "mapping_scan_processing_seconds"
QUEUE_DEPTH = "mapping_ingest_queue_depth"
ROBOTS_SEEN = "mapping_robots_seen"


def declare_metrics(metrics: Metrics, depths: Callable[[], list[tuple[Labels, float]]]) -> None:
    metrics.counter(SCANS_ACCEPTED, "Scans recorded and mapped, by robot.")
    metrics.counter(SCANS_REJECTED, "Scans refused by validation, by reason.")
    metrics.counter(SCANS_UNMAPPED, "Valid scans from robots without an active session.")
    metrics.counter(
        SCANS_DROPPED,
        "Scans not processed: queue_full (oldest dropped), too_many_robots, store_error, "
        "mapper_lost (its mapper process died before recording it).",
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
    last_received_ns: int = 0


@dataclass(frozen=True, slots=True)
class RobotStatus:
    robot_id: str
    queue_depth: int
    last_received_ns: int


class Ingest:
    """Routes scan payloads from Zenoh to sessions. `on_sample` is the Zenoh callback."""

    def __init__(
        self,
        prefix: str,
        sessions: SessionManager,
        publish: Callable[[Pose, bytes | None], None],
        metrics: Metrics,
        settings: IngestSettings,
        *,
        admit: Callable[[str, str | None], bool] | None = None,
    ) -> None:
        """`admit(robot_id, source_id)` may refuse a scan before it is queued (it counts and
        logs that itself): `PublisherGuard.admit`, against a second publisher on a key."""
        self._prefix = prefix
        self._admit = admit
        self._sessions = sessions
        self._publish = publish
        self._metrics = metrics
        self._settings = settings
        self._queues: dict[str, _RobotQueue] = {}
        self._queues_lock = threading.Lock()  # creation of queues and of the worker pool
        # One lock for every queue and the ready line: held for microseconds by the callback
        # and by a worker between scans, so one lock costs less than a lock per robot.
        self._lock = threading.Lock()
        self._ready: deque[_RobotQueue] = deque()
        self._wakeup = threading.Condition(self._lock)
        self._workers: list[threading.Thread] = []
        self._closing = False
        self.store_errors = 0
        self._logged: set[tuple[str, str]] = set()
        self._logged_lock = threading.Lock()
        # Called with each accepted scan and its pose after publishing (the Foxglove view);
        # an observer must not block: it runs on the worker.
        self.scan_observers: list[Callable[[Scan, Pose | None], None]] = []
        declare_metrics(metrics, self._depths)

    # -- Zenoh side (must never block) -----------------------------------------------------

    def on_sample(self, sample: Any) -> None:
        """Zenoh subscriber callback: copy the payload into its robot's queue, nothing more."""
        try:
            if sample.kind != zenoh.SampleKind.PUT:
                return
            key = str(sample.key_expr)
            if len(sample.payload) > self._settings.max_payload_bytes:
                robot = robot_id_from_key(key, self._prefix) or "?"
                self._reject("too_large", robot, f"{len(sample.payload)} bytes")
                return
            self.submit(key, sample.payload.to_bytes(), source_id_of(sample))
        except Exception:  # a callback that raises only prints; keep our own log instead
            log.exception("ingest callback failed")

    def submit(self, key: str, payload: bytes, source: str | None = None) -> None:
        """Queue one payload received on `key` from publisher `source` (its Zenoh id, if
        known); non-blocking, drops the oldest when full."""
        robot_id = robot_id_from_key(key, self._prefix)
        if robot_id is None or not is_valid_robot_id(robot_id):
            self._reject("bad_key", "?", key[:120])
            return
        if self._admit is not None and not self._admit(robot_id, source):
            return
        queue = self._queue_for(robot_id)
        if queue is None:
            self._metrics.inc(SCANS_DROPPED, robot="", reason="too_many_robots")
            self._log_once("too_many_robots", robot_id, "robot limit reached; dropping its scans")
            return
        dropped = False
        with self._lock:
            if len(queue.items) >= queue.depth:
                queue.items.popleft()
                dropped = True
            queue.items.append(payload)
            queue.last_received_ns = time.time_ns()
            if not queue.scheduled:
                queue.scheduled = True
                self._ready.append(queue)
                self._wakeup.notify()
        if dropped:
            self._metrics.inc(SCANS_DROPPED, robot=robot_id, reason="queue_full")
            self._log_once("queue_full", robot_id, "ingest queue full; dropping oldest scans")

    def _queue_for(self, robot_id: str) -> _RobotQueue | None:
        queue = self._queues.get(robot_id)  # dict reads are atomic; the lock is for creation
        if queue is not None:
            return queue
        with self._queues_lock:
            queue = self._queues.get(robot_id)
            if queue is not None:
                return queue
            if self._closing or len(self._queues) >= self._settings.max_robots:
                return None
            queue = _RobotQueue(robot_id, self._settings.queue_depth)
            self._queues[robot_id] = queue
            if not self._workers:
                self._start_workers()
        log.info("robot %s: first scan received", robot_id)
        return queue

    def _start_workers(self) -> None:
        """Start the worker pool (once, with the first robot; `_queues_lock` held)."""
        for index in range(self._settings.worker_threads):
            thread = threading.Thread(target=self._run, name=f"ingest-{index}", daemon=True)
            self._workers.append(thread)
            thread.start()
        log.info("ingest: %d worker thread(s) started", self._settings.worker_threads)

    # -- worker side ---------------------------------------------------------------------------

    def _run(self) -> None:
        """Serve the ready line round-robin, one scan per turn, until closed and drained."""
        while True:
            with self._lock:
                while not self._ready:
                    if self._closing:
                        return
                    self._wakeup.wait()
                queue = self._ready.popleft()
                if not queue.items:  # cannot happen (drop-oldest never empties); be safe
                    queue.scheduled = False
                    continue
                payload = queue.items.popleft()
                queue.busy = True
            deferred = False
            try:
                deferred = self._handle(queue, payload)
            except Exception:  # a worker must never die: its robots would go unmapped
                log.exception("ingest worker failed on a scan of %s", queue.robot_id)
            if not deferred:
                self._release(queue, notify=False)

    def _release(self, queue: _RobotQueue, *, notify: bool) -> None:
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

    def _handle(self, queue: _RobotQueue, payload: bytes) -> bool:
        """Validate and hand one scan to its session; True when the session answers later
        (its mapper process records and maps it, then `_completed` runs)."""
        robot_id = queue.robot_id
        t0 = time.perf_counter()
        try:
            scan = decode_scan(payload, max_payload_bytes=self._settings.max_payload_bytes)
        except DecodeError as err:
            self._reject(err.reason, robot_id, err.detail)
            return False
        if scan.robot_id != robot_id:
            self._reject("robot_id_mismatch", robot_id, f"payload says {scan.robot_id!r}")
            return False
        session = self._sessions.active_for(robot_id)
        on_done = functools.partial(self._completed, queue, scan, t0)
        try:
            result = session.ingest(payload, scan, on_done) if session is not None else None
        except (OSError, ServiceError) as err:  # disk full, I/O error: not durable, not counted
            self._store_error(robot_id, str(err))
            return False
        if result is DEFERRED:
            return True
        self._finish(robot_id, scan, result, t0)
        return False

    def _completed(self, queue: _RobotQueue, scan: Scan, t0: float, result: Ingested) -> None:
        """A deferred scan's answer (on its mapper process's reader thread)."""
        try:
            self._finish(queue.robot_id, scan, result, t0)
        finally:
            self._release(queue, notify=True)

    def _finish(self, robot_id: str, scan: Scan, result: Ingested | None, t0: float) -> None:
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

    def _store_error(self, robot_id: str, detail: str) -> None:
        self.store_errors += 1
        self._metrics.inc(SCANS_DROPPED, robot=robot_id, reason="store_error")
        self._log_once("store_error", robot_id, f"could not record the scan: {detail}")

    # -- bookkeeping -----------------------------------------------------------------------

    def _reject(self, reason: str, robot_id: str, detail: str) -> None:
        self._metrics.inc(SCANS_REJECTED, reason=reason)
        self._log_once(reason, robot_id, f"rejected scan: {detail}")

    def _log_once(
        self, reason: str, robot_id: str, message: str, level: int = logging.WARNING
    ) -> None:
        """Log the first occurrence per (reason, robot); later ones are only counted."""
        pair = (reason, robot_id)
        with self._logged_lock:
            if pair in self._logged or len(self._logged) > _MAX_LOGGED_PAIRS:
                return
            self._logged.add(pair)
            if len(self._logged) > _MAX_LOGGED_PAIRS:
                message += " (log limit reached: further new reasons/robots are only counted)"
        log.log(level, "robot %s: %s [%s; further ones only counted]", robot_id, message, reason)

    def _depths(self) -> list[tuple[Labels, float]]:
        return [(labels(robot=s.robot_id), float(s.queue_depth)) for s in self.robots()]

    def robots(self) -> list[RobotStatus]:
        with self._queues_lock:
            queues = list(self._queues.values())
        return [
            RobotStatus(q.robot_id, len(q.items), q.last_received_ns)
            for q in sorted(queues, key=lambda q: q.robot_id)
        ]

    def pending(self) -> int:
        """Scans queued or being processed (for orderly shutdown and tests)."""
        with self._queues_lock:
            queues = list(self._queues.values())
        with self._lock:
            return sum(len(q.items) + (1 if q.busy else 0) for q in queues)

    def close(self, timeout_s: float = 10.0) -> None:
        """Stop the workers after they drain what is already queued."""
        with self._queues_lock:
            workers = list(self._workers)
            with self._lock:
                self._closing = True
                self._wakeup.notify_all()
        deadline = time.monotonic() + timeout_s
        for thread in workers:
            thread.join(max(0.0, deadline - time.monotonic()))
            if thread.is_alive():
                log.warning("ingest worker %s did not stop in time", thread.name)
