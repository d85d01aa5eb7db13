"""Mapping sessions: one estimator and one occupancy grid per session, one active session per robot.

A `MappingSession` is driven by exactly one ingest worker (its robot's) and read by HTTP handlers;
its lock serialises the two. Every accepted scan, then its pose, is appended to the session's
recording before the counters and the trajectory show it, so a restart that replays the recording
rebuilds exactly what clients were told.

A restart registers every session at once, in status `restoring`, and replays them in a
background thread (`SessionManager.load_all` then `restore_all`), so HTTP answers at once. While
a session restores, its control and map requests answer 503, and its robot's scans wait in a
bounded buffer that is recorded and mapped when the replay ends. Damage found in a session's
files (a damaged record, a rejected checkpoint, an unreadable `session.json`) never drops the
session: it is restored from what is intact and reported as `degraded` (or `damaged` when it
cannot be restored at all), with the records and bytes lost.
"""

from __future__ import annotations

import bisect
import contextlib
import errno
import functools
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Final, Literal, NamedTuple, Protocol, TypeVar

import numpy as np
import numpy.typing as npt

from clients.recording import MAGIC as RECORDING_MAGIC
from clients.recording import (
    MAX_RECORD_BYTES,
    Damage,
    RawRecord,
    RecordingReport,
    iter_raw_records,
    record_kind,
)
from clients.wire import (
    ROBOT_ID_PATTERN,
    DecodeError,
    Pose,
    Scan,
    decode_pose,
    decode_scan,
    encode_pose,
)
from service.app import checkpoint as ckpt
from service.app.backend import EMPTY_SNAPSHOT, GraphSnapshot, correct_poses
from service.app.errors import (
    ConflictError,
    NotFoundError,
    ServiceError,
    StoreError,
    UnavailableError,
    restoring_error,
)
from service.app.mapper import (
    Done,
    Engine,
    LeaseSpec,
    MappedScan,
    Mapper,
    MapperError,
    MapperFactory,
    MapperLostError,
    local_mapper_factory,
    make_pose,
)
from service.app.store import (
    DataDir,
    MapStore,
    SavedMapMeta,
    Segment,
    SessionFrontEnd,
    SessionMeta,
    SessionState,
    SessionStore,
    check_id,
    new_session_id,
    parse_segment,
    read_meta,
    read_repairs,
    session_front_end,
    write_atomic,
)

log = logging.getLogger(__name__)

SessionStatus = Literal["restoring", "ok", "degraded", "damaged"]

# Scans of a restoring session's robot held in memory until its replay ends (100 s at 40 Hz).
HELD_SCANS_MAX: Final = 4096
# A session whose robot sent nothing for this long has its recording closed (descriptors).
IDLE_CLOSE_S: Final = 30.0
# At shutdown, how long a session waits for its back end to take in the nodes handed to it.
BACKEND_DRAIN_S: Final = 10.0
# Tries to lease a recording to a mapper process that dies meanwhile (each rebuilds first).
LEASE_ATTEMPTS: Final = 5
# Checkpoints kept per session: the newest, and one before it in case the newest is damaged.
CHECKPOINTS_KEPT: Final = 2
# A map read waits this long at most for the back end to draw a map nobody read lately
# (`LiveBackend.image`: at its thread's next turn), asking again every MAP_POLL_S.
MAP_DRAW_WAIT_S: Final = 10.0
MAP_POLL_S: Final = 0.005

_T = TypeVar("_T")


@dataclass(frozen=True, slots=True)
class MapSnapshot:
    image: Any  # service.core.maps.grid.GridImage
    trajectory_xy_m: npt.NDArray[np.float64]  # (N, 2)
    last_pose: Pose | None
    revision: int


@dataclass(frozen=True, slots=True)
class DamageSummary:
    """What a restore found wrong in a session's files."""

    records_lost: int = 0  # a lower bound where a length field was damaged
    bytes_lost: int = 0
    regions: int = 0  # damaged stretches of the recording
    checkpoints_rejected: int = 0  # checksum or format failures (replayed instead)
    notes: tuple[str, ...] = ()

    @property
    def found(self) -> bool:
        return bool(self.regions or self.checkpoints_rejected or self.notes)


@dataclass(frozen=True, slots=True)
class SessionInfo:
    """A consistent copy of a session's public state (for HTTP answers)."""

    id: str
    robot_id: str
    state: SessionState
    created_ns: int
    scans_accepted: int
    poses: int
    resolution_m: float
    use_odometry: bool
    last_pose: Pose | None
    status: SessionStatus = "ok"
    damage: DamageSummary = field(default_factory=DamageSummary)
    # The back end's, for its counters (not compared: its revision counts the thread's work).
    graph: GraphSnapshot | None = field(default=None, compare=False)


class Ingested(NamedTuple):
    """What `MappingSession.ingest` did with a scan."""

    accepted: bool
    pose: Pose | None  # None when not accepted, when held during a restore, or estimator failed
    pose_bytes: bytes | None  # `encode_pose(pose)`, as recorded
    # Not accepted because it could not be recorded ("store: ...") or its mapper process died
    # before recording it ("lost: ..."); None otherwise.
    error: str | None = None


_NOT_ACCEPTED: Final = Ingested(False, None, None)
_HELD: Final = Ingested(True, None, None)
# The scan went to the session's mapper process; the answer comes to `on_done` later.
DEFERRED: Final = Ingested(True, None, None)

OnIngested = Callable[[Ingested], None]


class _CancelledError(Exception):
    """The service is shutting down in the middle of a replay."""


