"""ACES through the default front end alone (the matcher, no loop closure), against the
published relation errors and at a place where a front end slid.

The whole log is replayed (7,374 SICK scans). Measured (mean translational / rotational relation
error, 1,279 relations): with odometry 0.086 m / 0.447°, without 0.091 m / 0.438°; published
sequential scan matching 0.173 m. Bounds: the measurement plus about 10 %. The core front end is
tested here, not the offline mapper, so the back end of `mapping-service map` does not move
these figures (docs/benchmarks.md has the CLI's, loops closed).
"""

from __future__ import annotations

import itertools
import math

import pytest
from conftest import dataset_path

from clients.logs import iter_log_scans
from service.bridge import scan_to_laser
from service.core.metrics import parse_relations, relation_errors
from service.core.slam import make_frontend
from service.core.types import Pose2D

PUBLISHED_SEQUENTIAL_SCAN_MATCHING_M = 0.173


def _aces_relation_errors(*, use_odometry: bool) -> tuple[float, float]:
    """Mean translational (m) and rotational (deg) relation error over the whole log."""
    bag = dataset_path("aces", "aces.sort.bag")
    relations = parse_relations(
        dataset_path("aces", "aces.relations").read_text(encoding="utf-8").splitlines()
    )
    est = make_frontend(use_odometry=use_odometry)
    stamps: list[int] = []
    poses: list[Pose2D] = []
    for scan in iter_log_scans(bag, use_odom=use_odometry):
        stamps.append(scan.stamp_ns)
        poses.append(est.process(scan_to_laser(scan, use_odometry=use_odometry)).pose)
    errors = relation_errors(stamps, poses, relations)
    assert errors.missing == 0
    return errors.trans_mean_m, errors.rot_mean_deg


@pytest.mark.slow
@pytest.mark.datasets
@pytest.mark.timeout(400)
def test_aces_with_odometry_beats_sequential_scan_matching() -> None:
    trans_m, rot_deg = _aces_relation_errors(use_odometry=True)
    assert trans_m < PUBLISHED_SEQUENTIAL_SCAN_MATCHING_M
    assert trans_m < 0.095, trans_m  # 0.086 m measured
    assert rot_deg < 0.49, rot_deg  # 0.447° measured


@pytest.mark.slow
@pytest.mark.datasets
@pytest.mark.timeout(400)
def test_aces_without_odometry_beats_sequential_scan_matching() -> None:
    trans_m, rot_deg = _aces_relation_errors(use_odometry=False)
    assert trans_m < PUBLISHED_SEQUENTIAL_SCAN_MATCHING_M
    assert trans_m < 0.1, trans_m  # 0.091 m measured
    assert rot_deg < 0.48, rot_deg  # 0.438° measured


@pytest.mark.slow
@pytest.mark.datasets
@pytest.mark.timeout(120)
def test_aces_robot_standing_still_in_a_corridor_stays() -> None:
    """Scans 4,095-4,190: 19 s standing still (odometry: 5 mm) where the corridor's axis has
    few points; a front end that predicted on at the last speed moved 9.6 m here."""
    bag = dataset_path("aces", "aces.sort.bag")
    est = make_frontend(use_odometry=False)
    poses: dict[int, Pose2D] = {}
    for i, scan in enumerate(itertools.islice(iter_log_scans(bag, use_odom=False), 4191)):
        if i >= 3990:
            poses[i] = est.process(scan_to_laser(scan, use_odometry=False)).pose
    a, b = poses[4095], poses[4190]
    assert math.hypot(b.x_m - a.x_m, b.y_m - a.y_m) < 0.05  # 0.002 m measured
