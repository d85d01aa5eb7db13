"""Scan sources: log replay (pacing, stop, errors) and the emulator source."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import dataset_path

from clients.recording import RecordingWriter
from clients.wire import Scan, encode_scan
from sensor_agent.errors import SourceError
from sensor_agent.scene import RectangleRoom
from sensor_agent.sources import EmulatorSource, ReplaySource

T0_NS = 1_700_000_000_000_000_000


def write_mrec(path: Path, gaps_ms: list[int]) -> list[Scan]:
    scans = []
    t = T0_NS
    for i, gap in enumerate([0, *gaps_ms]):
        t += gap * 1_000_000
        scans.append(
            Scan(
                robot_id="recorded-bot",
                seq=100 + i,
                sensor_stamp_ns=t - T0_NS,
                host_stamp_ns=t,
                angle_min_rad=-1.5,
                angle_increment_rad=0.01,
                range_min_m=0.02,
                range_max_m=30.0,
                ranges_m=np.full(301, 2.0 + i / 1000.0),
            )
        )
    writer = RecordingWriter(path)
    for s in scans:
        writer.append(encode_scan(s))
    writer.close()
    return scans


def test_replay_as_fast_as_possible_keeps_stamps_and_order(tmp_path: Path) -> None:
    recorded = write_mrec(tmp_path / "log.mrec", [1000] * 9)  # 9 s of log
    source = ReplaySource(tmp_path / "log.mrec", "bot-2", rate=0)
    source.open()
    got = list(source.scans(threading.Event()))
    source.close()
    assert [s.host_stamp_ns for s in got] == [s.host_stamp_ns for s in recorded]
    np.testing.assert_array_equal(got[4].ranges_m, recorded[4].ranges_m)
    assert source.stats()["replayed"] == 10


def test_replay_at_recorded_speed_is_paced(tmp_path: Path) -> None:
    write_mrec(tmp_path / "log.mrec", [50] * 10)  # 0.5 s of log
    source = ReplaySource(tmp_path / "log.mrec", "bot-2", rate=1.0)
    t0 = time.monotonic()
    got = list(source.scans(threading.Event()))
    assert len(got) == 11
    assert time.monotonic() - t0 >= 0.45  # a lower bound only: load can only slow it down
    fast = ReplaySource(tmp_path / "log.mrec", "bot-2", rate=5.0)
    t0 = time.monotonic()
    assert len(list(fast.scans(threading.Event()))) == 11
    assert time.monotonic() - t0 >= 0.09


def test_stop_interrupts_a_long_wait(tmp_path: Path) -> None:
    write_mrec(tmp_path / "log.mrec", [3_600_000])  # the second scan is due in an hour
    source = ReplaySource(tmp_path / "log.mrec", "bot-2", rate=1.0)
    stop = threading.Event()
    threading.Timer(0.2, stop.set).start()
    assert len(list(source.scans(stop))) == 1


def test_replay_errors_are_source_errors(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="no such file"):
        ReplaySource(tmp_path / "missing.bag", "bot-2")
    (tmp_path / "junk.bin").write_bytes(b"not a log")
    with pytest.raises(SourceError, match="not a ROS 1 bag"):
        ReplaySource(tmp_path / "junk.bin", "bot-2")
    write_mrec(tmp_path / "ok.mrec", [])
    with pytest.raises(SourceError, match="rate"):
        ReplaySource(tmp_path / "ok.mrec", "bot-2", rate=-1)


@pytest.mark.datasets
def test_replay_of_a_real_damaged_ros1_bag() -> None:
    bag = dataset_path("urg-04lx-demo", "laser_scan_matcher_demo.bag")
    source = ReplaySource(bag, "urg-bot", rate=0)
    got = list(source.scans(threading.Event()))
    assert len(got) == 360
    assert {s.robot_id for s in got} == {"urg-bot"}
    assert np.all(np.diff([s.host_stamp_ns for s in got]) >= 0)


def test_emulator_source_goes_through_the_real_driver() -> None:
    source = EmulatorSource("emu-bot", scene=RectangleRoom(seed=3))
    stop = threading.Event()
    got: list[Scan] = []
    source.open()
    try:
        for scan in source.scans(stop):
            got.append(scan)
            if len(got) == 5:
                stop.set()
        assert source.driver.device_info is not None
        stats = source.stats()
        assert stats["scans"] == 5
        assert stats["emulator_sent"] >= 5
    finally:
        source.close()
    assert not source._dir.exists()
    assert {s.robot_id for s in got} == {"emu-bot"}
    assert got[0].beam_count == 1081
    assert got[0].range_min_m == pytest.approx(0.023)
