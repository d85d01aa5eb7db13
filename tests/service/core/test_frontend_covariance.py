"""The front end's covariance (`service.core.frontend.covariance`): a measured axis is its
match, an unmeasured one grows with time as the carried speed's error integrates."""

from __future__ import annotations

import math
import pickle

import pytest

from service.core.frontend.covariance import AxisCovariance, CovarianceParams, CovarianceTracker


def _carry(tracker: CovarianceTracker, seconds: float, rate_hz: float) -> float:
    """σ along x after `seconds` with x unmeasured and y measured, at `rate_hz`."""
    for _ in range(round(seconds * rate_hz)):
        cov = tracker.update(None, 0.01, True, dt_s=1.0 / rate_hz)
    return math.sqrt(cov[0])


def test_an_unmeasured_axis_grows_with_time_not_with_the_number_of_scans() -> None:
    slow = _carry(CovarianceTracker(), 4.0, 5.0)
    fast = _carry(CovarianceTracker(), 4.0, 40.0)
    assert fast == pytest.approx(slow, rel=0.02)


def test_from_a_standing_start_the_speed_is_unknown() -> None:
    """Nothing measured yet: 10 s at the unknown speed's σ (1 m/s) is metres, not the
    millimetres of the match it has never had."""
    sigma = _carry(CovarianceTracker(), 10.0, 10.0)
    assert sigma > 0.9 * CovarianceParams().unknown_speed_sigma_m_s * 10.0


def test_a_measured_speed_grows_slowly_then_the_unknown_speed_caps_it() -> None:
    tracker = CovarianceTracker()
    for _ in range(100):  # 10 s of sharp matches on both axes
        tracker.update(0.006, 0.006, True, dt_s=0.1)
    tracker.restart()
    short = _carry(tracker, 1.0, 10.0)
    assert 0.01 < short < 0.3  # a second carried at a speed known to a few cm/s
    assert tracker.along_x.speed_var_m2_s2 < 0.5**2
    _carry(tracker, 600.0, 10.0)
    assert tracker.along_x.speed_var_m2_s2 == pytest.approx(1.0)  # capped, still PSD
    a = tracker.along_x
    assert a.pos_speed_cov_m2_s**2 <= a.pos_var_m2 * a.speed_var_m2_s2 * (1.0 + 1e-9)


def test_a_match_sets_the_position_and_teaches_the_speed() -> None:
    axis = AxisCovariance(speed_var_m2_s2=1.0)
    axis.predict(0.1, 0.05, 1.0)
    axis.measure(0.01)
    assert axis.pos_var_m2 == pytest.approx(1e-4)  # the match's own, not a fused one
    # From the keyframe (exact) to a fix 0.1 s on, 1 cm: the speed to about 0.1 m/s.
    assert axis.speed_var_m2_s2 < 0.15**2
    axis.restart()
    assert axis.pos_var_m2 == 0.0
    assert axis.speed_var_m2_s2 > 0.0  # the speed is the robot's, not the keyframe's


def test_the_tracker_is_pickled_by_name() -> None:
    tracker = CovarianceTracker()
    tracker.update(None, 0.01, False, dt_s=0.2, frame_rad=0.5)
    back = pickle.loads(pickle.dumps(tracker))
    assert back.covariance() == tracker.covariance()
    assert back.along_x == tracker.along_x
    # A checkpoint of the older tracker (a variance per axis, no speeds) starts afresh.
    old = CovarianceTracker.__new__(CovarianceTracker)
    old.__setstate__((None, {"var_x": 0.1, "var_y": 0.2, "var_theta": 0.0, "frame_rad": 0.0}))
    assert old.covariance()[0] == 0.0
    assert old.along_x.speed_var_m2_s2 == pytest.approx(1.0)


def test_a_heading_anchored_again_carries_the_drift_of_its_keyframe() -> None:
    """A keyframe taken after 40 scans without walls has drifted by their relative heading
    errors; the walls measuring the heading again correct that drift, so the motion since the
    keyframe carries it. A keyframe on walls adds nothing to the anchored heading's σ."""
    p = CovarianceParams()
    anchored_var = math.radians(p.anchored_heading_sigma_deg) ** 2
    relative_var = math.radians(p.relative_heading_sigma_deg) ** 2
    tracker = CovarianceTracker()
    tracker.update(0.01, 0.01, True, dt_s=0.1)
    tracker.restart()
    assert tracker.update(0.01, 0.01, True, dt_s=0.1)[8] == pytest.approx(anchored_var)
    for _ in range(40):
        tracker.update(0.01, 0.01, False, dt_s=0.1)
    tracker.restart()
    relative = tracker.update(0.01, 0.01, False, dt_s=0.1)[8]
    assert relative == pytest.approx(relative_var)  # the keyframe's drift cancels
    tracker.restart()
    again = tracker.update(0.01, 0.01, True, dt_s=0.1)[8]
    assert again == pytest.approx(anchored_var + 41 * relative_var)
    tracker.restart()
    assert tracker.update(0.01, 0.01, True, dt_s=0.1)[8] == pytest.approx(anchored_var)
    back = pickle.loads(pickle.dumps(tracker))
    assert back.drift_var_theta == tracker.drift_var_theta
