"""The estimator on the synthetic Manhattan world (sensor_agent.sim.world), UTM-30LX beam model.

The paper's setting (270°, 1,081 beams, a scan every 0.3 m) on the small building (a ~92 m loop)
to stay within the test budget; `docs/estimator.md` has the full paper-size numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from sensor_agent.sim.world import (
    LaserModel,
    generate_building,
    generate_trajectory,
    simulate_scan,
)
from service.core.frontend.estimator import ManhattanEstimator
from service.core.types import LaserScan, Pose2D, wrap_angle


@dataclass(frozen=True)
class LoopRun:
    worst_heading_deg: float
    gap_m: float  # last estimated position to the first (the true path closes)
    path_est_m: float
    path_true_m: float
    ate_rms_m: float  # position error against the truth in the map frame, every scan
    ate_max_m: float


def _run(seed: int) -> LoopRun:
    world = generate_building(seed, "small")
    traj = generate_trajectory(world, seed)
    model = LaserModel.utm30lx()
    rng = np.random.default_rng(seed + 1000)
    est = ManhattanEstimator()
    frame: Pose2D | None = None
    worst_heading_deg = 0.0
    est_xy: list[tuple[float, float]] = []
    true_xy: list[tuple[float, float]] = []
    for i in range(len(traj)):
        truth_world = Pose2D(*map(float, traj.poses[i]))
        sample = simulate_scan(world, truth_world, model, rng)
        scan = LaserScan(
            int(traj.stamps_ns[i]),
            model.angle_min_rad,
            model.angle_increment_rad,
            sample.ranges_m,
            model.range_min_m,
            model.range_max_m,
        )
        out = est.process(scan)
        if frame is None:  # map frame = first scan's Manhattan axes, origin at the first pose
            frame = Pose2D(0.0, 0.0, out.theta_rad).compose(truth_world.inverse())
        truth = frame.compose(truth_world)
        err = abs(math.degrees(wrap_angle(out.theta_rad - truth.theta_rad)))
        worst_heading_deg = max(worst_heading_deg, err)
        est_xy.append((out.pose.x_m, out.pose.y_m))
        true_xy.append((truth.x_m, truth.y_m))
    e, t = np.array(est_xy), np.array(true_xy)
    errors = np.hypot(*(e - t).T)
    return LoopRun(
        worst_heading_deg=worst_heading_deg,
        gap_m=float(np.hypot(*(e[-1] - e[0]))),
        path_est_m=float(np.sum(np.hypot(*np.diff(e, axis=0).T))),
        path_true_m=float(np.sum(np.hypot(*np.diff(t, axis=0).T))),
        ate_rms_m=float(np.sqrt(np.mean(errors**2))),
        ate_max_m=float(errors.max()),
    )


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_synthetic_loop_heading_and_gap(seed: int) -> None:
    """Measured (seeds 0, 1, 2; the same to 1e-11 under the Haswell, Zen, Sandybridge and
    Prescott OpenBLAS kernels): worst heading 0.19 / 0.15 / 0.21°, loop gap 3.7 / 7.7 / 6.8 mm
    (the paper: 0.24 m / 0.22 m), path length within 0.006 % of the true ~92 m, ATE RMS
    3.7 / 12 / 26 mm, worst 8 / 20 / 45 mm. Bounds: the worst seed plus about 50 %.

    The gap alone would pass a tracker frozen at its first pose (gap 0): the path length and
    the ATE are what it fails.
    """
    run = _run(seed)
    assert run.worst_heading_deg < 0.3, run
    assert run.gap_m < 0.012, run
    assert abs(run.path_est_m - run.path_true_m) < 0.005 * run.path_true_m, run
    assert run.ate_rms_m < 0.04, run
    assert run.ate_max_m < 0.07, run
