"""Durable state in the data directory: session metadata, session recordings, saved maps.

Layout::

    <data>/service.lock                      flock: one service per data directory
    <data>/sessions/<session_id>/session.json metadata (atomically replaced)
    <data>/sessions/<session_id>/epoch-NNNNNN.mrec   accepted scans and their poses (segment 0)
    <data>/maps/<map_id>/<version>/map.png|map.pgm|map.yaml|map.json
    <data>/trash/                            directories being deleted

    <data>/sessions/<session_id>/epoch-NNNNNN.SSSSSS.mrec   its later segments (one per checkpoint)
    <data>/sessions/<session_id>/epoch-NNNNNN.SSSSSS.poses.mrec  a pruned segment: poses only
    <data>/sessions/<session_id>/checkpoint-NNNNNN.SSSSSS.mck    estimator + grid before segment S

The recording of a session (clients.recording format) is the source of truth: every accepted
scan and every pose is appended to it, and written to the kernel, before it is counted. A reset
starts a new epoch file and switches `session.json` to it (the commit point), so a crash in the
middle leaves either the old state or the new one.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import re
import shutil
import threading
import time
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Final, Literal

from clients.recording import (
    RawRecord,
    RecordingError,
    RecordingReport,
    RecordingWriter,
    iter_raw_records,
)
from clients.wire import ROBOT_ID_PATTERN, SESSION_ID_PATTERN
from service.app.errors import NotFoundError, StoreError

log = logging.getLogger(__name__)

META_FORMAT: Final = 1
# The front ends a session can be created with (`service.core.slam.FRONT_ENDS` less the
# offline-only "paper"), as `session.json` names them.
SessionFrontEnd = Literal["matcher"]
SESSION_FRONT_ENDS: Final[tuple[SessionFrontEnd, ...]] = ("matcher",)
# Front ends a `session.json` may name that this version no longer has: "manhattan", the
# projection cascade, deleted when the matcher replaced it. Such a session is restored with the
# matcher from its whole recording (`SessionMeta.retired_front_end`).
RETIRED_FRONT_ENDS: Final = ("manhattan",)
# The front end of a `session.json` that names none: one written before sessions recorded theirs,
# when every session's was the service's setting, by default "manhattan".
LEGACY_FRONT_END: Final = "manhattan"


def session_front_end(name: object) -> SessionFrontEnd:
    """`name` as a session's front end; ValueError for any other (the live service has no
    "paper": offline only)."""
    for front_end in SESSION_FRONT_ENDS:
        if name == front_end:
            return front_end
    raise ValueError(f"front end {name!r} cannot run a live session")


MAP_FILES: Final = ("map.png", "map.pgm", "map.yaml")
_SEGMENT_FILE = re.compile(r"^epoch-(\d{6})(?:\.(\d{6}))?(\.poses)?\.mrec$")
_CHECKPOINT_FILE = re.compile(r"^checkpoint-(\d{6})\.(\d{6})\.mck$")
_PACK_FILE = re.compile(r"^frozen-(\d{6})\.mpack$")
LEGACY_CHECKPOINT: Final = "checkpoint.pickle"

SessionState = Literal["active", "stopped"]


def new_session_id() -> str:
    return "s-" + uuid.uuid4().hex[:16]


def check_id(value: str, what: str = "id") -> str:
    """Ids become directory names: only the wire contract's safe pattern, never `..` or `/`."""
    if SESSION_ID_PATTERN.fullmatch(value) is None:
        raise NotFoundError(f"no such {what} {value[:80]!r}")
    return value


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: Path, data: bytes) -> None:
    """Replace `path` with `data` so that a crash leaves the old or the new file, never half."""
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


# What `mapping-service fsck --repair` cut out of a session's recording: the rewritten segment
# holds only intact records, so without this note a restore would find nothing wrong.
FSCK_REPAIRS: Final = "fsck-repairs.json"


@dataclass(frozen=True, slots=True)
class RecordingRepair:
    """One segment rewritten by fsck with its intact records only."""

    segment: str  # the segment's file name (its epoch is in it)
    records_lost: int
    bytes_lost: int
    regions: int
    backup: str  # the original's file name, kept beside it
    repaired_unix_s: int


def read_repairs(directory: Path) -> list[RecordingRepair]:
    """The repairs fsck recorded in a session folder (none if the file is absent or unreadable:
    a note about past damage must never stop a restore)."""
    try:
        entries = json.loads((directory / FSCK_REPAIRS).read_bytes())
        return [RecordingRepair(**entry) for entry in entries]
    except FileNotFoundError:
        return []
    except (OSError, ValueError, TypeError) as err:
        log.warning("%s: %s unreadable (%s); ignored", directory.name, FSCK_REPAIRS, err)
        return []


