"""Motion model without odometry: bursty stamps, bounded acceleration."""

from __future__ import annotations

import math

import numpy as np
from test_estimator_known import cast, l_corridor  # sibling test module (pytest prepends its dir)

from service.core.frontend.estimator import ManhattanEstimator
from service.core.frontend.params import EstimatorParams
from service.core.types import Pose2D, wrap_angle


def _l_corridor_poses() -> list[Pose2D]:
    poses = [Pose2D(-10.0 + 0.3 * i, 0.0, 0.0) for i in range(34)]
    poses += [Pose2D(0.0, 0.0, math.radians(10.0 * k)) for k in range(1, 10)]
    poses += [Pose2D(0.0, 0.3 * i, math.pi / 2.0) for i in range(1, 35)]
    return poses


def test_bursty_stamps_do_not_break_tracking() -> None:
    """Logged stamps 1 ms then 0.6 s apart (Intel-like), the robot moving evenly per scan."""
    segs = l_corridor()
    poses = _l_corridor_poses()
    rng = np.random.default_rng(3)
    est = ManhattanEstimator(EstimatorParams(use_odometry=False))
    stamp_ns = 0
    for k, truth in enumerate(poses):
        stamp_ns += 1_000_000 if k % 2 else 600_000_000
        out = est.process(cast(segs, truth, noise_m=0.01, rng=rng, stamp_ns=stamp_ns))
        assert abs(math.degrees(wrap_angle(out.theta_rad - truth.theta_rad))) < 0.5, k
        rel = (truth.x_m - poses[0].x_m, truth.y_m - poses[0].y_m)
        assert math.hypot(out.x_m - rel[0], out.y_m - rel[1]) < 0.15, (k, out.pose, rel)


def test_time_based_period_is_clipped_to_recent_median() -> None:
    est = ManhattanEstimator(EstimatorParams(scan_period_s=0.0, period_clip_ratio=2.0))
    segs = l_corridor()
    for k in range(8):  # regular 0.2 s stamps
        est.process(cast(segs, Pose2D(-10.0 + 0.1 * k, 0.0, 0.0), stamp_ns=k * 200_000_000))
    burst = cast(segs, Pose2D(-9.1, 0.0, 0.0), stamp_ns=7 * 200_000_000 + 1_000_000)
    gap = cast(segs, Pose2D(-9.1, 0.0, 0.0), stamp_ns=7 * 200_000_000 + 5_000_000_000)
    assert math.isclose(est._dt_s(burst), 0.1)
    assert math.isclose(est._dt_s(gap), 0.4)


def test_bounded_acceleration_limits_a_sudden_jump() -> None:
    """A far-ahead match raises the predicted motion by at most max_accel·dt per scan."""
    params = EstimatorParams(use_odometry=False)
    est = ManhattanEstimator(params)
    segs = l_corridor()
    x = -10.0
    for k in range(6):
        est.process(cast(segs, Pose2D(x, 0.0, 0.0), stamp_ns=k * 200_000_000))
        x += 0.1
    v_before = est._velocity
    assert v_before is not None
    est.process(cast(segs, Pose2D(x + 0.25, 0.0, 0.0), stamp_ns=6 * 200_000_000))
    v_after = est._velocity
    assert v_after is not None
    dv = math.hypot(v_after.x_m - v_before.x_m, v_after.y_m - v_before.y_m)
    assert dv <= params.max_accel_m_s2 * params.scan_period_s + 1e-9
