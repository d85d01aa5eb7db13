"""The UTM-30LX emulator: the device state machine (no IO), its pty/TCP links and faults."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import serial
from conftest import wait_for

from sensor_agent.emulator import (
    Emulator,
    FaultConfig,
    ScanRecorder,
    Utm30lxDevice,
    _cluster_min,
    read_sent_scans,
)
from sensor_agent.errors import EmulatorError
from sensor_agent.scene import UTM_STEPS, RectangleRoom, SceneScan, WorldScene, make_scene
from sensor_agent.scip import (
    ChecksumError,
    CommandOk,
    CommandRejectedError,
    DeviceStateError,
    LaserOffError,
    ParameterError,
    ReplyError,
    ScanData,
    ScanStarted,
    ScipCodec,
    SensorParameters,
    SensorState,
    TimeReply,
    UndefinedCommandError,
    VersionInfo,
)
from sensor_agent.scip import commands as c
from sensor_agent.scip.commands import Command

PERIOD = 0.025


class Bench:
    """A device driven by hand: fake clock, real codec."""

    def __init__(self, faults: FaultConfig | None = None, offset_ms: int = 0) -> None:
        self.now = 100.0
        self.device = Utm30lxDevice(
            RectangleRoom(seed=1), now_s=self.now, faults=faults, timestamp_offset_ms=offset_ms
        )
        self.codec = ScipCodec()

    def ask(self, cmd: Command) -> list[object]:
        return list(self.codec.receive(self.device.receive(self.codec.send(cmd), self.now)))

    def raw(self, line: bytes, echo: Command | None = None) -> list[object]:
        if echo is not None:
            self.codec.send(echo)
        return list(self.codec.receive(self.device.receive(line, self.now)))

    def advance(self, seconds: float) -> list[object]:
        self.now += seconds
        out: list[object] = []
        for frame in self.device.tick(self.now):
            out += self.codec.receive(frame.data)
        return out


def only(events: list[object]) -> object:
    assert len(events) == 1, events
    return events[0]


def test_information_commands() -> None:
    b = Bench()
    vv = only(b.ask(c.vv()))
    assert isinstance(vv, VersionInfo)
    assert vv.product == "SOKUIKI Sensor TOP-URG UTM-30LX"
    assert vv.protocol == "SCIP 2.0"
    pp = only(b.ask(c.pp()))
    assert isinstance(pp, SensorParameters)
    assert (pp.model, pp.dmin_mm, pp.dmax_mm, pp.ares) == ("UTM-30LX", 23, 60000, 1440)
    assert (pp.amin, pp.amax, pp.afrt, pp.scan_rpm) == (0, 1080, 540, 2400)
    ii = only(b.ask(c.ii()))
    assert isinstance(ii, SensorState)
    assert ii.laser_on is False
    assert ii.status_text.startswith("Stable")


def test_kv_checksums_exclude_the_semicolon() -> None:
    b = Bench()
    reply = b.device.receive(b"PP\n", b.now)
    for line in reply.split(b"\n")[2:-2]:
        body, total = line[:-2], line[-1]
        assert line[-2:-1] == b";"
        assert (sum(body) & 0x3F) + 0x30 == total


@pytest.mark.parametrize(
    ("line", "status", "cls"),
    [
        (b"XX", "0E", UndefinedCommandError),
        (b"SCIP2.0", "0E", UndefinedCommandError),  # the UTM-30LX is SCIP 2.0 native
        (b"BMX", "0D", CommandRejectedError),
        (b"MD0000108001", "0C", CommandRejectedError),
        (b"VV;" + b"a" * 17, "0G", CommandRejectedError),
        (b"VV;a#b", "0H", CommandRejectedError),
        (b"MDx000108001000", "01", ParameterError),
        (b"MD0000x08001000", "02", ParameterError),
        (b"MD00001080x1000", "03", ParameterError),
        (b"MD000010800100x", "07", ParameterError),
        (b"MD0000108001x00", "06", ParameterError),
        (b"MD0000108101000", "04", ParameterError),
        (b"MD0100005001000", "05", ParameterError),
        (b"GD0000108001", "10", LaserOffError),  # GD needs the laser on
        (b"TM1", "04", DeviceStateError),
        (b"TM2", "03", DeviceStateError),
        (b"TM9", "01", ParameterError),
    ],
)
def test_error_statuses(line: bytes, status: str, cls: type) -> None:
    b = Bench()
    ev = only(b.raw(line + b"\n", c.raw(line)))
    assert isinstance(ev, ReplyError)
    assert type(ev.error) is cls
    assert ev.error.status == status


def test_line_endings_and_empty_lines() -> None:
    b = Bench()
    assert b.device.receive(b"\n\r\n", b.now) == b""
    assert b.device.receive(b"QT\r\n", b.now) == b"QT\n00P\n\n"
    assert b.device.receive(b"QT\r", b.now) == b"QT\n00P\n\n"


def test_time_adjust_mode() -> None:
    b = Bench()
    assert isinstance(only(b.ask(c.tm(0))), CommandOk)
    ev = only(b.ask(c.tm(0)))
    assert isinstance(ev, ReplyError)
    assert ev.error.status == "02"
    b.now += 1.234
    t = only(b.ask(c.tm(1)))
    assert isinstance(t, TimeReply)
    assert t.timestamp_ms == 1234
    refused = only(b.ask(c.md(0, 1080)))
    assert isinstance(refused, ReplyError)
    assert refused.error.status == "10"
    assert isinstance(only(b.ask(c.tm(2))), CommandOk)


def test_bm_twice_and_gd() -> None:
    b = Bench()
    assert isinstance(only(b.ask(c.bm())), CommandOk)
    again = only(b.ask(c.bm()))
    assert isinstance(again, CommandOk)
    assert again.status == "02"
    b.advance(0.1)
    scan = only(b.ask(c.gd(0, 1080, 3)))
    assert isinstance(scan, ScanData)
    assert scan.ranges_mm.shape == (361,)


def test_finite_md_with_skipped_scans() -> None:
    b = Bench()
    assert isinstance(only(b.ask(c.md(0, 1080, interval=1, nscans=3))), ScanStarted)
    assert b.device.laser_on
    scans: list[ScanData] = []
    for _ in range(12):
        scans += [e for e in b.advance(PERIOD) if isinstance(e, ScanData)]
    assert [s.remaining for s in scans] == [2, 1, 0]
    assert [s.timestamp_raw_ms for s in scans] == [0, 50, 100]  # every other scan
    assert not b.device.streaming
    assert not b.device.laser_on  # MD switched it on, so it goes off again


def test_unlimited_me_stream_and_qt() -> None:
    b = Bench()
    b.ask(c.me(0, 1080))
    events = b.advance(0.1)
    scans = [e for e in events if isinstance(e, ScanData)]
    assert len(scans) == 4
    assert all(s.intensities is not None and s.intensities.shape == (1081,) for s in scans)
    assert [s.timestamp_ms for s in scans] == [0, 25, 50, 75]
    assert isinstance(only(b.ask(c.qt())), CommandOk)
    assert b.advance(0.1) == []


def test_catching_up_is_bounded() -> None:
    b = Bench()
    b.ask(c.md(0, 1080))
    events = b.advance(10.0)  # the loop was descheduled for 10 s
    assert 1 <= len(events) <= 5


def test_timestamps_wrap_at_24_bits() -> None:
    b = Bench(offset_ms=(1 << 24) - 60)
    b.ask(c.md(540, 540))
    scans = [e for _ in range(8) for e in b.advance(PERIOD) if isinstance(e, ScanData)]
    raws = [s.timestamp_raw_ms for s in scans]
    assert raws[0] > raws[-1]  # wrapped
    stamps = [s.timestamp_ms for s in scans]
    assert np.all(np.diff(stamps) == 25)


def test_rs_resets_the_timestamp() -> None:
    b = Bench()
    b.now += 5.0
    b.device.tick(b.now)
    b.ask(c.rs())
    b.ask(c.md(540, 540))
    scans = [e for e in b.advance(0.1) if isinstance(e, ScanData)]
    assert scans[0].timestamp_raw_ms < 100


@pytest.mark.parametrize("before_boundary_s", [0.0005, 0.0124, 0.0249])
def test_a_stream_after_rs_never_stamps_two_scans_alike(before_boundary_s: float) -> None:
    """The scan under way at RS + MD began before the reset; streaming it would stamp it 0 ms,
    and the next scan too when the reset came within 1 ms of its start (CI failed on that:
    the agent saw one stamp twice). A stream starts with the first scan after the command."""
    b = Bench()
    b.now += 5.0 + PERIOD - before_boundary_s  # scans start at 100 s + k * PERIOD
    b.device.tick(b.now)
    b.ask(c.rs())
    b.ask(c.md(540, 540))
    scans = [e for _ in range(8) for e in b.advance(PERIOD) if isinstance(e, ScanData)]
    stamps = [s.timestamp_ms for s in scans]
    assert len(stamps) >= 6
    assert stamps[0] == math.floor(before_boundary_s * 1000.0 + 1e-6)
    assert np.all(np.diff(stamps) == 25), stamps


def test_cluster_minimum_skips_error_codes() -> None:
    values = np.array([5, 100, 50, 3, 1, 2, 700], dtype=np.uint32)
    assert _cluster_min(values, 2).tolist() == [100, 50, 1, 700]
    assert _cluster_min(values, 3).tolist() == [50, 3, 700]  # all errors: the first
    assert _cluster_min(values, 1).tolist() == values.tolist()


def test_corrupted_lines_are_exactly_the_rejected_scans() -> None:
    b = Bench(FaultConfig(corrupt_line_prob=0.02, seed=3))
    b.ask(c.md(0, 1080))
    corrupted = delivered = 0
    for _ in range(60):
        b.now += PERIOD
        for frame in b.device.tick(b.now):
            events = b.codec.receive(frame.data)
            got_scan = any(isinstance(e, ScanData) for e in events)
            assert got_scan != frame.corrupted
            if frame.corrupted:
                assert any(
                    isinstance(e, ReplyError) and isinstance(e.error, ChecksumError) for e in events
                )
            corrupted += frame.corrupted
            delivered += got_scan
    assert corrupted > 0
    assert delivered > 0
    assert b.device.stats.corrupted_lines >= corrupted


def test_garbage_precedes_flagged_scans() -> None:
    b = Bench(FaultConfig(garbage_prob=0.5, seed=4))
    b.ask(c.md(0, 1080))
    b.now += 1.0
    frames = []
    for _ in range(40):
        b.now += PERIOD
        frames += b.device.tick(b.now)
    flagged = [f for f in frames if f.garbage]
    assert flagged
    assert all(not f.data.startswith(b"MD") for f in flagged)
    assert all(f.data.startswith(b"MD") for f in frames if not f.garbage)


def test_scenes_are_deterministic() -> None:
    room = RectangleRoom(seed=2)
    a, b = room.scan(10), RectangleRoom(seed=2).scan(10)
    assert isinstance(a, SceneScan)
    assert a.ranges_mm.shape == (UTM_STEPS,)
    assert a.ranges_mm.dtype == np.uint32
    np.testing.assert_array_equal(a.ranges_mm, b.ranges_mm)
    assert not np.array_equal(a.ranges_mm, room.scan(11).ranges_mm)
    world = make_scene(5)
    assert isinstance(world, WorldScene)
    w = world.scan(3)
    np.testing.assert_array_equal(w.ranges_mm, WorldScene(5).scan(3).ranges_mm)
    assert int(w.ranges_mm.max()) <= 60000


# -- links ----------------------------------------------------------------------------------------


@pytest.fixture
def emu_dir() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="sa-emu-") as d:
        yield Path(d)


def start_emulator(d: Path, faults: FaultConfig | None = None) -> Emulator:
    device = Utm30lxDevice(RectangleRoom(seed=1), now_s=time.monotonic(), faults=faults)
    return Emulator(device, link_path=d / "tty", recorder=ScanRecorder(d / "sent.rec")).start()


def read_events(
    port: serial.Serial, codec: ScipCodec, until: Callable[[list[object]], bool]
) -> list[object]:
    events: list[object] = []
    deadline = time.monotonic() + 10
    while not until(events):
        assert time.monotonic() < deadline, f"not seen in time: {events[-3:]}"
        events += codec.receive(port.read(max(1, port.in_waiting)))
    return events


def test_pty_round_trip_and_recording(emu_dir: Path) -> None:
    with start_emulator(emu_dir):
        assert (emu_dir / "tty").is_symlink()
        port = serial.serial_for_url(str(emu_dir / "tty"), timeout=0.05)
        codec = ScipCodec()
        port.write(codec.send(c.vv()) + codec.send(c.md(0, 1080)))
        events = read_events(port, codec, lambda ev: sum(isinstance(e, ScanData) for e in ev) >= 10)
        port.close()
    assert isinstance(events[0], VersionInfo)
    scans = [e for e in events if isinstance(e, ScanData)]
    sent = {s.timestamp_ms: s for s in read_sent_scans(emu_dir / "sent.rec")}
    for s in scans:
        np.testing.assert_array_equal(s.ranges_mm, sent[s.timestamp_raw_ms].ranges_mm)
    assert not (emu_dir / "tty").exists()  # stop() removes the link


def test_a_stalled_host_makes_the_emulator_drop_scans_not_block(emu_dir: Path) -> None:
    with start_emulator(emu_dir) as emu:
        port = serial.serial_for_url(str(emu_dir / "tty"), timeout=0.05)
        codec = ScipCodec()
        port.write(codec.send(c.md(0, 1080)))
        wait_for(
            lambda: emu.stats.scans_dropped >= 10, 10, "10 dropped scans"
        )  # nobody reads: the pty fills up
        # The device still answers and streams once the host reads again.
        port.reset_input_buffer()
        codec.receive(b"\n\n")
        port.write(codec.send(c.vv()))
        events = read_events(
            port,
            codec,
            lambda ev: (
                any(isinstance(e, VersionInfo) for e in ev)
                and sum(isinstance(e, ScanData) for e in ev) >= 3
            ),
        )
        port.close()
    assert sum(isinstance(e, ScanData) for e in events) >= 3


def read_until_error(port: serial.Serial, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        port.read(1)


def test_unplug_removes_and_recreates_the_link(emu_dir: Path) -> None:
    with start_emulator(emu_dir) as emu:
        link = emu_dir / "tty"
        port = serial.serial_for_url(str(link), timeout=0.05)
        emu.unplug(0.3)
        wait_for(lambda: not link.exists(), 10, "the link to go")
        with pytest.raises(serial.SerialException):
            read_until_error(port)  # EIO: the device is gone
        port.close()
        assert emu.replugged.wait(5)
        assert link.is_symlink()
        port = serial.serial_for_url(str(link), timeout=0.05)
        codec = ScipCodec()
        port.write(codec.send(c.pp()))
        events = read_events(
            port, codec, lambda ev: any(isinstance(e, SensorParameters) for e in ev)
        )
        port.close()
        assert emu.stats.unplugs == 1
        assert emu.stats.links == 2
        assert events


def test_stall_silences_the_device(emu_dir: Path) -> None:
    with start_emulator(emu_dir) as emu:
        port = serial.serial_for_url(str(emu_dir / "tty"), timeout=0.05)
        codec = ScipCodec()
        port.write(codec.send(c.md(0, 1080)))
        read_events(port, codec, lambda ev: any(isinstance(e, ScanData) for e in ev))
        emu.stall(0.5)
        wait_for(lambda: emu.stats.stalls == 1, 10, "one stall")
        t0 = time.monotonic()
        events = read_events(port, codec, lambda ev: any(isinstance(e, ScanData) for e in ev))
        port.close()
        assert emu.stats.scans_dropped > 0
        assert events
        assert time.monotonic() - t0 > 0.2  # scans in flight, then nothing until the stall ends


def test_tcp_link(emu_dir: Path) -> None:
    from conftest import free_port

    port_no = free_port()
    device = Utm30lxDevice(RectangleRoom(seed=1), now_s=time.monotonic())
    with Emulator(device, tcp_address=("127.0.0.1", port_no)):
        port = serial.serial_for_url(f"socket://127.0.0.1:{port_no}", timeout=0.05)
        codec = ScipCodec()
        port.write(codec.send(c.vv()) + codec.send(c.md(0, 1080)))
        events = read_events(port, codec, lambda ev: sum(isinstance(e, ScanData) for e in ev) >= 3)
        port.close()
    assert isinstance(events[0], VersionInfo)


def test_recording_ignores_a_torn_tail(emu_dir: Path) -> None:
    with start_emulator(emu_dir) as emu:
        port = serial.serial_for_url(str(emu_dir / "tty"), timeout=0.05)
        codec = ScipCodec()
        port.write(codec.send(c.md(0, 1080)))
        wait_for(lambda: emu.stats.scans_sent >= 3, 10, "3 scans sent")
        port.close()
    path = emu_dir / "sent.rec"
    full = read_sent_scans(path)
    assert len(full) >= 3
    with open(path, "ab") as f:
        f.write(b"\x01\x02\x03")
    assert len(read_sent_scans(path)) == len(full)
    path.write_bytes(b"nope")
    with pytest.raises(EmulatorError):
        read_sent_scans(path)


def test_emulator_needs_a_link() -> None:
    device = Utm30lxDevice(RectangleRoom(seed=1), now_s=0.0)
    with pytest.raises(EmulatorError):
        Emulator(device)


def test_emulator_process_rejects_bad_arguments() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "sensor_agent.emulator", "--corrupt-lines", "0.1"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])},
    )
    assert out.returncode == 2
    assert "--link" in out.stderr
