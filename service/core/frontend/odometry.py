"""How far the odometry's heading can be trusted, learnt from the scans themselves.

Odometry predicts each scan's pose from the previous one. Where the walls measure the heading,
the odometry's error over one scan is seen directly: the innovation between the heading the walls
gave and the one the odometry predicted. `OdometryConsistency` keeps a robust running mean
square of it. Where the walls do not measure the heading (clutter, no dominant wall), the pose
follows the odometry, and its heading error grows with every such scan. Odometry errors are
correlated (a miscalibrated wheel base, a gyro bias: Intel's odometry turns about 0.1° per scan
away from the walls, all one way), so the drift is bounded as linear in the scans, which holds
for a bias as well as for noise. The estimator widens the odometry's heading prior by that drift
and lets strong walls re-anchor a heading that has drifted that far: a pose that followed poor
odometry is not held to a prediction that has walked away from the walls (which made Intel
worse with odometry than without it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from service.core.types import fields_by_name, restore_fields


@dataclass(frozen=True, slots=True)
class OdometryParams:
    """The learning of the odometry's heading error per scan."""

    initial_heading_step_deg: float = 0.5  # before any innovation is seen
    learning_rate: float = 0.02  # weight of each new innovation in the running mean square
    clip_sigmas: float = 3.0  # an innovation beyond this × the current RMS counts as this

    def __getstate__(self) -> dict[str, object]:
        return fields_by_name(self)

    def __setstate__(self, state: object) -> None:
        restore_fields(self, state if isinstance(state, dict) else {}, OdometryParams())


@dataclass(slots=True)
class OdometryConsistency:
    """The odometry's heading error per scan, and the scans since the heading was measured."""

    params: OdometryParams = field(default_factory=OdometryParams)
    heading_step_ms_rad2: float = -1.0  # mean square innovation per scan (< 0: unset)
    unmeasured_scans: int = 0  # consecutive poses whose heading followed the odometry

    def __post_init__(self) -> None:
        if self.heading_step_ms_rad2 < 0.0:
            self.heading_step_ms_rad2 = math.radians(self.params.initial_heading_step_deg) ** 2

    def __getstate__(self) -> dict[str, object]:
        return fields_by_name(self)

    def __setstate__(self, state: object) -> None:
        restore_fields(self, state if isinstance(state, dict) else {}, OdometryConsistency())

    @property
    def heading_step_rms_rad(self) -> float:
        return math.sqrt(self.heading_step_ms_rad2)

    def heading_drift_rad(self) -> float:
        """The heading error the odometry may have added since the walls last measured the
        heading: the learnt RMS per scan, times the scans since (linear: a bias as well)."""
        return self.unmeasured_scans * self.heading_step_rms_rad

    def observe(self, innovation_rad: float | None, measured: bool) -> None:
        """One scan: `innovation_rad` is measured − odometry-predicted heading, given only when
        this heading and the previous one were both measured (the odometry's error over one
        scan); `measured` says whether this pose's heading came from the walls."""
        if innovation_rad is not None:
            p = self.params
            bound = p.clip_sigmas * self.heading_step_rms_rad
            e = min(abs(innovation_rad), bound)
            self.heading_step_ms_rad2 += p.learning_rate * (e * e - self.heading_step_ms_rad2)
        self.unmeasured_scans = 0 if measured else self.unmeasured_scans + 1
