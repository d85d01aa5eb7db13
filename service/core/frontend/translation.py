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
import numpy.typing as npt
from numpy.lib.stride_tricks import as_strided

from service.core.types import FloatArray, parabolic_offset


def orientation_weights(
    directions_rad: FloatArray,
    reliable: npt.NDArray[np.bool_],
    theta_rad: float,
    isolated_weight: float = 0.15,
    weak: npt.NDArray[np.bool_] | None = None,
) -> FloatArray:
    """(M, 2) weights: column 0 = how much a point constrains x, column 1 = y.

    `directions_rad` are the points' surface directions in the laser frame
    (`rotation.tangent_directions`); `theta_rad` turns them into the map frame. A wall along y
    (tangent angle β = 90°) constrains x: w_x = sin²β, w_y = cos²β, sharpened. Points without
    a reliable direction (no close neighbours) vote `isolated_weight` on both axes. `weak`
    points (a direction from far, collinear neighbours only) vote `isolated_weight` across
    their wall and nothing along it: a grazing wall point keeps its place relative to the
    robot, so along the wall it votes for standing still.
    """
    s2 = np.sin(directions_rad + theta_rad)
    s2 *= s2
    # Sharpen: a tangent within ~25° of an axis votes only for the other axis.
    w = np.empty((s2.shape[0], 2))
    np.clip((s2 - 0.5) * 1.6 + 0.5, 0.0, 1.0, out=w[:, 0])
    np.clip(0.5 - (s2 - 0.5) * 1.6, 0.0, 1.0, out=w[:, 1])
    unreliable = ~reliable
    if weak is not None:
        w[weak] *= isolated_weight
        unreliable &= ~weak
    w[unreliable] = isolated_weight
    return w


@dataclass(frozen=True, slots=True)
class AxisMatch:
    """The result of one 1-D correlation."""

    offset_m: float  # the chosen shift (prediction when ambiguous)
    peak_offsets_m: tuple[float, ...]  # candidate peaks, best first
    sharpness: float  # 0 (flat) .. 1 (single sharp peak)
    support: float  # weighted number of current points constraining the axis
    ambiguous: bool


@dataclass(frozen=True, slots=True)
class AxisDensity:
    """A reference's density along one map axis, ready for every shift of every scan.

    The reference points are binned at the shift step and smoothed by the paper's bin once per
    reference (the local map changes only with a keyframe), with `pad` zero bins on each side so
    that a window of up to ±`max_half_steps` shifts that starts outside reads only zeros.
    """

    origin_m: float  # coordinate of bin 0's lower edge (a multiple of step_m)
    step_m: float
    max_half_steps: int  # the widest window it serves, in steps each side
    values: FloatArray


