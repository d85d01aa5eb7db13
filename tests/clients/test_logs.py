"""clients.logs: bags and recordings as wire scans, odometry attachment, damaged files."""

from __future__ import annotations

import itertools
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import dataset_path
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.typesys import Stores, get_typestore

from clients.logs import (
    LogError,
    LogReadError,
    _parse_record,
    count_log_scans,
    detect_log_kind,
    iter_log_scans,
    probe_log,
)
from clients.recording import RecordingWriter
from clients.wire import OdometryPose, Scan, decode_scan, encode_scan

T0_NS = 1_700_000_000_000_000_000
SCAN_PERIOD_NS = 100_000_000  # 10 Hz
ODOM_PERIOD_NS = 40_000_000  # 25 Hz, deliberately not aligned with the scans
BEAMS = 181
SPEED_M_S = 0.5
YAW_RATE_RAD_S = 0.3


def _stamp(ts: Any, ns: int) -> Any:
    return ts.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _header(ts: Any, ns: int, frame: str) -> Any:
    return ts.types["std_msgs/msg/Header"](seq=0, stamp=_stamp(ts, ns), frame_id=frame)


def _laser_msg(ts: Any, ns: int, k: int) -> Any:
    ranges = (2.0 + 0.01 * k + np.linspace(0.0, 1.0, BEAMS)).astype(np.float32)
    ranges[5] = np.inf  # an invalid beam must survive untouched
    return ts.types["sensor_msgs/msg/LaserScan"](
        header=_header(ts, ns, "laser"),
        angle_min=np.float32(-math.pi / 2),
        angle_max=np.float32(math.pi / 2),
        angle_increment=np.float32(math.pi / (BEAMS - 1)),
        time_increment=0.0,
        scan_time=0.1,
        range_min=0.1,
        range_max=30.0,
        ranges=ranges,
        intensities=np.zeros(0, dtype=np.float32),
    )


def _odom_pose(ns: int) -> tuple[float, float, float]:
    t_s = (ns - T0_NS) / 1e9
    return SPEED_M_S * t_s, 0.0, math.remainder(YAW_RATE_RAD_S * t_s, 2 * math.pi)


def _odom_msg(ts: Any, ns: int) -> Any:
    x, y, yaw = _odom_pose(ns)
    t = ts.types
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
        ),
    )
    twist = t["geometry_msgs/msg/Twist"](
        linear=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
    )
    return t["nav_msgs/msg/Odometry"](
        header=_header(ts, ns, "odom"),
        child_frame_id="base_link",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )


def _timeline(n_scans: int) -> list[tuple[int, str]]:
    """(stamp, kind) sorted by time: scans at 10 Hz, odometry at 25 Hz around them."""
    end = T0_NS + n_scans * SCAN_PERIOD_NS
    items = [(T0_NS + 5_000_000 + k * SCAN_PERIOD_NS, "scan") for k in range(n_scans)]
    items += [(ns, "odom") for ns in range(T0_NS, end + ODOM_PERIOD_NS, ODOM_PERIOD_NS)]
    return sorted(items)


def write_ros1_bag(path: Path, n_scans: int, *, chunk_bytes: int = 8192) -> list[int]:
    ts = get_typestore(Stores.ROS1_NOETIC)
    writer = Ros1Writer(path)
    writer.set_compression(Ros1Writer.CompressionFormat.BZ2)
    writer.chunk_threshold = chunk_bytes
    scan_stamps = []
    with writer:
        scan_conn = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        odom_conn = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
        k = itertools.count()
        for ns, kind in _timeline(n_scans):
            if kind == "scan":
                msg = _laser_msg(ts, ns, next(k))
                writer.write(scan_conn, ns, ts.serialize_ros1(msg, "sensor_msgs/msg/LaserScan"))
                scan_stamps.append(ns)
            else:
                raw = ts.serialize_ros1(_odom_msg(ts, ns), "nav_msgs/msg/Odometry")
                writer.write(odom_conn, ns, raw)
    return scan_stamps


@pytest.fixture(scope="module")
def ros1_bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[int]]:
    path = tmp_path_factory.mktemp("bags") / "synthetic.bag"
    return path, write_ros1_bag(path, 60)


def _check_odometry(scans: list[Scan]) -> None:
    for scan in scans:
        assert scan.odom is not None
        x, y, yaw = _odom_pose(scan.stamp_ns)
        assert scan.odom.stamp_ns == scan.stamp_ns
        # Linear interpolation of a linear motion is exact (up to float rounding).
        assert scan.odom.x_m == pytest.approx(x, abs=1e-9)
        assert scan.odom.y_m == pytest.approx(y, abs=1e-9)
        assert math.remainder(scan.odom.theta_rad - yaw, 2 * math.pi) == pytest.approx(0, abs=1e-9)


