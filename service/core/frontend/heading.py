"""Heading against the major walls (paper §II): projection histograms over rotation angles.

Convention: rotating the laser-frame points by the robot heading θ gives them the map's
orientation. Walls parallel to the map axes then project onto a single histogram bin, so the
rotation α that maximises the projection-histogram peak is the heading modulo 90° (Manhattan
walls come in two perpendicular families; modulo 180° for one family). The absolute heading is
the member of {α + k·90°} nearest to the prediction: the paper's ±45° rule.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from service.core.frontend import kernels
from service.core.types import FloatArray, parabolic_offset

QUARTER = math.pi / 2.0


def thin_points(points_xy_m: FloatArray, spacing_m: float) -> FloatArray:
    """Keep points so that consecutive kept points are roughly `spacing_m` apart (vectorised).

    Walks the scan in beam order: a point is kept each time the cumulative path length along
    the scan crosses a multiple of `spacing_m` (a range jump always starts a new point).
    """
    n = points_xy_m.shape[0]
    if n < 2 or spacing_m <= 0.0:
        return points_xy_m
    steps = np.hypot(*np.diff(points_xy_m, axis=0).T)
    cell = np.floor(np.concatenate(([0.0], np.cumsum(steps))) / spacing_m)
    keep = np.empty(n, dtype=bool)
    keep[0] = True
    keep[1:] = cell[1:] != cell[:-1]
    # `take` of indices: (n, 2) boolean indexing is ~10x slower.
    return points_xy_m.take(np.flatnonzero(keep), axis=0)


def wrap_quarter(angle_rad: float | FloatArray) -> float | FloatArray:
    """Wrap to [-45°, 45°)."""
    return (angle_rad + QUARTER / 2.0) % QUARTER - QUARTER / 2.0


_WORK = threading.local()  # per-thread scratch buffers: estimators may run in worker threads


def _scratch(name: str, size: int, dtype: type[np.generic]) -> npt.NDArray[Any]:
    """A reusable 1-D buffer of at least `size` items (fresh large arrays cost page faults)."""
    buf: npt.NDArray[Any] | None = getattr(_WORK, name, None)
    if buf is None or buf.size < size:
        buf = np.empty(max(size, 1024), dtype=dtype)
        setattr(_WORK, name, buf)
    return buf[:size]


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


def _rotate_into(points_xy_m: FloatArray, columns: FloatArray, out: FloatArray) -> None:
    """out (M, 2K) = x·columns[0] + y·columns[1], as two products and a sum per element.

    Not a matrix product: BLAS kernels differ in the last bits (a fused multiply-add or not,
    `OPENBLAS_CORETYPE`), a point on a bin edge then changes bins, and a decision downstream
    with it (ACES: 0.138 or 0.192 m by kernel). Element-wise ufuncs round the same everywhere.
    """
    tmp = _scratch("rotate_tmp", out.size, np.float64).reshape(out.shape)
    np.multiply(points_xy_m[:, 0:1], columns[0], out=out)
    np.multiply(points_xy_m[:, 1:2], columns[1], out=tmp)
    out += tmp


def _projection_indices(
    points_xy_m: FloatArray, angles_rad: FloatArray, bin_m: float
) -> tuple[FloatArray, npt.NDArray[np.intp], int]:
    """Rotated coordinates in bin units (shifted positive) and their flat bin indices.

    Returns (proj (M, 2K), idx (M, 2K), width): column j < K is the x coordinate at angle j,
    column K + j the y coordinate; idx = floor(proj) + column · width. Both arrays are scratch
    buffers, valid until the next call in this thread.
    """
    k = angles_rad.shape[0]
    m = points_xy_m.shape[0]
    # Both coordinates of R(α)·p for every α: (M, 2K).
    proj = _scratch("proj", m * 2 * k, np.float64).reshape(m, 2 * k)
    _rotate_into(points_xy_m, _rotation_columns(angles_rad, bin_m), proj)
    lo = math.floor(float(proj.min())) - 1
    width = math.ceil(float(proj.max())) - lo + 2
    proj -= lo  # now positive: truncation is floor
    idx = _scratch("idx", m * 2 * k, np.intp).reshape(m, 2 * k)
    np.copyto(idx, proj, casting="unsafe")
    idx += np.arange(2 * k, dtype=np.intp) * width
    return proj, idx, width


def _hard_offset(points_xy_m: FloatArray, bin_m: float) -> tuple[int, int]:
    """(offset, width) in bins of hard bins: the offset from the largest range instead of the
    data's extremes (only bin membership matters for hard bins, and an offset by whole bins
    does not change it)."""
    x, y = points_xy_m[:, 0], points_xy_m[:, 1]
    r2_max = float((x * x + y * y).max()) if points_xy_m.shape[0] else 0.0  # not sum(axis=1)
    r_bins = math.sqrt(r2_max) / bin_m
    lo = -math.ceil(r_bins) - 1
    return lo, math.ceil(r_bins) - lo + 2


def _hard_indices(
    points_xy_m: FloatArray, angles_rad: FloatArray, bin_m: float
) -> tuple[npt.NDArray[np.intp], int]:
    """Flat bin indices (M, 2K) for hard binning (offset: `_hard_offset`)."""
    k = angles_rad.shape[0]
    m = points_xy_m.shape[0]
    lo, width = _hard_offset(points_xy_m, bin_m)
    proj = _scratch("proj", m * 2 * k, np.float64).reshape(m, 2 * k)
    _rotate_into(points_xy_m, _rotation_columns(angles_rad, bin_m), proj)
    proj -= float(lo)
    idx = _scratch("idx", m * 2 * k, np.intp).reshape(m, 2 * k)
    np.copyto(idx, proj, casting="unsafe")  # positive: truncation is floor
    idx += np.arange(2 * k, dtype=np.intp) * width
    return idx, width


def _projection_histograms(
    points_xy_m: FloatArray, angles_rad: FloatArray, bin_m: float, soft: bool
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Histograms of the rotated points' x and y coordinates, one row per angle.

    Returns (hist_x, hist_y), each (K, B). `soft` splits each point between its two nearest
    bins (linear interpolation), which makes the score smooth in the angle.
    """
    k = angles_rad.shape[0]
    if soft:
        proj, idx, width = _projection_indices(points_xy_m, angles_rad, bin_m)
        h = _soft_counts(proj, idx, 2 * k * width)
    else:
        idx, width = _hard_indices(points_xy_m, angles_rad, bin_m)
        h = np.bincount(idx.ravel(), minlength=2 * k * width).astype(np.float64)
    h2: FloatArray = np.asarray(h[: 2 * k * width], dtype=np.float64).reshape(2 * k, width)
    return h2[:k], h2[k:]


