"""Our own UTM-30LX: SCIP 2.0 on a pty (and optionally TCP 10940), 40 Hz, with fault injection.

Three layers:

* `Utm30lxDevice` is the sensor without IO: command lines in, reply bytes out, and `tick(now)`
  returns the scan frames completed since the last call (one every 25 ms while MD/ME streams).
  Corrupted checksums and garbage bytes are injected here, deterministically from a seed.
* `Emulator` runs a device on a pty (the driver opens a stable symlink to it, re-pointed when the
  "USB cable" is re-plugged) and/or a TCP listener, in one thread. Writes are non-blocking: when
  the host does not read, whole scans are dropped instead of blocking the device. `unplug()` and
  `stall()` inject link faults.
* `python -m sensor_agent.emulator --link PATH ...` runs it as its own process; SIGUSR1 unplugs
  the device for `--unplug-s` seconds and SIGUSR2 stalls it for `--stall-s` seconds.

With `--record FILE`, every scan handed to the link is appended to a small binary log
(`read_sent_scans`) so that tests can check bit for bit what reached the subscriber.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import logging
import math
import os
import queue
import select
import signal
import socket
import struct
import sys
import threading
import time
import tty
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import BinaryIO, Final

import numpy as np
import numpy.typing as npt

from sensor_agent.errors import EmulatorError
from sensor_agent.scene import (
    UTM_AFRT,
    UTM_AMAX,
    UTM_AMIN,
    UTM_ARES,
    UTM_DMAX_MM,
    UTM_DMIN_MM,
    UTM_SCAN_PERIOD_S,
    Scene,
    make_scene,
)
from sensor_agent.scip.encoding import (
    TIMESTAMP_MODULUS,
    checksum,
    encode_value,
    encode_values,
)

# Under `python -m` this module is __main__; keep the logger name stable for log filters.
log = logging.getLogger("sensor_agent.emulator")

DEFAULT_TCP_PORT: Final = 10940
DEFAULT_SERIAL: Final = "H0900000"
MAX_CATCH_UP_SCANS: Final = 4  # after a longer hiccup the missed scans are skipped, not burst
_MAX_INPUT_LINE: Final = 256
_EPS_MS: Final = 1e-6  # float noise in clock differences must not lose a millisecond
_TAG_CHARS: Final = frozenset(
    b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789 ._+@"
)
_FIXED_LENGTH: Final = {
    b"VV": 2,
    b"PP": 2,
    b"II": 2,
    b"BM": 2,
    b"QT": 2,
    b"RS": 2,
    b"RT": 2,
    b"TM": 3,
    b"GD": 12,
    b"MD": 15,
    b"ME": 15,
}
_ALLOWED_IN_TIME_ADJUST: Final = frozenset({b"TM", b"VV", b"PP", b"II", b"RS", b"RT"})

Line = tuple[bytes, int]  # line content and its checksum byte


@dataclass(frozen=True, slots=True)
class FaultConfig:
    """Faults injected into what the device sends; all draws come from `seed`."""

    corrupt_line_prob: float = 0.0  # per checksummed line: the checksum character is changed
    garbage_prob: float = 0.0  # per scan: 1-32 random bytes are sent before the scan reply
    seed: int = 0


@dataclass(frozen=True, slots=True)
class DeviceIdentity:
    vendor: str = "Hokuyo Automatic Co.,Ltd."
    product: str = "SOKUIKI Sensor TOP-URG UTM-30LX"
    firmware: str = "1.16.01(16/Nov./2009)"
    protocol: str = "SCIP 2.0"
    serial: str = DEFAULT_SERIAL
    model: str = "UTM-30LX"


@dataclass(frozen=True, slots=True, eq=False)
class ScanFrame:
    """One scan reply as produced by the device, with what it encodes."""

    data: bytes
    index: int  # scan number since the emulator started (scene time = index * 25 ms)
    timestamp_ms: int  # the 24-bit counter value in the reply
    ranges_mm: npt.NDArray[np.uint32]  # the values sent (after clustering)
    intensities: npt.NDArray[np.uint32] | None
    corrupted: bool  # at least one line's checksum was falsified
    garbage: bool  # random bytes were sent just before it


@dataclass(slots=True)
class DeviceStats:
    commands: int = 0
    scans_generated: int = 0
    corrupted_lines: int = 0
    garbage_bursts: int = 0


@dataclass(slots=True)
class _Stream:
    name: bytes  # b"MD" or b"ME"
    head: bytes  # echo prefix before the scan count: MDssssEEEEcci
    tag: bytes  # b";tag" or b""
    start: int
    end: int
    cluster: int
    interval: int
    remaining: int | None  # None = unlimited
    first_index: int  # the first scan whose step 0 comes after the command
    skip_left: int = 0
    laser_was_off: bool = False


class Utm30lxDevice:
    """A UTM-30LX without IO. Times are seconds on any monotonic clock."""

    def __init__(
        self,
        scene: Scene,
        *,
        now_s: float,
        faults: FaultConfig | None = None,
        identity: DeviceIdentity | None = None,
        timestamp_offset_ms: int = 0,
    ) -> None:
        self.scene = scene
        self.faults = faults or FaultConfig()
        self.identity = identity or DeviceIdentity()
        self.stats = DeviceStats()
        self._rng = np.random.default_rng(self.faults.seed)
        self._timestamp_offset_ms = timestamp_offset_ms
        self._t0_s = now_s  # motor start: scan k covers [t0 + k P, t0 + (k+1) P)
        self._t_reset_s = now_s  # the timestamp counter counts from here
        self._next_index = 0
        self._inbuf = bytearray()
        self.laser_on = False
        self.time_adjust = False
        self._stream: _Stream | None = None

    # -- time --------------------------------------------------------------------------------

    def timestamp_at(self, t_s: float) -> int:
        # A scan that began just before a reset is stamped 0, not with a negative time.
        ms = (
            max(0, math.floor((t_s - self._t_reset_s) * 1000.0 + _EPS_MS))
            + self._timestamp_offset_ms
        )
        return ms % TIMESTAMP_MODULUS

    def _scan_start_s(self, index: int) -> float:
        return self._t0_s + index * UTM_SCAN_PERIOD_S

    def next_tick_s(self) -> float:
        """When the next scan completes."""
        return self._scan_start_s(self._next_index + 1)

    @property
    def streaming(self) -> bool:
        return self._stream is not None

    # -- host -> device ----------------------------------------------------------------------

    def receive(self, data: bytes, now_s: float) -> bytes:
        """Bytes from the host; returns the replies to every complete command line."""
        self._inbuf += data
        out = bytearray()
        while True:
            ends = [i for i in (self._inbuf.find(b"\n"), self._inbuf.find(b"\r")) if i >= 0]
            if not ends:
                if len(self._inbuf) > _MAX_INPUT_LINE:
                    self._inbuf.clear()
                break
            end = min(ends)
            line = bytes(self._inbuf[:end])
            del self._inbuf[: end + 1]
            if line:  # empty lines (the LF of a CR+LF) get no reply
                out += self._command(line, now_s)
        return bytes(out)

    def _command(self, line: bytes, now_s: float) -> bytes:
        self.stats.commands += 1
        body, sep, tag = line.partition(b";")
        name = body[:2]
        if sep and len(tag) > 16:
            return self._reply(line, "0G")
        if sep and not set(tag) <= _TAG_CHARS:
            return self._reply(line, "0H")
        if name not in _FIXED_LENGTH:
            return self._reply(line, "0E")
        n = _FIXED_LENGTH[name]
        if len(body) < n:
            return self._reply(line, "0C")
        if len(body) > n:
            return self._reply(line, "0D")
        if self.time_adjust and name not in _ALLOWED_IN_TIME_ADJUST:
            return self._reply(line, "10")
        tagged = sep + tag
        if name == b"VV":
            i = self.identity
            return self._reply(
                line,
                "00",
                _kv(
                    ("VEND", i.vendor),
                    ("PROD", i.product),
                    ("FIRM", i.firmware),
                    ("PROT", i.protocol),
                    ("SERI", i.serial),
                ),
            )
        if name == b"PP":
            return self._reply(
                line,
                "00",
                _kv(
                    ("MODL", self.identity.model),
                    ("DMIN", str(UTM_DMIN_MM)),
                    ("DMAX", str(UTM_DMAX_MM)),
                    ("ARES", str(UTM_ARES)),
                    ("AMIN", str(UTM_AMIN)),
                    ("AMAX", str(UTM_AMAX)),
                    ("AFRT", str(UTM_AFRT)),
                    ("SCAN", str(round(60.0 / UTM_SCAN_PERIOD_S))),
                ),
            )
        if name == b"II":
            mode = "004 Multi_scan" if self._stream else "000 Idle"
            return self._reply(
                line,
                "00",
                _kv(
                    ("MODL", self.identity.model),
                    ("LASR", "ON" if self.laser_on else "OFF"),
                    ("SCSP", "Standard 2400[rpm]"),
                    ("MESM", mode),
                    ("SBPS", "USB only"),
                    ("TIME", f"{self.timestamp_at(now_s):06X}"),
                    ("STAT", "Stable 000 no error."),
                ),
            )
        if name == b"BM":
            if self.laser_on:
                return self._reply(line, "02")
            self.laser_on = True
            return self._reply(line, "00")
        if name == b"QT":
            self._stop()
            return self._reply(line, "00")
        if name in (b"RS", b"RT"):
            self._stop()
            self.time_adjust = False
            self._t_reset_s = now_s
            return self._reply(line, "00")
        if name == b"TM":
            return self._tm(line, body[2:3], now_s)
        if name == b"GD":
            return self._gd(line, body, now_s)
        return self._start_stream(line, body, tagged, now_s)

    def _stop(self) -> None:
        self._stream = None
        self.laser_on = False

    def _tm(self, line: bytes, code: bytes, now_s: float) -> bytes:
        if code == b"0":
            if self.time_adjust:
                return self._reply(line, "02")
            self._stop()
            self.time_adjust = True
            return self._reply(line, "00")
        if code == b"1":
            if not self.time_adjust:
                return self._reply(line, "04")
            ts = encode_value(self.timestamp_at(now_s), 4)
            return self._reply(line, "00", [(ts, checksum(ts))])
        if code == b"2":
            if not self.time_adjust:
                return self._reply(line, "03")
            self.time_adjust = False
            return self._reply(line, "00")
        return self._reply(line, "01")

    def _scan_params(self, body: bytes, stream: bool) -> tuple[str, tuple[int, ...]]:
        """Parse GD/MD/ME fields; returns (status, values). Status "00" means valid."""
        fields = [(body[2:6], "01"), (body[6:10], "02"), (body[10:12], "03")]
        if stream:
            fields += [(body[12:13], "06"), (body[13:15], "07")]
        values = []
        for raw, status in fields:
            if not raw.isdigit():
                return status, ()
            values.append(int(raw))
        start, end = values[0], values[1]
        if start < UTM_AMIN or end > UTM_AMAX:
            return "04", ()
        if end < start:
            return "05", ()
        return "00", tuple(values)

    def _gd(self, line: bytes, body: bytes, now_s: float) -> bytes:
        status, v = self._scan_params(body, stream=False)
        if status != "00":
            return self._reply(line, status)
        if not self.laser_on:
            return self._reply(line, "10")
        index = max(0, self._next_index - 1)
        ranges, intens = self._values(index, v[0], v[1], v[2], with_intensity=False)
        ts = self.timestamp_at(self._scan_start_s(index))
        return self._reply(line, "00", _scan_lines(ts, ranges, intens))

    def _start_stream(self, line: bytes, body: bytes, tagged: bytes, now_s: float) -> bytes:
        status, v = self._scan_params(body, stream=True)
        if status != "00":
            return self._reply(line, status)
        start, end, cluster, interval, nscans = v
        self._stream = _Stream(
            name=body[:2],
            head=body[:13],
            tag=tagged,
            start=start,
            end=end,
            cluster=max(1, cluster),
            interval=interval,
            remaining=nscans if nscans > 0 else None,
            # A scan already under way was measured before the request (and before an RS that
            # came with it, which would stamp two scans 0 ms): the stream starts with the next.
            first_index=math.ceil((now_s - self._t0_s) / UTM_SCAN_PERIOD_S - 1e-9),
            laser_was_off=not self.laser_on,
        )
        self.laser_on = True  # MD/ME switch the laser on by themselves
        return self._reply(line, "00")

    # -- device -> host ----------------------------------------------------------------------

    def tick(self, now_s: float) -> list[ScanFrame]:
        """Scan frames for every scan completed since the last call (if streaming)."""
        done = math.floor((now_s - self._t0_s) / UTM_SCAN_PERIOD_S + 1e-9)
        if done - self._next_index > MAX_CATCH_UP_SCANS:
            self._next_index = done - 1
        frames: list[ScanFrame] = []
        while self._next_index < done:
            index = self._next_index
            self._next_index += 1
            frame = self._stream_scan(index)
            if frame is not None:
                frames.append(frame)
        return frames

    def _stream_scan(self, index: int) -> ScanFrame | None:
        s = self._stream
        if s is None or index < s.first_index:
            return None
        if s.skip_left > 0:
            s.skip_left -= 1
            return None
        s.skip_left = s.interval
        if s.remaining is not None:
            s.remaining -= 1
            left = s.remaining
            if left == 0:
                self._stream = None
                if s.laser_was_off:
                    self.laser_on = False
        else:
            left = 0
        ranges, intens = self._values(index, s.start, s.end, s.cluster, s.name == b"ME")
        ts = self.timestamp_at(self._scan_start_s(index))
        echo = s.head + f"{left:02d}".encode() + s.tag
        data, corrupted = self._assemble(echo, "99", _scan_lines(ts, ranges, intens))
        garbage = bool(self.faults.garbage_prob) and self._rng.random() < self.faults.garbage_prob
        if garbage:
            self.stats.garbage_bursts += 1
            junk = self._rng.integers(0, 256, int(self._rng.integers(1, 33)), dtype=np.uint8)
            data = junk.tobytes() + data
        self.stats.scans_generated += 1
        return ScanFrame(data, index, ts, ranges, intens, corrupted, garbage)

    def _values(
        self, index: int, start: int, end: int, cluster: int, with_intensity: bool
    ) -> tuple[npt.NDArray[np.uint32], npt.NDArray[np.uint32] | None]:
        scan = self.scene.scan(index)
        lo, hi = start - UTM_AMIN, end - UTM_AMIN + 1
        ranges = _cluster_min(scan.ranges_mm[lo:hi], max(1, cluster))
        if not with_intensity:
            return ranges, None
        # Intensity of a cluster: that of its first step (the spec leaves it open).
        return ranges, np.ascontiguousarray(scan.intensities[lo:hi][:: max(1, cluster)])

    def _reply(self, echo: bytes, status: str, lines: Sequence[Line] = ()) -> bytes:
        return self._assemble(echo, status, lines)[0]

    def _assemble(self, echo: bytes, status: str, lines: Sequence[Line]) -> tuple[bytes, bool]:
        st = status.encode("ascii")
        all_lines: list[Line] = [(st, checksum(st)), *lines]
        parts = [echo]
        corrupted = False
        p = self.faults.corrupt_line_prob
        for content, total in all_lines:
            sent = total
            if p > 0.0 and self._rng.random() < p:
                # Any other checksum character: the host must notice.
                sent = (total - 0x30 + int(self._rng.integers(1, 64))) % 64 + 0x30
                corrupted = True
                self.stats.corrupted_lines += 1
            parts.append(content + bytes([sent]))
        return b"\n".join(parts) + b"\n\n", corrupted


def _kv(*pairs: tuple[str, str]) -> list[Line]:
    """`KEY:VALUE;sum` lines; the sum covers `KEY:VALUE` without the `;` (PROTOCOLS.md A.2)."""
    out: list[Line] = []
    for key, value in pairs:
        body = f"{key}:{value}".encode("ascii")
        out.append((body + b";", checksum(body)))
    return out


def _scan_lines(
    timestamp_ms: int,
    ranges_mm: npt.NDArray[np.uint32],
    intensities: npt.NDArray[np.uint32] | None,
) -> list[Line]:
    ts = encode_value(timestamp_ms, 4)
    if intensities is None:
        payload = encode_values(ranges_mm, 3)
    else:
        payload = encode_values(np.stack([ranges_mm, intensities], axis=1), 3)
    lines: list[Line] = [(ts, checksum(ts))]
    for i in range(0, len(payload), 64):
        chunk = payload[i : i + 64]
        lines.append((chunk, checksum(chunk)))
    return lines


def _cluster_min(values: npt.NDArray[np.uint32], cluster: int) -> npt.NDArray[np.uint32]:
    """Per cluster the minimum valid (>= DMIN) value, else the first value (spec p.10)."""
    v = np.asarray(values, dtype=np.uint32)
    if cluster == 1:
        return v.copy()
    n = -(-v.size // cluster)
    padded = np.zeros(n * cluster, dtype=np.int64)
    padded[: v.size] = v
    groups = padded.reshape(n, cluster)
    valid = groups >= UTM_DMIN_MM
    valid.reshape(-1)[v.size :] = False
    big = np.iinfo(np.int64).max
    best = np.where(valid, groups, big).min(axis=1)
    return np.where(best == big, groups[:, 0], best).astype(np.uint32)


# ---------------------------------------------------------------------------------------------
# Record of what was sent


_REC_MAGIC: Final = b"UTMEMU1\n"
_REC_HEAD: Final = struct.Struct("<QIBH")
_FLAG_CORRUPTED: Final = 1
_FLAG_GARBAGE: Final = 2
_FLAG_INTENSITY: Final = 4


@dataclass(frozen=True, slots=True, eq=False)
class SentScan:
    index: int
    timestamp_ms: int
    ranges_mm: npt.NDArray[np.uint32]
    intensities: npt.NDArray[np.uint32] | None
    corrupted: bool
    garbage: bool


class ScanRecorder:
    """Appends every scan handed to the link; flushed per scan so readers see it at once."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._f: BinaryIO = open(self.path, "wb")  # noqa: SIM115  # closed in close()
        self._f.write(_REC_MAGIC)
        self._f.flush()
        self._lock = threading.Lock()

    def write(self, frame: ScanFrame) -> None:
        flags = (
            (_FLAG_CORRUPTED if frame.corrupted else 0)
            | (_FLAG_GARBAGE if frame.garbage else 0)
            | (_FLAG_INTENSITY if frame.intensities is not None else 0)
        )
        parts = [
            _REC_HEAD.pack(frame.index, frame.timestamp_ms, flags, frame.ranges_mm.size),
            frame.ranges_mm.astype("<u4").tobytes(),
        ]
        if frame.intensities is not None:
            parts.append(frame.intensities.astype("<u4").tobytes())
        with self._lock:
            self._f.write(b"".join(parts))
            self._f.flush()

    def close(self) -> None:
        with self._lock:
            self._f.close()


