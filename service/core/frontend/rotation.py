"""Relative rotation from angle histograms: the heading where the Manhattan walls fail.

Every point gets the direction of the local surface (modulo 180°) from its scan neighbours. The
histogram of those directions in the map frame (from the local map) is matched against the
current scan's directions rotated by candidate headings. Unlike the projection-histogram heading
(paper §II), this works for any structure (clutter, oblique walls), but it is relative: errors
accumulate. The estimator uses it as a sharp prediction for the Manhattan heading, and instead of
it when no Manhattan wall is consistent with the motion.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from service.core.types import FloatArray, convolve_valid, parabolic_offset

_BIN_RAD = math.radians(0.5)
_N_BINS = round(math.pi / _BIN_RAD)
_SMOOTH = np.exp(-0.5 * (np.arange(-6, 7) / 2.0) ** 2)  # σ = 1°


def tangent_directions(
    points_xy_m: FloatArray, max_gap_m: float = 0.3, max_line_deviation: float = 0.0
) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """Surface direction (radians, modulo π) of every point and whether it is reliable.

    The direction is the chord from the second neighbour before to the second after. It is
    reliable when the five points are close together (`max_gap_m`), or, farther apart, when
    they lie on a line: the middle three within `max_line_deviation` × the chord's length of
    it. Far along a wall the beams are spread wide; without a direction those points would
    vote on both axes, and as they keep their place relative to the robot, they vote for
    standing still (a corridor seen at grazing angles). `max_line_deviation` 0: close points only.
    """
    ang, close, line = split_tangent_directions(points_xy_m, max_gap_m, max_line_deviation)
    return ang, close | line


def split_tangent_directions(
    points_xy_m: FloatArray,
    max_gap_m: float = 0.3,
    max_line_deviation: float = 0.0,
    *,
    one_sided: bool = False,
) -> tuple[FloatArray, npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
    """`tangent_directions` with its two kinds of reliable point apart: (angles, close, line).

    `line` are the points with a direction only from far, collinear neighbours (not `close`).
    `one_sided`: a point left without one whose four neighbours on one side are collinear
    with it takes their line (`line`): the last return of a wall before the beams run out
    (down a corridor, beyond the range) is on that wall, not a point without direction.
    """
    m = points_xy_m.shape[0]
    ang = np.zeros(m)
    close = np.zeros(m, dtype=bool)
    line = np.zeros(m, dtype=bool)
    if m < 5:
        return ang, close, line
    d = points_xy_m[4:] - points_xy_m[:-4]
    gaps = np.hypot(*np.diff(points_xy_m, axis=0).T)
    near = gaps < max_gap_m
    good = near[:-3] & near[1:-2] & near[2:-1] & near[3:]
    # Coincident neighbours have no direction (column by column: (n, 2) sums are slow).
    distinct = np.abs(d[:, 0]) + np.abs(d[:, 1]) > 1e-6
    if max_line_deviation > 0.0:
        # Distance of each middle point from the chord line, times the chord's length.
        deviation = np.zeros(m - 4)
        for k in (1, 2, 3):
            v = points_xy_m[k : m - 4 + k] - points_xy_m[:-4]
            np.maximum(deviation, np.abs(d[:, 0] * v[:, 1] - d[:, 1] * v[:, 0]), out=deviation)
        collinear = deviation < max_line_deviation * (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])
        line[2:-2] = collinear & ~good & distinct
    window_ang = np.arctan2(d[:, 1], d[:, 0]) % math.pi
    ang[2:-2] = window_ang
    close[2:-2] = good & distinct
    if one_sided and max_line_deviation > 0.0:
        straight = collinear & distinct  # window w: points w .. w + 4
        for first, last in ((4, m), (0, m - 4)):  # the window ending, then starting, at j
            take = np.zeros(m, dtype=bool)
            take[first:last] = straight
            take &= ~(close | line)
            ang[take] = window_ang[np.flatnonzero(take) - first]
            line |= take
    return ang, close, line


def direction_counts(directions_rad: FloatArray) -> npt.NDArray[np.intp]:
    """Circular histogram counts (modulo π) of surface directions: the counts of sets add up."""
    idx = np.floor((directions_rad % math.pi) / _BIN_RAD).astype(np.int64) % _N_BINS
    return np.bincount(idx, minlength=_N_BINS)


def _smoothed(counts: npt.NDArray[np.intp]) -> FloatArray:
    h = counts.astype(np.float64)
    padded = np.concatenate((h[-6:], h, h[:6]))
    return convolve_valid(padded, _SMOOTH)


def direction_histogram(directions_rad: FloatArray) -> FloatArray:
    """Smoothed circular histogram (modulo π) of surface directions."""
    return _smoothed(direction_counts(directions_rad))


def direction_spectrum(counts: npt.NDArray[np.intp]) -> npt.NDArray[np.complex128]:
    """Spectrum of the histogram of these `direction_counts`: `match_rotation`'s reference.

    From counts, so that a local map sums its keyframes' counts instead of re-binning them all.
    """
    return np.asarray(np.fft.rfft(_smoothed(counts)), dtype=np.complex128)


def match_rotation(
    ref_spectrum: npt.NDArray[np.complex128],
    cur_directions_rad: FloatArray,
    predicted_rad: float,
    half_window_rad: float,
) -> tuple[float, float]:
    """Heading that best aligns the current directions with the reference (its spectrum).

    Returns (heading_rad, contrast) where contrast in [0, 1] compares the peak with the mean
    of the window (0 = flat).
    """
    # Circular cross-correlation of the two direction histograms (all shifts at once), then
    # the window around the prediction and a parabolic sub-bin peak.
    cur_hist = direction_histogram(cur_directions_rad)
    corr = np.fft.irfft(ref_spectrum * np.conj(np.fft.rfft(cur_hist)), n=_N_BINS)
    # corr[k] = Σ_i ref[i + k] · cur[i]: the current directions rotated by k bins.
    n_half = max(1, round(half_window_rad / _BIN_RAD))
    centre = predicted_rad / _BIN_RAD
    c0 = round(centre)
    ks = c0 + np.arange(-n_half, n_half + 1)
    score = corr[ks % _N_BINS]
    i = int(np.argmax(score))
    offset = 0.0
    if 0 < i < len(ks) - 1:
        offset = parabolic_offset(float(score[i - 1]), float(score[i]), float(score[i + 1]))
    peak = float(score[i])
    contrast = (peak - float(score.mean())) / peak if peak > 0.0 else 0.0
    at_edge = i in (0, len(ks) - 1)
    theta = (float(ks[i]) + offset) * _BIN_RAD
    # Back to the branch of the prediction (the histogram is modulo 180°).
    theta = predicted_rad + ((theta - predicted_rad + math.pi / 2.0) % math.pi - math.pi / 2.0)
    return theta, (0.0 if at_edge else contrast)