def _soft_counts(proj: FloatArray, idx: npt.NDArray[np.intp], n_bins: int) -> FloatArray:
    """Linear-interpolation histogram: each point split between its bin and the next one."""
    frac = proj.ravel()  # reuse: proj is scratch
    tmp = _scratch("tmp", frac.shape[0], np.float64)
    np.floor(frac, out=tmp)
    frac -= tmp
    np.subtract(1.0, frac, out=tmp)
    flat_idx = idx.ravel()
    h = np.asarray(np.bincount(flat_idx, weights=tmp, minlength=n_bins), dtype=np.float64)
    flat_idx += 1
    h += np.bincount(flat_idx, weights=frac, minlength=n_bins)
    return h


def heading_scores(
    points_xy_m: FloatArray,
    angles_rad: FloatArray,
    bin_m: float,
    score: str = "energy",
    soft: bool = True,
) -> FloatArray:
    """Manhattan score of each candidate rotation.

    "max": the paper's hmax(α) (largest bin of the x projection) plus the same for y, so that
    both wall families count; "energy": Σ h² over both projections (pairs of points sharing a
    bin), smoother and less sensitive to which single wall is longest.
    """
    k = angles_rad.shape[0]
    if score == "energy" and soft:
        proj, idx, width = _projection_indices(points_xy_m, angles_rad, bin_m)
        h = _soft_counts(proj, idx, 2 * k * width)[: 2 * k * width].reshape(2 * k, width)
        sq = np.einsum("ij,ij->i", h, h)
        return np.asarray(sq[:k] + sq[k:], dtype=np.float64)
    # Hard bins: integer counts, so Σ h² and the maxima are exact in int64.
    if score == "max":
        hidx, width = _hard_indices(points_xy_m, angles_rad, bin_m)
        n_bins = 2 * k * width
        hi = np.bincount(hidx.ravel(), minlength=n_bins)[:n_bins].reshape(2 * k, width)
        per_row = hi.max(axis=1)
        return np.asarray(per_row[:k] + per_row[k:], dtype=np.float64)
    lo, width = _hard_offset(points_xy_m, bin_m)
    columns = _rotation_columns(angles_rad, bin_m)
    return kernels.hard_energies(points_xy_m, columns, float(lo), width).astype(np.float64)