def axis_density(
    ref_coords_m: FloatArray,
    ref_weights: FloatArray,
    step_m: float,
    bin_m: float,
    max_half_window_m: float,
) -> AxisDensity:
    """Bin the reference at `step_m` and smooth it by the `bin_m` triangle.

    Binning both scans at `bin_m` and averaging over the bin phase gives a triangle of
    half-width `bin_m`: peaked, so the sub-step refinement works (a plain box would give a
    flat-topped correlation). The triangle is a box convolved with itself, so it is two running
    sums.
    """
    half = max(1, round(bin_m / step_m))
    max_half_steps = max(1, round(max_half_window_m / step_m))
    pad = 2 * max_half_steps + 2 * half + 2  # > any window (2·max_half_steps + 1) + the smoothing
    if ref_coords_m.shape[0] == 0:
        return AxisDensity(0.0, step_m, max_half_steps, np.zeros(2 * pad))
    lo_bin = math.floor(float(ref_coords_m.min()) / step_m) - pad
    hi_bin = math.floor(float(ref_coords_m.max()) / step_m) + pad
    origin_m = lo_bin * step_m
    n_bins = hi_bin - lo_bin + 1
    idx = np.floor((ref_coords_m - origin_m) / step_m).astype(np.intp)
    raw = np.bincount(idx, weights=ref_weights, minlength=n_bins)[:n_bins]
    # Box of `half + 1` bins twice = the triangle 1 - |t| / (half + 1), |t| <= half, centred.
    width = half + 1
    values: FloatArray = np.asarray(raw, dtype=np.float64)  # float already: no copy
    for lead in (half // 2 + half % 2, half // 2):  # the two boxes' centring adds up to `half`
        c = np.zeros(n_bins + width)
        values.cumsum(out=c[width:])
        # boxed[j] = c[width + j] - c[j] = Σ values[j - width + 1 .. j], shifted left by `lead`.
        boxed = np.zeros(n_bins)
        np.subtract(c[width + lead :], c[lead:-width], out=boxed[: n_bins - lead])
        values = boxed
    return AxisDensity(
        origin_m, step_m, max_half_steps, np.asarray(values / width, dtype=np.float64)
    )


def correlate_axis(
    density: AxisDensity,
    cur_coords_m: FloatArray,
    cur_weights: FloatArray,
    centre_m: float,
    half_window_m: float,
) -> tuple[FloatArray, FloatArray]:
    """E(shift) for shifts `centre + k·step` within ±half_window (paper eq. 1/2).

    `cur_coords_m` are current points' coordinates before the shift; E(s) is the correlation of
    the current histogram shifted by s with the reference histogram: the reference density read
    at every shifted current point, weighted.
    """
    step_m = density.step_m
    n_half = max(1, min(round(half_window_m / step_m), density.max_half_steps))
    shifts = centre_m + step_m * np.arange(-n_half, n_half + 1, dtype=np.float64)
    k = shifts.shape[0]
    dens = density.values
    n_starts = dens.shape[0] - k + 1
    # Points that do not constrain this axis add nothing, and points in the same fine bin add
    # the same row: gather each occupied bin once with the summed weight.
    voting = np.flatnonzero(cur_weights > 0.0)
    start = np.floor((cur_coords_m[voting] + (shifts[0] - density.origin_m)) / step_m)
    inside = (start >= 0.0) & (start < n_starts)  # outside: every shift reads zero padding
    start_i = start[inside].astype(np.intp)
    if start_i.shape[0] == 0:
        return shifts, np.zeros(k, dtype=np.float64)
    s0 = int(start_i.min())
    summed = np.bincount(start_i - s0, weights=cur_weights[voting][inside])
    occupied = np.flatnonzero(summed)
    # Row i of the sliding-window view = dens[b_i : b_i + K]: one fancy index, (M', K).
    step_b = dens.strides[0]
    windows = as_strided(dens, (n_starts, k), (step_b, step_b), writeable=False)
    rows = windows[occupied + s0]
    # Row by row, not a BLAS product: kernels differ in the last bits (see heading.py).
    rows *= summed[occupied, None]
    energy = rows.sum(axis=0)
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
    # The few peaks in plain Python from here (fewer numpy calls: speed).
    peak_e = energy[peaks].tolist()
    peak_s = shifts_m[peaks].tolist()
    # Rank the peaks by correlation × a Gaussian motion prior around the prediction (no prior:
    # the paper's plain argmax).
    if prior_sigma_m > 0.0:
        rank = [
            e * math.exp(-0.5 * ((x - predicted_m) / prior_sigma_m) ** 2)
            for e, x in zip(peak_e, peak_s, strict=True)
        ]
    else:
        rank = peak_e
    order = sorted(range(len(rank)), key=lambda j: -rank[j])
    best = order[0]
    e_max = peak_e[best]
    e_min = float(energy.min())
    step = float(shifts_m[1] - shifts_m[0])
    # Strongest rival peak well separated from the best one.
    far = [j for j in order if abs(peak_s[j] - peak_s[best]) > separation_m]
    rival = max(peak_e[j] for j in far) if far else e_min
    contrast = (e_max - rival) / max(e_max - e_min, 1e-12) if e_max > e_min else 0.0
    ambiguous = rival >= ambiguity_ratio * e_max or e_max - e_min < 1e-9
    chosen_peak = best
    if ambiguous and far:
        close = [j for j in order if peak_e[j] >= ambiguity_ratio * e_max]
        chosen_peak = min(close, key=lambda j: abs(peak_s[j] - predicted_m))
    chosen = int(peaks[chosen_peak])
    offset = 0.0
    if refine and 0 < chosen < n - 1:
        offset = parabolic_offset(
            float(energy[chosen - 1]), float(energy[chosen]), float(energy[chosen + 1])
        )
    value = peak_s[chosen_peak] + offset * step
    at_edge = chosen in (0, n - 1)
    if at_edge:
        ambiguous = True
    cands = tuple(peak_s[j] for j in order[:3])
    return AxisMatch(value, cands, min(max(contrast, 0.0), 1.0), support, ambiguous)
