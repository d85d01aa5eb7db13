"""ACES with its odometry as the motion prior, against the published relation errors.

Without odometry the estimator does not yet beat sequential scan matching on ACES (see
docs/estimator.md); with odometry it does (0.072 m measured vs 0.173 m published), and this test
guards that. The whole log is replayed (7,374 SICK scans).
"""

from __future__ import annotations

import pytest
from conftest import dataset_path

from clients.logs import iter_log_scans
from service.core.estimator import ManhattanEstimator
from service.core.metrics import parse_relations, relation_errors
from service.core.types import LaserScan, Pose2D

PUBLISHED_SEQUENTIAL_SCAN_MATCHING_M = 0.173


@pytest.mark.slow
@pytest.mark.datasets
@pytest.mark.timeout(300)
def test_aces_with_odometry_beats_sequential_scan_matching() -> None:
    bag = dataset_path("aces", "aces.sort.bag")
    relations = parse_relations(
        dataset_path("aces", "aces.relations").read_text(encoding="utf-8").splitlines()
    )
    est = ManhattanEstimator()
    stamps: list[int] = []
    poses: list[Pose2D] = []
    for scan in iter_log_scans(bag, use_odom=True):
        odom = scan.odom
        out = est.process(
            LaserScan(
                stamp_ns=scan.stamp_ns,
                angle_min_rad=scan.angle_min_rad,
                angle_increment_rad=scan.angle_increment_rad,
                ranges_m=scan.ranges_m,
                range_min_m=scan.range_min_m,
                range_max_m=scan.range_max_m,
                odom=None if odom is None else Pose2D(odom.x_m, odom.y_m, odom.theta_rad),
            )
        )
        stamps.append(scan.stamp_ns)
        poses.append(out.pose)
    errors = relation_errors(stamps, poses, relations)
    assert errors.missing == 0
    assert errors.trans_mean_m < PUBLISHED_SEQUENTIAL_SCAN_MATCHING_M