def record_repair(directory: Path, repair: RecordingRepair) -> None:
    """Add `repair` to the session folder's list (atomically)."""
    entries = [asdict(r) for r in read_repairs(directory)] + [asdict(repair)]
    write_atomic(directory / FSCK_REPAIRS, json.dumps(entries, indent=1).encode())


@dataclass(frozen=True, slots=True)
class SessionMeta:
    id: str
    robot_id: str
    created_ns: int
    state: SessionState
    resolution_m: float
    use_odometry: bool
    # The front end its core runs (`service.core.slam.make_frontend`): the service's setting
    # when the session was created; a restart under another setting keeps it.
    front_end: SessionFrontEnd
    epoch: int = 0
    format: int = META_FORMAT
    # The retired front end (`RETIRED_FRONT_ENDS`) `session.json` names, or `LEGACY_FRONT_END`
    # when it names none; None for a session of a live front end. Such a session runs
    # `front_end` (the matcher); its checkpoints hold the retired one's state, so its restore
    # replays the whole recording and then clears this (`SessionStore.retire_front_end`).
    # Written as `front_end` until then, so a crash before it leaves the session as it was.
    retired_front_end: str | None = None

    def to_json(self) -> bytes:
        obj = asdict(self)
        retired = obj.pop("retired_front_end")
        if retired is not None:
            obj["front_end"] = retired
        return json.dumps(obj, indent=1).encode()

    @classmethod
    def from_json(cls, data: bytes) -> SessionMeta:
        obj: Any = json.loads(data)
        if not isinstance(obj, dict) or obj.get("format") != META_FORMAT:
            raise StoreError("session.json has an unknown format")
        named = obj.get("front_end", LEGACY_FRONT_END)
        retired = named if named in RETIRED_FRONT_ENDS else None
        try:
            front_end = session_front_end("matcher" if retired is not None else named)
        except ValueError:
            raise StoreError(
                f"session.json names an unknown front end {obj['front_end']!r}"
            ) from None
        meta = cls(
            id=str(obj["id"]),
            robot_id=str(obj["robot_id"]),
            created_ns=int(obj["created_ns"]),
            state="active" if obj["state"] == "active" else "stopped",
            resolution_m=float(obj["resolution_m"]),
            use_odometry=bool(obj["use_odometry"]),
            front_end=front_end,
            epoch=int(obj["epoch"]),
            retired_front_end=retired,
        )
        if SESSION_ID_PATTERN.fullmatch(meta.id) is None:
            raise StoreError(f"unsafe session id {meta.id!r}")
        if ROBOT_ID_PATTERN.fullmatch(meta.robot_id) is None:
            raise StoreError(f"unsafe robot id {meta.robot_id!r}")
        return meta


@dataclass(frozen=True, slots=True)
class Segment:
    """One file of a session's recording: segment `index` of the current epoch."""

    index: int
    path: Path
    pruned: bool  # only its pose records are left (retention); its scans are covered


def segment_name(epoch: int, index: int, *, pruned: bool = False) -> str:
    if pruned:
        return f"epoch-{epoch:06d}.{index:06d}.poses.mrec"
    if index == 0:
        return f"epoch-{epoch:06d}.mrec"  # the name before segments existed: old data reads on
    return f"epoch-{epoch:06d}.{index:06d}.mrec"


def checkpoint_name(epoch: int, segment: int) -> str:
    return f"checkpoint-{epoch:06d}.{segment:06d}.mck"


def parse_segment(name: str) -> tuple[int, int, bool] | None:
    """(epoch, index, pruned) of a segment file name, else None."""
    m = _SEGMENT_FILE.fullmatch(name)
    if m is None:
        return None
    return int(m.group(1)), int(m.group(2) or 0), m.group(3) is not None


def parse_checkpoint(name: str) -> tuple[int, int] | None:
    m = _CHECKPOINT_FILE.fullmatch(name)
    return (int(m.group(1)), int(m.group(2))) if m is not None else None


def pack_name(epoch: int) -> str:
    """The epoch's array pack: what its checkpoints hold that never changes, written once."""
    return f"frozen-{epoch:06d}.mpack"


def parse_pack(name: str) -> int | None:
    """The epoch of an array pack's file name, else None."""
    m = _PACK_FILE.fullmatch(name)
    return int(m.group(1)) if m is not None else None


