"""The two motion models and their weighting (`service.core.frontend.motion`), on their own."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest

from service.core.frontend.motion import MotionModels

SCAN_PERIOD_S = 0.2  # the estimator's nominal period of the per-scan model
MAX_ACCEL_M_S2 = 0.5
BOUNDS = {"max_speed_m_s": 2.0, "max_step_change_m": MAX_ACCEL_M_S2 * SCAN_PERIOD_S**2}


def _drive(
    models: MotionModels, steps_m: list[float], periods_s: list[float], sigma_m: float = 0.01
) -> tuple[float, float]:
    """Feed forward steps (x only) with their stamp periods, the per-scan model updated as
    the estimator does (0.3 / 0.7 smoothing, bounded by max_accel × the nominal period).
    Returns the per-scan model's step at the end."""
    per_scan_m_s: float | None = None
    for step_m, dt_s in zip(steps_m, periods_s, strict=True):
        predicted = None if per_scan_m_s is None else (per_scan_m_s * SCAN_PERIOD_S, 0.0)
        models.observe((step_m, 0.0), predicted, dt_s, sigma_m=sigma_m, **BOUNDS)
        v = step_m / SCAN_PERIOD_S
        if per_scan_m_s is not None:
            v = 0.3 * per_scan_m_s + 0.7 * v
            dv_max = MAX_ACCEL_M_S2 * SCAN_PERIOD_S
            v = per_scan_m_s + max(-dv_max, min(dv_max, v - per_scan_m_s))
        per_scan_m_s = v
    assert per_scan_m_s is not None
    return per_scan_m_s * SCAN_PERIOD_S, 0.0


def test_scans_every_fixed_distance_or_turn_weigh_the_per_second_model() -> None:
    """0.7 m/s, a scan every 0.3 m, through a corner every 10° (0.17 m): the per-scan model
    lags behind the corner's short steps, the per-second model sees one speed throughout."""
    speed_m_s = 0.7
    steps = [0.3] * 10 + [0.17] * 9 + [0.3] * 4
    periods = [s / speed_m_s for s in steps]
    models = MotionModels()
    per_scan_step = _drive(models, steps, periods)
    assert per_scan_step[0] < 0.27  # still lagging four scans after the corner
    assert models.per_second_weight > 0.99
    step = models.predict(per_scan_step, 0.3 / speed_m_s)
    assert step[0] == pytest.approx(0.3, abs=0.005)


def test_bursty_stamps_keep_the_per_scan_model() -> None:
    """Intel-like stamps, 1 ms then 0.6 s apart, the robot moving 0.1 m every scan."""
    steps = [0.1] * 30
    periods = [0.001 if k % 2 else 0.6 for k in range(30)]
    models = MotionModels()
    per_scan_step = _drive(models, steps, periods)
    assert models.per_second_weight < 1e-6
    assert models.predict(per_scan_step, 0.6)[0] == pytest.approx(per_scan_step[0], abs=1e-6)


def test_where_both_predict_alike_the_per_scan_model_keeps_the_larger_share() -> None:
    """A steady scanner at a steady speed: the two predict the same within the match noise,
    and the per-scan model (the default) keeps its share behind the margin."""
    rng = np.random.default_rng(1)
    steps = list(0.1 + rng.normal(0.0, 0.005, 60))
    models = MotionModels()
    _drive(models, steps, [SCAN_PERIOD_S] * 60)
    assert models.per_second_weight < 0.5


def test_a_carried_step_teaches_neither_model() -> None:
    models = MotionModels()
    _drive(models, [0.3, 0.3, 0.3], [0.43, 0.43, 0.43])
    before = pickle.dumps(models)
    models.observe((0.0, 0.0), (0.3, 0.0), 0.43, sigma_m=None, **BOUNDS)
    assert pickle.dumps(models) == before


def test_no_velocity_yet_predicts_the_per_scan_step() -> None:
    models = MotionModels()
    assert models.predict((0.12, -0.03), 0.5) == (0.12, -0.03)
    models.observe((0.3, 0.0), None, 0.0, sigma_m=0.01, **BOUNDS)  # no time: nothing learnt
    assert models.velocity_xy_m_s is None


def test_speed_is_clamped_and_state_survives_pickling() -> None:
    models = MotionModels()
    models.observe((5.0, 0.0), None, 0.5, sigma_m=0.01, **BOUNDS)
    assert models.velocity_xy_m_s is not None
    assert math.hypot(*models.velocity_xy_m_s) == pytest.approx(2.0)
    restored = pickle.loads(pickle.dumps(models))
    assert restored == models