@dataclass(frozen=True, slots=True)
class HeadingMeasurement:
    """The Manhattan angle of one scan."""

    angle_rad: float  # in [-45°, 45°): heading modulo 90°
    peak_fraction: float  # share of points on the strongest line of each family
    contrast: float  # chosen coarse peak score relative to the median angle (≥ 1 when clear)
    rival_ratio: float  # best other coarse peak / chosen peak (1 = two equal directions)
    prior_offset_rad: float  # chosen angle minus predicted angle, wrapped to ±45°
    major_axis: int  # 0 when the strongest wall is parallel to the map y axis, 1 for x
    # The coarse curve and its chosen index, for a second measurement of the same points.
    coarse_scores: FloatArray | None = field(default=None, compare=False, repr=False)
    coarse_index: int = field(default=-1, compare=False, repr=False)


def _median(values: FloatArray) -> float:
    """`np.median` of a finite 1-D array, bit for bit, without its generic overhead."""
    n = values.shape[0]
    half = n // 2
    if n % 2:
        return float(np.partition(values, half)[half])
    part = np.partition(values, (half - 1, half))
    return (float(part[half - 1]) + float(part[half])) / 2.0


def _circular_peaks(scores: FloatArray) -> npt.NDArray[np.int64]:
    left = np.concatenate((scores[-1:], scores[:-1]))
    right = np.concatenate((scores[1:], scores[:1]))
    peaks = np.flatnonzero((scores >= left) & (scores > right))
    if peaks.size == 0:
        peaks = np.array([int(np.argmax(scores))])
    return peaks.astype(np.int64)


_FINE_FIRST_STEPS = 7  # the fine peak is within ±0.6° of the 1° coarse peak (measured)
_TRACK_FIRST_STEPS = 3  # a steady prediction is within a few tenths of a degree


