"""The walls' heading prior (paper §II), as evidence the match can outvote, never as a rule.

Each scan's projection histogram gives the angle α (modulo 90°) that turns its major walls
onto the axes (`heading.measure_heading`). A *wall family* is a map-frame direction f (modulo
90°); a scan at heading θ seeing that family measures α = θ - f, so the walls say θ = f + α
(the member nearest the prediction). Its σ comes from how decisive the histogram is.

- The first family is the first decisive scan's walls, and it keeps being estimated: every
  decisive scan's matched θ - α moves it, by a running mean, so one scan's error is not kept.
- A scan whose walls fit no family gets no prior and is flagged NON_MANHATTAN. If the matcher's
  own rotation keeps saying the same new direction over `new_family_travel_m` of travel, it
  becomes a family (a wing at 30°). Clutter says a different direction every scan: never.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from service.core.frontend.heading import QUARTER, measure_heading, wrap_quarter
from service.core.types import FloatArray


@dataclass(frozen=True, slots=True)
class WallOptions:
    sigma_deg: float = 1.0  # σ of a fully decisive histogram's heading
    min_peak_fraction: float = 0.15  # share of points on the major lines: below, no prior ...
    full_peak_fraction: float = 0.5  # ... at and above, σ = sigma_deg (between: σ / √weight)
    family_gate_deg: float = 4.0  # a measured direction this close to a family belongs to it
    new_family_travel_m: float = 3.0  # a new direction must hold over this much travel ...
    new_family_agree_deg: float = 1.0  # ... within this
    axis_memory: int = 200  # the family angle is a running mean over at most this many scans
    step_deg: float = 0.1  # the paper's histogram search: rotation step ...
    bin_m: float = 0.02  # ... and bin
    max_range_m: float = 12.0


@dataclass(frozen=True, slots=True)
class WallMeasurement:
    angle_rad: float  # α in [-45°, 45°)
    weight: float  # decisiveness in [0, 1]


@dataclass
class WallState:
    """The families (map-frame angles in [-45°, 45°)) and the candidate for a new one."""

    families_rad: list[float] = field(default_factory=list)
    family_counts: list[int] = field(default_factory=list)
    candidate_rad: float | None = None
    candidate_travel_m: float = 0.0


def measure(points_xy_m: FloatArray, opts: WallOptions) -> WallMeasurement | None:
    """The scan's wall angle and how decisive it is (None: too few points)."""
    if points_xy_m.shape[0] < 10:
        return None
    m = measure_heading(
        points_xy_m, math.radians(opts.step_deg), opts.bin_m, max_range_m=opts.max_range_m
    )
    span = opts.full_peak_fraction - opts.min_peak_fraction
    weight = min(max((m.peak_fraction - opts.min_peak_fraction) / span, 0.0), 1.0)
    return WallMeasurement(m.angle_rad, weight)


def family_of(state: WallState, direction_rad: float, opts: WallOptions) -> int | None:
    """The family within the gate of a map-frame direction (modulo 90°), if any."""
    best, best_d = None, math.radians(opts.family_gate_deg)
    for k, f in enumerate(state.families_rad):
        d = abs(float(wrap_quarter(direction_rad - f)))
        if d <= best_d:
            best, best_d = k, d
    return best


def heading_prior(
    state: WallState, meas: WallMeasurement | None, predicted_rad: float, opts: WallOptions
) -> tuple[float | None, float]:
    """(absolute heading the walls say, σ) for a scan predicted at `predicted_rad`; (None, inf)
    when the walls are not decisive or fit no family."""
    if meas is None or meas.weight <= 0.0 or not state.families_rad:
        return None, math.inf
    k = family_of(state, predicted_rad - meas.angle_rad, opts)
    if k is None:
        return None, math.inf
    walls_rad = state.families_rad[k] + meas.angle_rad
    turns = round((predicted_rad - walls_rad) / QUARTER)
    return walls_rad + turns * QUARTER, math.radians(opts.sigma_deg) / math.sqrt(meas.weight)


def observe(
    state: WallState,
    meas: WallMeasurement | None,
    theta_rad: float,
    travel_m: float,
    opts: WallOptions,
) -> bool:
    """Learn from a matched scan; True when its walls fit a family."""
    if meas is None or meas.weight <= 0.0:
        return False
    direction = float(wrap_quarter(theta_rad - meas.angle_rad))
    if not state.families_rad:
        state.families_rad.append(direction)
        state.family_counts.append(1)
        return True
    k = family_of(state, direction, opts)
    if k is not None:
        count = min(state.family_counts[k] + 1, opts.axis_memory)
        f = state.families_rad[k]
        state.families_rad[k] = float(wrap_quarter(f + float(wrap_quarter(direction - f)) / count))
        state.family_counts[k] = count
        return True
    agree = math.radians(opts.new_family_agree_deg)
    if (
        state.candidate_rad is None
        or abs(float(wrap_quarter(direction - state.candidate_rad))) > agree
    ):
        state.candidate_rad, state.candidate_travel_m = direction, 0.0
        return False
    state.candidate_travel_m += travel_m
    if state.candidate_travel_m >= opts.new_family_travel_m:
        state.families_rad.append(state.candidate_rad)
        state.family_counts.append(1)
        state.candidate_rad, state.candidate_travel_m = None, 0.0
    return False