class MappingSession:
    # A restart replays only the scans after the last checkpoint; one a minute at 40 Hz
    # bounds that replay to about a minute of estimator time. Each checkpoint also starts a
    # new recording segment (retention prunes whole segments).
    checkpoint_every_scans = 2400

    def __init__(
        self, store: SessionStore, make_mapper: MapperFactory, *, restoring: bool = False
    ) -> None:
        meta = store.meta
        self.id = meta.id
        self.robot_id = meta.robot_id
        self.created_ns = meta.created_ns
        self.resolution_m = meta.resolution_m
        self.use_odometry = meta.use_odometry
        self.front_end: SessionFrontEnd = meta.front_end
        self.lock = threading.Lock()
        self._store = store
        self._make_mapper = make_mapper
        self._mapper: Mapper | None = None
        self._poses: list[Pose] = []
        self._deleted = False
        self.scans_accepted = 0
        self.estimator_errors = 0
        self.map_revision = 0
        self._image_cache: tuple[Any, int] | None = None
        self._payload: bytes | None = None  # wire bytes of the scan being estimated (lock held)
        # The back end (loop closure): the correction its answer to the latest scan carried,
        # the revisions it reported, and the latest graph snapshot fetched for reads.
        self._correction: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._graph_rev_seen = 0
        self._image_rev_seen = 0
        self._graph: GraphSnapshot = EMPTY_SNAPSHOT
        self._graph_fetched_s = 0.0
        self._ckpt_segment = 0  # the segment the checkpoint in use starts (0: none)
        self._records_tail = 0  # records in segments >= _ckpt_segment
        self._checkpoint_scans = 0  # scans_accepted at the last checkpoint
        self._restoring = restoring
        self._held: deque[tuple[bytes, Scan]] = deque()
        self.held_dropped = 0
        self._damage = DamageSummary()
        self._broken = False  # `damaged`: files that cannot be restored at all
        self._cancel = threading.Event()
        # The recording is leased to the session's mapper process (mapper.py): while it is,
        # the mapper's reader thread applies each scan's answer (`_done`), the only writer of
        # the counters and the trajectory then; control operations take the lease back first.
        self._leased = False
        self._lost = False  # the mapper process died while it held the lease: rebuild first
        self._checkpoint_due = False
        self._checkpoint_asked = False
        self.fsync_each = store._fsync_each
        # Where its poses go besides Zenoh when its mapper process ingests and publishes them
        # itself (the browser streams: `PoseFanout.to_streams`).
        self.on_pose: Callable[[Pose], None] | None = None
        if not restoring:
            self._mapper = make_mapper(
                meta.id, meta.use_odometry, meta.resolution_m, meta.front_end
            )
            self._attach(self._mapper)

    @classmethod
    def damaged(cls, directory: Path, reason: str, make_mapper: MapperFactory) -> MappingSession:
        """A placeholder for a session folder whose `session.json` cannot be read: listed,
        reported, deletable, never mapped into, and its files left as they are."""
        meta = SessionMeta(
            id=directory.name,
            robot_id=_robot_id_from_recording(directory) or "unknown",
            created_ns=int(directory.stat().st_mtime * 1e9),
            state="stopped",
            resolution_m=0.05,
            use_odometry=True,
            front_end="matcher",  # never mapped into
        )
        session = cls(SessionStore(directory, meta, fsync_each=False), make_mapper)
        session._broken = True
        session._damage = DamageSummary(notes=(reason,))
        return session

    @property
    def state(self) -> SessionState:
        return self._store.meta.state

    @property
    def is_active(self) -> bool:
        return self.state == "active" and not self._deleted and not self._broken

    @property
    def status(self) -> SessionStatus:
        if self._broken:
            return "damaged"
        if self._restoring:
            return "restoring"
        return "degraded" if self._damage.found else "ok"

    @property
    def damage(self) -> DamageSummary:
        return self._damage

    def _ready(self) -> Mapper:
        """The mapper, for requests that need the restored state (lock held); 503 otherwise."""
        if self._restoring:
            raise restoring_error(self.id)
        if self._broken:
            raise ConflictError(f"session {self.id} has damaged files (see mapping-service fsck)")
        if self._lost:
            self._recover()
        assert self._mapper is not None
        return self._mapper

    # -- the hot path (ingest worker) ---------------------------------------------------------

    def ingest(self, payload: bytes, scan: Scan, on_done: OnIngested | None = None) -> Ingested:
        """Record, estimate and map one validated scan.

        Not accepted, and nothing recorded, when the session is no longer active. An accepted
        scan has no pose only if the estimator failed on it, or if it is held until the
        session's restore ends. The pose comes with its wire encoding, the bytes just recorded,
        so that publishing does not encode it again.

        With `on_done` and a mapper process, the scan is forwarded to the process, which
        records and maps it, and `DEFERRED` is returned: `on_done(Ingested)` runs later on the
        mapper's reader thread, after the counters and the trajectory show the scan.
        """
        with self.lock:
            if not self.is_active:
                return _NOT_ACCEPTED
            if self._restoring:
                if len(self._held) >= HELD_SCANS_MAX:
                    self._held.popleft()
                    self.held_dropped += 1
                self._held.append((payload, scan))
                return _HELD
            if self._lost:
                self._recover()
            mapper = self._mapper
            if on_done is None or mapper is None or not getattr(mapper, "delegates", False):
                return self._ingest_locked(payload, scan)
            if self._checkpoint_due:
                self._revoke()
                self._write_checkpoint()
            try:
                if not self._leased:
                    self._delegate()
                mapper.forward(payload, functools.partial(self._done, on_done))  # type: ignore[attr-defined]
            except MapperLostError as err:
                log.error("session %s: %s; rebuilding it from the recording", self.id, err)
                self._lost = True
                self._recover()
                return self._ingest_locked(payload, scan)
            return DEFERRED

    # -- the lease: the per-scan path in the mapper process ------------------------------------

    def _delegate(self) -> None:
        """Lease the recording to the mapper process (lock held)."""
        path, end = self._store.lease_out()
        spec = LeaseSpec(
            session_id=self.id,
            robot_id=self.robot_id,
            path=str(path),
            end_offset=end,
            next_seq=self._poses[-1].seq + 1 if self._poses else 0,
            fsync_each=self.fsync_each,
            last_stamp_ns=self._poses[-1].stamp_ns if self._poses else None,
        )
        try:
            self._mapper.delegate(spec)  # type: ignore[union-attr]
        except BaseException:
            self._store.lease_back(None)
            raise
        self._leased = True

    def _revoke(self, *, recover: bool = True) -> None:
        """Take the recording back from the mapper process (lock held): every scan forwarded
        before has been applied when this returns. A process that died leaves the session
        `_lost`: rebuilt from the recording now (`recover`) or at the next use."""
        if not self._leased:
            return
        self._leased = False
        try:
            end = self._mapper.revoke()  # type: ignore[union-attr]
        except MapperError as err:
            self._store.lease_back(None)
            if not isinstance(err, MapperLostError):
                raise
            self._lost = True
            if recover:
                log.error("session %s: %s; rebuilding it from the recording", self.id, err)
                self._recover()
            return
        self._store.lease_back(end)

    # -- mapper processes that ingest: the lease is theirs whenever the session is active ------

    @property
    def _pushes(self) -> bool:
        return bool(getattr(self._mapper, "pushes", False))

    def _attach(self, mapper: Mapper) -> None:
        """Hear from a mapper process that ingests the robot's scans itself."""
        if getattr(mapper, "pushes", False):
            mapper.on_pushed = self._on_pushed  # type: ignore[attr-defined]
            mapper.on_want = self.lease_if_ready  # type: ignore[attr-defined]
            mapper.on_lost = self._on_lost  # type: ignore[attr-defined]

    def lease_if_ready(self) -> None:
        """Give the mapper process that ingests the robot's scans the recording's lease, when
        the session is active and ready: after its creation or restore, a checkpoint, a
        reset, an idle close, or its process's death (rebuilt first). The process holds the
        robot's scans until then."""
        with self.lock:
            self._lease_locked()

    def _lease_locked(self) -> None:
        self._checkpoint_asked = False
        if not self.is_active or self._restoring or not self._pushes or self._cancel.is_set():
            return  # not mapping, or shutting down (`close` took the lease back for good)
        for attempt in range(LEASE_ATTEMPTS):
            try:
                if self._lost:
                    self._recover()
                if self._checkpoint_due:
                    self._revoke()
                    self._write_checkpoint()
                if not self._leased and self._pushes:
                    self._delegate()
                return
            except MapperLostError as err:  # its process died (again): started at the next call
                log.error("session %s: %s; rebuilding it", self.id, err)
                self._lost = True
                time.sleep(0.1 * (attempt + 1))  # a process just killed may not be reaped yet
            except (MapperError, OSError, ServiceError) as err:
                log.error("session %s: the lease could not be given: %s", self.id, err)
                return

    def _on_lost(self) -> None:
        """Its mapper process died (task thread): rebuild from the recording, lease again."""
        self._lost = True
        self.lease_if_ready()

    def _on_pushed(self, done: Done) -> None:
        """A scan the mapper process ingested, recorded, mapped and published itself (on its
        reader thread): the trajectory, the counters and the browser streams learn it."""
        self._done(self._pushed_applied, done, encode=False)

    def _pushed_applied(self, result: Ingested) -> None:
        if result.pose is not None and self.on_pose is not None:
            self.on_pose(result.pose)
        if self._checkpoint_due and not self._checkpoint_asked:
            self._checkpoint_asked = True  # once: the lease is taken back, written, given again
            later = getattr(self._mapper, "later", None)
            if later is not None:
                later(self.lease_if_ready)

    def _done(self, on_done: OnIngested, done: Done, *, encode: bool = True) -> None:
        """A forwarded scan's answer, on the mapper's reader thread (no session lock: a
        control operation may hold it while it waits for the lease back)."""
        if not done.recorded:
            if done.error is not None and done.error.startswith("lost"):
                self._lost = True
            on_done(Ingested(False, None, None, done.error or "lost"))
            return
        self._store.leased_append()
        self._records_tail += 1
        self.scans_accepted += 1
        pose: Pose | None = None
        published: Pose | None = None
        encoded = done.pose_bytes
        if done.mapped is not None:
            pose = self._pose_from_mapped(done.mapped, done.stamp_ns, done.seq)
            self._records_tail += 1
            self._poses.append(pose)
            # Recorded as the front end's (as on the sync path); published where the back end's
            # graph puts it now.
            published = _moved(pose, self._correction)
            if published is not pose:
                encoded = encode_pose(published) if encode else None
        elif done.error is not None and done.error.startswith("estimator"):
            self._note_estimator_error(done.seq, done.error)
        if self.scans_accepted - self._checkpoint_scans >= self.checkpoint_every_scans:
            self._checkpoint_due = True  # written before the next scan is forwarded
        on_done(Ingested(True, published, encoded, done.error if pose is None else None))

    def _recover(self) -> None:
        """Rebuild the session from its checkpoint and recording after its mapper process
        died (lock held): the recording is the truth, whatever answers were lost with it."""
        damage = self._damage
        self._leased = False
        self._store.lease_back(None)
        self._poses = []
        self.scans_accepted = 0
        self._records_tail = 0
        self._ckpt_segment = 0
        self._checkpoint_scans = 0
        self._checkpoint_due = False
        self._replay()
        self._damage = damage  # the replay found the same damage again
        self.map_revision += 1
        self._lost = False
        log.info("session %s: rebuilt after its mapper process was lost", self.id)

    def _ingest_locked(self, payload: bytes, scan: Scan) -> Ingested:
        self._store.append(payload)  # durable before it counts
        self._records_tail += 1
        self.scans_accepted += 1
        pose = self._estimate_payload(scan, payload)
        encoded: bytes | None = None
        published: Pose | None = None
        if pose is not None:
            # The recording keeps the front end's pose (deterministic: a replay checks it);
            # clients are told where the back end's graph puts it now.
            encoded = encode_pose(pose)
            self._store.append(encoded)
            self._records_tail += 1
            self._poses.append(pose)
            published = _moved(pose, self._correction)
            if published is not pose:
                encoded = encode_pose(published)
        if self.scans_accepted - self._checkpoint_scans >= self.checkpoint_every_scans:
            self._write_checkpoint()
        return Ingested(True, published, encoded)

    def _estimate_payload(self, scan: Scan, payload: bytes) -> Pose | None:
        """`_estimate` of a scan whose wire bytes are at hand: a mapper in another process is
        sent those instead of the pickled `Scan` (lock held)."""
        self._payload = payload
        try:
            return self._estimate(scan)
        finally:
            self._payload = None

    def _estimate(self, scan: Scan) -> Pose | None:
        """Run estimator and grid on `scan` (lock held). None if the estimator failed."""
        seq = self._poses[-1].seq + 1 if self._poses else 0  # = len unless records were lost
        try:
            mapped = self._map(scan, self._payload, seq)
        except Exception as err:
            # The estimator promises not to raise on bad data; if it does anyway, the scan stays
            # recorded (a replay meets the same failure) and the session carries on.
            self._note_estimator_error(scan.seq, repr(err), exc_info=True)
            return None
        return self._pose_from_mapped(mapped, scan.stamp_ns, seq)

    def _pose_from_mapped(self, mapped: MappedScan, stamp_ns: int, seq: int) -> Pose:
        """The pose of a mapped scan (the front end's, as recorded), and the session's
        bookkeeping of the answer (both transports: the sync path under the lock, a lease's
        answers on its reader thread)."""
        if mapped.is_keyframe or mapped.image_revision != self._image_rev_seen:
            self.map_revision += 1
            self._image_rev_seen = mapped.image_revision
        self._correction = mapped.correction
        self._graph_rev_seen = mapped.graph_revision
        return make_pose(mapped, self.id, self.robot_id, seq, stamp_ns)

    def _note_estimator_error(self, seq: int, detail: str, *, exc_info: bool = False) -> None:
        self.estimator_errors += 1
        if self.estimator_errors == 1 or math.log2(self.estimator_errors).is_integer():
            log.error(
                "session %s: estimator failed on scan %d (%d failures so far): %s",
                self.id,
                seq,
                self.estimator_errors,
                detail,
                exc_info=exc_info,
            )

    def _map(self, scan: Scan, payload: bytes | None, seq: int) -> MappedScan:
        """The mapper's answer; a lost mapper (its process died) is rebuilt first (lock held)."""
        assert self._mapper is not None
        try:
            return self._mapper.map_scan(scan, payload, seq)
        except MapperLostError as err:
            log.error("session %s: %s; rebuilding its map from the recording", self.id, err)
            self._rebuild_mapper()
            return self._mapper.map_scan(scan, payload, seq)

    def _new_mapper(self) -> Mapper:
        if self._mapper is not None:
            self._mapper.close()
        self._mapper = self._make_mapper(
            self.id, self.use_odometry, self.resolution_m, self.front_end
        )
        self._attach(self._mapper)
        return self._mapper

    def _rebuild_mapper(self) -> None:
        """A new mapper with the state of every record before the current one (lock held):
        the checkpoint's, then the recorded scans after it, as a restart would."""
        mapper = self._new_mapper()
        start = 0
        next_seq = 0  # the sequence of the next scan's pose (the back end names nodes by it)
        if self._ckpt_segment:
            try:
                header, state = ckpt.read(self._store.checkpoint_path(self._ckpt_segment))
                mapper.restore(state, str(self._store.pack_path))
                start = self._ckpt_segment
                next_seq = header.poses
            except Exception as err:  # the recording is the truth; a checkpoint saves time
                log.warning("session %s: checkpoint does not restore: %s", self.id, err)
                mapper = self._new_mapper()
        tail_seen = 0
        replayed = 0
        upto = self._records_tail - 1  # the current scan is recorded already; the caller maps it
        for seg in self._store.segments():
            if seg.index < start:
                continue
            for record in self._store.records(seg):
                in_tail = seg.index >= self._ckpt_segment
                if in_tail:
                    if tail_seen >= upto:
                        break
                    tail_seen += 1
                try:
                    if record.kind == "pose":
                        next_seq = decode_pose(record.payload).seq + 1
                    if record.kind != "scan":
                        continue
                    scan = decode_scan(record.payload, max_payload_bytes=MAX_RECORD_BYTES)
                    mapper.map_scan(scan, record.payload, next_seq)
                except DecodeError:
                    continue
                replayed += 1
        self.map_revision += 1
        log.info("session %s: map rebuilt (%d scans re-estimated)", self.id, replayed)

    # -- checkpoints ------------------------------------------------------------------------

    def _write_checkpoint(self) -> bool:
        """Persist estimator and grid (lock held) and start a new recording segment. The
        recording is fsynced first so that a checkpoint never covers records a power loss
        could take back. False if it could not be written (logged)."""
        assert self._mapper is not None
        try:
            # Frozen arrays go to the epoch's pack once (fsynced before this returns), so a
            # checkpoint costs what changed since the last one, not the whole session.
            state = self._mapper.state(str(self._store.pack_path))
            segment = self._store.roll()  # fsyncs and closes the segment the checkpoint covers
            header = ckpt.CheckpointHeader(
                epoch=self._store.meta.epoch,
                segment=segment,
                scans_accepted=self.scans_accepted,
                poses=len(self._poses),
                map_revision=self.map_revision,
            )
            write_atomic(self._store.checkpoint_path(segment), ckpt.encode(header, state))
            self._ckpt_segment = segment
            self._records_tail = 0
            self._drop_old_checkpoints(segment)
            written = True
        except (OSError, MapperError, ValueError, TypeError) as err:
            log.warning("session %s: checkpoint not written: %s", self.id, err)
            written = False
        self._checkpoint_scans = self.scans_accepted
        self._checkpoint_due = False
        return written

    def _drop_old_checkpoints(self, newest: int) -> None:
        """Keep the newest checkpoint and the newest other one that passes its checksum (the
        fallback if the newest is damaged later); delete the rest."""
        fallback_found = False
        for segment, path in self._store.checkpoint_paths():
            if segment == newest:
                continue
            if not fallback_found:
                try:
                    ckpt.read(path)
                    fallback_found = True
                    continue
                except ckpt.CheckpointError:
                    pass
            path.unlink(missing_ok=True)

    def _checkpoints(self) -> Iterator[tuple[ckpt.CheckpointHeader, bytes]]:
        """This epoch's checkpoints that pass their checksum, newest first; each rejected
        one is counted and logged."""
        for segment, path in self._store.checkpoint_paths():
            try:
                header, state = ckpt.read(path)
                if header.epoch != self._store.meta.epoch or header.segment != segment:
                    raise ckpt.CheckpointError("names another epoch or segment")
            except ckpt.CheckpointError as err:
                self._note_checkpoint_rejected(f"{path.name}: {err}")
                continue
            yield header, state

    def _note_checkpoint_rejected(self, detail: str) -> None:
        log.warning(
            "session %s: checkpoint rejected (%s); replaying the recording", self.id, detail
        )
        self._damage = replace(
            self._damage,
            checkpoints_rejected=self._damage.checkpoints_rejected + 1,
            notes=(*self._damage.notes, f"checkpoint rejected ({detail}); replayed instead"),
        )

    # -- recovery ---------------------------------------------------------------------------

    def restore(self) -> None:
        """Replay the recording (from the newest checkpoint that restores), then the scans held
        meanwhile; the session is then ready. Reads each recording segment once."""
        t0 = time.monotonic()
        try:
            self._replay()
        except _CancelledError:
            log.info("session %s: restore interrupted by shutdown", self.id)
            return
        with self.lock:
            held = list(self._held)
            self._held.clear()
            self._restoring = False
            for payload, scan in held:
                if not self.is_active:
                    break
                try:
                    self._ingest_locked(payload, scan)
                except (OSError, StoreError) as err:
                    log.error("session %s: a held scan could not be recorded: %s", self.id, err)
            self._lease_locked()  # a process that ingests held the robot's scans meanwhile
        if self.held_dropped:
            log.warning(
                "session %s: %d scans arrived during the restore beyond the %d held; dropped",
                self.id,
                self.held_dropped,
                HELD_SCANS_MAX,
            )
        level = logging.WARNING if self._damage.found else logging.INFO
        log.log(
            level,
            "session %s (robot %s, %s): restored %d scans, %d poses in %.2f s%s",
            self.id,
            self.robot_id,
            self.state,
            self.scans_accepted,
            len(self._poses),
            time.monotonic() - t0,
            f"; DEGRADED: {self._damage_text()}" if self._damage.found else "",
        )

    def replay(self) -> None:
        """`restore()` for callers that construct a session by hand (tests, tools)."""
        self._restoring = True
        self.restore()

    def _damage_text(self) -> str:
        d = self._damage
        parts = []
        if d.regions:
            parts.append(
                f"{d.records_lost} records / {d.bytes_lost} bytes lost in {d.regions} place(s)"
            )
        parts.extend(d.notes)
        return "; ".join(parts)

    def _replay(self) -> None:
        """Rebuild estimator, grid, counters and trajectory (no lock: the session refuses
        everything else while `_restoring`). Records covered by the checkpoint only restore
        the trajectory; the estimator runs on the records after it."""
        mapper = self._new_mapper()
        segments = self._store.segments()
        header: ckpt.CheckpointHeader | None = None
        retired = self._store.meta.retired_front_end
        if retired is not None:
            # Its checkpoints hold a deleted front end's state: never loaded, the whole
            # recording is replayed with this one (`retire_front_end` below, once it is).
            log.warning(
                "session %s: recorded with the front end %r, which this version no longer "
                "has; restored with %r by replaying its whole recording (its checkpoints hold "
                "the old front end's state and are deleted)",
                self.id,
                retired,
                self.front_end,
            )
        # Every checkpoint is checked (two files), so that a damaged fallback is reported too.
        for candidate, state in [] if retired is not None else list(self._checkpoints()):
            if header is not None:
                break
            if not segments or candidate.segment > segments[-1].index:
                self._note_checkpoint_rejected(
                    f"segment {candidate.segment}: ahead of the recording"
                )
                continue
            try:
                mapper.restore(state, str(self._store.pack_path))
            except Exception as err:  # written by another version, say: replay instead
                self._note_checkpoint_rejected(
                    f"segment {candidate.segment}: does not restore: {err}"
                )
                mapper = self._new_mapper()
                continue
            header = candidate
        start = header.segment if header is not None else 0
        pruned_uncovered = [s for s in segments if s.pruned and s.index >= start]
        if pruned_uncovered:
            self._add_note(
                "no valid checkpoint covers the pruned segment(s) from "
                f"{pruned_uncovered[0].index}: the map holds only the scans still recorded"
            )
        if header is not None:
            self.map_revision = header.map_revision
        self._ckpt_segment = start
        indices = [s.index for s in segments]
        missing = sorted(set(range(indices[-1] + 1)) - set(indices)) if indices else []
        if missing:
            self._add_note(f"recording segment(s) {missing[:5]} missing")
        total = RecordingReport()
        last: tuple[Segment, RecordingReport] | None = None
        pending: Pose | None = None  # recomputed pose of the last scan, until its record comes
        mismatches = undecodable = covered_scans = 0
        for seg in segments:
            report = RecordingReport()
            covered = seg.index < start
            for record in self._segment_records(seg, report):
                if self._cancel.is_set():
                    raise _CancelledError
                kind = record.kind
                try:
                    if covered:
                        if kind == "pose":
                            self._poses.append(decode_pose(record.payload))
                        elif kind == "scan":
                            covered_scans += 1
                        continue
                    self._records_tail += 1
                    if kind == "scan":
                        if pending is not None:
                            self._poses.append(pending)
                        scan = decode_scan(record.payload, max_payload_bytes=MAX_RECORD_BYTES)
                        self.scans_accepted += 1
                        pending = self._estimate_payload(scan, record.payload)
                    elif kind == "pose":
                        recorded = decode_pose(record.payload)
                        if pending is not None and not _same_pose(pending, recorded):
                            mismatches += 1
                        # The recorded pose is what clients were told: keep it.
                        self._poses.append(recorded)
                        pending = None
                    else:
                        undecodable += 1
                except DecodeError:
                    undecodable += 1
            total.merge(report)
            last = (seg, report)
        if header is not None:
            covered_poses = sum(1 for p in self._poses if p.seq < header.poses)
            if covered_poses < header.poses:
                self._add_note(
                    f"{header.poses - covered_poses} of the {header.poses} poses before the "
                    "checkpoint are missing from the recording"
                )
            self.scans_accepted += header.scans_accepted
            if covered_scans and covered_scans != header.scans_accepted:
                log.info(
                    "session %s: %d scans in the covered segments, the checkpoint says %d",
                    self.id,
                    covered_scans,
                    header.scans_accepted,
                )
        if total.damage:
            self._damage = replace(
                self._damage,
                records_lost=self._damage.records_lost + total.records_lost,
                bytes_lost=self._damage.bytes_lost + total.bytes_lost,
                regions=self._damage.regions + len(total.damage),
            )
        self._count_fsck_repairs()
        tail_repaired = False
        if pending is not None:
            # Crash between a scan's record and its pose's: the pose is recomputed and,
            # if the session goes on, recorded now.
            self._poses.append(pending)
            tail_repaired = True
        self._poses.sort(key=lambda p: p.seq)  # only a damaged recording can disorder them
        if self.state != "active":
            mapper.finish()  # a stopped session's scans are over (as `stop` did)
        if self.state == "active":
            last_report = (
                last[1] if last is not None and last[0].index == self._store.segment else None
            )
            self._store.open_for_append(last_report)
            if tail_repaired and pending is not None:
                self._store.append(encode_pose(pending))
                self._records_tail += 1
        self._checkpoint_scans = header.scans_accepted if header is not None else 0
        if retired is not None:
            self._store.retire_front_end()  # once: the next start restores it as any other
        # Another front end's recorded poses differ from the replay's: expected, not news.
        if (mismatches and retired is None) or undecodable:
            log.warning(
                "session %s: replay found %d pose mismatches and %d unreadable records",
                self.id,
                mismatches,
                undecodable,
            )

    def _count_fsck_repairs(self) -> None:
        """Records `fsck --repair` cut out of this epoch's recording count as lost: the
        rewritten segments read as intact, yet the map lacks those scans."""
        epoch = self._store.meta.epoch
        repairs = [
            r
            for r in read_repairs(self._store.directory)
            if (parsed := parse_segment(r.segment)) is not None and parsed[0] == epoch
        ]
        if not repairs:
            return
        lost = sum(r.records_lost for r in repairs)
        segments = ", ".join(r.segment for r in repairs)
        self._damage = replace(
            self._damage,
            records_lost=self._damage.records_lost + lost,
            bytes_lost=self._damage.bytes_lost + sum(r.bytes_lost for r in repairs),
            regions=self._damage.regions + sum(r.regions for r in repairs),
            notes=(
                *self._damage.notes,
                f"fsck --repair cut {lost} damaged record(s) out of {segments}",
            ),
        )

    def _segment_records(self, seg: Segment, report: RecordingReport) -> Iterator[RawRecord]:
        """The segment's intact records; a file that is not a recording at all (its header is
        damaged) counts as damage in full, and appends go to a fresh segment after it."""
        try:
            yield from self._store.records(seg, report)
        except StoreError as err:
            size = seg.path.stat().st_size if seg.path.exists() else 0
            report.damage.append(Damage(0, size, 1, "header"))
            self._add_note(f"{seg.path.name} unreadable ({err.reason}); its records are skipped")
            if seg.index == self._store.segment:
                self._store.segment += 1  # never append after a damaged header

    def _add_note(self, note: str) -> None:
        log.warning("session %s: %s", self.id, note)
        self._damage = replace(self._damage, notes=(*self._damage.notes, note))

    def cancel_restore(self) -> None:
        self._cancel.set()

    # -- control --------------------------------------------------------------------------

    def stop(self) -> None:
        with self.lock:
            self._ready()
            self._revoke()
            if self.state == "active":
                try:
                    # The end of its scans: the core's final search and batch optimisation,
                    # as `mapping-service map` ends (queued to the back end's thread).
                    self._ready().finish()
                except MapperError as err:  # its process died: the restore finishes it
                    log.warning("session %s: finishing on stop failed: %s", self.id, err)
                self._checkpoint_if_behind()
                self._store.close_writer()
                self._store.set_state("stopped")

    def mark_stopped(self) -> None:
        """Stop a session that is not restored yet (a second active session of its robot)."""
        with self.lock:
            self._store.set_state("stopped")

    def reset(self) -> None:
        """Forget the map and the trajectory; the next scan starts a new map frame."""
        with self.lock:
            mapper = self._ready()
            self._revoke()
            mapper = self._ready()  # rebuilt if the revoke found it lost
            self._store.new_epoch()
            if self.state != "active":
                self._store.close_writer()
            mapper.reset()
            self._graph = EMPTY_SNAPSHOT
            self._correction = (0.0, 0.0, 0.0)
            self._poses = []
            self.scans_accepted = 0
            self.map_revision += 1
            self._records_tail = 0
            self._ckpt_segment = 0
            self._checkpoint_scans = 0
            self._lease_locked()

    def delete(self, trash_dir: Any) -> None:
        self._cancel.set()
        with self.lock:
            self._deleted = True
            self._leased = False  # dropping the mapper closes the lease in its process
            if self._mapper is not None:
                self._mapper.close()
            self._store.delete(trash_dir)

    def sync(self) -> None:
        self._store.sync()

    def close_if_idle(self, idle_s: float = IDLE_CLOSE_S) -> bool:
        """Close the recording of a session whose robot has been quiet for `idle_s` (it is
        reopened by the next scan). Never waits for a busy session."""
        if not self.lock.acquire(blocking=False):
            return False
        try:
            if self._store.writer_open and self._store.idle_for_s() >= idle_s:
                self._revoke()
                self._store.close_writer()
                return True
            return False
        finally:
            self.lock.release()

    @property
    def writer_open(self) -> bool:
        return self._store.writer_open

    def prune(self, older_than_s: float) -> int:
        """Cut the scans out of recording segments that a checkpoint before the newest covers
        (so a damaged newest checkpoint still has a replayable fallback). Bytes freed."""
        with self.lock:
            if self._restoring or self._broken or self._deleted:
                return 0
            kept = [segment for segment, _ in self._store.checkpoint_paths()[:CHECKPOINTS_KEPT]]
            if len(kept) < CHECKPOINTS_KEPT:
                return 0
            below = min(kept)
            segments = self._store.segments()
            if not any(not s.pruned and s.index < below for s in segments):
                return 0
            # Both kept checkpoints must be intact: otherwise they are not a fallback.
            valid = [h.segment for h, _ in self._checkpoints() if h.segment in kept]
            if len(valid) < CHECKPOINTS_KEPT:
                return 0
            return self._store.prune(older_than_s, below)

    def close(self) -> bool:
        """Release everything; True if a checkpoint was written (scans since the last one)."""
        self._cancel.set()
        if not self._restoring:
            # Shutdown lets the back end take in the nodes it was handed (seconds at most), so
            # the last map and graph are complete; the checkpoint would carry them anyway.
            self.wait_backend(BACKEND_DRAIN_S)
        with self.lock:
            with contextlib.suppress(MapperError):  # a process gone: the recording stays
                self._revoke(recover=False)
            checkpointed = False
            if self.is_active and not self._restoring and not self._lost:
                checkpointed = self._checkpoint_if_behind()
            self._store.close_writer()
            if self._mapper is not None:
                self._mapper.close()
        return checkpointed

    def _checkpoint_if_behind(self) -> bool:
        """A checkpoint at a clean stop or shutdown makes the next start instant (lock held)."""
        if self.scans_accepted > self._checkpoint_scans:
            return self._write_checkpoint()
        return False

    # -- reads ----------------------------------------------------------------------------

    def info(self) -> SessionInfo:
        with self.lock:
            restoring = self._restoring
            return SessionInfo(
                id=self.id,
                robot_id=self.robot_id,
                state=self.state,
                created_ns=self.created_ns,
                scans_accepted=0 if restoring else self.scans_accepted,
                poses=0 if restoring else len(self._poses),
                resolution_m=self.resolution_m,
                use_odometry=self.use_odometry,
                last_pose=(
                    self._corrected(self._poses[-1:])[0] if self._poses and not restoring else None
                ),
                status=self.status,
                damage=self._damage,
                graph=None if restoring else self._graph_snapshot(),
            )

    def recording_path(self) -> Path:
        """The segment of the current map's recording that grows (see `recording_paths`)."""
        with self.lock:
            return self._store.recording_path

    def recording_paths(self) -> list[Path]:
        """The current map's recording, segment by segment (scans and poses; a pruned segment
        has its poses only); the last may be read while it grows: readers stop at the last
        complete record."""
        with self.lock:
            return [seg.path for seg in self._store.segments()]

    @property
    def last_pose(self) -> Pose | None:
        """The latest pose, where the back end's graph puts it now."""
        with self.lock:
            if self._restoring or not self._poses:
                return None
            return self._corrected([self._poses[-1]])[0]

    def pose_for_read(self) -> Pose | None:
        """`last_pose` for `GET .../pose`: a session still restoring is a 503 to retry, not a
        session without a pose (None)."""
        with self.lock:
            self._ready_for_reads()
            if not self._poses:
                return None
            return self._corrected([self._poses[-1]])[0]

    def trajectory(self) -> list[Pose]:
        """Every pose, corrected by the latest graph (each by its latest node's correction)."""
        with self.lock:
            self._ready_for_reads()
            poses = list(self._poses)  # references: the correction is done unlocked
            snap = self._graph_snapshot()
        return _corrected(snap, poses)

    # -- the back end's graph (loop closure) -------------------------------------------------

    def _graph_snapshot(self, *, fresh: bool = False) -> GraphSnapshot:
        """The latest graph the mapper published (lock held): asked again when the mapper
        reported a newer revision than the one held, a second after the last ask, or when
        `fresh` (a client asking for the graph itself: a node queued since the last scan's
        answer is not in the revision that answer carried)."""
        mapper = self._mapper
        if mapper is None or self._restoring:
            return self._graph
        now = time.monotonic()
        recent = now - self._graph_fetched_s < 1.0
        if not fresh and self._graph.revision == self._graph_rev_seen and recent:
            return self._graph
        try:
            snap = mapper.graph(self._graph.revision)
        except MapperError as err:  # a lost mapper process: the next scan rebuilds it
            log.debug("session %s: graph unavailable: %s", self.id, err)
            return self._graph
        self._graph_fetched_s = now
        if snap is not None:
            self._graph = snap
            if snap.image_revision != self._image_rev_seen:
                self._image_rev_seen = snap.image_revision
                self.map_revision += 1
        return self._graph

    def _corrected(self, poses: Sequence[Pose]) -> list[Pose]:
        """`poses` (the front end's) moved onto the latest graph (lock held)."""
        return _corrected(self._graph_snapshot(), poses)

    def graph(self) -> GraphSnapshot:
        """The back end's graph for `GET /sessions/{id}/graph` (empty without a back end)."""
        with self.lock:
            self._ready_for_reads()
            return self._graph_snapshot(fresh=True)

    def wait_backend(self, timeout_s: float = 60.0) -> bool:
        """Until the back end has every node and its map drawn (tests, benchmarks, tools)."""
        with self.lock:
            mapper = self._mapper
        wait = getattr(mapper, "wait_backend", None)
        try:
            done = True if wait is None else bool(wait(timeout_s))
        except MapperError as err:  # its process is gone or shutting down: nothing to wait for
            log.debug("session %s: back end not waited for: %s", self.id, err)
            done = False
        with self.lock:
            self._graph_fetched_s = 0.0  # the next read asks for the graph and map again
        return done

    def graph_counts(self) -> GraphSnapshot | None:
        """The latest graph for counters (/metrics); None while restoring."""
        with self.lock:
            if self._restoring or self._mapper is None:
                return None
            return self._graph_snapshot()

    def loop_closures(self) -> list[tuple[tuple[float, float], tuple[float, float]]]:
        """Accepted closures as segments between their nodes' optimised positions (map)."""
        with self.lock:
            if self._restoring:
                return []
            snap = self._graph_snapshot()
        out = []
        for c in snap.closures:
            if c.accepted and max(c.from_node, c.to_node) < snap.nodes:
                a, b = snap.optimised[c.from_node], snap.optimised[c.to_node]
                out.append(((float(a[0]), float(a[1])), (float(b[0]), float(b[1]))))
        return out

    def trajectory_page(
        self, since_seq: int = 0, limit: int | None = None, every: int = 1
    ) -> tuple[list[Pose], int | None, int]:
        """Poses with `sequence >= since_seq` whose sequence is a multiple of `every`, at most
        `limit`; with the sequence to ask for next (None at the end) and the total count."""
        with self.lock:
            self._ready_for_reads()
            poses = self._poses
            total = len(poses)
            start = bisect.bisect_left(poses, since_seq, key=lambda p: p.seq)
            out: list[Pose] = []
            index = start
            if every > 1:
                # Jump from multiple to multiple (sequence == index unless records were lost).
                while index < total and (limit is None or len(out) < limit):
                    pose = poses[index]
                    if pose.seq % every == 0:
                        out.append(pose)
                        index += 1
                        target = pose.seq + every
                        index = bisect.bisect_left(poses, target, lo=index, key=lambda p: p.seq)
                    else:
                        target = pose.seq + (every - pose.seq % every)
                        index = bisect.bisect_left(poses, target, lo=index, key=lambda p: p.seq)
            else:
                stop = total if limit is None else min(total, start + limit)
                out = poses[start:stop]
                index = stop
            next_seq = poses[index].seq if index < total else None
            snap = self._graph_snapshot()
        # Unlocked: up to 10,000 poses to move must not hold the session's ingest.
        return _corrected(snap, out), next_seq, total

    def _ready_for_reads(self) -> None:
        if self._restoring:
            raise restoring_error(self.id)

    def _image(self) -> Any:
        """The grid snapshot, cached per map revision (lock held): the live page polls the
        map several times a second while it only changes at keyframes. None while the back
        end draws it (a map nobody read lately is drawn when asked): `_with_image` waits."""
        if self._restoring or self._mapper is None:
            raise restoring_error(self.id)
        if self._lost:
            self._recover()
        self._graph_snapshot()  # a map drawn since the last scan bumps the revision
        if self._image_cache is None or self._image_cache[1] != self.map_revision:
            try:
                image = self._mapper.snapshot()
            except MapperLostError as err:
                log.error("session %s: %s; rebuilding it from the recording", self.id, err)
                self._lost = True
                self._recover()
                image = self._mapper.snapshot()
            if image is None:
                return None
            self._image_cache = (image, self.map_revision)
        return self._image_cache[0]

    def _with_image(self, read: Callable[[Any], _T]) -> _T:
        """`read(image)` under the lock, with the map at its latest revision. While the back
        end draws a map nobody read lately (at its thread's next turn), the lock is let go:
        the session's scans and reads go on meanwhile."""
        deadline = time.monotonic() + MAP_DRAW_WAIT_S
        while True:
            with self.lock:
                image = self._image()
                if image is not None:
                    return read(image)
            if time.monotonic() > deadline:
                raise UnavailableError(
                    f"session {self.id}: its map is being drawn; retry in a second",
                    retry_after_s=1,
                )
            time.sleep(MAP_POLL_S)

    def map_image(self) -> MapSnapshot:
        """The map alone (no trajectory): for PGM/YAML and plain PNGs."""
        return self._with_image(
            lambda image: MapSnapshot(
                image=image,
                trajectory_xy_m=np.empty((0, 2)),
                last_pose=self._corrected(self._poses[-1:])[0] if self._poses else None,
                revision=self.map_revision,
            )
        )

    def map_snapshot(self) -> MapSnapshot:
        """The map with the trajectory's positions and the last pose."""
        # A cheap copy of references; the work is done unlocked.
        image, poses, revision, snap = self._with_image(
            lambda image: (image, list(self._poses), self.map_revision, self._graph_snapshot())
        )
        n = len(poses)
        xyt = np.fromiter(
            (c for p in poses for c in (p.x_m, p.y_m, p.theta_rad)), dtype=np.float64, count=3 * n
        ).reshape(-1, 3)
        if n and snap.nodes:
            seqs = np.fromiter((p.seq for p in poses), dtype=np.int64, count=n)
            xyt = correct_poses(snap, seqs, xyt)
        last = None
        if poses:
            x, y, t = (float(v) for v in xyt[-1])
            last = replace(poses[-1], x_m=x, y_m=y, theta_rad=t)
        return MapSnapshot(
            image=image, trajectory_xy_m=xyt[:, :2].copy(), last_pose=last, revision=revision
        )