def read_sent_scans(path: str | Path) -> list[SentScan]:
    """Every complete record of a `ScanRecorder` file (a torn last record is ignored)."""
    data = Path(path).read_bytes()
    if not data.startswith(_REC_MAGIC):
        raise EmulatorError(f"{path}: not an emulator scan record")
    out: list[SentScan] = []
    pos = len(_REC_MAGIC)
    while pos + _REC_HEAD.size <= len(data):
        index, ts, flags, n = _REC_HEAD.unpack_from(data, pos)
        size = 4 * n * (2 if flags & _FLAG_INTENSITY else 1)
        body = pos + _REC_HEAD.size
        if body + size > len(data):
            break
        ranges = np.frombuffer(data, dtype="<u4", count=n, offset=body).astype(np.uint32)
        intens = None
        if flags & _FLAG_INTENSITY:
            intens = np.frombuffer(data, "<u4", count=n, offset=body + 4 * n).astype(np.uint32)
        out.append(
            SentScan(
                index,
                ts,
                ranges,
                intens,
                bool(flags & _FLAG_CORRUPTED),
                bool(flags & _FLAG_GARBAGE),
            )
        )
        pos = body + size
    return out


# ---------------------------------------------------------------------------------------------
# Links: pty and TCP


@dataclass(slots=True)
class EmulatorStats:
    scans_sent: int = 0  # handed to at least one link
    scans_dropped: int = 0  # the host did not keep up, or the link was down/stalled
    bytes_written: int = 0
    unplugs: int = 0
    stalls: int = 0
    links: int = 0  # pty (re)creations and TCP connections accepted


