"""Motion model without odometry: bursty stamps, bounded acceleration."""

from __future__ import annotations

import itertools
import math

import numpy as np
from test_estimator_known import cast, l_corridor  # sibling test module (pytest prepends its dir)

from service.core.frontend.estimator import ManhattanEstimator
from service.core.frontend.params import EstimatorParams
from service.core.types import LaserScan, Pose2D, wrap_angle


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


def test_bursty_stamps_leave_the_per_scan_model_alone() -> None:
    """Stamps in bursts do not measure the time between scans: the per-second model
    (`motion`) stays out, and the estimate is the per-scan model's, bit for bit."""
    segs = l_corridor()
    poses = _l_corridor_poses()
    runs = []
    for motion_models in (False, True):
        rng = np.random.default_rng(3)
        est = ManhattanEstimator(EstimatorParams(use_odometry=False, motion_models=motion_models))
        stamp_ns, out = 0, []
        for k, truth in enumerate(poses):
            stamp_ns += 1_000_000 if k % 2 else 600_000_000
            out.append(est.process(cast(segs, truth, noise_m=0.01, rng=rng, stamp_ns=stamp_ns)))
        runs.append([e.pose for e in out])
    assert runs[0] == runs[1]


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


def test_a_corner_at_the_paper_setting_does_not_shorten_the_plain_corridor_after_it() -> None:
    """A tuning ring (`sensor_agent.sim.families`): a scan every 0.3 m or 10° of turn, the
    robot at a steady 0.7 m/s, so the steps through each corner are 0.15-0.2 m and 0.3 m
    again after it. The 116 m corridor after the first corner is plain on both sides: 86 m of
    it carried on the motion model alone. Constant motion per scan carried the corner's short
    steps into it (0.22 m per scan instead of 0.29: the corridor 22 m short, the loop open by
    22 m); the stamps say the speed never changed, and the per-second model takes over."""
    from sensor_agent.sim import families

    gw = families.generate("ring", 1)
    est = ManhattanEstimator(EstimatorParams(use_odometry=False))
    model = gw.model
    truth: list[tuple[float, float, float]] = []
    poses: list[Pose2D] = []
    for sim in families.iter_scans(gw):
        scan = LaserScan(
            sim.stamp_ns,
            model.angle_min_rad,
            model.angle_increment_rad,
            np.asarray(sim.sample.ranges_m, dtype=np.float64),
            model.range_min_m,
            model.range_max_m,
        )
        poses.append(est.process(scan).pose)
        truth.append(sim.pose)
    true_m = sum(math.dist(a[:2], b[:2]) for a, b in itertools.pairwise(truth))
    xy = [(p.x_m, p.y_m) for p in poses]
    estimated_m = sum(math.dist(a, b) for a, b in itertools.pairwise(xy))
    assert abs(estimated_m - true_m) < 0.03 * true_m, (estimated_m, true_m)
    # The loop ends where it started (the truth's first and last poses coincide).
    assert math.dist(truth[0][:2], truth[-1][:2]) < 0.01
    assert math.hypot(poses[-1].x_m - poses[0].x_m, poses[-1].y_m - poses[0].y_m) < 2.0
