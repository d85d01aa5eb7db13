"""Sans-IO SCIP 2.0 codec: command bytes out, reply bytes in, typed events out.

`ScipCodec.send(cmd)` returns the bytes to write and remembers that a reply with that echo is
expected; `ScipCodec.receive(data)` takes whatever bytes arrived and returns events. Replies are
framed on the empty line that ends each of them; a reply whose echo was not asked for is
discarded, so that after garbage on the line the codec falls back into step on the next reply.

The codec never raises on received bytes. A reply that is expected but broken (bad checksum,
wrong shape, error status) comes out as a `ReplyError` event carrying a `ScipError`; bytes that
match nothing come out as a `Discarded` event. The caller decides what to count and retry.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Final

import numpy as np
import numpy.typing as npt

from sensor_agent.scip.commands import Command
from sensor_agent.scip.encoding import (
    TIMESTAMP_CHARS,
    TIMESTAMP_MODULUS,
    checksum,
    decode_value,
    decode_values,
)
from sensor_agent.scip.errors import (
    ChecksumError,
    MalformedReplyError,
    ScipError,
    is_success,
    status_error,
)

log = logging.getLogger(__name__)

DEFAULT_MAX_FRAME_BYTES: Final = 16_384  # a full ME scan is 6717 bytes
MAX_PENDING: Final = 32
_TERMINATOR: Final = b"\n\n"
_STREAM_ECHO_PREFIX: Final = 13  # "MD" + start(4) + end(4) + cluster(2) + interval(1)
_STREAM_ECHO_COUNT: Final = slice(13, 15)


# ---------------------------------------------------------------------------------------------
# Events


@dataclass(frozen=True, slots=True)
class CommandOk:
    """A successful reply without a dedicated event (BM, QT, RS, RT, TM0, TM2, unknown)."""

    command: Command
    status: str
    lines: tuple[bytes, ...] = ()  # data lines without their checksum characters


@dataclass(frozen=True, slots=True)
class VersionInfo:
    """VV: who made the sensor and which firmware it runs."""

    command: Command
    vendor: str
    product: str
    firmware: str
    protocol: str
    serial: str
    fields: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class SensorParameters:
    """PP: the scan geometry. Angle of step s = (s - afrt) * 2π / ares."""

    command: Command
    model: str
    dmin_mm: int
    dmax_mm: int
    ares: int  # steps per revolution
    amin: int  # first measurable step
    amax: int  # last measurable step
    afrt: int  # step on the front axis
    scan_rpm: int
    fields: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class SensorState:
    """II: laser, motor and measurement state, as text fields."""

    command: Command
    laser_on: bool | None
    status_text: str
    fields: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class TimeReply:
    """TM1: the sensor's 24-bit millisecond counter."""

    command: Command
    timestamp_ms: int


@dataclass(frozen=True, slots=True)
class ScanStarted:
    """The acknowledgement of an MD/ME command: scans follow."""

    command: Command


@dataclass(frozen=True, slots=True, eq=False)
class ScanData:
    """One scan from GD, MD or ME. Values below DMIN are the device's error codes."""

    command: Command
    remaining: int  # scans still to come (0 for GD and for unlimited streams)
    timestamp_raw_ms: int  # the 24-bit counter as sent
    timestamp_ms: int  # unwrapped since the codec was created or the device was reset (RS/RT)
    ranges_mm: npt.NDArray[np.uint32]
    intensities: npt.NDArray[np.uint32] | None = None


@dataclass(frozen=True, slots=True)
class ReplyError:
    """An expected reply that is unusable; `error` says why (checksum, shape or status)."""

    command: Command
    error: ScipError
    echo: bytes = b""


@dataclass(frozen=True, slots=True)
class Discarded:
    """Bytes that are not a reply to anything we asked for (resynchronisation)."""

    frame: bytes
    reason: str


Event = (
    CommandOk
    | VersionInfo
    | SensorParameters
    | SensorState
    | TimeReply
    | ScanStarted
    | ScanData
    | ReplyError
    | Discarded
)


