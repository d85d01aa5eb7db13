"""The turn between two consecutive scans from their range profiles, without walls.

A robot that turns by k beam increments between two scans sees, in beam i, what it saw in beam
i + k before; its translation between two scans is small against the ranges. Sliding one range
profile along the other and counting the beams that agree gives that turn with no assumption
about the structure: it works where the Manhattan heading has no wall (the round hall of ACES)
and is not ambiguous by 90°, which the projection histograms and the direction histograms are.
The estimator uses it, without odometry, as the heading prediction (a gyroscope from the laser).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from numpy.lib.stride_tricks import sliding_window_view

from service.core.types import FloatArray


@dataclass(frozen=True, slots=True)
class ProfileTurn:
    turn_rad: float  # heading of the current scan minus that of the previous one
    score: float  # share of the current scan's valid beams that agree at that turn


def _agreement(
    previous_ranges_m: FloatArray, current_ranges_m: FloatArray, tolerance_m: FloatArray, m: int
) -> npt.NDArray[np.intp]:
    """Beams that agree for every shift -m..m of the previous profile (row j: shift j - m)."""
    n = current_ranges_m.shape[0]
    padded = np.full(n + 2 * m, np.nan)
    padded[m : m + n] = previous_ranges_m
    # Row j holds the previous beam i + j - m under current beam i.
    shifted = sliding_window_view(padded, n)
    with np.errstate(invalid="ignore"):
        agree = np.abs(shifted - current_ranges_m) < tolerance_m  # NaN compares false
    hits: npt.NDArray[np.intp] = np.count_nonzero(agree, axis=1)
    return hits


def profile_turn(
    previous_ranges_m: FloatArray,
    current_ranges_m: FloatArray,
    increment_rad: float,
    max_turn_rad: float,
    *,
    tolerance_m: float = 0.03,
    tolerance_per_m: float = 0.02,
    coarse_step_rad: float = math.radians(1.0),
) -> ProfileTurn | None:
    """Best turn within ±`max_turn_rad`, in whole beams. NaN marks invalid beams.

    A beam agrees when the ranges differ by less than `tolerance_m` + `tolerance_per_m` × range
    (the robot's own motion changes far ranges more). Dense scanners are searched coarse to
    fine: every `coarse_step_rad` on every such beam, then beam by beam around the best turn
    (speed: a UTM-30LX has 1,081 beams, a ±72° search 577 shifts). None: different scanners
    or no valid beams.
    """
    n = current_ranges_m.shape[0]
    if n == 0 or previous_ranges_m.shape[0] != n or increment_rad <= 0.0:
        return None
    valid = np.count_nonzero(np.isfinite(current_ranges_m))
    if valid == 0:
        return None
    m = max(1, min(n - 1, int(max_turn_rad / increment_rad)))
    tolerance = tolerance_m + tolerance_per_m * current_ranges_m
    stride = max(1, round(coarse_step_rad / increment_rad))
    if stride == 1 or m < 2 * stride:
        hits = _agreement(previous_ranges_m, current_ranges_m, tolerance, m)
        j = int(np.argmax(hits))
        return ProfileTurn((j - m) * increment_rad, float(hits[j]) / valid)
    coarse = _agreement(
        previous_ranges_m[::stride], current_ranges_m[::stride], tolerance[::stride], m // stride
    )
    centre = (int(np.argmax(coarse)) - m // stride) * stride
    # Beam by beam within one coarse step of it: the previous profile shifted by `centre`.
    lo = max(-m, centre - stride)
    hi = min(m, centre + stride)
    best_k, best_hits = 0, -1
    for k in range(lo, hi + 1):
        if k >= 0:
            d = np.abs(previous_ranges_m[k:] - current_ranges_m[: n - k])
            t = tolerance[: n - k]
        else:
            d = np.abs(previous_ranges_m[: n + k] - current_ranges_m[-k:])
            t = tolerance[-k:]
        with np.errstate(invalid="ignore"):
            h = int(np.count_nonzero(d < t))
        if h > best_hits:
            best_k, best_hits = k, h
    return ProfileTurn(best_k * increment_rad, best_hits / valid)
