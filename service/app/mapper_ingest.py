"""The per-scan path inside a mapper process, when mapper processes ingest (`ingest_in_mappers`).

Each mapper process opens its own Zenoh session (a client of the service's Zenoh endpoints: the
service's session routes the robots' scans to it) and subscribes to the scan keys, into a Zenoh
channel that one thread drains between two scans (`_pump`). Exactly one process takes each
robot's scans: a robot with an active session is assigned by the service to the least busy
process when the session starts (every process is told: `assign`); any other robot goes by
`owner(robot_id, K)`, a BLAKE2b digest of the id modulo K (stable across runs and processes,
unlike Python's salted `hash`). A process drops the other robots' scans as it takes them.

Its own `Ingest` (service/app/ingest.py: per-robot queues, validation, the time contract,
newcomers and forgetting, the second-publisher guard) hands each valid scan to the robot's
session here (`ProcessSession`), which records and maps it under the session's lease
(`_Lease.handle`); the pose is published on Zenoh from this process. The service's process gets
a small entry per pose (`pushed`, batched; for its trajectory, GET pose and the browser
streams) and, every `STATS_PERIOD_S`, this process's counters (`stats`, for /metrics and
/health).

Which robots have an active session, and which session, the service says (`activate`,
`deactivate`); a scan of an active session without a lease here (its session is restoring,
being checkpointed or stopped, or the lease was taken back at an idle close) is held, bounded,
and the service is asked once for the lease (`want`); the held scans are mapped, in order, when
it comes (`delegated`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple

import zenoh
from zenoh.handlers import FifoChannel

from clients.fleet import RobotPatterns
from clients.keyexpr import (
    pose_key,
    publisher_alive_wildcard,
    publisher_from_alive_key,
    robot_id_from_key,
    scan_wildcard,
)
from clients.wire import Pose, Scan, encode_pose
from clients.zenoh_config import build_zenoh_config
from service.app.fanout import POSE_PUBLISH_ERRORS, POSES_PUBLISHED
from service.app.ingest import SCANS_REJECTED, Ingest
from service.app.mapper import Done, LeaseSpec, flat_done, make_pose
from service.app.metrics import Metrics
from service.app.publishers import DUPLICATE_PUBLISHERS, PublisherGuard
from service.app.sessions import HELD_SCANS_MAX, Ingested, moved_pose
from service.app.settings import IngestSettings

if TYPE_CHECKING:
    from service.app.mapper import _Lease

log = logging.getLogger(__name__)

STATS_PERIOD_S = 0.5  # how often the service's /metrics and /health learn this process's counts
# Samples Zenoh holds for the ingest thread between two of its turns (a turn maps one scan, a
# few ms; a full channel would hold up the Zenoh session's receiving, so it is deep).
CHANNEL_DEPTH = 4096
# `pushed` messages go to the service in batches: when the ingest thread has nothing ready,
# before any reply on the pipe (a revoke's reply must follow its scans), or at these bounds.
PUSHED_BATCH = 16
PUSHED_BATCH_S = 0.02

_NOT_ACCEPTED = Ingested(False, None, None)
_HELD = Ingested(True, None, None)


def owner(robot_id: str, processes: int) -> int:
    """The mapper process that owns `robot_id`'s scans and sessions (stable everywhere)."""
    digest = hashlib.blake2b(robot_id.encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") % processes


@dataclass(frozen=True, slots=True)
class IngestConfig:
    """What a mapper process needs to ingest its share of the robots (picklable)."""

    index: int
    processes: int
    prefix: str
    patterns: tuple[str, ...]
    endpoints: tuple[str, ...]  # the service's Zenoh endpoints; this process is a client
    settings: IngestSettings


class _Stamp(NamedTuple):
    stamp_ns: int


class ProcessSession:
    """What ingest sees of a robot's active session in this process."""

    def __init__(self, host: ProcessIngest, robot_id: str, session_id: str) -> None:
        self._host = host
        self.robot_id = robot_id
        self.id = session_id
        self.held: deque[tuple[bytes, Scan]] = deque()
        self.held_dropped = 0
        self.want_sent = False
        self.last_stamp_ns: int | None = None

    @property
    def last_pose(self) -> _Stamp | None:
        """The previous mapped scan's stamp, for the time contract (`Ingest._check_time`)."""
        return None if self.last_stamp_ns is None else _Stamp(self.last_stamp_ns)

    def ingest(self, payload: bytes, scan: Scan, on_done: Any = None) -> Ingested:
        return self._host.handle(self, payload, scan)


class ProcessIngest:
    """Zenoh, ingest and the robots' sessions of one mapper process."""

    def __init__(
        self,
        cfg: IngestConfig,
        work_lock: threading.Lock,
        leases: dict[str, _Lease],
        send: Callable[[tuple[Any, ...]], None],
    ) -> None:
        self._cfg = cfg
        self._lock = work_lock  # held by whoever uses a mapper or a lease of this process
        self._leases = leases
        self._send = send
        self._robots: dict[str, ProcessSession] = {}
        self._patterns = RobotPatterns(cfg.patterns)
        self.metrics = Metrics()
        self.metrics.counter(POSES_PUBLISHED, "Poses published on Zenoh.")
        self.metrics.counter(POSE_PUBLISH_ERRORS, "Zenoh pose publications that failed.")
        # One worker: the work holds this process's GIL. Robots without a session are split
        # over the processes like the others: each tracks its share of `max_robots`.
        settings = cfg.settings.model_copy(
            update={
                "workers": 1,
                "max_robots": max(1, -(-cfg.settings.max_robots // cfg.processes)),
            }
        )
        self.metrics.counter(
            DUPLICATE_PUBLISHERS,
            "Second publishers detected on a robot's key (their scans are refused).",
        )
        # The second-publisher guard needs the scans' source ids: it runs where they arrive.
        # Every process follows every robot's publisher tokens (ownership can move).
        # Robots with an active session -> the process that takes their scans (the service
        # assigns them, tells every process); the others go by `owner`.
        self._assigned: dict[str, int] = {}
        self.publishers = PublisherGuard(
            speaks_for=self._mine,
            on_refused=lambda robot: self.metrics.inc(SCANS_REJECTED, reason="duplicate_publisher"),
            on_intruder=lambda robot: self.metrics.inc(DUPLICATE_PUBLISHERS, robot=robot),
        )
        # One robot pattern (the usual case): the scans wait in a Zenoh channel (on the Rust
        # side, no GIL) and one thread both takes them in and maps them, between two scans.
        # A Python callback per sample instead made Zenoh's thread take the GIL from the
        # estimator several hundred times a second: measured ~0.6 CPU-ms more per scan.
        self._channel = len(self._patterns.patterns) == 1
        self.ingest = Ingest(
            cfg.prefix,
            self,
            self.publish,
            self.metrics,
            settings,
            admit=self.publishers.admit,
            forget=self.publishers.forget,
            process=f"mapper-{cfg.index}",
            driven=self._channel,
        )
        self._pushed: list[tuple[str, tuple[Any, ...]]] = []  # work lock held
        self._pushed_since = 0.0
        self._stop_key = f"{cfg.prefix}/_mapper_stop/scan"  # no robot id has a leading _
        self._scan_sub: Any = None
        self._pump_thread: threading.Thread | None = None
        self._zenoh: zenoh.Session | None = None
        self._subscribers: list[Any] = []
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._pub_lock = threading.Lock()  # publish runs on the worker and on the pipe loop
        self._stop = threading.Event()
        self._stats: threading.Thread | None = None

    # -- lifecycle -----------------------------------------------------------------------------

    def start(self) -> None:
        cfg = self._cfg
        conf = build_zenoh_config(mode="client", connect=cfg.endpoints)
        self._zenoh = zenoh.open(conf)
        patterns = self._patterns.patterns
        for index, pattern in enumerate(patterns):
            if self._channel:
                self._scan_sub = self._zenoh.declare_subscriber(
                    scan_wildcard(cfg.prefix, pattern), FifoChannel(CHANNEL_DEPTH)
                )
            else:
                on_scan = self._callback(index)
                self._subscribers.append(
                    self._zenoh.declare_subscriber(scan_wildcard(cfg.prefix, pattern), on_scan)
                )
            self._subscribers.append(
                self._zenoh.liveliness().declare_subscriber(
                    publisher_alive_wildcard(cfg.prefix, pattern),
                    self._on_publisher_alive,
                    history=True,
                )
            )
        self._stats = threading.Thread(target=self._report, name="ingest-stats", daemon=True)
        self._stats.start()
        if self._channel:
            self._pump_thread = threading.Thread(target=self._pump, name="ingest", daemon=True)
            self._pump_thread.start()
        log.info(
            "mapper process %d: ingesting its share of %s (client of %s)",
            cfg.index,
            ", ".join(patterns),
            ", ".join(cfg.endpoints),
        )

    def close(self) -> None:
        """Unsubscribe, drain ingest, close Zenoh (an unclosed session with a callback
        subscriber hangs the interpreter at exit)."""
        self._stop.set()
        if self._pump_thread is not None and self._zenoh is not None:
            # A channel cannot be undeclared while a thread waits on it: wake it with a
            # sample that never leaves this session.
            try:
                self._zenoh.put(
                    self._stop_key, b"", allowed_destination=zenoh.Locality.SESSION_LOCAL
                )
            except Exception as err:
                log.debug("stop sample: %s", err)
            self._pump_thread.join(timeout=10)
            if self._pump_thread.is_alive():
                log.warning("the ingest thread did not stop")
            else:
                self._subscribers.append(self._scan_sub)
        for sub in self._subscribers:
            try:
                sub.undeclare()
            except Exception as err:
                log.debug("undeclare: %s", err)
        self._subscribers.clear()
        self.ingest.close()
        for publisher in self._publishers.values():
            try:
                undeclare: Any = publisher.undeclare  # untyped in zenoh's stubs
                undeclare()
            except Exception as err:
                log.debug("undeclare: %s", err)
        self._publishers.clear()
        if self._zenoh is not None:
            close: Any = self._zenoh.close
            close()
            self._zenoh = None

    def _callback(self, pattern_index: int | None) -> Callable[[Any], None]:
        """What to do with a sample: ingest it if its robot is this process's."""
        prefix, count, index = self._cfg.prefix, self._cfg.processes, self._cfg.index
        first_match = self._patterns.first_match
        on_sample = self.ingest.on_sample
        assigned = self._assigned

        def on_scan(sample: Any) -> None:
            """Keep our robots' scans (a few microseconds for the others'). Keys that name no
            robot are refused (and counted) by process 0 alone."""
            robot_id = robot_id_from_key(str(sample.key_expr), prefix)
            if robot_id is None:
                mine = index == 0
            else:
                taker = assigned.get(robot_id)  # dict reads are atomic
                mine = (owner(robot_id, count) if taker is None else taker) == index
            if not mine:
                return
            overlapping = pattern_index is not None and robot_id is not None
            if overlapping and first_match(robot_id) != pattern_index:  # type: ignore[arg-type]
                return
            on_sample(sample)

        return on_scan

    def _on_publisher_alive(self, sample: Any) -> None:
        parsed = publisher_from_alive_key(str(sample.key_expr), self._cfg.prefix)
        if parsed is not None:
            robot_id, source = parsed
            self.publishers.token_changed(robot_id, source, sample.kind == zenoh.SampleKind.PUT)

    def _mine(self, robot_id: str) -> bool:
        taker = self._assigned.get(robot_id)
        if taker is None:
            taker = owner(robot_id, self._cfg.processes)
        return taker == self._cfg.index

    def _pump(self) -> None:
        """Take samples in, then serve the ready robots one scan at a time, taking in what
        arrived between two scans (so queues, drops and the round-robin are ingest's)."""
        sub = self._scan_sub
        take = self._callback(None)
        stop_key = self._stop_key
        serve_one = self.ingest.serve_one

        def drain(sample: Any) -> bool:
            while sample is not None:
                if str(sample.key_expr) == stop_key:
                    return False
                take(sample)
                sample = sub.try_recv()
            return True

        try:
            while drain(sub.recv()):
                while serve_one():
                    if not drain(sub.try_recv()):
                        return
                self.idle()  # nothing ready: the service learns the last poses now
        except Exception:  # the channel ended: the session is closing
            if not self._stop.is_set():
                log.exception("mapper process %d: the ingest thread failed", self._cfg.index)

    def _report(self) -> None:
        while not self._stop.wait(STATS_PERIOD_S):
            if self._channel:
                self.ingest.sweep_if_due()
            try:
                publishers = tuple(p for p in self.publishers.status() if self._mine(p.robot_id))
                stats = dataclasses.replace(self.ingest.stats(), publishers=publishers)
                self._send(("stats", self.metrics.export(), stats))
            except Exception as err:  # the pipe is gone: the process is ending
                log.debug("stats not sent: %s", err)
                return

    # -- the service's orders (on the pipe loop, work lock held) -----------------------------

    def assign(self, robot_id: str, index: str) -> None:
        """Which process takes `robot_id`'s scans ("": back to `owner`)."""
        if index:
            self._assigned[robot_id] = int(index)
        else:
            self._assigned.pop(robot_id, None)

    def activate(self, robot_id: str, session_id: str) -> None:
        current = self._robots.get(robot_id)
        if current is None or current.id != session_id:
            self._robots[robot_id] = ProcessSession(self, robot_id, session_id)

    def deactivate(self, robot_id: str, session_id: str) -> None:
        current = self._robots.get(robot_id)
        if current is not None and current.id == session_id:
            del self._robots[robot_id]
            if current.held:
                log.info(
                    "session %s stopped with %d scans held; not mapped",
                    session_id,
                    len(current.held),
                )

    def delegated(self, spec: LeaseSpec) -> None:
        """The lease of `spec`'s session came: map the scans held meanwhile, in order."""
        self.activate(spec.robot_id, spec.session_id)
        session = self._robots[spec.robot_id]
        if session.last_stamp_ns is None:
            session.last_stamp_ns = spec.last_stamp_ns
        lease = self._leases[spec.session_id]
        held, session.held = session.held, deque()
        session.want_sent = False
        for payload, scan in held:
            result = self._apply(session, lease, payload, scan)
            if result.pose is not None:
                self.publish(result.pose, result.pose_bytes)

    # -- the per-scan path (ingest worker) ---------------------------------------------------

    def active_for(self, robot_id: str) -> ProcessSession | None:
        return self._robots.get(robot_id)  # dict reads are atomic

    def handle(self, session: ProcessSession, payload: bytes, scan: Scan) -> Ingested:
        with self._lock:
            if self._robots.get(session.robot_id) is not session:
                return _NOT_ACCEPTED  # stopped meanwhile
            lease = self._leases.get(session.id)
            if lease is None:
                if len(session.held) >= HELD_SCANS_MAX:
                    session.held.popleft()
                    session.held_dropped += 1
                session.held.append((payload, scan))
                if not session.want_sent:
                    session.want_sent = True
                    self._send(("want", session.id))
                return _HELD
            return self._apply(session, lease, payload, scan)

    def _apply(
        self, session: ProcessSession, lease: _Lease, payload: bytes, scan: Scan
    ) -> Ingested:
        """Record and map one scan under its lease; tell the service (work lock held)."""
        done: Done = lease.handle(payload, scan)
        # The service applies it to the session's trajectory and browser streams; the pose's
        # bytes stay here (published below).
        if not self._pushed:
            self._pushed_since = time.monotonic()
        self._pushed.append((session.id, flat_done(done._replace(pose_bytes=None))))
        if (
            len(self._pushed) >= PUSHED_BATCH
            or time.monotonic() - self._pushed_since >= PUSHED_BATCH_S
        ):
            self.flush()
        if not done.recorded:
            return Ingested(False, None, None, done.error or "lost")
        session.last_stamp_ns = done.stamp_ns
        mapped = done.mapped
        if mapped is None:
            return Ingested(True, None, None, done.error)
        spec = lease.spec
        pose = make_pose(mapped, spec.session_id, spec.robot_id, done.seq, done.stamp_ns)
        # Recorded as the front end's; published where the back end's graph puts it now.
        published = moved_pose(pose, mapped.correction)
        encoded = done.pose_bytes if published is pose else encode_pose(published)
        return Ingested(True, published, encoded)

    def flush(self) -> None:
        """Send the `pushed` messages not sent yet, in order (work lock held)."""
        if self._pushed:
            batch, self._pushed = self._pushed, []
            self._send(("pushed", batch))

    def idle(self) -> None:
        with self._lock:
            self.flush()

    def publish(self, pose: Pose, encoded: bytes | None) -> None:
        """Put a pose on `<prefix>/<robot>/pose` from this process."""
        session = self._zenoh
        if session is None:
            return
        try:
            with self._pub_lock:
                publisher = self._publishers.get(pose.robot_id)
            if publisher is None:
                publisher = session.declare_publisher(
                    pose_key(pose.robot_id, self._cfg.prefix),
                    encoding=zenoh.Encoding.APPLICATION_OCTET_STREAM,
                    congestion_control=zenoh.CongestionControl.DROP,
                )
                with self._pub_lock:  # kept: dropping undeclares
                    publisher = self._publishers.setdefault(pose.robot_id, publisher)
            publisher.put(encoded if encoded is not None else encode_pose(pose))
            self.metrics.inc(POSES_PUBLISHED)
        except Exception as err:  # ZError when the session is closing
            self.metrics.inc(POSE_PUBLISH_ERRORS)
            log.debug("pose publication failed: %s", err)
