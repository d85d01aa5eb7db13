"""The walls' angle of one scan (paper §II): projection histograms over rotation angles.

Convention: rotating the laser-frame points by the robot heading θ gives them the map's
orientation. Walls parallel to the map axes then project onto a single histogram bin, so the
rotation α that maximises the projection-histogram peak is the heading modulo 90° (walls come
in two perpendicular families; modulo 180° for one family). `walls` turns it into the
matcher's heading prior.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from service.core.frontend import kernels
from service.core.types import FloatArray, parabolic_offset

QUARTER = math.pi / 2.0


def wrap_quarter(angle_rad: float | FloatArray) -> float | FloatArray:
    """Wrap to [-45°, 45°)."""
    return (angle_rad + QUARTER / 2.0) % QUARTER - QUARTER / 2.0


def _rotation_columns(angles_rad: FloatArray, bin_m: float) -> FloatArray:
    """(2, 2K): row 0 multiplies x, row 1 multiplies y, giving both coordinates of R(α)·p for
    every α, in bin units."""
    k = angles_rad.shape[0]
    c = np.cos(angles_rad)
    s = np.sin(angles_rad)
    dirs = np.empty((2, 2 * k))
    dirs[0, :k] = c  # x' = c·x - s·y
    dirs[1, :k] = -s
    dirs[0, k:] = s  # y' = s·x + c·y
    dirs[1, k:] = c
    dirs /= bin_m
    return dirs


def _hard_offset(points_xy_m: FloatArray, bin_m: float) -> tuple[int, int]:
    """(offset, width) in bins of hard bins: the offset from the largest range instead of the
    data's extremes (only bin membership matters for hard bins, and an offset by whole bins
    does not change it)."""
    x, y = points_xy_m[:, 0], points_xy_m[:, 1]
    r2_max = float((x * x + y * y).max()) if points_xy_m.shape[0] else 0.0  # not sum(axis=1)
    r_bins = math.sqrt(r2_max) / bin_m
    lo = -math.ceil(r_bins) - 1
    return lo, math.ceil(r_bins) - lo + 2


def heading_scores(
    points_xy_m: FloatArray, angles_rad: FloatArray, bin_m: float, soft: bool = True
) -> FloatArray:
    """The walls' score of each candidate rotation: Σ h² over both projections (pairs of points
    sharing a bin), so that both wall families count. `soft` splits each point between its two
    nearest bins, which makes the score smooth in the angle."""
    k = angles_rad.shape[0]
    if soft:
        h, _ = kernels.soft_histograms(points_xy_m, _rotation_columns(angles_rad, bin_m))
        sq = np.einsum("ij,ij->i", h, h)
        return np.asarray(sq[:k] + sq[k:], dtype=np.float64)
    # Hard bins: integer counts, so Σ h² is exact in int64.
    lo, width = _hard_offset(points_xy_m, bin_m)
    columns = _rotation_columns(angles_rad, bin_m)
    energy, _ = kernels.hard_counts(points_xy_m, columns, float(lo), width)
    return (energy[:k] + energy[k:]).astype(np.float64)


@dataclass(frozen=True, slots=True)
class HeadingMeasurement:
    """The walls' angle of one scan."""

    angle_rad: float  # in [-45°, 45°): heading modulo 90°
    peak_fraction: float  # share of points on the strongest line of each family


def _circular_peaks(scores: FloatArray) -> npt.NDArray[np.int64]:
    left = np.concatenate((scores[-1:], scores[:-1]))
    right = np.concatenate((scores[1:], scores[:1]))
    peaks = np.flatnonzero((scores >= left) & (scores > right))
    if peaks.size == 0:
        peaks = np.array([int(np.argmax(scores))])
    return peaks.astype(np.int64)


_FINE_FIRST_STEPS = 7  # the fine peak is within ±0.6° of the 1° coarse peak (measured)


