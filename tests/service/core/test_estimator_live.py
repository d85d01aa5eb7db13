"""The estimator at the UTM-30LX's 40 Hz along the simulator's continuous robot motion.

This is what the service sees from a robot (and what the load generator sends): scans 25 ms
apart, so the heading is tracked by the fine search alone and the translation window is
bounded by the scan period. Seed 1 drove 0.64 m off for 9 s in a corridor before the gated
along-axis correlation, and 1.9 m with a 0.1 m translation window.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.loadgen import path_scans
from sensor_agent.sim import world as sim
from service.core.frontend.estimator import ManhattanEstimator
from service.core.types import Pose2D, wrap_angle

PERIOD_S = 1.0 / 40.0


@pytest.mark.slow
@pytest.mark.timeout(180)
@pytest.mark.parametrize("seed", [1, 2])
def test_40hz_track_stays_within_centimetres(seed: int) -> None:
    """Measured (seeds 1, 2; the same under four OpenBLAS kernels): worst position error
    22 / 13 mm, worst heading error 0.05 / 0.19°, end point 3.8 / 4.8 mm, distance 13.65 m
    within 0.02 %. Bounds: the worst seed plus about 50 %; the distance is what a tracker
    frozen at its first pose fails."""
    n = 800  # 20 s, ~14 m
    truth = sim.RobotMotion(sim.generate_building(seed), seed).poses_at(np.arange(n) * PERIOD_S)
    est = ManhattanEstimator()
    out = [est.process(scan) for scan in path_scans(seed, n, PERIOD_S)]
    first_est, first_truth = out[0].pose, Pose2D(*map(float, truth[0]))
    worst_m = worst_deg = 0.0
    est_xy, true_xy = [], []
    for o, t in zip(out, truth, strict=True):
        a = first_est.between(o.pose)
        b = first_truth.between(Pose2D(*map(float, t)))
        worst_m = max(worst_m, math.hypot(a.x_m - b.x_m, a.y_m - b.y_m))
        worst_deg = max(worst_deg, abs(math.degrees(wrap_angle(a.theta_rad - b.theta_rad))))
        est_xy.append((a.x_m, a.y_m))
        true_xy.append((b.x_m, b.y_m))
    # Distances on 0.5 s steps (per-scan noise would add to the estimated one).
    e, t = np.array(est_xy)[::20], np.array(true_xy)[::20]
    distance_est = float(np.sum(np.hypot(*np.diff(e, axis=0).T)))
    distance_true = float(np.sum(np.hypot(*np.diff(t, axis=0).T)))
    end_m = math.dist(est_xy[-1], true_xy[-1])
    figures = (worst_m, worst_deg, end_m, distance_est, distance_true)
    assert worst_m < 0.035, figures
    assert worst_deg < 0.3, figures
    assert end_m < 0.01, figures
    assert abs(distance_est - distance_true) < 0.01 * distance_true, figures