def _has_records(directory: Path) -> bool:
    """True if a recording segment in `directory` holds more than its header."""
    return any(
        parse_segment(p.name) is not None and p.stat().st_size > len(RECORDING_MAGIC)
        for p in directory.iterdir()
    )


def _robot_id_from_recording(directory: Path) -> str | None:
    """The robot id of the first readable scan in any recording segment of `directory`."""
    for path in sorted(directory.iterdir()):
        if parse_segment(path.name) is None:
            continue
        try:
            for record in iter_raw_records(path):
                if record_kind(record.payload) == "scan":
                    robot_id = decode_scan(
                        record.payload, max_payload_bytes=MAX_RECORD_BYTES
                    ).robot_id
                    return robot_id if ROBOT_ID_PATTERN.fullmatch(robot_id) else None
        except Exception:  # a placeholder's name is best effort
            continue
    return None


def _corrected(snap: GraphSnapshot, poses: Sequence[Pose]) -> list[Pose]:
    """`poses` (the front end's) moved onto the graph of `snap`; unmoved ones kept as they are."""
    if snap.nodes == 0 or not poses:
        return list(poses)
    seqs = np.fromiter((p.seq for p in poses), dtype=np.int64, count=len(poses))
    xyt = np.array([(p.x_m, p.y_m, p.theta_rad) for p in poses], dtype=np.float64)
    moved = correct_poses(snap, seqs, xyt)
    same = (moved == xyt).all(axis=1).tolist()
    return [
        p if keep else replace(p, x_m=float(m[0]), y_m=float(m[1]), theta_rad=float(m[2]))
        for p, m, keep in zip(poses, moved.tolist(), same, strict=True)
    ]