def test_ros1_bag_scans_and_interpolated_odometry(ros1_bag: tuple[Path, list[int]]) -> None:
    path, stamps = ros1_bag
    assert detect_log_kind(path) == "ros1"
    scans = list(iter_log_scans(path, robot_id="bot-1"))
    assert [s.stamp_ns for s in scans] == stamps
    assert [s.seq for s in scans] == list(range(len(stamps)))
    first = scans[0]
    assert first.robot_id == "bot-1"
    assert first.sensor_stamp_ns == first.host_stamp_ns == stamps[0]
    assert first.beam_count == BEAMS
    assert first.ranges_encoding == "f32_m"
    assert first.angle_min_rad == float(np.float32(-math.pi / 2))
    assert first.range_max_m == pytest.approx(30.0)
    assert np.isinf(first.ranges_m[5])
    assert not first.valid_mask()[5]
    expected = (2.0 + np.linspace(0.0, 1.0, BEAMS)).astype(np.float32).astype(np.float64)
    expected[5] = np.inf
    np.testing.assert_array_equal(first.ranges_m, expected)
    _check_odometry(scans)
    # f32_m keeps the exact values through the wire contract.
    assert decode_scan(encode_scan(first)) == first


def test_ros1_bag_without_odometry(ros1_bag: tuple[Path, list[int]]) -> None:
    path, stamps = ros1_bag
    scans = list(iter_log_scans(path, use_odom=False))
    assert len(scans) == len(stamps)
    assert all(s.odom is None for s in scans)


def test_probe_and_count_ros1(ros1_bag: tuple[Path, list[int]]) -> None:
    path, stamps = ros1_bag
    info = probe_log(path)
    assert info.kind == "ros1"
    assert info.scan_count == len(stamps) == count_log_scans(path)
    assert info.has_odom
    assert not info.tolerant
    assert info.topics["/scan"] == "sensor_msgs/msg/LaserScan"
    assert 5.0 < info.duration_s < 7.0


def test_missing_scan_topic_is_a_clear_error(ros1_bag: tuple[Path, list[int]]) -> None:
    path, _ = ros1_bag
    with pytest.raises(LogReadError, match="no /laser topic"):
        list(iter_log_scans(path, scan_topic="/laser"))
    with pytest.raises(LogReadError, match="not sensor_msgs/LaserScan"):
        list(iter_log_scans(path, scan_topic="/odom"))


