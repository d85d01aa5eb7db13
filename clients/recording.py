"""The project's own recording format: an append-only log of wire messages.

Layout (all integers little-endian):

    header  = b"MMREC01\\n"                     8 bytes, once
    record  = length:u32  crc32:u32  payload    payload = one msgpack wire message (scan or pose)

A crash can leave a torn last record; readers stop there and `RecordingWriter` truncates it
away when it reopens the file, so every complete record before it is kept. A record counts as
torn when the file ends inside it, or when everything from its start to the end of the file is
zero bytes (the zero-filled tail some file systems leave after a power loss).

Damage anywhere else (a CRC mismatch, an impossible length) is skipped: the reader looks for the
next intact frame (a plausible length whose CRC matches), goes on from there, and reports what it
skipped in a `RecordingReport` (`Damage` regions, records and bytes lost). A damaged record whose
length field is intact is skipped exactly (one record lost); a damaged length is resynchronised
by search, and the records lost in between are then a lower bound (at least one). Only a file
that is not a recording at all (bad magic) raises `RecordingError`.
"""

from __future__ import annotations

import logging
import mmap
import os
import re
import shutil
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import msgpack

from clients.wire import (
    DEFAULT_MAX_PAYLOAD_BYTES,
    DecodeError,
    Pose,
    Scan,
    decode_pose,
    decode_scan,
)

MAGIC: Final = b"MMREC01\n"
_RECORD_HEADER: Final = struct.Struct("<II")
MAX_RECORD_BYTES: Final = 4 * DEFAULT_MAX_PAYLOAD_BYTES

log = logging.getLogger(__name__)


class RecordingError(Exception):
    """A file that is not a recording (bad magic)."""


@dataclass(frozen=True, slots=True)
class Damage:
    """Bytes skipped between two intact records (or to the end of the file)."""

    offset: int  # first damaged byte
    length_bytes: int
    records_lost: int  # exact when the damaged record's length was intact, else a lower bound
    reason: str  # "crc" or "length"


@dataclass(slots=True)
class RecordingReport:
    """What a read found: intact records, damage, and the torn tail (filled in while reading)."""

    records: int = 0
    valid_end: int = 0  # byte just after the last intact record (or the header)
    size_bytes: int = 0
    torn_tail_bytes: int = 0
    damage: list[Damage] = field(default_factory=list)

    @property
    def records_lost(self) -> int:
        return sum(d.records_lost for d in self.damage)

    @property
    def bytes_lost(self) -> int:
        return sum(d.length_bytes for d in self.damage)

    @property
    def damaged(self) -> bool:
        return bool(self.damage)

    def merge(self, other: RecordingReport) -> None:
        """Add another file's counts (a session's recording is several segment files)."""
        self.records += other.records
        self.size_bytes += other.size_bytes
        self.torn_tail_bytes += other.torn_tail_bytes
        self.damage.extend(other.damage)


@dataclass(frozen=True, slots=True)
class RawRecord:
    offset: int
    payload: bytes

    @property
    def kind(self) -> str:
        """`"scan"`, `"pose"` or `"unknown"`, read from the msgpack map without decoding it."""
        return record_kind(self.payload)


def record_kind(payload: bytes) -> str:
    """The `type` field of a msgpack map, skipping the other values (cheap for big scans)."""
    try:
        unpacker = msgpack.Unpacker(raw=False, max_buffer_size=len(payload) + 1)
        unpacker.feed(payload)
        for _ in range(unpacker.read_map_header()):
            key = unpacker.unpack()
            if key == "type":
                kind = unpacker.unpack()
                return kind if isinstance(kind, str) else "unknown"
            unpacker.skip()
    except Exception:
        return "unknown"
    return "unknown"