def _moved(pose: Pose, correction: tuple[float, float, float]) -> Pose:
    """`pose` moved by a correction (x, y, theta); the same object when it is the identity."""
    cx, cy, ct = correction
    if cx == 0.0 and cy == 0.0 and ct == 0.0:
        return pose
    c, s = math.cos(ct), math.sin(ct)
    theta = (pose.theta_rad + ct + math.pi) % (2 * math.pi) - math.pi
    return replace(
        pose,
        x_m=cx + c * pose.x_m - s * pose.y_m,
        y_m=cy + s * pose.x_m + c * pose.y_m,
        theta_rad=theta,
    )


moved_pose = _moved  # for mapper processes that publish poses themselves


def _same_pose(a: Pose, b: Pose) -> bool:
    return (
        a.seq == b.seq
        and math.isclose(a.x_m, b.x_m, abs_tol=1e-9)
        and math.isclose(a.y_m, b.y_m, abs_tol=1e-9)
        and math.isclose(a.theta_rad, b.theta_rad, abs_tol=1e-9)
    )


class ScanRouter(Protocol):
    """Mapper processes that ingest their robots' scans (`MapperPool` with `ingest`)."""

    def place(self, session_id: str, robot_id: str) -> None: ...
    def activate(self, robot_id: str, session_id: str) -> None: ...
    def deactivate(self, robot_id: str, session_id: str) -> None: ...