def _fine_search(
    pts: FloatArray,
    centre_rad: float,
    *,
    step_rad: float,
    bin_m: float,
    score: str,
    half_rad: float,
    first_steps: int = _FINE_FIRST_STEPS,
) -> tuple[FloatArray, FloatArray]:
    """Scores at `centre + k·step`, |k·step| <= half_rad, around the maximum nearest the centre.

    Starts with ±`first_steps` and extends a side only while the maximum sits on its edge, so
    the usual case scores a fraction of the angles of the whole window.
    """
    n_half = max(1, round(half_rad / step_rad))
    lo = hi = min(n_half, first_steps)
    ks = np.arange(-lo, hi + 1, dtype=np.float64)
    scores = heading_scores(pts, centre_rad + step_rad * ks, bin_m, score)
    while True:
        i = int(np.argmax(scores))
        if i == 0 and lo < n_half:
            more = np.arange(-min(n_half, lo + _FINE_FIRST_STEPS), -lo, dtype=np.float64)
            lo = -int(more[0])
            ks = np.concatenate((more, ks))
            scores = np.concatenate(
                (heading_scores(pts, centre_rad + step_rad * more, bin_m, score), scores)
            )
        elif i == ks.shape[0] - 1 and hi < n_half:
            more = np.arange(hi + 1, min(n_half, hi + _FINE_FIRST_STEPS) + 1, dtype=np.float64)
            hi = int(more[-1])
            ks = np.concatenate((ks, more))
            scores = np.concatenate(
                (scores, heading_scores(pts, centre_rad + step_rad * more, bin_m, score))
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
    predicted_rad: float | None,
    prior_sigma_rad: float,
    step_rad: float,
    bin_m: float,
    *,
    score: str = "energy",
    coarse_step_rad: float = math.radians(1.0),
    coarse_bin_m: float = 0.05,
    fine_half_rad: float = math.radians(1.5),
    refine: bool = True,
    max_range_m: float = 12.0,
    same_points: HeadingMeasurement | None = None,
    coarse_half_rad: float = QUARTER / 2.0,
) -> HeadingMeasurement:
    """The Manhattan angle: coarse search over the whole 90°, fine search around one peak.

    The coarse curve (`coarse_step_rad`, `coarse_bin_m`) covers every direction, so a badly
    predicted heading cannot hide the true peak; among its local maxima the one with the best
    score × Gaussian prior around the prediction wins (no prediction: the best score, the paper).
    The fine search uses the paper's step and bin and a parabolic sub-step refinement.

    `same_points`: a measurement of the same points with the same settings (another prior):
    its coarse curve is reused, and its fine result when the same coarse peak wins (speed).
    `coarse_half_rad` < 45° with a prediction: the coarse search covers only that much around
    it (a tight prior makes farther peaks lose anyway; speed).
    """
    pts = _within(points_xy_m, max_range_m)
    windowed = (
        predicted_rad is not None and prior_sigma_rad > 0.0 and coarse_half_rad < QUARTER / 2.0
    )
    coarse = np.arange(-QUARTER / 2.0, QUARTER / 2.0, coarse_step_rad)
    n_full = coarse.shape[0]
    n_coarse = math.ceil(coarse_half_rad / coarse_step_rad)
    windowed = windowed and 2 * n_coarse + 1 < n_full
    if windowed:
        assert predicted_rad is not None
        # The same angles as the whole-range search (same scores), only those near the
        # prediction, in circular order.
        centre = round((float(wrap_quarter(predicted_rad)) + QUARTER / 2.0) / coarse_step_rad)
        coarse = coarse[(centre + np.arange(-n_coarse, n_coarse + 1)) % n_full]
        s_coarse = heading_scores(pts, coarse, coarse_bin_m, score, soft=False)
        # Not circular: interior maxima only (none: the best score, possibly an edge).
        inner = (s_coarse[1:-1] >= s_coarse[:-2]) & (s_coarse[1:-1] > s_coarse[2:])
        peaks = (np.flatnonzero(inner) + 1).astype(np.int64)
        if peaks.size == 0:
            peaks = np.array([int(np.argmax(s_coarse))], dtype=np.int64)
    else:
        if same_points is not None and same_points.coarse_scores is not None:
            s_coarse = same_points.coarse_scores
        else:
            s_coarse = heading_scores(pts, coarse, coarse_bin_m, score, soft=False)
        peaks = _circular_peaks(s_coarse)
    if predicted_rad is None or prior_sigma_rad <= 0.0:
        weight = s_coarse[peaks]
        pred_q = 0.0
    else:
        pred_q = float(wrap_quarter(predicted_rad))
        d = wrap_quarter(coarse[peaks] - pred_q)
        weight = s_coarse[peaks] * np.exp(-0.5 * (np.asarray(d) / prior_sigma_rad) ** 2)
    order = peaks[np.argsort(-weight)]
    chosen = int(order[0])
    by_score = peaks[np.argsort(-s_coarse[peaks])]
    rivals = by_score[by_score != chosen]
    rival_ratio = float(s_coarse[rivals[0]] / s_coarse[chosen]) if rivals.size else 0.0
    median = _median(s_coarse)
    contrast = float(s_coarse[chosen]) / max(median, 1e-9)
    if not windowed and same_points is not None and same_points.coarse_index == chosen:
        prior_offset = (
            float(wrap_quarter(same_points.angle_rad - pred_q))
            if predicted_rad is not None
            else 0.0
        )
        return replace(
            same_points, contrast=contrast, rival_ratio=rival_ratio, prior_offset_rad=prior_offset
        )

    angles, scores = _fine_search(
        pts,
        float(coarse[chosen]),
        step_rad=step_rad,
        bin_m=bin_m,
        score=score,
        half_rad=fine_half_rad,
    )
    return _fine_measurement(
        pts,
        angles,
        scores,
        step_rad=step_rad,
        bin_m=bin_m,
        refine=refine,
        predicted_rad=predicted_rad,
        contrast=contrast,
        rival_ratio=rival_ratio,
        # Only the whole-range curve can serve another prior.
        coarse_scores=None if windowed else s_coarse,
        coarse_index=-1 if windowed else chosen,
    )