class SessionStore:
    """The on-disk half of one session. Not thread-safe except `sync()`; callers serialise.

    The recording of the current epoch is a list of segment files; the writer appends to the
    last one and `roll()` starts the next (at each checkpoint). The writer is opened on the
    first append and closed when the session is idle (`close_if_idle`): descriptors stay
    bounded by the robots that are actually sending.
    """

    def __init__(self, directory: Path, meta: SessionMeta, *, fsync_each: bool) -> None:
        self.directory = directory
        self.meta = meta
        self._fsync_each = fsync_each
        self._io_lock = threading.Lock()  # guards the writer's lifecycle against sync()
        self._dirty = False
        self._writer: RecordingWriter | None = None
        self.segment = 0  # index of the segment appends go to
        self._known_end: tuple[int, int] | None = None  # (segment, byte length) we wrote
        self._last_append = time.monotonic()
        # Leased to a mapper process (`lease_out`): it appends, this object only fsyncs.
        self.leased = False

    # -- lifecycle -----------------------------------------------------------------------

    @classmethod
    def create(cls, sessions_dir: Path, meta: SessionMeta, *, fsync_each: bool) -> SessionStore:
        """Make the session's files; on any failure nothing is left behind."""
        directory = sessions_dir / check_id(meta.id, "session")
        directory.mkdir(parents=True)
        try:
            store = cls(directory, meta, fsync_each=fsync_each)
            store._open_writer()
            store._close_writer_locked()  # reopened on the first scan
            write_atomic(directory / "session.json", meta.to_json())
            _fsync_dir(sessions_dir)
        except BaseException:
            shutil.rmtree(directory, ignore_errors=True)
            raise
        return store

    @classmethod
    def load(cls, directory: Path, *, fsync_each: bool) -> SessionStore:
        meta = read_meta(directory)
        store = cls(directory, meta, fsync_each=fsync_each)
        store._remove_stale_files()
        segments = store.segments()
        store.segment = segments[-1].index if segments else 0
        if segments and segments[-1].pruned:
            store.segment += 1  # never append to a pruned segment
        return store

    def segment_path(self, index: int, *, pruned: bool = False) -> Path:
        return self.directory / segment_name(self.meta.epoch, index, pruned=pruned)

    @property
    def recording_path(self) -> Path:
        """The segment appends go to."""
        return self.segment_path(self.segment)

    def segments(self) -> list[Segment]:
        """The current epoch's segments in order (a pruned copy stands for a pruned segment)."""
        out = []
        for path in segment_files(self.directory, self.meta.epoch):
            parsed = parse_segment(path.name)
            assert parsed is not None
            out.append(Segment(parsed[1], path, parsed[2]))
        return out

    def checkpoint_paths(self) -> list[tuple[int, Path]]:
        """(segment, path) of this epoch's checkpoints, newest first."""
        out = []
        for path in self.directory.iterdir():
            parsed = parse_checkpoint(path.name)
            if parsed is not None and parsed[0] == self.meta.epoch:
                out.append((parsed[1], path))
        return sorted(out, reverse=True)

    def checkpoint_path(self, segment: int) -> Path:
        return self.directory / checkpoint_name(self.meta.epoch, segment)

    @property
    def pack_path(self) -> Path:
        """The array pack this epoch's checkpoints refer to (`statecodec.ArrayPack`)."""
        return self.directory / pack_name(self.meta.epoch)

    def _open_writer(self, report: RecordingReport | None = None) -> None:
        # The writer truncates a torn tail left by a crash before appending anything.
        path = self.recording_path
        if report is None and self._known_end is not None and self._known_end[0] == self.segment:
            report = RecordingReport(valid_end=self._known_end[1], size_bytes=self._known_end[1])
        self._writer = RecordingWriter(
            path, fsync_every=1 if self._fsync_each else 0, report=report
        )
        self._known_end = (self.segment, self._writer.end_offset)

    def _close_writer_locked(self, *, fsync: bool = False) -> None:
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                if self._dirty or fsync:
                    writer.sync()
            finally:
                writer.close()
                self._known_end = (self.segment, writer.end_offset)
        self._dirty = False

    def _remove_stale_files(self) -> None:
        """Files of other epochs are leftovers of an interrupted reset; temp files of a crash."""
        for path in self.directory.iterdir():
            parsed = parse_segment(path.name)
            ckpt = parse_checkpoint(path.name)
            epoch = parsed[0] if parsed is not None else ckpt[0] if ckpt is not None else None
            if epoch is None:
                epoch = parse_pack(path.name)
            if epoch is not None and epoch != self.meta.epoch:
                log.info("%s: removing stale %s", self.directory.name, path.name)
                path.unlink()
            elif path.name == LEGACY_CHECKPOINT:
                # A pickle is code: never loaded. The recording rebuilds what it held.
                log.warning(
                    "%s: ignoring the old-format %s (a replay rebuilds it)",
                    self.directory.name,
                    LEGACY_CHECKPOINT,
                )
            elif path.name.startswith(".") and path.name.endswith(".tmp"):
                path.unlink()

    def records(
        self, segment: Segment, report: RecordingReport | None = None
    ) -> Iterator[RawRecord]:
        """Every intact record of one segment, streamed; damage is skipped into `report`."""
        try:
            yield from iter_raw_records(
                segment.path, report if report is not None else RecordingReport()
            )
        except RecordingError as err:
            raise StoreError(f"{segment.path.name}: {err}") from err
        except FileNotFoundError:
            return

    def open_for_append(self, report: RecordingReport | None = None) -> None:
        """Open the writer after a replay; `report` of the last segment spares a re-read."""
        with self._io_lock:
            if self._writer is None:
                self._open_writer(report)

    # -- appends ---------------------------------------------------------------------------

    def append(self, payload: bytes) -> None:
        """Append one wire message; it is in the kernel (survives kill -9) when this returns."""
        if self.leased:
            raise StoreError(f"session {self.meta.id}: the recording is leased to a mapper")
        writer = self._writer
        if writer is None:
            if self.meta.state != "active":
                raise StoreError(f"session {self.meta.id} is not open for writing")
            with self._io_lock:
                if self._writer is None:
                    self._open_writer()
                writer = self._writer
                assert writer is not None
        writer.append(payload)
        self._dirty = True
        self._last_append = time.monotonic()

    def sync(self) -> None:
        """fsync the recording if anything was appended since the last sync (any thread)."""
        with self._io_lock:
            if not self._dirty or (self._writer is None and not self.leased):
                return
            self._dirty = False
            # A separate descriptor: fsync flushes the file, whichever descriptor wrote it, and
            # the worker keeps appending while the disk works.
            fd = os.open(self.recording_path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    # -- the lease (a mapper process appends; docs/service.md, "Mapper processes") ---------------

    def lease_out(self) -> tuple[Path, int | None]:
        """Close the writer and hand the current segment over: its path, and where its intact
        records end if this object knows (else the lessee reads the file to find out)."""
        with self._io_lock:
            self._close_writer_locked()
            self.leased = True
            end = self._known_end
        return self.recording_path, end[1] if end is not None and end[0] == self.segment else None

    def lease_back(self, end_offset: int | None) -> None:
        """The lessee closed (and fsynced) the segment at `end_offset` (None: unknown, the
        next writer reads the file)."""
        with self._io_lock:
            self.leased = False
            self._dirty = False
            self._known_end = (self.segment, end_offset) if end_offset is not None else None

    def leased_append(self) -> None:
        """The lessee appended: the next group commit fsyncs the file, the idle clock restarts."""
        self._dirty = True
        self._last_append = time.monotonic()

    def idle_for_s(self) -> float:
        return time.monotonic() - self._last_append

    @property
    def writer_open(self) -> bool:
        return self._writer is not None or self.leased

    # -- state changes ---------------------------------------------------------------------

    def set_state(self, state: SessionState) -> None:
        self.meta = replace(self.meta, state=state)
        write_atomic(self.directory / "session.json", self.meta.to_json())

    def retire_front_end(self) -> None:
        """After a session of a retired front end was restored with `meta.front_end` from its
        recording: delete its checkpoints and their array pack (the retired front end's state,
        never loadable), then name the live front end in `session.json`, so the next start
        restores it as any other session. A crash between the two leaves a session without
        checkpoints, restored the same way again."""
        if self.meta.retired_front_end is None:
            return
        for _, path in self.checkpoint_paths():
            path.unlink(missing_ok=True)
        self.pack_path.unlink(missing_ok=True)
        _fsync_dir(self.directory)
        self.meta = replace(self.meta, retired_front_end=None)
        write_atomic(self.directory / "session.json", self.meta.to_json())

    def roll(self) -> int:
        """Close the current segment (fsynced) and start the next; returns its index."""
        with self._io_lock:
            self._close_writer_locked(fsync=True)  # a checkpoint must never outlive its records
            self.segment += 1
            self._known_end = None
            try:
                self._open_writer()
            except BaseException:
                self.segment -= 1
                raise
            self._dirty = False
        _fsync_dir(self.directory)
        return self.segment

    def new_epoch(self) -> None:
        """Start an empty recording (reset). The old epoch is deleted after the commit."""
        old = [seg.path for seg in self.segments()] + [p for _, p in self.checkpoint_paths()]
        old.append(self.pack_path)
        with self._io_lock:
            self._close_writer_locked()
            self.meta = replace(self.meta, epoch=self.meta.epoch + 1)
            self.segment = 0
            self._known_end = None
            self._open_writer()
            self._dirty = False
        write_atomic(self.directory / "session.json", self.meta.to_json())
        for path in old:
            path.unlink(missing_ok=True)

    def close_writer(self) -> None:
        with self._io_lock:
            self._close_writer_locked()

    def prune(self, older_than_s: float, below_segment: int) -> int:
        """Cut the scans out of closed segments below `below_segment` (covered by a checkpoint
        that is not the newest) whose last write is older than `older_than_s`; their poses
        stay (the trajectory). Returns the bytes freed."""
        freed = 0
        now = time.time()
        for seg in self.segments():
            if seg.pruned or seg.index >= min(below_segment, self.segment):
                continue
            try:
                stat = seg.path.stat()
            except FileNotFoundError:
                continue
            if now - stat.st_mtime < older_than_s:
                continue
            target = self.segment_path(seg.index, pruned=True)
            tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex[:8]}.tmp")
            with RecordingWriter(tmp, fsync_every=0) as writer:
                for record in self.records(seg):
                    if record.kind == "pose":
                        writer.append(record.payload)
                writer.sync()
            os.replace(tmp, target)
            _fsync_dir(self.directory)
            seg.path.unlink()
            _fsync_dir(self.directory)
            freed += stat.st_size - target.stat().st_size
            log.info("%s: pruned the scans of %s", self.directory.name, seg.path.name)
        return freed

    def delete(self, trash_dir: Path) -> None:
        self.close_writer()
        trash_dir.mkdir(parents=True, exist_ok=True)
        target = trash_dir / f"{self.directory.name}-{uuid.uuid4().hex[:8]}"
        os.replace(self.directory, target)  # atomic: a restart never sees half a session
        _fsync_dir(self.directory.parent)
        shutil.rmtree(target, ignore_errors=True)


