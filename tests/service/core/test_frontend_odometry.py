"""Odometry weighted by its own consistency (`service.core.frontend.odometry`)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_estimator_known import cast, room  # sibling test module (pytest prepends its dir)

from clients.wire import PoseFlag
from service.core.frontend.estimator import ManhattanEstimator
from service.core.frontend.odometry import OdometryConsistency
from service.core.frontend.params import EstimatorParams
from service.core.types import LaserScan, Pose2D, wrap_angle


def test_the_odometry_error_is_learnt_and_its_drift_grows_linearly() -> None:
    odometry = OdometryConsistency()
    for _ in range(400):  # a steady 0.3° per scan, all one way (a bias)
        odometry.observe(math.radians(0.3), measured=True)
    assert math.degrees(odometry.heading_step_rms_rad) == pytest.approx(0.3, abs=0.01)
    assert odometry.heading_drift_rad() == 0.0  # just measured: nothing carried
    for _ in range(20):
        odometry.observe(None, measured=False)
    assert math.degrees(odometry.heading_drift_rad()) == pytest.approx(6.0, abs=0.2)
    odometry.observe(math.radians(90.0), measured=True)  # one wild innovation is clipped
    assert math.degrees(odometry.heading_step_rms_rad) < 0.5
    assert odometry.heading_drift_rad() == 0.0


def _stick_field(rng: np.random.Generator, count: int = 80) -> np.ndarray:
    """Short sticks at random angles: no dominant wall, so no heading from walls."""
    centres = rng.uniform(-6.0, 6.0, (count, 2))
    centres = centres[np.hypot(centres[:, 0], centres[:, 1]) > 1.0]
    angle = rng.uniform(0.0, math.pi, centres.shape[0])
    half = rng.uniform(0.15, 0.3, centres.shape[0])[:, None]
    d = np.column_stack((np.cos(angle), np.sin(angle))) * half
    return np.hstack((centres - d, centres + d))


def _heading_errors_deg(params: EstimatorParams) -> tuple[list[float], list[PoseFlag]]:
    """Turning slowly in a room whose walls vanish behind clutter for 40 scans, with odometry
    that turns 0.6° per scan too far: 24° of drift by the time the walls are back."""
    rng = np.random.default_rng(3)
    est = ManhattanEstimator(params)
    sticks = _stick_field(rng)
    truth, odom = Pose2D(0.0, 0.0, 0.0), Pose2D(2.0, -1.0, 0.3)
    errors: list[float] = []
    flags: list[PoseFlag] = []
    for i in range(56):
        if i:
            turn = math.radians(0.5)
            truth = truth.compose(Pose2D(0.0, 0.0, turn))
            odom = odom.compose(Pose2D(0.0, 0.0, turn + math.radians(0.6)))
        s = cast(
            sticks if 8 <= i < 48 else room(), truth, noise_m=0.01, rng=rng, stamp_ns=i * 10**8
        )
        out = est.process(
            LaserScan(
                s.stamp_ns, s.angle_min_rad, s.angle_increment_rad, s.ranges_m, 0.02, 30.0, odom
            )
        )
        errors.append(math.degrees(wrap_angle(out.theta_rad - truth.theta_rad)))
        flags.append(out.flags)
    return errors, flags


@pytest.mark.timeout(60)
def test_a_heading_that_followed_drifting_odometry_is_taken_back_by_the_walls() -> None:
    errors, flags = _heading_errors_deg(EstimatorParams())
    assert all(f & PoseFlag.ODOMETRY_PRIOR for f in flags[1:])
    assert abs(errors[47]) > 20.0  # the clutter left the pose on the odometry's heading
    assert max(abs(e) for e in errors[48:]) < 0.5, errors[48:]  # the walls are back
    # The same odometry trusted at its fixed σ stays on its heading (the Intel failure).
    stuck, _ = _heading_errors_deg(EstimatorParams(odometry_consistency=False))
    assert min(abs(e) for e in stuck[48:]) > 20.0, stuck[48:]