def is_recording(path: str | Path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


def iter_raw_records(
    path: str | Path, report: RecordingReport | None = None
) -> Iterator[RawRecord]:
    """Yield every intact record, skipping damage; a torn tail ends the iteration.

    `report`, if given, is filled in as the iteration goes (complete once it ends). Without
    one, each damaged region is logged as a warning (a caller with a report reports it
    itself). Raises `RecordingError` for a bad magic.
    """
    log_damage = report is None
    report = report if report is not None else RecordingReport()
    with open(path, "rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise RecordingError(f"{Path(path).name}: not a recording (bad magic)")
        size = os.fstat(f.fileno()).st_size
        report.size_bytes = size
        report.valid_end = len(MAGIC)
        if size == len(MAGIC):
            return
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            yield from _records(mm, size, report, Path(path).name)
            if report.damage and log_damage:
                for d in report.damage:
                    log.warning(
                        "%s: %d damaged bytes at byte %d (%s): %d record(s) lost, skipped",
                        Path(path).name,
                        d.length_bytes,
                        d.offset,
                        d.reason,
                        d.records_lost,
                    )


def _frame_at(mm: mmap.mmap, pos: int, size: int) -> int:
    """Length of the intact frame starting at `pos`, or -1."""
    if pos + _RECORD_HEADER.size > size:
        return -1
    length, crc = _RECORD_HEADER.unpack_from(mm, pos)
    start = pos + _RECORD_HEADER.size
    if length == 0 or length > MAX_RECORD_BYTES or start + length > size:
        return -1
    if zlib.crc32(mm[start : start + length]) != crc:
        return -1
    return int(length)


# A record's payload is a msgpack map: a fixmap, map16 or map32 byte after the 8-byte header.
_CANDIDATE = re.compile(rb"(?=.{8}[\x80-\x8f\xde\xdf])", re.DOTALL)


def _resync(mm: mmap.mmap, start: int, size: int) -> int:
    """Offset of the next intact frame at or after `start`, or -1."""
    for match in _CANDIDATE.finditer(mm, start):
        pos = match.start()
        if _frame_at(mm, pos, size) > 0:
            return int(pos)
    return -1


def _is_zero_from(mm: mmap.mmap, pos: int, size: int) -> bool:
    step = 1 << 16
    return all(not mm[p : min(p + step, size)].strip(b"\0") for p in range(pos, size, step))


def _records(mm: mmap.mmap, size: int, report: RecordingReport, name: str) -> Iterator[RawRecord]:
    pos = len(MAGIC)
    while pos < size:
        length = _frame_at(mm, pos, size)
        if length > 0:
            start = pos + _RECORD_HEADER.size
            yield RawRecord(pos, mm[start : start + length])
            pos = start + length
            report.records += 1
            report.valid_end = pos
            continue
        # Not an intact frame: a torn tail, one damaged record, or damage to resynchronise past.
        if size - pos < _RECORD_HEADER.size or _is_zero_from(mm, pos, size):
            report.torn_tail_bytes = size - pos
            log.debug("%s: torn tail of %d bytes at byte %d", name, size - pos, pos)
            return
        declared, _ = _RECORD_HEADER.unpack_from(mm, pos)
        end = pos + _RECORD_HEADER.size + declared
        if (
            0 < declared <= MAX_RECORD_BYTES
            and end <= size
            and (end == size or _frame_at(mm, end, size) > 0)
        ):
            report.damage.append(Damage(pos, end - pos, 1, "crc"))  # length intact: exactly one
            pos = end
            continue
        found = _resync(mm, pos + 1, size)
        if found < 0:
            if 0 < declared <= MAX_RECORD_BYTES and end > size:
                # The file ends inside a plausible record: a write cut short by a crash.
                report.torn_tail_bytes = size - pos
                log.debug("%s: torn last record at byte %d", name, pos)
                return
            found = size
        report.damage.append(Damage(pos, found - pos, 1, "length"))
        pos = found


def read_messages(path: str | Path) -> Iterator[Scan | Pose]:
    """Decode every record as a `Scan` or `Pose`; undecodable records are skipped with a log."""
    for record in iter_raw_records(path):
        kind = record.kind
        message: Scan | Pose
        try:
            if kind == "scan":
                message = decode_scan(record.payload, max_payload_bytes=MAX_RECORD_BYTES)
            elif kind == "pose":
                message = decode_pose(record.payload)
            else:
                log.warning("%s: record at byte %d has unknown kind", path, record.offset)
                continue
        except DecodeError as err:
            log.warning("%s: record at byte %d does not decode: %s", path, record.offset, err)
            continue
        yield message


def scan_file(path: str | Path) -> RecordingReport:
    """Read a recording once and report it (records, damage, torn tail)."""
    report = RecordingReport()
    for _ in iter_raw_records(path, report):
        pass
    return report


def valid_length(path: str | Path) -> int:
    """Byte length of the header and records up to the end of the last intact record."""
    return scan_file(path).valid_end


def _starts_torn_magic(path: Path) -> bool:
    """True for a file shorter than the header whose bytes are a prefix of it."""
    with open(path, "rb") as f:
        head = f.read(len(MAGIC))
    return len(head) < len(MAGIC) and MAGIC.startswith(head)


class RecordingWriter:
    """Appends encoded messages; reopening an existing file first cuts off a torn tail.

    `fsync_every` = N makes every N-th append durable against power loss; 0 relies on the
    page cache, which already survives a process crash (`kill -9`).
    """

    def __init__(
        self, path: str | Path, *, fsync_every: int = 0, report: RecordingReport | None = None
    ) -> None:
        """`report`: this file's `RecordingReport` from a read just done, so that reopening
        does not read the file again (it is read anyway if the size no longer matches)."""
        self.path = Path(path)
        self._fsync_every = fsync_every
        self._since_sync = 0
        self.records_written = 0
        if self.path.exists() and self.path.stat().st_size > 0 and _starts_torn_magic(self.path):
            # Crashed while writing the header itself: nothing was recorded yet.
            log.warning("%s: torn header; starting the recording again", self.path)
            os.truncate(self.path, 0)
        if self.path.exists() and self.path.stat().st_size > 0:
            size = self.path.stat().st_size
            if report is None or report.size_bytes != size:
                report = scan_file(self.path)
            keep = report.valid_end
            if keep < size:
                if any(d.offset >= keep for d in report.damage):
                    # Damage (not a torn write) after the last intact record: keep a copy.
                    self._save_tail(keep)
                log.warning("%s: truncating %d bytes of torn tail", self.path.name, size - keep)
                os.truncate(self.path, keep)
            self._f = open(self.path, "ab")  # noqa: SIM115  # closed in close()
            self.end_offset = keep
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._f = open(self.path, "wb")  # noqa: SIM115
            self._f.write(MAGIC)
            self._f.flush()
            self.end_offset = len(MAGIC)

    def _save_tail(self, keep: int) -> None:
        backup = self.path.with_name(f"{self.path.name}.tail-{keep}.damaged")
        with open(self.path, "rb") as src, open(backup, "wb") as dst:
            src.seek(keep)
            shutil.copyfileobj(src, dst)
            dst.flush()
            os.fsync(dst.fileno())
        log.warning("%s: damaged tail kept in %s", self.path.name, backup.name)

    def append(self, payload: bytes) -> None:
        """Append one encoded wire message and push it to the OS before returning."""
        if not 0 < len(payload) <= MAX_RECORD_BYTES:
            raise RecordingError(
                f"record payload of {len(payload)} bytes outside 1..{MAX_RECORD_BYTES}"
            )
        self._f.write(_RECORD_HEADER.pack(len(payload), zlib.crc32(payload)) + payload)
        self._f.flush()
        self.end_offset += _RECORD_HEADER.size + len(payload)
        self.records_written += 1
        self._since_sync += 1
        if self._fsync_every and self._since_sync >= self._fsync_every:
            os.fsync(self._f.fileno())
            self._since_sync = 0

    def sync(self) -> None:
        self._f.flush()
        os.fsync(self._f.fileno())
        self._since_sync = 0

    def close(self) -> None:
        if not self._f.closed:
            self._f.flush()
            self._f.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
