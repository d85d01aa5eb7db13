"""Wire Scan -> core LaserScan."""

from __future__ import annotations

import math

import numpy as np

from clients.wire import OdometryPose, Scan
from service.bridge import scan_to_laser
from service.core.types import Pose2D


def make_scan(odom: OdometryPose | None = None) -> Scan:
    ranges = np.array([1.5, 0.001, 0.0, 31.0, np.nan, 0.02, 29.999, 0.023])
    return Scan(
        robot_id="r1",
        seq=3,
        sensor_stamp_ns=111,
        host_stamp_ns=1_700_000_000_000_000_123,
        angle_min_rad=-math.radians(135.0),
        angle_increment_rad=math.radians(0.25),
        range_min_m=0.023,
        range_max_m=30.0,
        ranges_m=ranges,
        odom=odom,
    )


def test_invalid_beams_become_nan_and_input_is_untouched() -> None:
    scan = make_scan()
    before = scan.ranges_m.copy()
    laser = scan_to_laser(scan)
    expected = [1.5, np.nan, np.nan, np.nan, np.nan, np.nan, 29.999, 0.023]
    np.testing.assert_array_equal(laser.ranges_m, expected)
    np.testing.assert_array_equal(scan.ranges_m, before)
    assert laser.ranges_m.dtype == np.float64
    assert laser.stamp_ns == scan.host_stamp_ns
    assert laser.angle_min_rad == scan.angle_min_rad
    assert laser.angle_increment_rad == scan.angle_increment_rad
    assert (laser.range_min_m, laser.range_max_m) == (0.023, 30.0)
    assert laser.odom is None
    assert laser.points_xy_m().shape == (3, 2)


def test_odometry_is_passed_when_wanted() -> None:
    scan = make_scan(OdometryPose(1.0, -2.0, 0.5, stamp_ns=99))
    assert scan_to_laser(scan).odom == Pose2D(1.0, -2.0, 0.5)
    assert scan_to_laser(scan, use_odometry=True).odom == Pose2D(1.0, -2.0, 0.5)
    assert scan_to_laser(scan, use_odometry=False).odom is None