def segment_files(directory: Path, epoch: int) -> list[Path]:
    """The recording of `epoch` in `directory`, segment by segment, in order (a pruned copy
    stands for a pruned segment)."""
    found: dict[int, tuple[bool, Path]] = {}
    for path in directory.iterdir():
        parsed = parse_segment(path.name)
        if parsed is None or parsed[0] != epoch:
            continue
        _, index, pruned = parsed
        if index not in found or found[index][0]:
            found[index] = (pruned, path)
    return [found[k][1] for k in sorted(found)]


def read_meta(directory: Path) -> SessionMeta:
    try:
        meta = SessionMeta.from_json((directory / "session.json").read_bytes())
    except (OSError, ValueError, KeyError, TypeError, StoreError) as err:
        reason = err.reason if isinstance(err, StoreError) else f"{type(err).__name__}: {err}"
        raise StoreError(f"unreadable session.json ({reason})") from err
    if meta.id != directory.name:
        raise StoreError(f"session.json names session {meta.id!r}")
    return meta


@dataclass(frozen=True, slots=True)
class SavedMapMeta:
    map_id: str
    version: int
    session_id: str
    robot_id: str
    saved_ns: int

    def to_json(self) -> bytes:
        return json.dumps(asdict(self), indent=1).encode()

    @classmethod
    def from_json(cls, data: bytes) -> SavedMapMeta:
        obj: Any = json.loads(data)
        return cls(
            map_id=check_id(str(obj["map_id"]), "map"),
            version=int(obj["version"]),
            session_id=str(obj["session_id"]),
            robot_id=str(obj["robot_id"]),
            saved_ns=int(obj["saved_ns"]),
        )


