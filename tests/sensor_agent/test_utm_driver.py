"""The UTM-30LX driver against the in-process emulator: start-up, geometry, errors, recovery."""

from __future__ import annotations

import math
import os
import tempfile
import threading
import time
import tty
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import serial
from conftest import free_port, wait_for

from sensor_agent.driver import DeviceScan, DriverConfig, Utm30lxDriver
from sensor_agent.emulator import (
    Emulator,
    FaultConfig,
    ScanRecorder,
    SentScan,
    Utm30lxDevice,
    read_sent_scans,
)
from sensor_agent.errors import DriverError
from sensor_agent.scene import RectangleRoom
from sensor_agent.scip import commands as c

FAST = DriverConfig(command_timeout_s=0.3, scan_timeout_s=0.6, backoff_max_s=0.4)


class Consumer:
    """Runs `driver.scans()` in a thread and keeps everything it yields."""

    def __init__(self, driver: Utm30lxDriver) -> None:
        self.driver = driver
        self.scans: list[DeviceScan] = []
        self.error: BaseException | None = None
        self.stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        try:
            for scan in self.driver.scans(self.stop):
                self.scans.append(scan)
        except BaseException as err:  # reported by the test
            self.error = err

    def __enter__(self) -> Consumer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self._thread.join(5)
        self.driver.close()

    def wait_scans(self, n: int, timeout_s: float = 10.0) -> None:
        def enough() -> bool:
            if self.error is not None:
                pytest.fail(f"driver failed: {self.error!r}")
            return len(self.scans) >= n

        wait_for(enough, timeout_s, f"{n} scans")


class Rig:
    def __init__(self, d: Path, faults: FaultConfig | None = None, tcp: bool = False) -> None:
        self.device = Utm30lxDevice(RectangleRoom(seed=2), now_s=time.monotonic(), faults=faults)
        self.link = d / "tty"
        self.record = d / "sent.rec"
        self.tcp_port = free_port() if tcp else None
        self.emulator = Emulator(
            self.device,
            link_path=None if tcp else self.link,
            tcp_address=("127.0.0.1", self.tcp_port) if self.tcp_port else None,
            recorder=ScanRecorder(self.record),
        ).start()

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.tcp_port}" if self.tcp_port else str(self.link)

    def sent(self) -> dict[int, list[SentScan]]:
        """Sent scans by timestamp; RS restarts the counter, so a timestamp can repeat."""
        by_stamp: dict[int, list[SentScan]] = {}
        for s in read_sent_scans(self.record):
            by_stamp.setdefault(s.timestamp_ms, []).append(s)
        return by_stamp


@pytest.fixture
def tmp() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="sa-drv-") as d:
        yield Path(d)


@pytest.fixture
def rig(tmp: Path) -> Iterator[Rig]:
    r = Rig(tmp)
    yield r
    r.emulator.stop()


def assert_exact(scans: list[DeviceScan], sent: dict[int, list[SentScan]]) -> None:
    """Every delivered scan is bit-exact with an uncorrupted scan the emulator sent."""
    for s in scans:
        matches = [
            rec
            for rec in sent[s.timestamp_raw_ms]
            if not rec.corrupted and np.array_equal(s.ranges_mm, rec.ranges_mm)
        ]
        assert matches, f"scan at {s.timestamp_raw_ms} ms matches nothing the emulator sent"


def test_start_up_device_info_and_geometry(rig: Rig) -> None:
    driver = Utm30lxDriver(rig.url, FAST)
    with Consumer(driver) as consumer:
        consumer.wait_scans(20)
    info = driver.device_info
    assert info is not None
    assert (info.model, info.serial_number, info.protocol) == ("UTM-30LX", "H0900000", "SCIP 2.0")
    assert info.firmware.startswith("1.16")
    assert info.state["LASR"] == "OFF"  # II was read before BM
    scan = consumer.scans[0]
    assert scan.ranges_mm.shape == (1081,)
    assert scan.angle_min_rad == pytest.approx(-3 * math.pi / 4)
    assert scan.angle_increment_rad == pytest.approx(math.radians(0.25))
    assert scan.angle_min_rad + 1080 * scan.angle_increment_rad == pytest.approx(3 * math.pi / 4)
    assert_exact(consumer.scans, rig.sent())
    stamps = [s.sensor_stamp_ns for s in consumer.scans]
    assert np.all(np.diff(stamps) > 0)
    assert driver.counters.scans == len(consumer.scans)
    # Closing switched the laser off.
    wait_for(lambda: not rig.device.streaming, 5, "QT at close")


def test_error_codes_below_dmin_are_kept_and_invalid(rig: Rig) -> None:
    driver = Utm30lxDriver(rig.url, FAST)
    with Consumer(driver) as consumer:
        consumer.wait_scans(40)
    codes = [s for s in consumer.scans if np.any(s.ranges_mm == 3)]
    assert codes, "the room scene has dropouts with the UTM-30LX code 3"
    scan = codes[0]
    mask = scan.valid_mask()
    assert not mask[scan.ranges_mm == 3].any()
    wire = scan.to_wire("bot-1", seq=5)
    assert wire.range_min_m == pytest.approx(0.023)
    np.testing.assert_array_equal(np.rint(wire.ranges_m * 1000).astype(np.uint32), scan.ranges_mm)
    np.testing.assert_array_equal(wire.valid_mask(), mask)


