"""Wire `Scan` -> core `LaserScan`: a conversion and nothing else.

Invalid beams (no return, device error codes, outside the range limits, per
`clients.wire.Scan.valid_mask`) become NaN. The scan's odometry, when present and wanted, becomes
a `Pose2D` in the robot's odom frame. The stamp is the scan's host stamp (`Scan.stamp_ns`).
"""

from __future__ import annotations

import numpy as np

from clients.wire import Scan
from service.core.types import LaserScan, Pose2D


def scan_to_laser(scan: Scan, use_odometry: bool = True) -> LaserScan:
    """The core's view of a wire scan; the caller's arrays are not modified."""
    ranges = np.array(scan.ranges_m, dtype=np.float64, copy=True)
    ranges[~scan.valid_mask()] = np.nan
    odom = None
    if use_odometry and scan.odom is not None:
        odom = Pose2D(float(scan.odom.x_m), float(scan.odom.y_m), float(scan.odom.theta_rad))
    return LaserScan(
        stamp_ns=int(scan.stamp_ns),
        angle_min_rad=float(scan.angle_min_rad),
        angle_increment_rad=float(scan.angle_increment_rad),
        ranges_m=ranges,
        range_min_m=float(scan.range_min_m),
        range_max_m=float(scan.range_max_m),
        odom=odom,
    )