@dataclass(slots=True)
class _Conn:
    fd: int
    kind: str  # "pty" or "tcp"
    out: bytearray = field(default_factory=bytearray)
    slave_fd: int = -1  # pty only: kept open so the master never sees EIO between hosts
    sock: socket.socket | None = None


class Emulator:
    """Runs a `Utm30lxDevice` on a pty symlink and/or a TCP port, in a background thread."""

    def __init__(
        self,
        device: Utm30lxDevice,
        *,
        link_path: str | Path | None = None,
        tcp_address: tuple[str, int] | None = None,
        recorder: ScanRecorder | None = None,
    ) -> None:
        if link_path is None and tcp_address is None:
            raise EmulatorError("the emulator needs a pty link path or a TCP address")
        self.device = device
        self.link_path = Path(link_path) if link_path is not None else None
        self.tcp_address = tcp_address
        self.recorder = recorder
        self.stats = EmulatorStats()
        self._pty: _Conn | None = None
        self._tcp: _Conn | None = None
        self._listener: socket.socket | None = None
        self._requests: queue.SimpleQueue[tuple[str, float]] = queue.SimpleQueue()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._unplugged_until: float | None = None
        self._stalled_until: float | None = None
        self._lock = threading.Lock()  # guards device access from the loop vs. callers
        self.replugged = threading.Event()

    # -- control (any thread) ----------------------------------------------------------------

    def start(self) -> Emulator:
        """Create the links and start the thread (a no-op if already started)."""
        if self._thread is not None:
            return self
        if self.link_path is not None:
            self._open_pty()
        if self.tcp_address is not None:
            self._open_listener()
        self._thread = threading.Thread(target=self._run, name="utm-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._close_pty()
        self._close_tcp()
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        if self.recorder is not None:
            self.recorder.close()

    def __enter__(self) -> Emulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def unplug(self, duration_s: float) -> None:
        """Pull the cable: the pty (and its symlink) or the TCP port vanish for `duration_s`."""
        self._requests.put(("unplug", duration_s))
        self._wake()

    def stall(self, duration_s: float) -> None:
        """The device goes silent (reads and writes nothing) for `duration_s`; scans are lost."""
        self._requests.put(("stall", duration_s))
        self._wake()

    @property
    def pty_name(self) -> str | None:
        """The current /dev/pts/N behind the symlink."""
        conn = self._pty
        return os.ttyname(conn.slave_fd) if conn is not None else None

    def _wake(self) -> None:
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")

    # -- links -------------------------------------------------------------------------------

    def _open_pty(self) -> None:
        assert self.link_path is not None
        master, slave = os.openpty()
        tty.setraw(slave)  # before the host opens it: no echo, no CR/LF translation
        os.set_blocking(master, False)
        name = os.ttyname(slave)
        tmp = self.link_path.with_name(self.link_path.name + ".new")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        os.symlink(name, tmp)
        os.replace(tmp, self.link_path)  # atomic re-point: the host never sees a half state
        self._pty = _Conn(master, "pty", slave_fd=slave)
        self.stats.links += 1
        log.info("emulated UTM-30LX on %s -> %s", self.link_path, name)

    def _close_pty(self) -> None:
        conn, self._pty = self._pty, None
        if conn is None:
            return
        if self.link_path is not None:
            with contextlib.suppress(FileNotFoundError):
                self.link_path.unlink()
        for fd in (conn.fd, conn.slave_fd):
            with contextlib.suppress(OSError):
                os.close(fd)

    def _open_listener(self) -> None:
        assert self.tcp_address is not None
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(self.tcp_address)
        except OSError as err:
            sock.close()
            raise EmulatorError(f"cannot listen on {self.tcp_address}: {err.strerror}") from err
        sock.listen(1)
        sock.setblocking(False)
        self._listener = sock
        log.info("emulated UTM-30LX on tcp %s:%d", *sock.getsockname()[:2])

    def _close_tcp(self) -> None:
        conn, self._tcp = self._tcp, None
        if conn is not None and conn.sock is not None:
            conn.sock.close()

    def _accept(self) -> None:
        assert self._listener is not None
        try:
            sock, peer = self._listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._close_tcp()  # one host at a time, like the real sensor
        self._tcp = _Conn(sock.fileno(), "tcp", sock=sock)
        self.stats.links += 1
        log.info("TCP host connected from %s:%d", *peer[:2])

    # -- loop --------------------------------------------------------------------------------

    def _conns(self) -> list[_Conn]:
        return [c for c in (self._pty, self._tcp) if c is not None]

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                self._step()
        except Exception:  # the thread must not die silently
            log.exception("emulator loop failed")
            raise

    def _step(self) -> None:
        now = time.monotonic()
        self._handle_requests(now)
        if self._unplugged_until is not None and now >= self._unplugged_until:
            self._replug()
        if self._stalled_until is not None and now >= self._stalled_until:
            self._stalled_until = None
            log.info("stall over")
        live = self._unplugged_until is None and self._stalled_until is None
        deadline = self.device.next_tick_s()
        for t in (self._unplugged_until, self._stalled_until):
            if t is not None:
                deadline = min(deadline, t)
        rlist: list[int] = [self._wake_r]
        wlist: list[int] = []
        if live:
            for c in self._conns():
                rlist.append(c.fd)
                if c.out:
                    wlist.append(c.fd)
            if self._listener is not None:
                rlist.append(self._listener.fileno())
        timeout = min(max(0.0, deadline - time.monotonic()), 0.1)
        readable, _, _ = select.select(rlist, wlist, [], timeout)
        if self._wake_r in readable:
            with contextlib.suppress(BlockingIOError):
                os.read(self._wake_r, 4096)
        now = time.monotonic()
        if live:
            if self._listener is not None and self._listener.fileno() in readable:
                self._accept()
            for c in self._conns():
                if c.fd in readable:
                    self._read(c, now)
        with self._lock:
            frames = self.device.tick(now)
        for frame in frames:
            self._offer(frame, live)
        if live:
            for c in self._conns():
                if c.out:
                    self._flush(c)

    def _handle_requests(self, now: float) -> None:
        while True:
            try:
                what, duration = self._requests.get_nowait()
            except queue.Empty:
                return
            if what == "unplug" and self._unplugged_until is None:
                log.info("unplugging for %.2f s", duration)
                self.stats.unplugs += 1
                self.replugged.clear()
                self._close_pty()
                self._close_tcp()
                if self._listener is not None:
                    self._listener.close()
                    self._listener = None
                self._unplugged_until = now + duration
            elif what == "stall":
                log.info("stalling for %.2f s", duration)
                self.stats.stalls += 1
                self._stalled_until = now + duration

    def _replug(self) -> None:
        self._unplugged_until = None
        if self.link_path is not None:
            self._open_pty()
        if self.tcp_address is not None:
            self._open_listener()
        log.info("replugged")
        self.replugged.set()

    def _read(self, c: _Conn, now: float) -> None:
        try:
            data = os.read(c.fd, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as err:
            data = b""
            if err.errno not in (errno.EIO, errno.ECONNRESET):
                log.warning("read on %s link failed: %s", c.kind, err)
        if not data:
            if c.kind == "tcp":
                log.info("TCP host disconnected")
                self._close_tcp()
            return
        with self._lock:
            reply = self.device.receive(data, now)
        c.out += reply

    def _offer(self, frame: ScanFrame, live: bool) -> None:
        taken = False
        if live:
            for c in self._conns():
                # A backlog means the host is not reading: drop the whole scan, never block.
                if not c.out:
                    c.out += frame.data
                    taken = True
        if taken:
            self.stats.scans_sent += 1
            if self.recorder is not None:
                self.recorder.write(frame)
        else:
            self.stats.scans_dropped += 1

    def _flush(self, c: _Conn) -> None:
        try:
            n = os.write(c.fd, c.out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as err:
            log.info("write on %s link failed: %s", c.kind, err)
            c.out.clear()
            if c.kind == "tcp":
                self._close_tcp()
            return
        self.stats.bytes_written += n
        del c.out[:n]


# ---------------------------------------------------------------------------------------------
# Process entry point


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m sensor_agent.emulator",
        description="Emulate a Hokuyo UTM-30LX (SCIP 2.0) on a pty symlink and/or TCP. "
        "SIGUSR1 unplugs it for --unplug-s seconds, SIGUSR2 stalls it for --stall-s seconds.",
    )
    p.add_argument("--link", metavar="PATH", help="symlink to the pty, e.g. /tmp/ttyUTM")
    p.add_argument(
        "--tcp",
        metavar="[HOST:]PORT",
        help=f"also listen on TCP (the Ethernet model uses {DEFAULT_TCP_PORT})",
    )
    p.add_argument("--seed", type=int, default=1, help="synthetic building seed (default: 1)")
    p.add_argument("--scene", choices=("world", "room"), default="world")
    p.add_argument("--corrupt-lines", type=float, default=0.0, metavar="P")
    p.add_argument("--garbage", type=float, default=0.0, metavar="P", help="per scan")
    p.add_argument("--fault-seed", type=int, default=0)
    p.add_argument("--unplug-s", type=float, default=0.5, help="SIGUSR1 unplug duration")
    p.add_argument("--stall-s", type=float, default=1.0, help="SIGUSR2 stall duration")
    p.add_argument("--timestamp-offset-ms", type=int, default=0)
    p.add_argument("--serial", default=DEFAULT_SERIAL, help="serial number in VV")
    p.add_argument("--record", metavar="FILE", help="append every scan sent to FILE")
    p.add_argument("-v", "--verbose", action="count", default=0)
    return p


def parse_tcp(value: str) -> tuple[str, int]:
    host, _, port = value.rpartition(":")
    if not (port.isascii() and port.isdigit()) or not 0 <= int(port) <= 65535:
        raise ValueError(f"bad TCP address {value!r}: use [HOST:]PORT")
    return host or "127.0.0.1", int(port)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if args.link is None and args.tcp is None:
        parser.error("give --link PATH and/or --tcp [HOST:]PORT")
    for name in ("corrupt_lines", "garbage"):
        if not 0.0 <= getattr(args, name) <= 1.0:
            parser.error(f"--{name.replace('_', '-')} must be within [0, 1]")
    try:
        tcp = parse_tcp(args.tcp) if args.tcp else None
    except ValueError as err:
        parser.error(str(err))
    stop = threading.Event()
    try:
        device = Utm30lxDevice(
            make_scene(args.seed, args.scene),
            now_s=time.monotonic(),
            faults=FaultConfig(args.corrupt_lines, args.garbage, args.fault_seed),
            identity=DeviceIdentity(serial=args.serial),
            timestamp_offset_ms=args.timestamp_offset_ms,
        )
        recorder = ScanRecorder(args.record) if args.record else None
        emulator = Emulator(device, link_path=args.link, tcp_address=tcp, recorder=recorder)
        emulator.start()
    except (EmulatorError, OSError) as err:
        print(f"emulator: {err}", file=sys.stderr)  # noqa: T201  # entry point
        return 1

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        if signum == signal.SIGUSR1:
            emulator.unplug(args.unplug_s)
        elif signum == signal.SIGUSR2:
            emulator.stall(args.stall_s)
        else:
            stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2):
        signal.signal(sig, on_signal)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        emulator.stop()
        s = emulator.stats
        log.info(
            "emulator stopped: %d scans sent, %d dropped, %d unplugs, %d stalls",
            s.scans_sent,
            s.scans_dropped,
            s.unplugs,
            s.stalls,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
