"""`--front-end paper` on known answers: the wall angle, the absolute heading through turns, a
robot tracked through a room, an honest covariance in a corridor, and bad scans
(`service.core.frontend.paper`)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scenes import CORRIDOR, ROOM, bad_scan, scan_of

from clients.wire import PoseFlag
from service.core.frontend.paper import PaperFrontEnd, PaperOptions, thin_points, wall_angle
from service.core.slam import FRONT_ENDS, make_frontend
from service.core.types import Pose2D, wrap_angle

pytestmark = pytest.mark.timeout(120)


def _quarter_deg(angle_rad: float) -> float:
    """An angle modulo 90°, in degrees within [-45, 45)."""
    return (math.degrees(angle_rad) + 45.0) % 90.0 - 45.0


def test_make_frontend_builds_the_paper_front_end() -> None:
    assert "paper" in FRONT_ENDS
    assert isinstance(make_frontend("paper"), PaperFrontEnd)


def test_thinning_spacing() -> None:
    """§II-A 1): consecutive kept points about `thinning_m` apart."""
    pts = np.column_stack((np.linspace(0.0, 5.0, 1001), np.zeros(1001)))
    thin = thin_points(pts, 0.05)
    gaps = np.diff(thin[:, 0])
    assert 95 <= thin.shape[0] <= 105
    assert np.all(gaps > 0.04)
    assert np.all(gaps < 0.06)


@pytest.mark.parametrize("heading_deg", [0.0, 7.3, -21.0, 38.5, 63.0, 101.2])
def test_the_wall_angle_turns_the_walls_onto_the_axes(heading_deg: float) -> None:
    """§II-A: in a Manhattan room, the rotation with the largest hmax(θ) is the robot's heading
    modulo 90° (the room's walls are on the axes), within 2.5 search steps (0.25°)."""
    rng = np.random.default_rng(2)
    scan = scan_of(ROOM, Pose2D(3.0, 2.5, math.radians(heading_deg)), rng)
    wall = wall_angle(scan.points_xy_m(), PaperOptions())
    assert 0.0 <= wall.angle_rad < math.pi
    assert abs(_quarter_deg(wall.angle_rad - math.radians(heading_deg))) < 0.25
    assert 0.0 < wall.sigma_rad < math.radians(1.0)


def test_the_heading_follows_a_turn_in_place_through_wall_switches() -> None:
    """§II-B: a 200° turn in place in 4° steps: the major wall switches (HEADING_SWITCH) and the
    heading, relative to the first scan's, stays within 0.5° of the truth all the way."""
    rng = np.random.default_rng(3)
    fe = PaperFrontEnd()
    start = Pose2D(3.0, 2.5, math.radians(5.0))
    first = None
    switches = 0
    for i in range(51):
        truth = Pose2D(3.0, 2.5, start.theta_rad + math.radians(4.0 * i))
        est = fe.process(scan_of(ROOM, truth, rng, stamp_ns=(i + 1) * 100_000_000))
        first = est.pose if first is None else first
        turned_est = wrap_angle(est.theta_rad - first.theta_rad)
        turned_true = wrap_angle(truth.theta_rad - start.theta_rad)
        assert abs(math.degrees(wrap_angle(turned_est - turned_true))) < 0.5, i
        switches += bool(est.flags & PoseFlag.HEADING_SWITCH)
    assert switches >= 2  # every 90° of turn, the other wall is the major one at some point


def test_the_front_end_follows_a_robot_through_a_room() -> None:
    """Scans 0.1 m apart at 10 Hz along a known path, turning slowly: every pose, relative to the
    first, within 4 cm and 0.5° (the paper's 0.1° heading step and 5 mm shift, no refinement);
    a keyframe every 0.3 m."""
    rng = np.random.default_rng(6)
    fe = PaperFrontEnd()
    start = Pose2D(1.5, 2.5, 0.2)
    first = None
    keyframes = 0
    for i in range(40):
        truth = Pose2D(1.5 + 0.1 * i, 2.5 + 0.02 * i, 0.2 + 0.01 * i)
        est = fe.process(scan_of(ROOM, truth, rng, stamp_ns=(i + 1) * 100_000_000))
        first = est.pose if first is None else first
        rel_est, rel_true = first.between(est.pose), start.between(truth)
        assert math.hypot(rel_est.x_m - rel_true.x_m, rel_est.y_m - rel_true.y_m) < 0.04, i
        assert abs(math.degrees(wrap_angle(rel_est.theta_rad - rel_true.theta_rad))) < 0.5, i
        assert not est.flags & (PoseFlag.DEGENERATE | PoseFlag.AMBIGUOUS_X | PoseFlag.AMBIGUOUS_Y)
        assert est.quality > 0.9
        sx, sy = math.sqrt(est.covariance[0]), math.sqrt(est.covariance[4])
        assert (sx, sy) == (0.0, 0.0) if i == 0 else 0.005 < min(sx, sy) <= max(sx, sy) < 0.05
        keyframes += est.is_keyframe
    assert 12 <= keyframes <= 16  # 4 m of travel, one every 0.3 m (and the first scan)


def test_a_plain_corridor_is_flagged_ambiguous_and_uncertain_along_it() -> None:
    """Two parallel walls and no end in range: the correlation along the corridor is flat, so
    that axis is flagged and its σ is the window's, while across it stays at centimetres."""
    rng = np.random.default_rng(4)
    fe = PaperFrontEnd()
    est = None
    for i in range(4):
        est = fe.process(scan_of(CORRIDOR, Pose2D(0.1 * i, 1.0, 0.0), rng, (i + 1) * 10**8))
    assert est is not None
    # The corridor runs along the robot's x; the map's y axis is along the first major wall.
    along, across = (4, 0) if abs(math.sin(est.theta_rad)) > 0.5 else (0, 4)
    flag_along = PoseFlag.AMBIGUOUS_Y if along == 4 else PoseFlag.AMBIGUOUS_X
    assert est.flags & flag_along
    assert math.sqrt(est.covariance[along]) > 0.2
    assert math.sqrt(est.covariance[across]) < 0.03
    assert est.quality < 0.5


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    kind=st.sampled_from(["empty", "max_range", "nan", "one_beam", "inf", "huge", "backwards"]),
    n=st.integers(min_value=1, max_value=1081),
)
def test_bad_scans_return_the_last_pose_flagged_and_never_raise(kind: str, n: int) -> None:
    """No points, NaN, all at max range, one beam, absurd ranges: the last pose (the paper has
    no motion model) flagged DEGENERATE, no keyframe; a stamp going back is not matched. The
    next good scan is matched again."""
    rng = np.random.default_rng(7)
    fe = PaperFrontEnd()
    last = None
    for i in range(3):
        last = fe.process(scan_of(ROOM, Pose2D(2.0 + 0.05 * i, 3.0, 0.0), rng, (i + 1) * 10**8))
    assert last is not None
    if kind == "backwards":
        est = fe.process(scan_of(ROOM, Pose2D(2.1, 3.0, 0.0), rng, stamp_ns=10**8))
        assert fe.stamp_backwards == 1
    else:
        est = fe.process(bad_scan(kind, 4 * 10**8, n))
    assert est.pose == last.pose
    assert est.flags & PoseFlag.DEGENERATE
    assert not est.is_keyframe
    assert est.quality == 0.0
    after = fe.process(scan_of(ROOM, Pose2D(2.15, 3.0, 0.0), rng, stamp_ns=5 * 10**8))
    assert not after.flags & PoseFlag.DEGENERATE
    assert math.hypot(after.x_m - last.x_m, after.y_m - last.y_m) == pytest.approx(0.05, abs=0.02)


def test_reset_starts_a_new_map() -> None:
    rng = np.random.default_rng(9)
    fe = PaperFrontEnd()
    for i in range(3):
        fe.process(scan_of(ROOM, Pose2D(2.0 + 0.2 * i, 3.0, 0.1), rng, (i + 1) * 10**8))
    assert fe.wall_families_rad == (0.0,)
    fe.reset()
    assert fe.wall_families_rad == ()
    est = fe.process(scan_of(ROOM, Pose2D(5.0, 3.0, 0.1), rng, stamp_ns=1))  # time restarts too
    assert est.is_keyframe
    assert (est.x_m, est.y_m) == (0.0, 0.0)
