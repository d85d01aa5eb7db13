"""The UTM-30LX driver: pyserial IO around the sans-IO SCIP codec, with recovery.

The port is opened with `serial.serial_for_url`, so a device path (`/dev/ttyACM0`), a pty
symlink (the emulator) and `socket://192.168.0.10:10940` (the Ethernet model) all work.

Start-up follows the peer drivers (PROTOCOLS.md A.7): QT and drain, RS, PP/VV/II, BM, then MD
streaming. While streaming:

* a scan with a bad checksum, a wrong shape or an error status is dropped and counted; it never
  reaches the caller;
* after `max_consecutive_errors` failed replies in a row the stream is restarted (QT, wait for
  its reply while still delivering the scans already in flight, MD again);
* a read/write error (unplugged USB: EIO / SerialException) or no scan for `scan_timeout_s`
  closes the port and reopens it with exponential backoff, logged and counted.

`Utm30lxDriver.open()` makes the first connection, which must succeed (otherwise `DriverError`:
wrong port, not a SCIP 2.0 device); `scans(stop)` then yields `DeviceScan`s until `stop` is set,
retrying later losses forever; `close()` switches the laser off and closes the port.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np
import numpy.typing as npt
import serial

from clients.wire import Scan
from sensor_agent.errors import DriverError
from sensor_agent.scip import commands as cmds
from sensor_agent.scip.codec import (
    CommandOk,
    Discarded,
    Event,
    ReplyError,
    ScanData,
    ScanStarted,
    ScipCodec,
    SensorParameters,
    SensorState,
    VersionInfo,
)
from sensor_agent.scip.commands import Command
from sensor_agent.scip.errors import (
    ChecksumError,
    DeviceStateError,
    MalformedReplyError,
    StatusError,
)

log = logging.getLogger(__name__)

_READ_CHUNK: Final = 4096


@dataclass(frozen=True, slots=True)
class DriverConfig:
    read_timeout_s: float = 0.05  # one blocking read; bounds how fast `stop` is noticed
    command_timeout_s: float = 0.5  # per attempt, during start-up
    command_retries: int = 2
    scan_timeout_s: float = 1.0  # no scan for this long while streaming: reopen the port
    max_consecutive_errors: int = 10  # failed replies in a row before the stream is restarted
    backoff_initial_s: float = 0.1
    backoff_max_s: float = 1.0
    intensity: bool = False  # ME (distance + intensity) instead of MD
    cluster: int = 1
    start_step: int | None = None  # None = AMIN
    end_step: int | None = None  # None = AMAX


@dataclass(frozen=True, slots=True)
class DeviceInfo:
    """What the device said about itself (VV, PP, II) at the last connection."""

    vendor: str
    product: str
    firmware: str
    protocol: str
    serial_number: str
    model: str
    dmin_mm: int
    dmax_mm: int
    ares: int
    amin: int
    amax: int
    afrt: int
    scan_rpm: int
    state: dict[str, str] = field(default_factory=dict)

    @property
    def scan_period_s(self) -> float:
        return 60.0 / self.scan_rpm if self.scan_rpm > 0 else 0.025

    def step_angle_rad(self, step: float) -> float:
        """Angle of `step` in the laser frame: (step - AFRT) * 2π / ARES, counter-clockwise."""
        return (step - self.afrt) * 2.0 * math.pi / self.ares


@dataclass(slots=True)
class DriverCounters:
    scans: int = 0  # good scans delivered
    checksum_errors: int = 0  # replies dropped for a bad checksum
    malformed_replies: int = 0  # replies dropped for a wrong shape
    status_errors: int = 0  # error statuses from the device
    discarded_frames: int = 0  # bytes that answered nothing we asked (garbage, resync)
    stream_restarts: int = 0
    link_losses: int = 0  # an open connection failed (unplugged, I/O error, no scans)
    reopen_failures: int = 0  # attempts to reopen that failed (device still absent)
    reconnects: int = 0  # successful reopenings
    timeouts: int = 0  # no scan within scan_timeout_s

    @property
    def device_errors(self) -> int:
        return (
            self.checksum_errors
            + self.malformed_replies
            + self.status_errors
            + self.discarded_frames
        )

    def as_dict(self) -> dict[str, int]:
        return {
            "scans": self.scans,
            "checksum_errors": self.checksum_errors,
            "malformed_replies": self.malformed_replies,
            "status_errors": self.status_errors,
            "discarded_frames": self.discarded_frames,
            "stream_restarts": self.stream_restarts,
            "link_losses": self.link_losses,
            "reopen_failures": self.reopen_failures,
            "reconnects": self.reconnects,
            "timeouts": self.timeouts,
        }


@dataclass(frozen=True, slots=True, eq=False)
class DeviceScan:
    """One scan as the device sent it, with its geometry.

    `ranges_mm` (N,) uint32 keeps the raw values: anything below DMIN is a device error code
    (UTM-30LX: 1 no object, 2 too near, 3 measurement error, 4 out of range, 5 other).
    """

    ranges_mm: npt.NDArray[np.uint32]
    intensities: npt.NDArray[np.uint32] | None
    sensor_stamp_ns: int  # the device clock, unwrapped and continued across reconnects
    host_stamp_ns: int  # time.time_ns() when the reply was complete
    timestamp_raw_ms: int  # the 24-bit counter as sent
    angle_min_rad: float
    angle_increment_rad: float
    dmin_mm: int
    dmax_mm: int

    def valid_mask(self) -> npt.NDArray[np.bool_]:
        return (self.ranges_mm >= self.dmin_mm) & (self.ranges_mm <= self.dmax_mm)

    def to_wire(self, robot_id: str, seq: int = 0) -> Scan:
        """The wire message; error codes travel as they are (millimetres below DMIN)."""
        return Scan(
            robot_id=robot_id,
            seq=seq,
            sensor_stamp_ns=self.sensor_stamp_ns,
            host_stamp_ns=self.host_stamp_ns,
            angle_min_rad=self.angle_min_rad,
            angle_increment_rad=self.angle_increment_rad,
            range_min_m=self.dmin_mm / 1000.0,
            range_max_m=self.dmax_mm / 1000.0,
            ranges_m=self.ranges_mm.astype(np.float64) / 1000.0,
            intensities=None if self.intensities is None else self.intensities.astype(np.float32),
        )


class _LinkLostError(Exception):
    """Internal: the port must be closed and reopened."""


OpenFn = Callable[..., Any]


class Utm30lxDriver:
    """Reads a UTM-30LX (or anything speaking SCIP 2.0 alike) at `url`."""

    def __init__(
        self,
        url: str,
        config: DriverConfig | None = None,
        *,
        open_fn: OpenFn = serial.serial_for_url,
    ) -> None:
        self.url = url
        self.config = config or DriverConfig()
        self.counters = DriverCounters()
        self.device_info: DeviceInfo | None = None
        self.connected = threading.Event()
        self._open_fn = open_fn
        self._port: Any = None
        self._codec = ScipCodec()
        self._stream_cmd: Command | None = None
        # Sensor clock continuity across reconnects (RS restarts the device counter).
        self._clock_offset_ms = 0
        self._rebase = False
        self._last_sensor_ms: int | None = None
        self._last_host_ns = 0

    # -- public ------------------------------------------------------------------------------

    def open(self) -> None:
        """Connect and start streaming; `DriverError` if the device cannot be opened or does
        not answer like a SCIP 2.0 sensor. Later losses are handled inside `scans()`."""
        if self._port is None:
            self._connect()

    def close(self) -> None:
        """Laser off (best effort) and close the port."""
        self._shutdown()

    def scans(self, stop: threading.Event) -> Iterator[DeviceScan]:
        """Yield scans until `stop` is set, reconnecting as needed (opens first if needed)."""
        cfg = self.config
        self.open()
        backoff = cfg.backoff_initial_s
        failures = 0  # reopen attempts since the link was lost
        while not stop.is_set():
            try:
                if self._port is None:
                    self._connect()
                    self.counters.reconnects += 1
                    log.info("reconnected to %s", self.url)
                for scan in self._stream(stop):
                    backoff = cfg.backoff_initial_s
                    yield scan
            except (_LinkLostError, DriverError, serial.SerialException, OSError) as err:
                if self._port is not None:
                    self.counters.link_losses += 1
                    failures = 0
                    log.warning("%s: link lost: %s", self.url, _describe(err))
                else:
                    self.counters.reopen_failures += 1
                    failures += 1
                    # 1st, 2nd, 4th, 8th... failure: an absent device does not flood the log.
                    level = logging.INFO if failures & (failures - 1) == 0 else logging.DEBUG
                    log.log(
                        level,
                        "%s: still unavailable (%d attempts): %s",
                        self.url,
                        failures,
                        _describe(err),
                    )
                self._close()
                log.debug("reopening %s in %.1f s", self.url, backoff)
                stop.wait(backoff)
                backoff = min(2.0 * backoff, cfg.backoff_max_s)

    # -- connection --------------------------------------------------------------------------

    def _connect(self) -> None:
        cfg = self.config
        try:
            # exclusive: a second agent (or urg_node) on the same port fails clearly at open.
            self._port = self._open_fn(
                self.url,
                baudrate=115200,  # ignored over USB CDC-ACM and TCP
                timeout=cfg.read_timeout_s,
                write_timeout=1.0,
                exclusive=True,
            )
        except (serial.SerialException, OSError, ValueError) as err:
            raise DriverError(f"cannot open {self.url}: {_describe(err)}") from err
        try:
            self._codec.reset()
            self._port.reset_input_buffer()
            self._handshake()
        except (serial.SerialException, OSError) as err:
            self._close()
            raise DriverError(f"{self.url}: {_describe(err)}") from err
        except DriverError:
            self._close()
            raise
        self._rebase = True
        self.connected.set()

    def _handshake(self) -> None:
        # QT stops a stream left running by a previous host; its scans are discarded by echo.
        if self._request(cmds.qt()) is None:
            raise DriverError(f"no SCIP 2.0 reply from {self.url} (is it a Hokuyo laser?)")
        rs = self._request(cmds.rs())
        if isinstance(rs, ReplyError) and isinstance(rs.error, DeviceStateError):
            self._request(cmds.tm(2))  # left in time-adjust mode: leave it, then reset
            rs = self._request(cmds.rs())
        if not isinstance(rs, CommandOk):
            raise DriverError(f"{self.url}: reset (RS) failed: {_reply_text(rs)}")
        pp = self._request(cmds.pp())
        if not isinstance(pp, SensorParameters):
            raise DriverError(f"{self.url}: no sensor parameters (PP): {_reply_text(pp)}")
        vv = self._request(cmds.vv())
        ii = self._request(cmds.ii())
        version = vv if isinstance(vv, VersionInfo) else None
        if version is None:
            log.warning("%s: no version information (VV): %s", self.url, _reply_text(vv))
        first = self.device_info is None
        self.device_info = DeviceInfo(
            vendor=version.vendor if version else "",
            product=version.product if version else "",
            firmware=version.firmware if version else "",
            protocol=version.protocol if version else "",
            serial_number=version.serial if version else "",
            model=pp.model,
            dmin_mm=pp.dmin_mm,
            dmax_mm=pp.dmax_mm,
            ares=pp.ares,
            amin=pp.amin,
            amax=pp.amax,
            afrt=pp.afrt,
            scan_rpm=pp.scan_rpm,
            state=ii.fields if isinstance(ii, SensorState) else {},
        )
        if first:
            i = self.device_info
            log.info(
                "%s: %s (model %s) serial %s, firmware %s, %s; steps %d..%d front %d, %d rpm",
                self.url,
                i.product or "unknown product",
                i.model,
                i.serial_number or "?",
                i.firmware or "?",
                i.protocol or "?",
                i.amin,
                i.amax,
                i.afrt,
                i.scan_rpm,
            )
        bm = self._request(cmds.bm())
        if not isinstance(bm, CommandOk):
            raise DriverError(f"{self.url}: laser on (BM) failed: {_reply_text(bm)}")
        self._start_stream()

    def _scan_command(self) -> Command:
        info = self.device_info
        assert info is not None
        cfg = self.config
        start = info.amin if cfg.start_step is None else cfg.start_step
        end = info.amax if cfg.end_step is None else cfg.end_step
        build = cmds.me if cfg.intensity else cmds.md
        return build(start, end, cfg.cluster)

    def _start_stream(self) -> None:
        self._stream_cmd = self._scan_command()
        self._write(self._codec.send(self._stream_cmd))

    def _request(self, command: Command) -> Event | None:
        """Send `command` and wait for its reply (retrying); None if it never came."""
        cfg = self.config
        for _attempt in range(cfg.command_retries + 1):
            self._write(self._codec.send(command))
            reply = self._await_reply(command, time.monotonic() + cfg.command_timeout_s)
            if reply is not None:
                return reply
            self._codec.clear_pending()
        return None

    def _await_reply(self, command: Command, deadline: float) -> Event | None:
        """The reply to `command`; None on timeout or if it arrived garbled (ask again)."""
        while time.monotonic() < deadline:
            for ev in self._codec.receive(self._read()):
                if isinstance(ev, Discarded):
                    self.counters.discarded_frames += 1
                elif getattr(ev, "command", None) is command:
                    if isinstance(ev, ReplyError) and not isinstance(ev.error, StatusError):
                        self._count_error(ev)
                        return None
                    return ev
        return None

    def _close(self) -> None:
        self.connected.clear()
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError) as err:
                log.debug("closing %s: %s", self.url, err)

    def _shutdown(self) -> None:
        """Laser off (best effort) and close the port."""
        if self._port is not None:
            try:
                self._write(cmds.qt().encode())
                self._port.flush()
            except (serial.SerialException, OSError) as err:
                log.debug("QT at shutdown failed: %s", err)
        self._close()

    # -- IO ----------------------------------------------------------------------------------

    def _read(self) -> bytes:
        port = self._port
        if port is None:
            raise _LinkLostError("port closed")
        data: bytes = port.read(min(_READ_CHUNK, max(1, port.in_waiting)))
        return data

    def _write(self, data: bytes) -> None:
        port = self._port
        if port is None:
            raise _LinkLostError("port closed")
        port.write(data)

    # -- streaming ---------------------------------------------------------------------------

    def _stream(self, stop: threading.Event) -> Iterator[DeviceScan]:
        cfg = self.config
        consecutive = 0
        last_scan = time.monotonic()
        restart_qt: Command | None = None
        while not stop.is_set():
            data = self._read()
            host_ns = time.time_ns()
            for ev in self._codec.receive(data):
                if isinstance(ev, ScanData):
                    consecutive = 0
                    last_scan = time.monotonic()
                    yield self._device_scan(ev, host_ns)
                elif isinstance(ev, ReplyError):
                    if restart_qt is not None and ev.command is restart_qt:
                        restart_qt = None  # a garbled QT reply still means QT was done
                        self._start_stream()
                        continue
                    self._count_error(ev)
                    consecutive += 1
                elif isinstance(ev, Discarded):
                    self.counters.discarded_frames += 1
                    consecutive += 1
                    log.debug("discarded %d bytes: %s", len(ev.frame), ev.reason)
                elif isinstance(ev, CommandOk) and restart_qt is not None:
                    if ev.command is restart_qt:
                        restart_qt = None
                        self._start_stream()
                elif isinstance(ev, ScanStarted):
                    log.debug("stream started: %r", ev.command.line)
            if consecutive >= cfg.max_consecutive_errors and restart_qt is None:
                self.counters.stream_restarts += 1
                log.warning(
                    "%s: %d failed replies in a row; restarting the stream", self.url, consecutive
                )
                consecutive = 0
                last_scan = time.monotonic()
                restart_qt = cmds.qt()
                self._write(self._codec.send(restart_qt))
            if time.monotonic() - last_scan > cfg.scan_timeout_s:
                self.counters.timeouts += 1
                raise _LinkLostError(f"no scan for {cfg.scan_timeout_s:.1f} s")

    def _count_error(self, ev: ReplyError) -> None:
        err = ev.error
        if isinstance(err, ChecksumError):
            self.counters.checksum_errors += 1
        elif isinstance(err, MalformedReplyError):
            self.counters.malformed_replies += 1
        elif isinstance(err, StatusError):
            self.counters.status_errors += 1
        else:
            self.counters.malformed_replies += 1
        log.debug("%r: %s", ev.echo[:20], err)

    def _device_scan(self, ev: ScanData, host_ns: int) -> DeviceScan:
        info = self.device_info
        assert info is not None
        assert ev.command.scan is not None
        if self._rebase:
            # First scan after (re)connecting: RS restarted the device counter, so continue
            # from the last published stamp plus the host time that passed.
            self._rebase = False
            if self._last_sensor_ms is not None:
                gap_ms = max(1, (host_ns - self._last_host_ns) // 1_000_000)
                self._clock_offset_ms = self._last_sensor_ms + gap_ms - ev.timestamp_ms
        sensor_ms = ev.timestamp_ms + self._clock_offset_ms
        self._last_sensor_ms = sensor_ms
        self._last_host_ns = host_ns
        self.counters.scans += 1
        req = ev.command.scan
        return DeviceScan(
            ranges_mm=ev.ranges_mm,
            intensities=ev.intensities,
            sensor_stamp_ns=sensor_ms * 1_000_000,
            host_stamp_ns=host_ns,
            timestamp_raw_ms=ev.timestamp_raw_ms,
            angle_min_rad=info.step_angle_rad(req.start_step),
            angle_increment_rad=req.effective_cluster * 2.0 * math.pi / info.ares,
            dmin_mm=info.dmin_mm,
            dmax_mm=info.dmax_mm,
        )


def _describe(err: BaseException) -> str:
    """One short line; pyserial wraps the OSError that says what really happened."""
    cause = err.__cause__ or err.__context__
    if "exclusively lock" in str(err):
        return "the port is in use by another program (it could not be locked)"
    if isinstance(err, serial.SerialException) and isinstance(cause, OSError) and cause.strerror:
        return cause.strerror
    if isinstance(err, OSError) and err.strerror:
        return err.strerror
    text = str(err) or type(err).__name__
    return text.splitlines()[0]


def _reply_text(ev: Event | None) -> str:
    if ev is None:
        return "no reply"
    if isinstance(ev, ReplyError):
        return str(ev.error)
    return type(ev).__name__


__all__ = [
    "DeviceInfo",
    "DeviceScan",
    "DriverConfig",
    "DriverCounters",
    "Utm30lxDriver",
]
