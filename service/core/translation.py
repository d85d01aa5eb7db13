"""Translation by 1-D histogram correlation along the map axes (paper §III).

The paper shifts the current scan by x' in 0.005 m steps, re-histograms it with 0.03 m bins and
correlates with the reference histogram: `Ex(x') = Σ_i hx_ref(i) · hx_cur(i, x')`. Summing over
bins equals summing over current points of the reference histogram value at the bin the shifted
point falls in, so here the reference is histogrammed once on a fine 0.005 m grid, smoothed by
the 0.03 m bin (a box filter: the average over bin phases of the paper's coarse histogram), and
every shift is a gather of that density at the shifted points: no re-histogramming.

Additions: points vote with weights saying which axis they constrain (a wall along y fixes x,
not y), the search can be centred on a prediction, and the peak is refined by a parabola and
checked for ambiguity (flat or multi-peak correlation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import as_strided

from service.core.heading import parabolic_offset
from service.core.types import FloatArray


def orientation_weights(
    points_xy_m: FloatArray, max_gap_m: float = 0.3, isolated_weight: float = 0.15
) -> FloatArray:
    """(M, 2) weights: column 0 = how much a point constrains x, column 1 = y.

    The local wall direction comes from the neighbours two points away in scan order (the points
    must already be in the map orientation). A wall along y (vertical tangent) constrains x:
    w_x = sin²β, w_y = cos²β with β the tangent angle. Points without close neighbours vote
    0.5 on both axes.
    """
    m = points_xy_m.shape[0]
    w = np.full((m, 2), isolated_weight)
    if m < 5:
        return w
    d = points_xy_m[4:] - points_xy_m[:-4]
    length = np.hypot(d[:, 0], d[:, 1])
    ok = (length > 1e-6) & (length < 4.0 * max_gap_m)
    # A wall point also needs its two immediate neighbours close (no depth jump in between).
    near = np.hypot(*np.diff(points_xy_m, axis=0).T) < max_gap_m
    ok &= near[:-3] & near[1:-2] & near[2:-1] & near[3:]
    safe = np.where(ok, length, 1.0)
    s2 = (d[:, 1] / safe) ** 2
    # Sharpen: a tangent within ~20° of an axis votes (almost) only for the other axis.
    wx = np.minimum(np.maximum((s2 - 0.5) * 1.6 + 0.5, 0.0), 1.0)
    wy = np.minimum(np.maximum(((1.0 - s2) - 0.5) * 1.6 + 0.5, 0.0), 1.0)
    w[2:-2, 0] = np.where(ok, wx, isolated_weight)
    w[2:-2, 1] = np.where(ok, wy, isolated_weight)
    return w


@dataclass(frozen=True, slots=True)
class AxisMatch:
    """The result of one 1-D correlation."""

    offset_m: float  # the chosen shift (prediction when ambiguous)
    peak_offsets_m: tuple[float, ...]  # candidate peaks, best first
    sharpness: float  # 0 (flat) .. 1 (single sharp peak)
    support: float  # weighted number of current points constraining the axis
    ambiguous: bool


def correlate_axis(  # noqa: PLR0917 - the paper's equation, argument for argument
    ref_coords_m: FloatArray,
    ref_weights: FloatArray,
    cur_coords_m: FloatArray,
    cur_weights: FloatArray,
    centre_m: float,
    half_window_m: float,
    step_m: float,
    bin_m: float,
) -> tuple[FloatArray, FloatArray]:
    """E(shift) for shifts `centre + k·step` within ±half_window.

    `cur_coords_m` are current points' coordinates before the shift; E(s) is the correlation of
    the current histogram shifted by s with the reference histogram (paper eq. 1/2).
    """
    n_half = max(1, round(half_window_m / step_m))
    shifts = centre_m + step_m * np.arange(-n_half, n_half + 1, dtype=np.float64)
    lo = min(float(ref_coords_m.min()), float(cur_coords_m.min()) + float(shifts[0])) - bin_m
    hi = max(float(ref_coords_m.max()), float(cur_coords_m.max()) + float(shifts[-1])) + bin_m
    n_bins = math.ceil((hi - lo) / step_m) + 2
    ref_idx = np.floor((ref_coords_m - lo) / step_m).astype(np.int64)
    dens = np.asarray(
        np.bincount(ref_idx, weights=ref_weights, minlength=n_bins)[:n_bins], dtype=np.float64
    )
    # Smooth by the paper's bin. Binning both scans at `bin_m` and averaging over the bin
    # phase gives a triangle of half-width `bin_m`: peaked, so the sub-step refinement works
    # (a plain box would give a flat-topped correlation). Only the bins the shifted current
    # points reach are smoothed (same values as smoothing the whole density).
    half = max(1, round(bin_m / step_m))
    tri = 1.0 - np.abs(np.arange(-half, half + 1)) / (half + 1)
    base = (cur_coords_m + shifts[0] - lo) / step_m
    base_idx = np.floor(base).astype(np.intp)
    k = shifts.shape[0]
    first = min(max(int(base_idx.min()), 0), n_bins - 1)
    last = min(max(int(base_idx.max()) + k - 1, first), n_bins - 1)
    padded = np.zeros(last - first + 1 + 2 * half)
    src_lo, src_hi = max(first - half, 0), min(last + half + 1, n_bins)
    padded[src_lo - (first - half) : src_hi - (first - half)] = dens[src_lo:src_hi]
    dens = np.asarray(np.convolve(padded, tri, mode="valid"), dtype=np.float64)
    # Gather the density at every shifted current point: row i = dens[b_i : b_i + K], (M, K).
    start = base_idx - first
    if int(start.min()) >= 0 and int(start.max()) + k <= dens.shape[0]:
        # Every window lies inside (the margins of lo/hi guarantee it): one fancy index of a
        # sliding-window view, no (M, K) index array.
        step_b = dens.strides[0]
        windows = as_strided(dens, (dens.shape[0] - k + 1, k), (step_b, step_b), writeable=False)
        vals = windows[start]
    else:  # defensive: clip indices to the bins, as a histogram edge would
        idx = start[:, None] + np.arange(k, dtype=np.intp)[None, :]
        vals = np.take(dens, idx, mode="clip")
    energy = cur_weights @ vals
    return shifts, np.asarray(energy, dtype=np.float64)


def pick_peak(
    shifts_m: FloatArray,
    energy: FloatArray,
    predicted_m: float,
    support: float,
    *,
    min_support: float,
    ambiguity_ratio: float,
    refine: bool,
    prior_sigma_m: float = 0.0,
    separation_m: float = 0.1,
) -> AxisMatch:
    """Choose the correlation peak; flag flat or multi-peak correlations as ambiguous.

    Flat or unsupported: fall back to the prediction. Several near-equal peaks: take the one
    nearest the prediction (the robot does not jump), still flagged.
    """
    n = energy.shape[0]
    e_max = float(energy.max()) if n else 0.0
    if n < 3 or e_max <= 0.0 or support < min_support:
        return AxisMatch(predicted_m, (), 0.0, support, True)
    # Local maxima (plateaus count once).
    interior = (energy[1:-1] >= energy[:-2]) & (energy[1:-1] > energy[2:])
    peaks = np.flatnonzero(interior) + 1
    if peaks.size == 0:
        i = int(np.argmax(energy))
        peaks = np.array([i])
    # Rank the peaks by correlation × a Gaussian motion prior around the prediction (no prior:
    # the paper's plain argmax).
    if prior_sigma_m > 0.0:
        rank = energy[peaks] * np.exp(-0.5 * ((shifts_m[peaks] - predicted_m) / prior_sigma_m) ** 2)
    else:
        rank = energy[peaks]
    order = peaks[np.argsort(-rank)]
    best = int(order[0])
    e_max = float(energy[best])
    e_min = float(energy.min())
    step = float(shifts_m[1] - shifts_m[0])
    # Strongest rival peak well separated from the best one.
    far = order[np.abs(shifts_m[order] - shifts_m[best]) > separation_m]
    rival = float(energy[far].max()) if far.size else e_min
    contrast = (e_max - rival) / max(e_max - e_min, 1e-12) if e_max > e_min else 0.0
    ambiguous = rival >= ambiguity_ratio * e_max or e_max - e_min < 1e-9
    chosen = best
    if ambiguous and far.size:
        close = order[energy[order] >= ambiguity_ratio * e_max]
        chosen = int(close[np.argmin(np.abs(shifts_m[close] - predicted_m))])
    offset = 0.0
    if refine and 0 < chosen < n - 1:
        offset = parabolic_offset(
            float(energy[chosen - 1]), float(energy[chosen]), float(energy[chosen + 1])
        )
    value = float(shifts_m[chosen]) + offset * step
    at_edge = chosen in (0, n - 1)
    if at_edge:
        ambiguous = True
    cands = tuple(float(shifts_m[j]) for j in order[:3])
    return AxisMatch(value, cands, min(max(contrast, 0.0), 1.0), support, ambiguous)