# ---------------------------------------------------------------------------------------------
# Timestamps


class TimestampUnwrapper:
    """Turns the 24-bit millisecond counter into a monotonic count.

    Each step is taken as the nearest one modulo 2^24, so a small backwards jump stays small
    and a wrap (every 4 h 39 min) adds 2^24 ms.
    """

    def __init__(self) -> None:
        self._last_raw: int | None = None
        self._total_ms = 0

    def reset(self) -> None:
        self._last_raw = None
        self._total_ms = 0

    def unwrap(self, raw_ms: int) -> int:
        if self._last_raw is None:
            self._total_ms = raw_ms
        else:
            delta = (raw_ms - self._last_raw) % TIMESTAMP_MODULUS
            if delta >= TIMESTAMP_MODULUS // 2:
                delta -= TIMESTAMP_MODULUS
            self._total_ms += delta
        self._last_raw = raw_ms
        return self._total_ms


# ---------------------------------------------------------------------------------------------
# Codec


class ScipCodec:
    """The host side of a SCIP 2.0 conversation, without any IO."""

    def __init__(self, *, max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES) -> None:
        self._max_frame_bytes = max_frame_bytes
        self._buf = bytearray()
        self._searched = 0  # bytes of _buf already searched for the terminator
        self._pending: list[tuple[int, Command]] = []  # (send number, command)
        self._sent = 0
        self._stream: Command | None = None
        self._stream_sent = 0  # send number of the stream command
        self._unwrapper = TimestampUnwrapper()

    # -- outgoing ----------------------------------------------------------------------------

    def send(self, command: Command) -> bytes:
        """Register `command` as awaiting a reply and return the bytes to write."""
        self._sent += 1
        self._pending.append((self._sent, command))
        if len(self._pending) > MAX_PENDING:
            del self._pending[0]
        if command.is_stream:
            # Scans of this stream are accepted from now on, even if its acknowledgement is lost.
            self._stream = command
            self._stream_sent = self._sent
        return command.encode()

    def clear_pending(self) -> None:
        """Forget every awaited reply (after a timeout); a late reply will then be discarded."""
        self._pending.clear()

    def reset(self) -> None:
        """Back to the state of a new codec (after reopening the port)."""
        self._buf.clear()
        self._searched = 0
        self._pending.clear()
        self._stream = None
        self._unwrapper.reset()

    @property
    def pending(self) -> tuple[Command, ...]:
        return tuple(cmd for _, cmd in self._pending)

    @property
    def stream(self) -> Command | None:
        """The MD/ME command whose scans are currently accepted."""
        return self._stream

    # -- incoming ----------------------------------------------------------------------------

    def receive(self, data: bytes) -> list[Event]:
        """Feed received bytes; return the events of every reply they complete."""
        self._buf += data
        events: list[Event] = []
        while True:
            end = self._buf.find(_TERMINATOR, max(0, self._searched - 1))
            if end < 0:
                self._searched = len(self._buf)
                break
            frame = bytes(self._buf[:end])
            del self._buf[: end + len(_TERMINATOR)]
            self._searched = 0
            events.extend(self._frame(frame))
        if len(self._buf) > self._max_frame_bytes:
            # No terminator for too long: keep only the last partial line.
            cut = self._buf.rfind(b"\n") + 1 or len(self._buf)
            events.append(Discarded(bytes(self._buf[:cut]), "no reply terminator"))
            del self._buf[:cut]
            self._searched = 0
        return events

    def _match(self, line: bytes) -> Command | None:
        for _, cmd in self._pending:
            if cmd.line == line:
                return cmd
        s = self._stream
        if (
            s is not None
            and len(line) == len(s.line)
            and line[:_STREAM_ECHO_PREFIX] == s.line[:_STREAM_ECHO_PREFIX]
            and line[_STREAM_ECHO_COUNT].isdigit()
            and line[_STREAM_ECHO_COUNT.stop :] == s.line[_STREAM_ECHO_COUNT.stop :]
        ):
            return s
        return None

    def _consume(self, cmd: Command, echo: bytes) -> int:
        """Remove the first pending command answered by `echo`; its send number, or 0."""
        for i, (sent, pending) in enumerate(self._pending):
            if pending is cmd and pending.line == echo:
                del self._pending[i]
                return sent
        return 0

    def _frame(self, frame: bytes) -> list[Event]:
        frame = frame.lstrip(b"\n")
        if not frame:
            return []
        lines = frame.split(b"\n")
        # The echo is normally the first line; junk lines before it (garbage that ended in a
        # line feed) are skipped so the reply itself is not lost.
        for i, line in enumerate(lines):
            cmd = self._match(line)
            if cmd is not None:
                events: list[Event] = []
                if i:
                    events.append(Discarded(b"\n".join(lines[:i]), "junk before echo"))
                events.extend(self._reply(cmd, lines[i:]))
                return events
        return [Discarded(frame, "unexpected echo")]

    def _reply(self, cmd: Command, lines: list[bytes]) -> list[Event]:
        echo = lines[0]
        if len(lines) < 2 or not lines[1]:
            # An echo alone is what a half-received or garbled reply looks like; the real reply
            # (if any) is still to come, so nothing is consumed.
            return [Discarded(b"\n".join(lines), "echo without status")]
        is_scan_frame = cmd.is_stream and lines[1][:2] == b"99"
        sent = 0 if is_scan_frame else self._consume(cmd, echo)
        try:
            status = _status(lines[1])
            if cmd.is_stream:
                return self._stream_reply(cmd, status, lines)
            if not is_success(cmd.name, status):
                raise status_error(cmd.name, status)
            return [self._success(cmd, status, lines, sent)]
        except ScipError as err:
            return [ReplyError(cmd, err, echo)]

    def _stream_reply(self, cmd: Command, status: str, lines: list[bytes]) -> list[Event]:
        echo = lines[0]
        if status == "99":
            remaining = int(echo[_STREAM_ECHO_COUNT])
            finite = cmd.scan is not None and cmd.scan.nscans > 0
            if finite and remaining == 0 and self._stream is cmd:
                self._stream = None  # the last scan of a finite stream
            return [self._scan(cmd, lines, remaining)]
        if status == "00":
            return [ScanStarted(cmd)]
        if self._stream is cmd and echo == cmd.line:
            self._stream = None  # the command was refused: no scans will come
        raise status_error(cmd.name, status)

    def _success(self, cmd: Command, status: str, lines: list[bytes], sent: int) -> Event:
        name = cmd.name
        if name == "GD":
            return self._scan(cmd, lines, 0)
        if name == "VV":
            f = _fields(lines)
            return VersionInfo(
                cmd,
                vendor=f.get("VEND", ""),
                product=f.get("PROD", ""),
                firmware=f.get("FIRM", ""),
                protocol=f.get("PROT", ""),
                serial=f.get("SERI", ""),
                fields=f,
            )
        if name == "PP":
            return _parameters(cmd, _fields(lines))
        if name == "II":
            f = _fields(lines)
            lasr = f.get("LASR", "").upper()
            laser_on = None if not lasr else ("ON" in lasr and "OFF" not in lasr)
            return SensorState(cmd, laser_on=laser_on, status_text=f.get("STAT", ""), fields=f)
        if name == "TM" and cmd.line.startswith(b"TM1"):
            payload = _data_payloads(lines[2:])
            if len(lines) != 3 or len(payload) != TIMESTAMP_CHARS:
                raise MalformedReplyError("TM1 reply without a 4-character timestamp line")
            return TimeReply(cmd, decode_value(payload))
        if name in ("RS", "RT", "QT"):
            # These stop any stream the device had; a stream requested after them goes on.
            if self._stream is not None and self._stream_sent < sent:
                self._stream = None
            if name != "QT":
                self._unwrapper.reset()  # the device restarts its timestamp counter
        return CommandOk(cmd, status, tuple(line[:-1] for line in lines[2:]))

    def _scan(self, cmd: Command, lines: list[bytes], remaining: int) -> ScanData:
        if cmd.scan is None:
            raise MalformedReplyError(f"{cmd.name} reply with scan data but no scan request")
        if len(lines) < 3:
            raise MalformedReplyError("scan reply without a timestamp line")
        ts_chars = _data_payloads(lines[2:3])
        if len(ts_chars) != TIMESTAMP_CHARS:
            raise MalformedReplyError(f"timestamp line {lines[2][:16]!r} is not 4 characters")
        raw_ms = decode_value(ts_chars)
        data = _data_payloads(lines[3:])
        n = cmd.scan.value_count
        expected = n * cmd.chars_per_step
        if len(data) != expected:
            raise MalformedReplyError(f"{len(data)} data characters, expected {expected}")
        values = decode_values(data, 3)
        if cmd.name == "ME":
            ranges_mm, intensities = values[0::2].copy(), values[1::2].copy()
        else:
            ranges_mm, intensities = values, None
        return ScanData(
            cmd,
            remaining=remaining,
            timestamp_raw_ms=raw_ms,
            timestamp_ms=self._unwrapper.unwrap(raw_ms),
            ranges_mm=ranges_mm,
            intensities=intensities,
        )


