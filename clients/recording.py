"""The project's own recording format: an append-only log of wire messages.

Layout (all integers little-endian):

    header  = b"MMREC01\\n"                     8 bytes, once
    record  = length:u32  crc32:u32  payload    payload = one msgpack wire message (scan or pose)

A crash can leave a torn last record; readers stop there and `RecordingWriter` truncates it
away when it reopens the file, so every complete record before it is kept. A record counts as
torn when the file ends inside it, when its CRC fails and it ends exactly at the end of the
file, or when everything from its start to the end of the file is zero bytes (the zero-filled
tail some file systems leave after a power loss). Damage anywhere else (a CRC mismatch or an
impossible length with more data after it) raises `RecordingError`: silently dropping the
rest of a log would hide data loss.
"""

from __future__ import annotations

import logging
import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Final

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
    """A file that is not a recording, or one damaged before its last record."""


@dataclass(frozen=True, slots=True)
class RawRecord:
    offset: int
    payload: bytes

    @property
    def kind(self) -> str:
        """`"scan"`, `"pose"` or `"unknown"`, read cheaply from the msgpack map."""
        try:
            body = msgpack.unpackb(self.payload, raw=False)
        except Exception:
            return "unknown"
        kind = body.get("type") if isinstance(body, dict) else None
        return kind if isinstance(kind, str) else "unknown"


def is_recording(path: str | Path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


def iter_raw_records(path: str | Path) -> Iterator[RawRecord]:
    """Yield every complete record; a torn tail ends the iteration with a warning.

    Raises `RecordingError` for a bad magic or for damage before the last record.
    """
    with open(path, "rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise RecordingError(f"{path}: not a recording (bad magic)")
        yield from _records(f, str(path))


def _records(f: BinaryIO, name: str) -> Iterator[RawRecord]:
    offset = len(MAGIC)
    while True:
        head = f.read(_RECORD_HEADER.size)
        if not head:
            return
        if len(head) < _RECORD_HEADER.size:
            log.warning("%s: torn record header at byte %d; stopping there", name, offset)
            return
        length, crc = _RECORD_HEADER.unpack(head)
        if length == 0 or length > MAX_RECORD_BYTES:
            # The writer never produces these. Past the end of the file it is a torn header.
            if _bytes_left(f) < length or _rest_is_zero(f):
                log.warning("%s: torn record at byte %d; stopping there", name, offset)
                return
            raise RecordingError(f"{name}: corrupt record at byte {offset} (length {length})")
        payload = f.read(length)
        if len(payload) < length:
            log.warning("%s: torn record at byte %d; stopping there", name, offset)
            return
        if zlib.crc32(payload) != crc:
            if _bytes_left(f) == 0 or (_is_zero(payload) and _rest_is_zero(f)):
                log.warning("%s: torn last record at byte %d; stopping there", name, offset)
                return
            raise RecordingError(f"{name}: CRC mismatch in the record at byte {offset}")
        yield RawRecord(offset, payload)
        offset += _RECORD_HEADER.size + length


def _bytes_left(f: BinaryIO) -> int:
    return os.fstat(f.fileno()).st_size - f.tell()


def _is_zero(data: bytes) -> bool:
    return not data.strip(b"\0")


def _rest_is_zero(f: BinaryIO) -> bool:
    """True if every byte from the current position to the end of the file is zero."""
    while chunk := f.read(1 << 16):
        if not _is_zero(chunk):
            return False
    return True


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


def valid_length(path: str | Path) -> int:
    """Byte length of the longest prefix made of the header and complete records."""
    end = len(MAGIC)
    for record in iter_raw_records(path):
        end = record.offset + _RECORD_HEADER.size + len(record.payload)
    return end


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

    def __init__(self, path: str | Path, *, fsync_every: int = 0) -> None:
        self.path = Path(path)
        self._fsync_every = fsync_every
        self._since_sync = 0
        self.records_written = 0
        if self.path.exists() and self.path.stat().st_size > 0 and _starts_torn_magic(self.path):
            # Crashed while writing the header itself: nothing was recorded yet.
            log.warning("%s: torn header; starting the recording again", self.path)
            os.truncate(self.path, 0)
        if self.path.exists() and self.path.stat().st_size > 0:
            keep = valid_length(self.path)
            size = self.path.stat().st_size
            if keep < size:
                log.warning("%s: truncating %d bytes of torn tail", self.path, size - keep)
                os.truncate(self.path, keep)
            self._f = open(self.path, "ab")  # noqa: SIM115  # closed in close()
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._f = open(self.path, "wb")  # noqa: SIM115
            self._f.write(MAGIC)
            self._f.flush()

    def append(self, payload: bytes) -> None:
        """Append one encoded wire message and push it to the OS before returning."""
        if not 0 < len(payload) <= MAX_RECORD_BYTES:
            raise RecordingError(
                f"record payload of {len(payload)} bytes outside 1..{MAX_RECORD_BYTES}"
            )
        self._f.write(_RECORD_HEADER.pack(len(payload), zlib.crc32(payload)) + payload)
        self._f.flush()
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
