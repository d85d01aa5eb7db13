"""Without odometry: the turn between two scans from their range profiles."""

from __future__ import annotations

import dataclasses
import math
import pickle

import numpy as np
import pytest
from test_estimator_known import Segments, box, cast, room  # sibling module (pytest's path)

from service.core.frontend.estimator import ManhattanEstimator
from service.core.frontend.heading import measure_heading
from service.core.frontend.params import EstimatorParams
from service.core.frontend.profile import profile_turn
from service.core.types import LaserScan, Pose2D, wrap_angle


def _profile(scan: LaserScan) -> np.ndarray:
    r = scan.ranges_m.copy()
    r[r >= scan.range_max_m] = np.nan
    return r


def _hall() -> Segments:
    """A round hall (a 36-gon of radius 6 m: no dominant wall) with a pillar and a doorway."""
    a = np.radians(np.arange(0.0, 360.0, 10.0))
    xy = 6.0 * np.column_stack((np.cos(a), np.sin(a)))
    segs = [(*xy[i], *xy[(i + 1) % len(xy)]) for i in range(len(xy)) if i != 4]
    segs += box(1.5, 0.5, 2.1, 1.1)
    return np.array(segs, dtype=np.float64)


@pytest.mark.parametrize(("beams", "fov_deg"), [(1081, 270.0), (181, 180.0)])
@pytest.mark.parametrize("turn_deg", [-40.0, -13.0, 0.0, 7.0, 25.0])
def test_profile_turn_in_place(beams: int, fov_deg: float, turn_deg: float) -> None:
    """A turn in place is found to within one beam, coarse to fine on the dense scanner."""
    rng = np.random.default_rng(5)
    start = Pose2D(0.3, -0.2, 0.4)
    before = cast(room(), start, beams=beams, fov_deg=fov_deg, noise_m=0.005, rng=rng)
    after_pose = Pose2D(start.x_m, start.y_m, start.theta_rad + math.radians(turn_deg))
    after = cast(room(), after_pose, beams=beams, fov_deg=fov_deg, noise_m=0.005, rng=rng)
    inc = before.angle_increment_rad
    got = profile_turn(_profile(before), _profile(after), inc, math.radians(60.0))
    assert got is not None
    assert abs(got.turn_rad - math.radians(turn_deg)) <= 1.01 * inc
    assert got.score > 0.7  # a turn leaves the beams at one edge without a partner


def test_profile_turn_refuses_other_scanners_and_empty_scans() -> None:
    a = np.full(100, 2.0)
    assert profile_turn(a, np.full(101, 2.0), 0.01, 0.5) is None
    assert profile_turn(a, np.full(100, np.nan), 0.01, 0.5) is None


def test_fast_turn_in_a_round_hall_keeps_the_heading() -> None:
    """80° in 6 scans at 5 Hz where no wall gives a Manhattan heading (ACES's round hall)."""
    segs = _hall()
    poses = [Pose2D(-0.5 + 0.1 * k, 0.0, 0.0) for k in range(6)]
    poses += [Pose2D(0.0, 0.0, math.radians(-80.0 * k / 6.0)) for k in range(1, 7)]
    poses += [Pose2D(0.0, 0.0, math.radians(-80.0))] * 4
    errors = {}
    for on in (True, False):
        est = ManhattanEstimator(EstimatorParams(use_odometry=False, profile_turn=on))
        rng = np.random.default_rng(11)
        first = poses[0]
        for k, truth in enumerate(poses):
            out = est.process(cast(segs, truth, noise_m=0.01, rng=rng, stamp_ns=k * 200_000_000))
        turned = truth.theta_rad - first.theta_rad
        errors[on] = abs(math.degrees(wrap_angle(out.theta_rad - turned)))
    assert errors[True] < 3.0, errors
    # The constant-velocity prediction alone does not follow this turn (the test has teeth).
    assert errors[False] > 5.0, errors


@pytest.mark.parametrize(
    ("drift_deg", "bound_deg", "anchored"),
    [(14.0, 30.0, True), (-25.0, 30.0, True), (40.0, 30.0, False), (14.0, 10.0, False)],
)
def test_drifted_relative_heading_is_reanchored_on_strong_walls(
    drift_deg: float, bound_deg: float, anchored: bool
) -> None:
    """A relative heading that drifted from the walls snaps back within the drift bound (30°
    without odometry; with it, as far as the odometry can have drifted)."""
    truth = Pose2D(0.2, 0.1, math.radians(17.0))
    est = ManhattanEstimator(EstimatorParams(use_odometry=False))
    pts = est._points(cast(room(), truth, noise_m=0.005, rng=np.random.default_rng(4)))
    meas = measure_heading(pts, None, 0.0, math.radians(0.1), 0.02)
    drifted = truth.theta_rad + math.radians(drift_deg)
    got = est._reanchor_on_walls(pts, meas, drifted, math.radians(bound_deg))
    if not anchored:
        assert got is None
        return
    assert got is not None
    assert abs(math.degrees(wrap_angle(got - truth.theta_rad))) < 0.3


def test_walls_too_weak_do_not_reanchor() -> None:
    est = ManhattanEstimator(EstimatorParams(use_odometry=False))
    pts = est._points(
        cast(_hall(), Pose2D(0.0, 0.0, 0.3), noise_m=0.01, rng=np.random.default_rng(1))
    )
    meas = measure_heading(pts, None, 0.0, math.radians(0.1), 0.02)
    assert est._reanchor_on_walls(pts, meas, 0.5, math.radians(30.0)) is None


def test_parameters_pickled_by_name_take_defaults_for_newer_ones() -> None:
    """A checkpoint written before a parameter existed resumes with that parameter's default."""
    params = EstimatorParams(use_odometry=False, min_points=25)
    assert pickle.loads(pickle.dumps(params)) == params
    state = params.__getstate__()
    del state["profile_turn"]  # "added later"
    older = object.__new__(EstimatorParams)
    older.__setstate__(state)
    assert older.profile_turn is EstimatorParams().profile_turn
    assert older.min_points == 25
    with pytest.raises(TypeError):  # the dataclass default (by position) is refused
        older.__setstate__([getattr(params, f.name) for f in dataclasses.fields(params)])