def test_truncated_bag_reads_a_prefix_with_a_warning(
    ros1_bag: tuple[Path, list[int]], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path, stamps = ros1_bag
    cut = tmp_path / "cut.bag"
    data = path.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    with caplog.at_level(logging.WARNING, logger="clients.logs"):
        scans = list(iter_log_scans(cut))
    assert 0 < len(scans) < len(stamps)
    assert [s.stamp_ns for s in scans] == stamps[: len(scans)]
    assert any("truncated" in r.getMessage() for r in caplog.records)
    _check_odometry(scans[:-1])  # the last scans may lack the odometry after them
    info = probe_log(cut)
    assert info.tolerant
    assert info.scan_count == len(scans) == count_log_scans(cut)


def test_damaged_index_record_is_skipped(ros1_bag: tuple[Path, list[int]], tmp_path: Path) -> None:
    """Like the URG-04LX demo bag: an index record with a wrong data length."""
    path, stamps = ros1_bag
    data = bytearray(path.read_bytes())
    at = data.find(b"op=\x04")  # the first index data record, after the first chunk
    assert at > 0
    records = (_parse_record(bytes(data), p, len(data)) for p in range(at - 64, at))
    rec = next(r for r in records if r is not None and r.op == 0x04)
    # Declare 100 more bytes than the record holds; the next record now looks misplaced.
    data[rec.data_start - 4 : rec.data_start] = (rec.data_end - rec.data_start + 100).to_bytes(
        4, "little"
    )
    damaged = tmp_path / "damaged.bag"
    damaged.write_bytes(bytes(data))
    scans = list(iter_log_scans(damaged))
    assert [s.stamp_ns for s in scans] == stamps
    _check_odometry(scans)


def test_garbage_and_missing_files(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.bag"
    garbage.write_bytes(b"this is not a bag at all\n" * 100)
    with pytest.raises(LogReadError, match="not a ROS 1 bag"):
        iter_log_scans(garbage)
    with pytest.raises(LogError, match="no such file"):
        probe_log(tmp_path / "absent.bag")
    fake = tmp_path / "fake.bag"
    fake.write_bytes(b"#ROSBAG V2.0\n" + bytes(range(256)) * 20)
    with pytest.raises(LogReadError) as info:
        list(iter_log_scans(fake))
    assert "\n" not in str(info.value)
    with pytest.raises(LogReadError):
        probe_log(fake)
    empty = tmp_path / "empty.mrec"
    empty.write_bytes(b"")
    with pytest.raises(LogReadError):
        iter_log_scans(empty)


def _scan(k: int, *, odom: bool) -> Scan:
    ranges = np.linspace(0.5, 10.0, 1081) + 0.001 * k
    ranges[::97] = 0.0
    return Scan(
        robot_id="sim-1",
        seq=k,
        sensor_stamp_ns=k * 25_000_000,
        host_stamp_ns=T0_NS + k * 25_000_000,
        angle_min_rad=-3 * math.pi / 4,
        angle_increment_rad=math.radians(0.25),
        range_min_m=0.02,
        range_max_m=30.0,
        ranges_m=ranges,
        odom=OdometryPose(0.1 * k, 0.0, 0.01 * k, T0_NS + k * 25_000_000) if odom else None,
        ranges_encoding="f32_m",
    )


def test_mrec_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "run.mrec"
    written = [_scan(k, odom=True) for k in range(20)]
    with RecordingWriter(path) as writer:
        for scan in written:
            writer.append(encode_scan(scan))
    expected = [decode_scan(encode_scan(s)) for s in written]  # f32 rounding of the ranges
    assert list(iter_log_scans(path)) == expected
    assert all(s.odom is None for s in iter_log_scans(path, use_odom=False))
    info = probe_log(path)
    assert (info.kind, info.scan_count, info.has_odom) == ("mrec", 20, True)
    assert info.duration_s == pytest.approx(19 * 0.025)
    assert count_log_scans(path) == 20


def test_ros2_bag(tmp_path: Path) -> None:
    ts = get_typestore(Stores.ROS2_HUMBLE)
    path = tmp_path / "ros2bag"
    stamps = []
    with Ros2Writer(path, version=9) as writer:
        scan_conn = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        odom_conn = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
        k = itertools.count()
        for ns, kind in _timeline(12):
            if kind == "scan":
                msg = _laser_msg_ros2(ts, ns, next(k))
                writer.write(scan_conn, ns, ts.serialize_cdr(msg, "sensor_msgs/msg/LaserScan"))
                stamps.append(ns)
            else:
                msg = _odom_msg_ros2(ts, ns)
                writer.write(odom_conn, ns, ts.serialize_cdr(msg, "nav_msgs/msg/Odometry"))
    assert detect_log_kind(path) == "ros2"
    scans = list(iter_log_scans(path))
    assert [s.stamp_ns for s in scans] == stamps
    _check_odometry(scans)
    assert probe_log(path).scan_count == 12


def _laser_msg_ros2(ts: Any, ns: int, k: int) -> Any:
    ros1 = _laser_msg(get_typestore(Stores.ROS1_NOETIC), ns, k)
    fields = {name: getattr(ros1, name) for name in ros1.__dataclass_fields__}
    fields["header"] = ts.types["std_msgs/msg/Header"](stamp=_stamp(ts, ns), frame_id="laser")
    return ts.types["sensor_msgs/msg/LaserScan"](**fields)


def _odom_msg_ros2(ts: Any, ns: int) -> Any:
    ros1 = _odom_msg(get_typestore(Stores.ROS1_NOETIC), ns)
    return ts.types["nav_msgs/msg/Odometry"](
        header=ts.types["std_msgs/msg/Header"](stamp=_stamp(ts, ns), frame_id="odom"),
        child_frame_id="base_link",
        pose=ros1.pose,
        twist=ros1.twist,
    )


# --- the shared real recordings --------------------------------------------------------------


@pytest.mark.datasets
def test_aces_first_scans_with_odometry() -> None:
    path = dataset_path("aces", "aces.sort.bag")
    scans = list(itertools.islice(iter_log_scans(path), 100))
    assert len(scans) == 100
    assert all(s.beam_count == 180 for s in scans)
    assert scans[0].stamp_ns == 70_289_900_000  # header stamp, as in aces.relations
    assert np.all(np.diff([s.stamp_ns for s in scans]) > 0)
    assert all(s.odom is not None for s in scans)
    assert scans[0].angle_min_rad == pytest.approx(-math.pi / 2)
    assert count_log_scans(path) == 7374


@pytest.mark.datasets
def test_urg_demo_bag_with_malformed_index_is_read_tolerantly() -> None:
    path = dataset_path("urg-04lx-demo", "laser_scan_matcher_demo.bag")
    info = probe_log(path)
    assert info.tolerant
    assert (info.scan_count, info.has_odom) == (360, False)
    scans = list(iter_log_scans(path))
    assert len(scans) == 360
    assert all(s.beam_count == 681 and s.odom is None for s in scans)
    assert scans[-1].angle_min_rad + 680 * scans[-1].angle_increment_rad == pytest.approx(
        -scans[-1].angle_min_rad, abs=0.01
    )
    assert np.all(np.diff([s.stamp_ns for s in scans]) > 0)