def _fine_search(
    pts: FloatArray, centre_rad: float, *, step_rad: float, bin_m: float, half_rad: float
) -> tuple[FloatArray, FloatArray]:
    """Scores at `centre + k·step`, |k·step| <= half_rad, around the maximum nearest the centre.

    Starts with ±`_FINE_FIRST_STEPS` and extends a side only while the maximum sits on its
    edge, so the usual case scores a fraction of the angles of the whole window.
    """
    n_half = max(1, round(half_rad / step_rad))
    lo = hi = min(n_half, _FINE_FIRST_STEPS)
    ks = np.arange(-lo, hi + 1, dtype=np.float64)
    scores = heading_scores(pts, centre_rad + step_rad * ks, bin_m)
    while True:
        i = int(np.argmax(scores))
        if i == 0 and lo < n_half:
            more = np.arange(-min(n_half, lo + _FINE_FIRST_STEPS), -lo, dtype=np.float64)
            lo = -int(more[0])
            ks = np.concatenate((more, ks))
            scores = np.concatenate(
                (heading_scores(pts, centre_rad + step_rad * more, bin_m), scores)
            )
        elif i == ks.shape[0] - 1 and hi < n_half:
            more = np.arange(hi + 1, min(n_half, hi + _FINE_FIRST_STEPS) + 1, dtype=np.float64)
            hi = int(more[-1])
            ks = np.concatenate((ks, more))
            scores = np.concatenate(
                (scores, heading_scores(pts, centre_rad + step_rad * more, bin_m))
            )
        else:
            return centre_rad + step_rad * ks, scores


def _within(points_xy_m: FloatArray, max_range_m: float) -> FloatArray:
    """The points within `max_range_m` (all of them when fewer than 10 are)."""
    r2 = points_xy_m[:, 0] ** 2 + points_xy_m[:, 1] ** 2
    near = points_xy_m.take(np.flatnonzero(r2 <= max_range_m**2), axis=0)
    return near if near.shape[0] >= 10 else points_xy_m


def measure_heading(
    points_xy_m: FloatArray,
    step_rad: float,
    bin_m: float,
    *,
    coarse_step_rad: float = math.radians(1.0),
    coarse_bin_m: float = 0.05,
    fine_half_rad: float = math.radians(1.5),
    refine: bool = True,
    max_range_m: float = 12.0,
) -> HeadingMeasurement:
    """The walls' angle: coarse search over the whole 90°, fine search around its best peak.

    The coarse curve (`coarse_step_rad`, `coarse_bin_m`) covers every direction; its best local
    maximum is searched again at the paper's step and bin, with a parabolic sub-step
    refinement (`refine`).
    """
    pts = _within(points_xy_m, max_range_m)
    coarse = np.arange(-QUARTER / 2.0, QUARTER / 2.0, coarse_step_rad)
    s_coarse = heading_scores(pts, coarse, coarse_bin_m, soft=False)
    peaks = _circular_peaks(s_coarse)
    chosen = int(peaks[np.argsort(-s_coarse[peaks])][0])
    angles, scores = _fine_search(
        pts, float(coarse[chosen]), step_rad=step_rad, bin_m=bin_m, half_rad=fine_half_rad
    )
    i = int(np.argmax(scores))
    offset = 0.0
    if refine and 0 < i < len(angles) - 1:
        offset = parabolic_offset(float(scores[i - 1]), float(scores[i]), float(scores[i + 1]))
    best = float(wrap_quarter(float(angles[i]) + offset * step_rad))
    n = max(1, pts.shape[0])
    return HeadingMeasurement(angle_rad=best, peak_fraction=float(_peaks(pts, best, bin_m)) / n)


def _peaks(points_xy_m: FloatArray, angle_rad: float, bin_m: float) -> int:
    """The points on the strongest line of each family at `angle_rad`: the peaks of its two
    hard projection histograms, added."""
    lo, width = _hard_offset(points_xy_m, bin_m)
    columns = _rotation_columns(np.array([angle_rad]), bin_m)
    _, peaks = kernels.hard_counts(points_xy_m, columns, float(lo), width)
    return int(peaks[0] + peaks[1])
