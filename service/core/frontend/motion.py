"""Two constant-velocity models of the translation, weighted by how well each has predicted.

Without odometry the front end predicts each scan's translation from the motion so far. Two
models of that motion are each right somewhere and wrong elsewhere:

- *per scan* (the estimator's `scan_period_s`, a nominal period): the robot moves about the
  same from scan to scan. Logged stamps can be bursty (Intel: 1 ms to 1.5 s between scans while
  the robot moves about the same per scan), and there only this model predicts well.
- *per second* (the stamps): the robot moves at about the same speed. Where scans are taken
  every 0.3 m or 10° of turn (the paper's setting), the steps through a corner are half as
  long, and a per-scan model then carries the corner's short steps into the corridor after
  it: along a featureless corridor, where nothing corrects it, that corridor comes out short
  (tuning rings: 0.22 instead of 0.29 m per scan over 86 m). A per-second model does not see
  the corner at all.

Each model's prediction is scored against every measured step (both axes matched) by its
Gaussian log-likelihood under that match's σ, discounted so that the recent scans decide.
The prediction blends the two by the posterior weight of the per-second model, which needs a
margin of evidence over the per-scan one (the default, as before this module): a weighting,
not a switch, so a tie does not flip on the last bits of a match. This is the "interacting
multiple models" idea of tracking, reduced to its mixing weight. The estimator keeps it on
dense scans with steady stamps only, and forgets it elsewhere (`ManhattanEstimator.
_observe_motion`): there the estimate is the per-scan model's, bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from service.core.types import fields_by_name, restore_fields


@dataclass(frozen=True, slots=True)
class MotionModelParams:
    """The per-second model's bounds and the evidence that weighs it against the per-scan one."""

    memory: float = 0.9  # discount of past evidence per measured scan (~10 scans)
    margin_nats: float = 3.0  # log-likelihood the per-second model must lead by to weigh half
    min_sigma_m: float = 0.01  # a match's σ, when scoring predictions, no smaller than this
    smoothing: float = 0.3  # weight of the previous velocity in each update (as per scan)

    def __getstate__(self) -> dict[str, object]:
        return fields_by_name(self)

    def __setstate__(self, state: object) -> None:
        restore_fields(self, state if isinstance(state, dict) else {}, MotionModelParams())


@dataclass(slots=True)
class MotionModels:
    """The per-second velocity (robot frame, m/s) and both models' discounted evidence."""

    params: MotionModelParams = field(default_factory=MotionModelParams)
    velocity_xy_m_s: tuple[float, float] | None = None
    log_likelihood_per_scan: float = 0.0
    log_likelihood_per_second: float = 0.0

    def __getstate__(self) -> dict[str, object]:
        return fields_by_name(self)

    def __setstate__(self, state: object) -> None:
        restore_fields(self, state if isinstance(state, dict) else {}, MotionModels())

    @property
    def per_second_weight(self) -> float:
        """The per-second model's share of the prediction, in (0, 1)."""
        lead = self.log_likelihood_per_second - self.log_likelihood_per_scan
        z = lead - self.params.margin_nats
        return 1.0 / (1.0 + math.exp(-z)) if z > -700.0 else 0.0

    def per_second_step(self, dt_s: float) -> tuple[float, float] | None:
        """The per-second model's step over `dt_s` (None: no velocity yet)."""
        if self.velocity_xy_m_s is None:
            return None
        return self.velocity_xy_m_s[0] * dt_s, self.velocity_xy_m_s[1] * dt_s

    def predict(self, per_scan_step_m: tuple[float, float], dt_s: float) -> tuple[float, float]:
        """The blended translation step, robot frame."""
        step = self.per_second_step(dt_s)
        if step is None:
            return per_scan_step_m
        w = self.per_second_weight
        return (
            (1.0 - w) * per_scan_step_m[0] + w * step[0],
            (1.0 - w) * per_scan_step_m[1] + w * step[1],
        )

    def observe(
        self,
        step_m: tuple[float, float],
        per_scan_step_m: tuple[float, float] | None,
        dt_s: float,
        *,
        sigma_m: float | None,
        max_speed_m_s: float,
        max_step_change_m: float,
    ) -> None:
        """One committed scan. `step_m`: its translation since the previous pose, robot frame;
        `per_scan_step_m`: what the per-scan model had predicted (None: nothing yet);
        `sigma_m`: the match's σ when both axes were measured (None: the step is only a
        prediction carried on, which teaches neither model); `max_step_change_m`: the most its
        step may change in one scan (the estimator passes its acceleration bound × the period²,
        a bound in time; one held to the per-scan model's change per scan measured worse on
        the tuning worlds, see docs/estimator.md item 31)."""
        if sigma_m is None or dt_s <= 0.0:
            return
        p = self.params
        predicted = self.per_second_step(dt_s)
        if predicted is not None and per_scan_step_m is not None:
            var = 2.0 * max(sigma_m, p.min_sigma_m) ** 2

            def log_likelihood(pred: tuple[float, float]) -> float:
                return -((step_m[0] - pred[0]) ** 2 + (step_m[1] - pred[1]) ** 2) / var

            self.log_likelihood_per_scan = p.memory * self.log_likelihood_per_scan
            self.log_likelihood_per_scan += log_likelihood(per_scan_step_m)
            self.log_likelihood_per_second = p.memory * self.log_likelihood_per_second
            self.log_likelihood_per_second += log_likelihood(predicted)
        vx, vy = step_m[0] / dt_s, step_m[1] / dt_s
        speed = math.hypot(vx, vy)
        if speed > max_speed_m_s:
            vx, vy = vx * max_speed_m_s / speed, vy * max_speed_m_s / speed
        if self.velocity_xy_m_s is not None:
            ox, oy = self.velocity_xy_m_s
            a = p.smoothing
            vx, vy = a * ox + (1.0 - a) * vx, a * oy + (1.0 - a) * vy
            dv_max = max_step_change_m / dt_s
            dvx, dvy = vx - ox, vy - oy
            dv = math.hypot(dvx, dvy)
            if dv > dv_max > 0.0:
                vx, vy = ox + dvx * dv_max / dv, oy + dvy * dv_max / dv
        self.velocity_xy_m_s = (vx, vy)
