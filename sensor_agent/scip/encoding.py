"""SCIP 2.0 character encodings and checksums (spec pp. 6-9).

Values are split into 6-bit groups, most significant first, each offset by 0x30. A line's
checksum is the low 6 bits of the byte sum of the line's content, plus 0x30.
"""

from __future__ import annotations

from typing import Final

import numpy as np
import numpy.typing as npt

from sensor_agent.scip.errors import MalformedReplyError

CHAR_OFFSET: Final = 0x30
CHAR_MAX: Final = 0x30 + 0x3F  # 'o'
TIMESTAMP_CHARS: Final = 4
TIMESTAMP_MODULUS: Final = 1 << 24  # the 24-bit millisecond counter
DATA_LINE_CHARS: Final = 64  # payload characters per data line, before the checksum


def checksum(data: bytes) -> int:
    """The checksum byte of `data` (the line content it covers, without the sum itself)."""
    return (sum(data) & 0x3F) + CHAR_OFFSET


def encode_value(value: int, n_chars: int) -> bytes:
    """`value` in the `n_chars`-character encoding (2, 3 or 4); raises ValueError if too large."""
    if not 0 <= value < 1 << (6 * n_chars):
        raise ValueError(f"{value} does not fit in {n_chars} SCIP characters")
    return bytes(((value >> (6 * (n_chars - 1 - i))) & 0x3F) + CHAR_OFFSET for i in range(n_chars))


def decode_value(chars: bytes) -> int:
    """Decode one value; raises `MalformedReplyError` on characters outside 0x30-0x6F."""
    value = 0
    for c in chars:
        if not CHAR_OFFSET <= c <= CHAR_MAX:
            raise MalformedReplyError(f"byte {c:#04x} is not a SCIP data character")
        value = (value << 6) | (c - CHAR_OFFSET)
    return value


def encode_values(values: npt.ArrayLike, n_chars: int) -> bytes:
    """Encode an array of non-negative ints back to back (vectorised)."""
    v = np.asarray(values, dtype=np.int64).reshape(-1)
    if v.size and (int(v.min()) < 0 or int(v.max()) >= 1 << (6 * n_chars)):
        raise ValueError(f"values out of range for {n_chars}-character encoding")
    shifts = 6 * np.arange(n_chars - 1, -1, -1, dtype=np.int64)
    chars = ((v[:, None] >> shifts[None, :]) & 0x3F) + CHAR_OFFSET
    return chars.astype(np.uint8).tobytes()


def decode_values(payload: bytes, n_chars: int) -> npt.NDArray[np.uint32]:
    """Decode back-to-back `n_chars`-character values into (N,) uint32 (vectorised)."""
    if len(payload) % n_chars:
        raise MalformedReplyError(f"{len(payload)} data characters is not a multiple of {n_chars}")
    raw = np.frombuffer(payload, dtype=np.uint8)
    if raw.size and (int(raw.min()) < CHAR_OFFSET or int(raw.max()) > CHAR_MAX):
        raise MalformedReplyError("data contains bytes outside 0x30-0x6F")
    groups = (raw.astype(np.uint32) - CHAR_OFFSET).reshape(-1, n_chars)
    out = np.zeros(groups.shape[0], dtype=np.uint32)
    for i in range(n_chars):
        out = (out << np.uint32(6)) | groups[:, i]
    return out


def split_lines(payload: bytes, line_chars: int = DATA_LINE_CHARS) -> list[bytes]:
    """Cut encoded data into lines of `line_chars` characters, each followed by its checksum."""
    return [
        payload[i : i + line_chars] + bytes([checksum(payload[i : i + line_chars])])
        for i in range(0, len(payload), line_chars)
    ]


__all__ = [
    "CHAR_MAX",
    "CHAR_OFFSET",
    "DATA_LINE_CHARS",
    "TIMESTAMP_CHARS",
    "TIMESTAMP_MODULUS",
    "checksum",
    "decode_value",
    "decode_values",
    "encode_value",
    "encode_values",
    "split_lines",
]
