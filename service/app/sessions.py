"""Mapping sessions: one estimator and one occupancy grid per session, one active session per robot.

A `MappingSession` is driven by exactly one ingest worker (its robot's) and read by HTTP handlers;
its lock serialises the two. Every accepted scan, then its pose, is appended to the session's
recording before the counters and the trajectory show it, so a restart that replays the recording
(`SessionManager.load_all`) rebuilds exactly what clients were told.
"""

from __future__ import annotations

import logging
import math
import pickle
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, NamedTuple

import numpy as np
import numpy.typing as npt

from clients.recording import MAX_RECORD_BYTES
from clients.wire import (
    DecodeError,
    Pose,
    PoseFlag,
    Scan,
    decode_pose,
    decode_scan,
    encode_pose,
)
from service.app.errors import ConflictError, NotFoundError, StoreError
from service.app.mapper import (
    Engine,
    MappedScan,
    Mapper,
    MapperError,
    MapperFactory,
    MapperLostError,
    local_mapper_factory,
)
from service.app.store import (
    DataDir,
    MapStore,
    SavedMapMeta,
    SessionMeta,
    SessionState,
    SessionStore,
    check_id,
    new_session_id,
    write_atomic,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class MapSnapshot:
    image: Any  # service.core.grid.GridImage
    trajectory_xy_m: npt.NDArray[np.float64]  # (N, 2)
    last_pose: Pose | None
    revision: int


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


@dataclass(frozen=True, slots=True)
class _Checkpoint:
    """Estimator and grid after the first `records` records of recording epoch `epoch`.

    A checkpoint only shortens a restart: the recording stays the source of truth, and a
    checkpoint that does not match it is ignored (full replay).
    """

    epoch: int
    records: int
    scans_accepted: int
    map_revision: int
    mapper_state: bytes  # `Mapper.state()`: estimator and grid


CHECKPOINT_FILE = "checkpoint.pickle"


class Ingested(NamedTuple):
    """What `MappingSession.ingest` did with a scan."""

    accepted: bool
    pose: Pose | None  # None when not accepted or when the estimator failed
    pose_bytes: bytes | None  # `encode_pose(pose)`, as recorded


_NOT_ACCEPTED: Final = Ingested(False, None, None)


class MappingSession:
    # A restart replays only the scans after the last checkpoint; one a minute at 40 Hz
    # bounds that replay to about a minute of estimator time.
    checkpoint_every_scans = 2400

    def __init__(self, store: SessionStore, make_mapper: MapperFactory) -> None:
        meta = store.meta
        self.id = meta.id
        self.robot_id = meta.robot_id
        self.created_ns = meta.created_ns
        self.resolution_m = meta.resolution_m
        self.use_odometry = meta.use_odometry
        self.lock = threading.Lock()
        self._store = store
        self._make_mapper = make_mapper
        self._mapper: Mapper = make_mapper(meta.id, meta.use_odometry, meta.resolution_m)
        self._poses: list[Pose] = []
        self._deleted = False
        self.scans_accepted = 0
        self.estimator_errors = 0
        self.map_revision = 0
        self._image_cache: tuple[Any, int] | None = None
        self._records = 0  # records in the current recording epoch
        self._payload: bytes | None = None  # wire bytes of the scan being estimated (lock held)
        self._checkpoint_scans = 0  # scans_accepted at the last checkpoint

    @property
    def state(self) -> SessionState:
        return self._store.meta.state

    @property
    def is_active(self) -> bool:
        return self.state == "active" and not self._deleted

    # -- the hot path (ingest worker) ---------------------------------------------------------

    def ingest(self, payload: bytes, scan: Scan) -> Ingested:
        """Record, estimate and map one validated scan.

        Not accepted, and nothing recorded, when the session is no longer active. An accepted
        scan has no pose only if the estimator failed on it. The pose comes with its wire
        encoding, the bytes just recorded, so that publishing does not encode it again.
        """
        with self.lock:
            if not self.is_active:
                return _NOT_ACCEPTED
            self._store.append(payload)  # durable before it counts
            self._records += 1
            self.scans_accepted += 1
            pose = self._estimate_payload(scan, payload)
            encoded: bytes | None = None
            if pose is not None:
                encoded = encode_pose(pose)
                self._store.append(encoded)
                self._records += 1
                self._poses.append(pose)
            if self.scans_accepted - self._checkpoint_scans >= self.checkpoint_every_scans:
                self._write_checkpoint()
            return Ingested(True, pose, encoded)

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
        try:
            mapped = self._map(scan, self._payload)
        except Exception:
            # The estimator promises not to raise on bad data; if it does anyway, the scan stays
            # recorded (a replay meets the same failure) and the session carries on.
            self.estimator_errors += 1
            if self.estimator_errors == 1 or math.log2(self.estimator_errors).is_integer():
                log.exception(
                    "session %s: estimator failed on scan %d (%d failures so far)",
                    self.id,
                    scan.seq,
                    self.estimator_errors,
                )
            return None
        if mapped.is_keyframe:
            self.map_revision += 1
        return Pose(
            session_id=self.id,
            robot_id=self.robot_id,
            seq=len(self._poses),
            stamp_ns=scan.stamp_ns,
            x_m=mapped.x_m,
            y_m=mapped.y_m,
            theta_rad=mapped.theta_rad,
            quality=min(max(mapped.quality, 0.0), 1.0),
            flags=PoseFlag(mapped.flags),
            covariance=mapped.covariance if len(mapped.covariance) == 9 else None,
        )

    def _map(self, scan: Scan, payload: bytes | None) -> MappedScan:
        """The mapper's answer; a lost mapper (its process died) is rebuilt first (lock held)."""
        try:
            return self._mapper.map_scan(scan, payload)
        except MapperLostError as err:
            log.error("session %s: %s; rebuilding its map from the recording", self.id, err)
            self._rebuild_mapper()
            return self._mapper.map_scan(scan, payload)

    def _rebuild_mapper(self) -> None:
        """A new mapper with the state of every record before the current one (lock held):
        the checkpoint's, then the recorded scans after it, as a restart would."""
        self._mapper.close()
        self._mapper = self._make_mapper(self.id, self.use_odometry, self.resolution_m)
        upto = self._records - 1  # the current scan is recorded already; the caller maps it
        checkpoint = self._load_checkpoint()
        skip = 0
        if checkpoint is not None and checkpoint.records <= upto:
            skip = self._restore(checkpoint)
        replayed = 0
        for index, record in enumerate(self._store.records()):
            if index >= upto:
                break
            if index < skip or record.kind != "scan":
                continue
            try:
                scan = decode_scan(record.payload, max_payload_bytes=MAX_RECORD_BYTES)
                self._mapper.map_scan(scan, record.payload)
            except DecodeError:
                continue
            replayed += 1
        self.map_revision += 1
        log.info("session %s: map rebuilt (%d scans re-estimated)", self.id, replayed)

    # -- recovery -------------------------------------------------------------------------

    def _write_checkpoint(self) -> None:
        """Persist estimator and grid (lock held); the recording is fsynced first so that a
        checkpoint never refers to records a power loss could take back."""
        try:
            checkpoint = _Checkpoint(
                epoch=self._store.meta.epoch,
                records=self._records,
                scans_accepted=self.scans_accepted,
                map_revision=self.map_revision,
                mapper_state=self._mapper.state(),
            )
            self._store.sync()
            data = pickle.dumps(checkpoint, protocol=pickle.HIGHEST_PROTOCOL)
            write_atomic(self._store.directory / CHECKPOINT_FILE, data)
        except (OSError, MapperError, pickle.PicklingError, TypeError) as err:
            log.warning("session %s: checkpoint not written: %s", self.id, err)
        self._checkpoint_scans = self.scans_accepted

    def _restore(self, checkpoint: _Checkpoint) -> int:
        """The mapper from `checkpoint` (lock held): the records it covers, or 0 when its state
        does not restore (pickled by an older version, say) and everything is replayed."""
        try:
            self._mapper.restore(checkpoint.mapper_state)
        except Exception as err:  # the recording is the truth; a checkpoint only saves time
            log.warning("session %s: checkpoint does not restore, replaying all: %s", self.id, err)
            self._mapper.close()
            self._mapper = self._make_mapper(self.id, self.use_odometry, self.resolution_m)
            return 0
        return checkpoint.records

    def _load_checkpoint(self) -> _Checkpoint | None:
        """The session's checkpoint if it matches the recording, else None (full replay)."""
        path = self._store.directory / CHECKPOINT_FILE
        if not path.exists():
            return None
        try:
            # The data directory is this service's own state, as trusted as its code.
            checkpoint = pickle.loads(path.read_bytes())
        except Exception as err:  # any unpickling failure (e.g. after an upgrade)
            log.warning("session %s: checkpoint unreadable, replaying all: %s", self.id, err)
            return None
        if not isinstance(checkpoint, _Checkpoint) or checkpoint.epoch != self._store.meta.epoch:
            return None
        if sum(1 for _ in self._store.records()) < checkpoint.records:
            log.warning("session %s: checkpoint ahead of the recording, replaying all", self.id)
            return None
        return checkpoint

    def replay(self) -> None:
        """Rebuild estimator, grid, counters and trajectory from the recording.

        Records covered by the checkpoint only restore counters and the trajectory; the
        estimator runs on the records after it.
        """
        pending: Pose | None = None  # recomputed pose of the last scan, until its record comes
        mismatches = 0
        undecodable = 0
        with self.lock:
            checkpoint = self._load_checkpoint()
            skip = 0
            if checkpoint is not None:
                skip = self._restore(checkpoint)
                if skip:
                    self.map_revision = checkpoint.map_revision
            for index, record in enumerate(self._store.records()):
                self._records += 1
                kind = record.kind
                try:
                    if index < skip:
                        if kind == "scan":
                            self.scans_accepted += 1
                        elif kind == "pose":
                            self._poses.append(decode_pose(record.payload))
                        continue
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
            tail_repaired = False
            if pending is not None:
                # Crash between a scan's record and its pose's: the pose is recomputed and,
                # if the session goes on, recorded now.
                self._poses.append(pending)
                tail_repaired = True
            if self.state == "active":
                self._store.open_for_append()
                if tail_repaired and pending is not None:
                    self._store.append(encode_pose(pending))
                    self._records += 1
            self._checkpoint_scans = checkpoint.scans_accepted if checkpoint is not None else 0
        if mismatches or undecodable:
            log.warning(
                "session %s: replay found %d pose mismatches and %d unreadable records",
                self.id,
                mismatches,
                undecodable,
            )
        log.info(
            "session %s (robot %s, %s): restored %d scans, %d poses",
            self.id,
            self.robot_id,
            self.state,
            self.scans_accepted,
            len(self._poses),
        )

    # -- control --------------------------------------------------------------------------

    def stop(self) -> None:
        with self.lock:
            if self.state == "active":
                self._checkpoint_if_behind()
                self._store.close_writer()
                self._store.set_state("stopped")

    def reset(self) -> None:
        """Forget the map and the trajectory; the next scan starts a new map frame."""
        with self.lock:
            self._store.new_epoch()
            if self.state != "active":
                self._store.close_writer()
            self._mapper.reset()
            self._poses = []
            self.scans_accepted = 0
            self.map_revision += 1
            self._records = 0
            self._checkpoint_scans = 0
            (self._store.directory / CHECKPOINT_FILE).unlink(missing_ok=True)

    def delete(self, trash_dir: Any) -> None:
        with self.lock:
            self._deleted = True
            self._mapper.close()
            self._store.delete(trash_dir)

    def sync(self) -> None:
        self._store.sync()

    def close(self) -> None:
        with self.lock:
            if self.state == "active" and not self._deleted:
                self._checkpoint_if_behind()
            self._store.close_writer()
            self._mapper.close()

    def _checkpoint_if_behind(self) -> None:
        """A checkpoint at a clean stop or shutdown makes the next start instant (lock held)."""
        if self.scans_accepted > self._checkpoint_scans:
            self._write_checkpoint()

    # -- reads ----------------------------------------------------------------------------

    def info(self) -> SessionInfo:
        with self.lock:
            return SessionInfo(
                id=self.id,
                robot_id=self.robot_id,
                state=self.state,
                created_ns=self.created_ns,
                scans_accepted=self.scans_accepted,
                poses=len(self._poses),
                resolution_m=self.resolution_m,
                use_odometry=self.use_odometry,
                last_pose=self._poses[-1] if self._poses else None,
            )

    def recording_path(self) -> Path:
        """The current map's recording (scans and poses); it may be read while it grows:
        readers stop at the last complete record."""
        with self.lock:
            return self._store.recording_path

    @property
    def last_pose(self) -> Pose | None:
        with self.lock:
            return self._poses[-1] if self._poses else None

    def trajectory(self) -> list[Pose]:
        with self.lock:
            return list(self._poses)

    def _image(self) -> Any:
        """The grid snapshot, cached per map revision (lock held): the live page polls the
        map several times a second while it only changes at keyframes."""
        if self._image_cache is None or self._image_cache[1] != self.map_revision:
            self._image_cache = (self._mapper.snapshot(), self.map_revision)
        return self._image_cache[0]

    def map_image(self) -> MapSnapshot:
        """The map alone (no trajectory): for PGM/YAML and plain PNGs."""
        with self.lock:
            return MapSnapshot(
                image=self._image(),
                trajectory_xy_m=np.empty((0, 2)),
                last_pose=self._poses[-1] if self._poses else None,
                revision=self.map_revision,
            )

    def map_snapshot(self) -> MapSnapshot:
        """The map with the trajectory's positions and the last pose."""
        with self.lock:
            image = self._image()
            poses = list(self._poses)  # a cheap copy of references; the work is done unlocked
            revision = self.map_revision
        xy = np.fromiter(
            (c for p in poses for c in (p.x_m, p.y_m)), dtype=np.float64, count=2 * len(poses)
        ).reshape(-1, 2)
        last = poses[-1] if poses else None
        return MapSnapshot(image=image, trajectory_xy_m=xy, last_pose=last, revision=revision)


def _same_pose(a: Pose, b: Pose) -> bool:
    return (
        a.seq == b.seq
        and math.isclose(a.x_m, b.x_m, abs_tol=1e-9)
        and math.isclose(a.y_m, b.y_m, abs_tol=1e-9)
        and math.isclose(a.theta_rad, b.theta_rad, abs_tol=1e-9)
    )


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
    ) -> None:
        self._data = data
        self._maps = maps
        self._fsync_each = fsync_each
        self._make_mapper = make_mapper or local_mapper_factory(engine or Engine())
        self._render = render_map_files
        self._lock = threading.Lock()
        self._sessions: dict[str, MappingSession] = {}
        self._active: dict[str, str] = {}  # robot_id -> session id

    def load_all(self) -> None:
        """Restore every session of the data directory (replaying its recording)."""
        for directory in self._data.session_dirs():
            if not (directory / "session.json").exists():
                # Interrupted creation: the client never got an answer for it.
                log.warning("removing incomplete session directory %s", directory.name)
                self._data.trash_dir.mkdir(exist_ok=True)
                directory.rename(self._data.trash_dir / directory.name)
                continue
            try:
                store = SessionStore.load(directory, fsync_each=self._fsync_each)
                session = MappingSession(store, self._make_mapper)
                session.replay()
            except StoreError as err:
                log.error("session %s not restored (files kept): %s", directory.name, err)
                continue
            with self._lock:
                self._sessions[session.id] = session
                if session.state == "active":
                    previous = self._active.get(session.robot_id)
                    if previous is not None:
                        log.warning(
                            "robot %s had two active sessions; stopping %s",
                            session.robot_id,
                            previous,
                        )
                        self._sessions[previous].stop()
                    self._active[session.robot_id] = session.id

    def create(self, robot_id: str, resolution_m: float, use_odometry: bool) -> MappingSession:
        with self._lock:
            current = self._active.get(robot_id)
            if current is not None:
                raise ConflictError(f"robot {robot_id!r} already has an active session {current}")
            meta = SessionMeta(
                id=new_session_id(),
                robot_id=robot_id,
                created_ns=time.time_ns(),
                state="active",
                resolution_m=resolution_m,
                use_odometry=use_odometry,
            )
            try:
                store = SessionStore.create(
                    self._data.sessions_dir, meta, fsync_each=self._fsync_each
                )
            except OSError as err:
                raise StoreError(f"cannot create session files: {err}") from err
            session = MappingSession(store, self._make_mapper)
            self._sessions[session.id] = session
            self._active[robot_id] = session.id
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
        log.info("session %s stopped", session.id)
        return session

    def reset(self, session_id: str) -> MappingSession:
        session = self.get(session_id)
        session.reset()
        log.info("session %s reset", session.id)
        return session

    def delete(self, session_id: str) -> None:
        session = self.get(session_id)
        with self._lock:
            self._sessions.pop(session.id, None)
            if self._active.get(session.robot_id) == session.id:
                del self._active[session.robot_id]
        session.delete(self._data.trash_dir)
        log.info("session %s deleted", session.id)

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

    def close(self) -> None:
        for session in self.list():
            try:
                session.close()
            except OSError as err:
                log.error("closing session %s failed: %s", session.id, err)