class SessionManager:
    """All sessions of this service; the index robot -> active session."""

    def __init__(
        self,
        data: DataDir,
        maps: MapStore,
        *,
        fsync_each: bool = False,
        engine: Engine | None = None,
        make_mapper: MapperFactory | None = None,
        render_map_files: Callable[[MapSnapshot], dict[str, bytes]] | None = None,
        max_open_sessions: int | None = None,
        router: ScanRouter | None = None,
        on_pose: Callable[[Pose], None] | None = None,
    ) -> None:
        """`router`: mapper processes that ingest their robots' scans themselves, told which
        robot has which active session; `on_pose`: where the poses they publish go besides
        Zenoh (the browser streams)."""
        self._data = data
        self._maps = maps
        self._fsync_each = fsync_each
        engine = engine or Engine()
        self._make_mapper = make_mapper or local_mapper_factory(engine)
        # New sessions' front end (each keeps its own: `SessionMeta.front_end`).
        self._front_end = session_front_end(engine.front_end)
        self._render = render_map_files
        self._lock = threading.Lock()
        self._sessions: dict[str, MappingSession] = {}
        self._active: dict[str, str] = {}  # robot_id -> session id
        self._restore_thread: threading.Thread | None = None
        self._restored = threading.Event()
        self._restored.set()
        self.max_open_sessions = max_open_sessions
        self._router = router
        self._on_pose = on_pose

    def load_all(self) -> None:
        """Register every session of the data directory, in status `restoring` (fast: reads
        only `session.json`); `restore_all` then replays them."""
        for directory in self._data.session_dirs():
            if not (directory / "session.json").exists() and not _has_records(directory):
                # Interrupted creation: the client never got an answer for it.
                log.warning("removing incomplete session directory %s", directory.name)
                self._data.trash_dir.mkdir(exist_ok=True)
                directory.rename(self._data.trash_dir / directory.name)
                continue
            try:
                store = SessionStore.load(directory, fsync_each=self._fsync_each)
                session = MappingSession(store, self._make_mapper, restoring=True)
            except StoreError as err:
                # Never silently gone: listed as `damaged`, files left for fsck.
                log.error("session %s cannot be restored (files kept): %s", directory.name, err)
                session = MappingSession.damaged(directory, err.reason, self._make_mapper)
            session.on_pose = self._on_pose
            if self._router is not None:
                self._router.place(session.id, session.robot_id)
            with self._lock:
                self._sessions[session.id] = session
                if session.state == "active" and session.status != "damaged":
                    previous = self._active.get(session.robot_id)
                    if previous is not None:
                        log.warning(
                            "robot %s had two active sessions; stopping %s",
                            session.robot_id,
                            previous,
                        )
                        self._sessions[previous].mark_stopped()
                    self._active[session.robot_id] = session.id
        if self._router is not None:
            with self._lock:
                active = list(self._active.items())
            for robot_id, session_id in active:  # their scans are held until the restore ends
                self._router.activate(robot_id, session_id)

    def restore_all(self, *, background: bool = True) -> None:
        """Replay every restoring session, oldest first (in a thread when `background`)."""
        restoring = [s for s in self.list() if s.status == "restoring"]
        self._restored.clear()

        def run() -> None:
            t0 = time.monotonic()
            try:
                for session in restoring:
                    try:
                        session.restore()
                    except Exception:  # one broken session must not keep the others waiting
                        log.exception("session %s: restore failed", session.id)
                        session._broken = True
                        session._restoring = False
                        session._damage = replace(
                            session.damage, notes=(*session.damage.notes, "restore failed")
                        )
                log.info(
                    "restored %d sessions from %s in %.2f s",
                    len(restoring),
                    self._data.root,
                    time.monotonic() - t0,
                )
            finally:
                self._restored.set()

        if background:
            self._restore_thread = threading.Thread(target=run, name="restore", daemon=True)
            self._restore_thread.start()
        else:
            run()

    def wait_restored(self, timeout_s: float | None = None) -> bool:
        return self._restored.wait(timeout_s)

    @property
    def restoring(self) -> bool:
        return not self._restored.is_set()

    def create(self, robot_id: str, resolution_m: float, use_odometry: bool) -> MappingSession:
        with self._lock:
            current = self._active.get(robot_id)
            if current is not None:
                raise ConflictError(f"robot {robot_id!r} already has an active session {current}")
            if self.max_open_sessions is not None and len(self._active) >= self.max_open_sessions:
                raise UnavailableError(
                    f"at the limit of {self.max_open_sessions} active sessions; stop one first"
                )
            meta = SessionMeta(
                id=new_session_id(),
                robot_id=robot_id,
                created_ns=time.time_ns(),
                state="active",
                resolution_m=resolution_m,
                use_odometry=use_odometry,
                front_end=self._front_end,
            )
            if self._router is not None:
                self._router.place(meta.id, robot_id)
                self._router.activate(robot_id, meta.id)
            try:
                store = SessionStore.create(
                    self._data.sessions_dir, meta, fsync_each=self._fsync_each
                )
                session = MappingSession(store, self._make_mapper)
            except OSError as err:
                if self._router is not None:
                    self._router.deactivate(robot_id, meta.id)
                # No paths in the answer: the reason only (it goes to clients).
                raise _create_error(err) from err
            except BaseException:
                if self._router is not None:
                    self._router.deactivate(robot_id, meta.id)
                raise
            session.on_pose = self._on_pose
            self._sessions[session.id] = session
            self._active[robot_id] = session.id
        session.lease_if_ready()  # the robot's mapper process maps its scans from now on
        log.info("session %s created for robot %s", session.id, robot_id)
        return session

    def get(self, session_id: str) -> MappingSession:
        with self._lock:
            session = self._sessions.get(check_id(session_id, "session"))
        if session is None:
            raise NotFoundError(f"no such session {session_id!r}")
        return session

    def list(self) -> list[MappingSession]:
        with self._lock:
            return sorted(self._sessions.values(), key=lambda s: (s.created_ns, s.id))

    def active_for(self, robot_id: str) -> MappingSession | None:
        with self._lock:
            session_id = self._active.get(robot_id)
            return self._sessions.get(session_id) if session_id is not None else None

    def active_count(self) -> int:
        with self._lock:
            return len(self._active)

    def stop(self, session_id: str) -> MappingSession:
        session = self.get(session_id)
        session.stop()
        with self._lock:
            if self._active.get(session.robot_id) == session.id:
                del self._active[session.robot_id]
        if self._router is not None:
            self._router.deactivate(session.robot_id, session.id)
        log.info("session %s stopped", session.id)
        return session

    def reset(self, session_id: str) -> MappingSession:
        session = self.get(session_id)
        session.reset()
        log.info("session %s reset", session.id)
        return session

    def delete(self, session_id: str, *, keep_maps: bool = False) -> Sequence[SavedMapMeta]:
        """Delete a session and its recording, and its saved maps unless `keep_maps`;
        returns the saved map versions deleted."""
        session = self.get(session_id)
        if session.status == "restoring":
            raise restoring_error(session.id)
        with self._lock:
            self._sessions.pop(session.id, None)
            if self._active.get(session.robot_id) == session.id:
                del self._active[session.robot_id]
        if self._router is not None:
            self._router.deactivate(session.robot_id, session.id)
        session.delete(self._data.trash_dir)
        maps: Sequence[SavedMapMeta] = ()
        if not keep_maps:
            maps = self._maps.delete(session.id, None, self._data.trash_dir)
        log.info(
            "session %s deleted%s",
            session.id,
            f" with {len(maps)} saved map version(s)" if maps else "",
        )
        return maps

    def save(self, session_id: str) -> SavedMapMeta:
        if self._render is None:
            raise StoreError("map rendering is not configured")
        session = self.get(session_id)
        files = self._render(session.map_image())
        session.sync()
        meta = self._maps.save(
            map_id=session.id,
            session_id=session.id,
            robot_id=session.robot_id,
            saved_ns=time.time_ns(),
            files=files,
        )
        log.info("session %s saved as map %s v%d", session.id, meta.map_id, meta.version)
        return meta

    def sync_all(self) -> None:
        for session in self.list():
            try:
                session.sync()
            except OSError as err:
                log.error("fsync of session %s failed: %s", session.id, err)

    def close_idle(self, idle_s: float = IDLE_CLOSE_S) -> int:
        """Close the recordings of quiet sessions; returns how many were closed."""
        closed = 0
        for session in self.list():
            try:
                closed += session.close_if_idle(idle_s)
            except OSError as err:
                log.error("closing the recording of session %s failed: %s", session.id, err)
        return closed

    def prune(self, older_than_s: float) -> int:
        freed = 0
        for session in self.list():
            try:
                freed += session.prune(older_than_s)
            except (OSError, StoreError) as err:
                log.error("pruning session %s failed: %s", session.id, err)
        return freed

    def close(self) -> tuple[int, int]:
        """Close every session: (sessions closed, checkpoints written), for the shutdown log."""
        for session in self.list():
            session.cancel_restore()
        if self._restore_thread is not None:
            self._restore_thread.join(timeout=30)
        closed = checkpoints = 0
        for session in self.list():
            try:
                checkpoints += session.close()
                closed += 1
            except OSError as err:
                log.error("closing session %s failed: %s", session.id, err)
        return closed, checkpoints


def _create_error(err: OSError) -> Exception:
    if err.errno in (errno.EMFILE, errno.ENFILE):
        return UnavailableError(
            "cannot open more files (descriptor limit reached): stop idle sessions or raise "
            "the service's descriptor limit, then retry"
        )
    if err.errno == errno.ENOSPC:
        return UnavailableError("no space left on the service's disk")
    return StoreError(f"cannot create session files: {err.strerror or type(err).__name__}")


__all__ = [
    "DamageSummary",
    "Ingested",
    "MapSnapshot",
    "MappingSession",
    "SessionInfo",
    "SessionManager",
    "SessionStatus",
    "read_meta",
]