def _fine_measurement(
    pts: FloatArray,
    angles: FloatArray,
    scores: FloatArray,
    *,
    step_rad: float,
    bin_m: float,
    refine: bool,
    predicted_rad: float | None,
    contrast: float,
    rival_ratio: float,
    coarse_scores: FloatArray | None = None,
    coarse_index: int = -1,
) -> HeadingMeasurement:
    """The measurement at the best fine angle (parabolic sub-step) and its peak fraction."""
    i = int(np.argmax(scores))
    offset = 0.0
    if refine and 0 < i < len(angles) - 1:
        offset = parabolic_offset(float(scores[i - 1]), float(scores[i]), float(scores[i + 1]))
    best = float(wrap_quarter(float(angles[i]) + offset * step_rad))
    hx, hy = _projection_histograms(pts, np.array([best]), bin_m, soft=False)
    mx, my = float(hx.max()), float(hy.max())
    n = max(1, pts.shape[0])
    pred_q = float(wrap_quarter(predicted_rad)) if predicted_rad is not None else 0.0
    return HeadingMeasurement(
        angle_rad=best,
        peak_fraction=(mx + my) / n,
        contrast=contrast,
        rival_ratio=rival_ratio,
        prior_offset_rad=float(wrap_quarter(best - pred_q)) if predicted_rad is not None else 0.0,
        major_axis=0 if mx >= my else 1,
        coarse_scores=coarse_scores,
        coarse_index=coarse_index,
    )


def track_heading(
    points_xy_m: FloatArray,
    predicted_rad: float,
    step_rad: float,
    bin_m: float,
    *,
    score: str = "energy",
    fine_half_rad: float = math.radians(1.5),
    refine: bool = True,
    max_range_m: float = 12.0,
) -> HeadingMeasurement | None:
    """The paper's fine search alone, around the predicted heading: steady motion, fast scans.

    When the Manhattan angle was measured on the previous scan and the robot is not turning,
    the coarse 90° search only finds the peak it already knows. Returns None when the best
    angle lies on the edge of ±`fine_half_rad` (the heading moved more than predicted): then
    `measure_heading` must search.
    """
    pts = _within(points_xy_m, max_range_m)
    angles, scores = _fine_search(
        pts,
        float(wrap_quarter(predicted_rad)),
        step_rad=step_rad,
        bin_m=bin_m,
        score=score,
        half_rad=fine_half_rad,
        first_steps=_TRACK_FIRST_STEPS,
    )
    i = int(np.argmax(scores))
    if i in (0, scores.shape[0] - 1):
        return None
    return _fine_measurement(
        pts,
        angles,
        scores,
        step_rad=step_rad,
        bin_m=bin_m,
        refine=refine,
        predicted_rad=predicted_rad,
        contrast=1.0,
        rival_ratio=0.0,
    )


def resolve_heading(manhattan_rad: float, predicted_rad: float) -> float:
    """The member of {manhattan + k·90°} nearest to the prediction (the ±45° rule)."""
    k = round((predicted_rad - manhattan_rad) / QUARTER)
    return manhattan_rad + k * QUARTER
