"""Durable state in the data directory: session metadata, session recordings, saved maps.

Layout::

    <data>/service.lock                      flock: one service per data directory
    <data>/sessions/<session_id>/session.json metadata (atomically replaced)
    <data>/sessions/<session_id>/epoch-NNNNNN.mrec   accepted scans and their poses
    <data>/maps/<map_id>/<version>/map.png|map.pgm|map.yaml|map.json
    <data>/trash/                            directories being deleted

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
import uuid
from collections.abc import Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Final, Literal

from clients.recording import RawRecord, RecordingError, RecordingWriter, iter_raw_records
from clients.wire import ROBOT_ID_PATTERN, SESSION_ID_PATTERN
from service.app.errors import NotFoundError, StoreError

log = logging.getLogger(__name__)

META_FORMAT: Final = 1
MAP_FILES: Final = ("map.png", "map.pgm", "map.yaml")
_EPOCH_FILE = re.compile(r"^epoch-(\d{6})\.mrec$")

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


@dataclass(frozen=True, slots=True)
class SessionMeta:
    id: str
    robot_id: str
    created_ns: int
    state: SessionState
    resolution_m: float
    use_odometry: bool
    epoch: int = 0
    format: int = META_FORMAT

    def to_json(self) -> bytes:
        return json.dumps(asdict(self), indent=1).encode()

    @classmethod
    def from_json(cls, data: bytes) -> SessionMeta:
        obj: Any = json.loads(data)
        if not isinstance(obj, dict) or obj.get("format") != META_FORMAT:
            raise StoreError("session.json has an unknown format")
        meta = cls(
            id=str(obj["id"]),
            robot_id=str(obj["robot_id"]),
            created_ns=int(obj["created_ns"]),
            state="active" if obj["state"] == "active" else "stopped",
            resolution_m=float(obj["resolution_m"]),
            use_odometry=bool(obj["use_odometry"]),
            epoch=int(obj["epoch"]),
        )
        if SESSION_ID_PATTERN.fullmatch(meta.id) is None:
            raise StoreError(f"unsafe session id {meta.id!r}")
        if ROBOT_ID_PATTERN.fullmatch(meta.robot_id) is None:
            raise StoreError(f"unsafe robot id {meta.robot_id!r}")
        return meta


class SessionStore:
    """The on-disk half of one session. Not thread-safe except `sync()`; callers serialise."""

    def __init__(self, directory: Path, meta: SessionMeta, *, fsync_each: bool) -> None:
        self.directory = directory
        self.meta = meta
        self._fsync_each = fsync_each
        self._io_lock = threading.Lock()  # guards the writer's lifecycle against sync()
        self._dirty = False
        self._writer: RecordingWriter | None = None

    # -- lifecycle -----------------------------------------------------------------------

    @classmethod
    def create(cls, sessions_dir: Path, meta: SessionMeta, *, fsync_each: bool) -> SessionStore:
        directory = sessions_dir / check_id(meta.id, "session")
        directory.mkdir(parents=True)
        store = cls(directory, meta, fsync_each=fsync_each)
        store._open_writer()
        write_atomic(directory / "session.json", meta.to_json())
        _fsync_dir(sessions_dir)
        return store

    @classmethod
    def load(cls, directory: Path, *, fsync_each: bool) -> SessionStore:
        try:
            meta = SessionMeta.from_json((directory / "session.json").read_bytes())
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise StoreError(f"{directory}: unreadable session.json: {err}") from err
        if meta.id != directory.name:
            raise StoreError(f"{directory}: session.json names session {meta.id!r}")
        store = cls(directory, meta, fsync_each=fsync_each)
        store._remove_stale_epochs()
        return store

    @property
    def recording_path(self) -> Path:
        return self.directory / f"epoch-{self.meta.epoch:06d}.mrec"

    def _open_writer(self) -> None:
        # The writer truncates a torn tail left by a crash before appending anything.
        self._writer = RecordingWriter(
            self.recording_path, fsync_every=1 if self._fsync_each else 0
        )

    def _remove_stale_epochs(self) -> None:
        """Epoch files other than the committed one are leftovers of an interrupted reset."""
        for path in self.directory.iterdir():
            m = _EPOCH_FILE.fullmatch(path.name)
            if m is not None and int(m.group(1)) != self.meta.epoch:
                log.info("%s: removing stale %s", self.directory.name, path.name)
                path.unlink()

    def records(self) -> Iterator[RawRecord]:
        """Every complete record of the current epoch (a torn tail is ignored), streamed."""
        if not self.recording_path.exists():
            return
        try:
            yield from iter_raw_records(self.recording_path)
        except RecordingError as err:
            raise StoreError(str(err)) from err

    def open_for_append(self) -> None:
        """Reopen the recording after a replay (only active sessions append)."""
        with self._io_lock:
            if self._writer is None:
                self._open_writer()

    # -- appends ---------------------------------------------------------------------------

    def append(self, payload: bytes) -> None:
        """Append one wire message; it is in the kernel (survives kill -9) when this returns."""
        writer = self._writer
        if writer is None:
            raise StoreError(f"session {self.meta.id} is not open for writing")
        writer.append(payload)
        self._dirty = True

    def sync(self) -> None:
        """fsync the recording if anything was appended since the last sync (any thread)."""
        with self._io_lock:
            if not self._dirty or self._writer is None:
                return
            self._dirty = False
            # A separate descriptor: fsync flushes the file, whichever descriptor wrote it, and
            # the worker keeps appending while the disk works.
            fd = os.open(self.recording_path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    # -- state changes ---------------------------------------------------------------------

    def set_state(self, state: SessionState) -> None:
        self.meta = replace(self.meta, state=state)
        write_atomic(self.directory / "session.json", self.meta.to_json())

    def new_epoch(self) -> None:
        """Start an empty recording (reset). The old epoch is deleted after the commit."""
        old_path = self.recording_path
        with self._io_lock:
            if self._writer is not None:
                self._writer.close()
                self._writer = None
            self.meta = replace(self.meta, epoch=self.meta.epoch + 1)
            self._open_writer()
            self._dirty = False
        write_atomic(self.directory / "session.json", self.meta.to_json())
        old_path.unlink(missing_ok=True)

    def close_writer(self) -> None:
        with self._io_lock:
            if self._writer is not None:
                self._writer.sync()
                self._writer.close()
                self._writer = None
            self._dirty = False

    def delete(self, trash_dir: Path) -> None:
        self.close_writer()
        trash_dir.mkdir(parents=True, exist_ok=True)
        target = trash_dir / f"{self.directory.name}-{uuid.uuid4().hex[:8]}"
        os.replace(self.directory, target)  # atomic: a restart never sees half a session
        _fsync_dir(self.directory.parent)
        shutil.rmtree(target, ignore_errors=True)


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