class MapStore:
    """Saved maps: `<maps>/<map_id>/<version>/`, written to a temp dir and renamed into place."""

    def __init__(self, maps_dir: Path) -> None:
        self._dir = maps_dir
        self._lock = threading.Lock()
        self._maps: dict[tuple[str, int], SavedMapMeta] = {}

    def load(self) -> None:
        self._dir.mkdir(parents=True, exist_ok=True)
        for map_dir in sorted(self._dir.iterdir()):
            if map_dir.name.startswith("."):
                shutil.rmtree(map_dir, ignore_errors=True)  # an interrupted save
                continue
            if not map_dir.is_dir():
                continue
            for version_dir in map_dir.iterdir():
                try:
                    meta = SavedMapMeta.from_json((version_dir / "map.json").read_bytes())
                except (OSError, ValueError, KeyError, TypeError, NotFoundError) as err:
                    log.warning("ignoring saved map %s: %s", version_dir, err)
                    continue
                self._maps[(meta.map_id, meta.version)] = meta

    def list(self) -> list[SavedMapMeta]:
        with self._lock:
            return sorted(self._maps.values(), key=lambda m: (m.map_id, m.version))

    def save(
        self, map_id: str, session_id: str, robot_id: str, saved_ns: int, files: dict[str, bytes]
    ) -> SavedMapMeta:
        check_id(map_id, "map")
        with self._lock:
            version = 1 + max((v for (m, v) in self._maps if m == map_id), default=0)
            meta = SavedMapMeta(map_id, version, session_id, robot_id, saved_ns)
            tmp = self._dir / f".{map_id}-{version}-{uuid.uuid4().hex[:8]}"
            tmp.mkdir(parents=True)
            for name, data in {**files, "map.json": meta.to_json()}.items():
                with open(tmp / name, "wb") as f:
                    f.write(data)
                    f.flush()
                    os.fsync(f.fileno())
            final = self._dir / map_id / str(version)
            final.parent.mkdir(exist_ok=True)
            os.replace(tmp, final)
            _fsync_dir(final.parent)
            self._maps[(map_id, version)] = meta
            return meta

    def delete(self, map_id: str, version: int | None, trash_dir: Path) -> Sequence[SavedMapMeta]:
        """Delete one version of a saved map (or every version with `version=None`)."""
        check_id(map_id, "map")
        with self._lock:
            gone = [
                m
                for (mid, v), m in self._maps.items()
                if mid == map_id and (version is None or v == version)
            ]
            if version is not None and not gone:
                raise NotFoundError(f"no saved map {map_id!r} version {version}")
            trash_dir.mkdir(parents=True, exist_ok=True)
            for meta in gone:
                source = self._dir / map_id / str(meta.version)
                target = trash_dir / f"map-{map_id}-{meta.version}-{uuid.uuid4().hex[:8]}"
                os.replace(source, target)  # atomic: a restart sees it or not
                del self._maps[(map_id, meta.version)]
                shutil.rmtree(target, ignore_errors=True)
            if gone:
                _fsync_dir(self._dir / map_id)
                if not any(mid == map_id for mid, _ in self._maps):
                    with contextlib.suppress(OSError):
                        (self._dir / map_id).rmdir()
                        _fsync_dir(self._dir)
        return sorted(gone, key=lambda m: m.version)

    def file(self, map_id: str, version: int, name: str) -> Path:
        if name not in MAP_FILES:
            raise NotFoundError(f"no such map file {name[:80]!r}")
        with self._lock:
            if (check_id(map_id, "map"), version) not in self._maps:
                raise NotFoundError(f"no saved map {map_id!r} version {version}")
        return self._dir / map_id / str(version) / name


class DataDir:
    """The service's data directory, held with an exclusive lock while the service runs."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.sessions_dir = root / "sessions"
        self.maps_dir = root / "maps"
        self.trash_dir = root / "trash"
        self._lock_fd: int | None = None

    def open(self) -> None:
        try:
            for d in (self.root, self.sessions_dir, self.maps_dir):
                d.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.root / "service.lock", os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise StoreError(f"cannot use data directory {self.root}: {err}") from err
        try:
            # The kernel drops the lock when the process dies, kill -9 included.
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            os.close(fd)
            raise StoreError(
                f"data directory {self.root} is in use by another mapping service"
            ) from err
        self._lock_fd = fd
        if self.trash_dir.exists():
            shutil.rmtree(self.trash_dir, ignore_errors=True)

    def session_dirs(self) -> list[Path]:
        return sorted(
            p for p in self.sessions_dir.iterdir() if p.is_dir() and not p.name.startswith(".")
        )

    def close(self) -> None:
        if self._lock_fd is not None:
            with contextlib.suppress(OSError):
                fcntl.flock(self._lock_fd, fcntl.LOCK_UN)
            os.close(self._lock_fd)
            self._lock_fd = None