def test_corrupted_scans_are_dropped_and_counted(tmp: Path) -> None:
    rig = Rig(tmp, FaultConfig(corrupt_line_prob=0.01, seed=11))
    try:
        driver = Utm30lxDriver(rig.url, FAST)
        with Consumer(driver) as consumer:
            consumer.wait_scans(40)
        sent = rig.sent()
        assert_exact(consumer.scans, sent)
        got = {s.timestamp_raw_ms for s in consumer.scans}
        lo, hi = min(got), max(got)
        window = [s for ts, group in sent.items() if lo <= ts <= hi for s in group]
        assert got == {s.timestamp_ms for s in window if not s.corrupted}
        assert driver.counters.checksum_errors >= sum(s.corrupted for s in window) > 0
    finally:
        rig.emulator.stop()


def test_garbage_on_the_line_is_survived(tmp: Path) -> None:
    rig = Rig(tmp, FaultConfig(garbage_prob=0.3, seed=12))
    try:
        driver = Utm30lxDriver(rig.url, FAST)
        with Consumer(driver) as consumer:
            consumer.wait_scans(40)
        assert_exact(consumer.scans, rig.sent())
        assert driver.counters.discarded_frames > 0
    finally:
        rig.emulator.stop()


def test_stream_restarts_after_consecutive_errors(rig: Rig) -> None:
    cfg = DriverConfig(
        command_timeout_s=0.3, scan_timeout_s=5.0, backoff_max_s=0.4, max_consecutive_errors=3
    )
    driver = Utm30lxDriver(rig.url, cfg)
    with Consumer(driver) as consumer:
        consumer.wait_scans(5)
        rig.device.faults = FaultConfig(corrupt_line_prob=1.0, seed=1)
        wait_for(lambda: driver.counters.stream_restarts >= 1, 10, "a stream restart")
        rig.device.faults = FaultConfig()
        n = len(consumer.scans)
        consumer.wait_scans(n + 10)
    assert_exact(consumer.scans, rig.sent())
    assert driver.counters.checksum_errors >= 3


def test_reconnects_after_unplug_and_keeps_the_clock_monotonic(rig: Rig) -> None:
    driver = Utm30lxDriver(rig.url, FAST)
    with Consumer(driver) as consumer:
        consumer.wait_scans(10)
        rig.emulator.unplug(0.3)
        wait_for(lambda: driver.counters.link_losses >= 1, 5, "the link loss")
        n = len(consumer.scans)
        consumer.wait_scans(n + 10)
    c_ = driver.counters
    assert c_.reconnects >= 1
    stamps = [s.sensor_stamp_ns for s in consumer.scans]
    assert np.all(np.diff(stamps) > 0)
    hosts = [s.host_stamp_ns for s in consumer.scans]
    assert np.all(np.diff(hosts) >= 0)


def test_a_silent_device_times_out_and_is_reopened(rig: Rig) -> None:
    driver = Utm30lxDriver(rig.url, FAST)
    with Consumer(driver) as consumer:
        consumer.wait_scans(5)
        rig.emulator.stall(1.0)
        wait_for(lambda: driver.counters.timeouts >= 1, 5, "a timeout")
        n = len(consumer.scans)
        consumer.wait_scans(n + 10)
    assert driver.counters.reconnects >= 1


def test_ethernet_model_over_socket_url(tmp: Path) -> None:
    rig = Rig(tmp, tcp=True)
    try:
        driver = Utm30lxDriver(rig.url, FAST)
        with Consumer(driver) as consumer:
            consumer.wait_scans(10)
        assert_exact(consumer.scans, rig.sent())
    finally:
        rig.emulator.stop()


def test_intensity_mode(rig: Rig) -> None:
    driver = Utm30lxDriver(rig.url, DriverConfig(intensity=True, cluster=2))
    with Consumer(driver) as consumer:
        consumer.wait_scans(5)
    scan = consumer.scans[0]
    assert scan.ranges_mm.shape == (541,)
    assert scan.intensities is not None
    assert scan.intensities.shape == (541,)
    assert scan.angle_increment_rad == pytest.approx(math.radians(0.5))
    wire = scan.to_wire("bot-1")
    assert wire.intensities is not None
    assert wire.intensities.dtype == np.float32


def test_a_device_left_streaming_by_another_host(rig: Rig) -> None:
    port = serial.serial_for_url(str(rig.link), timeout=0.05)
    port.write(c.md(0, 1080).encode())
    wait_for(lambda: rig.device.streaming, 5, "the stale stream")
    time.sleep(0.2)  # let stale scans pile up in the pty on purpose
    port.close()
    driver = Utm30lxDriver(rig.url, FAST)
    with Consumer(driver) as consumer:
        consumer.wait_scans(10)
    assert_exact(consumer.scans, rig.sent())


def test_a_missing_device_is_a_driver_error(tmp: Path) -> None:
    driver = Utm30lxDriver(str(tmp / "nothing"), FAST)
    with pytest.raises(DriverError, match="cannot open"):
        driver.open()


def test_a_port_that_does_not_speak_scip_is_a_driver_error() -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        cfg = DriverConfig(command_timeout_s=0.1, command_retries=1)
        driver = Utm30lxDriver(os.ttyname(slave), cfg)
        with pytest.raises(DriverError, match=r"no SCIP 2\.0 reply"):
            driver.open()
        driver.close()
    finally:
        os.close(master)
        os.close(slave)


def test_codec_state_is_fresh_after_reopen(rig: Rig) -> None:
    driver = Utm30lxDriver(rig.url, FAST)
    driver.open()
    driver.close()
    driver.open()  # a second open starts from a clean codec and a clean port
    stop = threading.Event()
    got = []
    for scan in driver.scans(stop):
        got.append(scan)
        if len(got) >= 3:
            stop.set()
    driver.close()
    assert len(got) == 3


def test_a_port_in_use_is_refused_clearly(rig: Rig) -> None:
    first = Utm30lxDriver(rig.url, FAST)
    first.open()
    try:
        with pytest.raises(DriverError, match="in use by another program"):
            Utm30lxDriver(rig.url, FAST).open()
    finally:
        first.close()