# ---------------------------------------------------------------------------------------------
# Line helpers


def _status(line: bytes) -> str:
    if len(line) != 3:
        raise MalformedReplyError(f"status line {line[:16]!r} is not 2 characters + sum")
    if checksum(line[:2]) != line[2]:
        raise ChecksumError(line)
    return line[:2].decode("latin-1")


def _data_payloads(lines: list[bytes]) -> bytes:
    """Verify each line's checksum and return the concatenated payloads."""
    out = bytearray()
    for line in lines:
        if len(line) < 2:
            raise MalformedReplyError(f"data line {line!r} is too short")
        if checksum(line[:-1]) != line[-1]:
            raise ChecksumError(line)
        out += line[:-1]
    return bytes(out)


def _fields(lines: list[bytes]) -> dict[str, str]:
    """`KEY:VALUE;S` lines (VV, PP, II). The sum covers `KEY:VALUE`, without the `;`.

    Some older documents include the `;`; that form is accepted too, as urg_c does.
    """
    out: dict[str, str] = {}
    for line in lines[2:]:
        if len(line) < 3 or line[-2] != ord(";"):
            raise MalformedReplyError(f"line {line[:40]!r} is not KEY:VALUE;sum")
        body, total = line[:-2], line[-1]
        if checksum(body) != total and checksum(line[:-1]) != total:
            raise ChecksumError(line)
        key, sep, value = body.partition(b":")
        if not sep:
            raise MalformedReplyError(f"line {line[:40]!r} has no ':'")
        out[key.decode("latin-1")] = value.decode("latin-1")
    return out


