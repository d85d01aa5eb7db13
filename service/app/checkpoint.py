"""Checkpoint files: a versioned header, the mapper's state (`statecodec`), and a checksum.

Layout::

    magic      b"MMCKPT1\\n"                 8 bytes
    header_len u32 little-endian
    header     JSON: format, epoch, segment, scans_accepted, poses, map_revision, state_bytes
    state      `Mapper.state()`: a compressed npz of arrays plus a JSON tree (no code); its
               frozen arrays are in the epoch's array pack (`statecodec.ArrayPack`)
    sha256     32 bytes over everything before it

A checkpoint only shortens a restart (the recording stays the truth), so any doubt, a bad
magic, a checksum mismatch, an unknown format, is `CheckpointError` and the caller replays.
"""

from __future__ import annotations

import hashlib
import json
import struct
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Final

MAGIC: Final = b"MMCKPT1\n"
FORMAT: Final = 1
_LEN = struct.Struct("<I")
_DIGEST = 32
_MAX_HEADER = 1 << 16


class CheckpointError(ValueError):
    """A checkpoint file that is damaged, foreign or from an unknown format."""


@dataclass(frozen=True, slots=True)
class CheckpointHeader:
    """Estimator and grid after every record of segments `< segment` of recording `epoch`."""

    epoch: int
    segment: int
    scans_accepted: int
    poses: int
    map_revision: int
    format: int = FORMAT


def encode(header: CheckpointHeader, state: bytes) -> bytes:
    head = json.dumps({**asdict(header), "state_bytes": len(state)}).encode()
    body = MAGIC + _LEN.pack(len(head)) + head + state
    return body + hashlib.sha256(body).digest()


def decode(data: bytes) -> tuple[CheckpointHeader, bytes]:
    if len(data) < len(MAGIC) + _LEN.size + _DIGEST or not data.startswith(MAGIC):
        raise CheckpointError("not a checkpoint (bad magic or too short)")
    body, digest = data[:-_DIGEST], data[-_DIGEST:]
    if hashlib.sha256(body).digest() != digest:
        raise CheckpointError("checksum mismatch")
    (head_len,) = _LEN.unpack_from(body, len(MAGIC))
    start = len(MAGIC) + _LEN.size
    if head_len > _MAX_HEADER or start + head_len > len(body):
        raise CheckpointError("bad header length")
    try:
        obj: Any = json.loads(body[start : start + head_len])
        if obj.get("format") != FORMAT:
            raise CheckpointError(f"unknown checkpoint format {obj.get('format')!r}")
        header = CheckpointHeader(
            epoch=int(obj["epoch"]),
            segment=int(obj["segment"]),
            scans_accepted=int(obj["scans_accepted"]),
            poses=int(obj["poses"]),
            map_revision=int(obj["map_revision"]),
        )
        state = body[start + head_len :]
        if len(state) != int(obj["state_bytes"]):
            raise CheckpointError("state length mismatch")
    except (ValueError, KeyError, TypeError, AttributeError) as err:
        if isinstance(err, CheckpointError):
            raise
        raise CheckpointError(f"bad header: {err}") from err
    return header, state


def read(path: Path) -> tuple[CheckpointHeader, bytes]:
    try:
        return decode(path.read_bytes())
    except OSError as err:
        raise CheckpointError(f"unreadable: {err.strerror or err}") from err
