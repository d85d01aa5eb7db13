"""Each step of `ManhattanEstimator._process` on its own, on ray-cast scans of known poses.

The steps, in order: prediction, points, heading, moving objects left out, translation,
confidence. Each test runs the estimator up to a scan, then calls one step with the next scan's
inputs and checks its answer against the truth.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from test_estimator_known import box, cast, room  # sibling module (pytest's path)

from clients.wire import PoseFlag
from service.core.frontend.estimator import ManhattanEstimator, _Heading, _ScanWork
from service.core.frontend.params import EstimatorParams
from service.core.types import LaserScan, Pose2D, wrap_angle

PERIOD_NS = 100_000_000  # 10 Hz: the motion model's dt


def _drive(est: ManhattanEstimator, segs: np.ndarray, poses: list[Pose2D]) -> None:
    for k, pose in enumerate(poses):
        est.process(cast(segs, pose, stamp_ns=k * PERIOD_NS))


def _steps_before_translation(
    est: ManhattanEstimator, scan: LaserScan
) -> tuple[Pose2D, _Heading, np.ndarray, _ScanWork]:
    pred, flags = est._predict(scan)
    pts = est._points(scan)
    work = _ScanWork(*est._directions(pts))
    heading = est._heading(scan, pred, flags, pts, work)
    return pred, heading, pts, work


def test_prediction_carries_the_last_motion_forward() -> None:
    """Without odometry: the last step's motion per second, over this scan's period."""
    est = ManhattanEstimator(EstimatorParams(use_odometry=False))
    poses = [Pose2D(-1.0 + 0.05 * k, 0.02 * k, 0.0) for k in range(8)]
    _drive(est, room(), poses)
    scan = cast(room(), Pose2D(-0.6, 0.16, 0.0), stamp_ns=8 * PERIOD_NS)
    pred, flags = est._predict(scan)
    last = est._pose
    assert flags == PoseFlag.NONE
    assert math.hypot(pred.x_m - (last.x_m + 0.05), pred.y_m - (last.y_m + 0.02)) < 0.01


def test_prediction_from_odometry_is_flagged() -> None:
    est = ManhattanEstimator(EstimatorParams(use_odometry=True))
    first = replace(cast(room(), Pose2D(0.0, 0.0, 0.0), stamp_ns=0), odom=Pose2D(5.0, 5.0, 0.0))
    est.process(first)
    scan = cast(room(), Pose2D(0.2, 0.0, 0.0), stamp_ns=PERIOD_NS)
    scan = replace(scan, odom=Pose2D(5.2, 5.1, 0.1))
    pred, flags = est._predict(scan)
    assert flags & PoseFlag.ODOMETRY_PRIOR
    # The first pose is the map's origin up to the heading measurement's last bits.
    assert math.isclose(pred.x_m, 0.2, abs_tol=1e-4)
    assert math.isclose(pred.y_m, 0.1, abs_tol=1e-4)
    assert math.isclose(pred.theta_rad, 0.1, abs_tol=1e-4)


def test_points_keep_valid_returns_thinned() -> None:
    est = ManhattanEstimator()
    scan = cast(room(), Pose2D(0.0, 0.0, 0.0))
    ranges = np.array(scan.ranges_m, dtype=np.float64)
    ranges[:100] = np.nan  # bad returns
    ranges[100:200] = scan.range_max_m  # no return
    damaged = LaserScan(0, scan.angle_min_rad, scan.angle_increment_rad, ranges, 0.02, 30.0)
    pts = est._points(damaged)
    assert 100 < pts.shape[0] < 881
    spacing = np.hypot(*np.diff(pts, axis=0).T)
    assert np.median(spacing) >= 0.8 * est.params.thinning_m


def test_heading_is_measured_from_the_walls_not_the_prediction() -> None:
    """The robot turned 4° more than the constant-motion model says: the walls tell. (The
    range profiles would see the turn too: off here, so that the prediction is wrong.)"""
    est = ManhattanEstimator(EstimatorParams(use_odometry=False, profile_turn=False))
    turn_deg = [0.0, 1.0, 2.0, 3.0]
    _drive(est, room(), [Pose2D(0.0, 0.0, math.radians(a)) for a in turn_deg])
    truth = math.radians(8.0)
    scan = cast(room(), Pose2D(0.0, 0.0, truth), stamp_ns=4 * PERIOD_NS)
    pred, heading, _, _ = _steps_before_translation(est, scan)
    assert abs(math.degrees(pred.theta_rad) - 4.0) < 0.3
    assert heading.measured
    assert heading.quality == 1.0
    assert abs(math.degrees(wrap_angle(heading.theta_rad - truth))) < 0.1


def test_heading_without_walls_falls_back_and_says_so() -> None:
    """Only clutter in view (short pieces at random angles): no walls, a fallback heading, a
    flag."""
    est = ManhattanEstimator(EstimatorParams(use_odometry=False))
    _drive(est, room(), [Pose2D(0.0, 0.0, 0.0), Pose2D(0.05, 0.0, 0.0)])
    rng = np.random.default_rng(3)
    centres = rng.uniform(-6.0, 6.0, size=(120, 2))
    centres = centres[np.hypot(centres[:, 0], centres[:, 1]) > 1.0]
    angle = rng.uniform(0.0, math.pi, size=centres.shape[0])
    half = 0.12 * np.column_stack((np.cos(angle), np.sin(angle)))
    segs = np.hstack((centres - half, centres + half))
    scan = cast(segs, Pose2D(0.1, 0.0, 0.0), stamp_ns=2 * PERIOD_NS)
    _, heading, _, _ = _steps_before_translation(est, scan)
    assert not heading.measured
    assert heading.quality < 1.0
    assert heading.flags & (PoseFlag.NO_DOMINANT_WALL | PoseFlag.NON_MANHATTAN)


def test_moved_in_points_are_left_out() -> None:
    """A box appears where the previous scan saw the far wall: its points go, the walls stay."""
    est = ManhattanEstimator(EstimatorParams(use_odometry=False))
    _drive(est, room(), [Pose2D(-0.1 * (3 - k), 0.0, 0.0) for k in range(4)])
    with_box = np.vstack((room(), np.array(box(2.0, -0.3, 2.4, 0.1))))
    scan = cast(with_box, Pose2D(0.1, 0.0, 0.0), stamp_ns=4 * PERIOD_NS)
    pred, heading, pts, work = _steps_before_translation(est, scan)
    kept, kept_work = est._without_moved(
        scan, pts, work, Pose2D(pred.x_m, pred.y_m, heading.theta_rad)
    )
    on_box = (np.abs(pts[:, 0] - 2.0) < 0.5) & (np.abs(pts[:, 1] + 0.1) < 0.4)
    assert on_box.sum() >= 5
    assert kept.shape[0] == pts.shape[0] - int(on_box.sum())
    assert kept_work.dirs_rad.shape[0] == kept.shape[0]


def test_translation_recovers_a_known_step() -> None:
    est = ManhattanEstimator(EstimatorParams(use_odometry=False))
    _drive(est, room(), [Pose2D(-0.5 + 0.1 * k, 0.0, 0.0) for k in range(5)])
    truth = Pose2D(0.07, 0.12, 0.0)  # off the constant-motion prediction (0.0, 0.0)
    scan = cast(room(), truth, stamp_ns=5 * PERIOD_NS)
    pred, heading, pts, work = _steps_before_translation(est, scan)
    move = est._translation(scan, pred, heading, pts, work)
    assert move is not None
    assert move.frame_rad == 0.0
    origin = Pose2D(-0.5, 0.0, 0.0)  # the map frame is the first scan's
    assert math.hypot(move.x_m - (truth.x_m - origin.x_m), move.y_m - truth.y_m) < 0.01
    assert not move.flags & (PoseFlag.AMBIGUOUS_X | PoseFlag.AMBIGUOUS_Y)


def test_confidence_drops_and_sigma_grows_along_a_plain_corridor() -> None:
    """Step 6 on step 5's answers: in a room both axes are sharp; in a corridor of plain walls
    the along-corridor axis is ambiguous, with a lower confidence and no σ (unmeasured: the
    covariance grows) or a wide one. The last returns down the corridor, where the beams run
    out, lie on their walls (`end_directions`): they must not pin the scan in place."""
    corridor = np.array([(-60.0, -1.2, 60.0, -1.2), (-60.0, 1.2, 60.0, 1.2)])
    answers = {}
    for name, segs in (("room", room()), ("corridor", corridor)):
        est = ManhattanEstimator(EstimatorParams(use_odometry=False))
        _drive(est, segs, [Pose2D(-0.5 + 0.1 * k, 0.0, 0.0) for k in range(5)])
        scan = cast(segs, Pose2D(0.0, 0.0, 0.0), stamp_ns=5 * PERIOD_NS)
        pred, heading, pts, work = _steps_before_translation(est, scan)
        move = est._translation(scan, pred, heading, pts, work)
        assert move is not None
        answers[name] = (move, *est._confidence(heading, move))
    _, room_q, room_sigmas = answers["room"]
    corridor_move, corridor_q, corridor_sigmas = answers["corridor"]
    assert corridor_move.flags & PoseFlag.AMBIGUOUS_X
    assert not corridor_move.flags & PoseFlag.AMBIGUOUS_Y
    assert corridor_q < room_q
    assert room_sigmas[0] is not None
    assert corridor_sigmas[0] is None or corridor_sigmas[0] > 3.0 * room_sigmas[0]