def _parameters(cmd: Command, f: dict[str, str]) -> SensorParameters:
    ints: dict[str, int] = {}
    for key in ("DMIN", "DMAX", "ARES", "AMIN", "AMAX", "AFRT", "SCAN"):
        value = f.get(key)
        if value is None or not (value.strip().isascii() and value.strip().isdigit()):
            raise MalformedReplyError(f"PP reply: {key} missing or not a number ({value!r})")
        ints[key] = int(value.strip())
    if ints["ARES"] <= 0 or ints["AMIN"] > ints["AMAX"]:
        raise MalformedReplyError(f"PP reply: inconsistent geometry {ints}")
    return SensorParameters(
        cmd,
        model=f.get("MODL", ""),
        dmin_mm=ints["DMIN"],
        dmax_mm=ints["DMAX"],
        ares=ints["ARES"],
        amin=ints["AMIN"],
        amax=ints["AMAX"],
        afrt=ints["AFRT"],
        scan_rpm=ints["SCAN"],
        fields=f,
    )


__all__ = [
    "CommandOk",
    "Discarded",
    "Event",
    "ReplyError",
    "ScanData",
    "ScanStarted",
    "ScipCodec",
    "SensorParameters",
    "SensorState",
    "TimeReply",
    "TimestampUnwrapper",
    "VersionInfo",
]
