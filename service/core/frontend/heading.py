"""The walls' angle of one scan (paper §II): projection histograms over rotation angles.

Convention: rotating the laser-frame points by the robot heading θ gives them the map's
orientation. Walls parallel to the map axes then project onto a single histogram bin, so the
rotation α that maximises the projection-histogram peak is the heading modulo 90° (walls come
in two perpendicular families; modulo 180° for one family). `walls` turns it into the
matcher's heading prior.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from service.core.frontend import kernels
from service.core.types import FloatArray, parabolic_offset

QUARTER = math.pi / 2.0


def wrap_quarter(angle_rad: float | FloatArray) -> float | FloatArray:
    """Wrap to [-45°, 45°)."""
    return (angle_rad + QUARTER / 2.0) % QUARTER - QUARTER / 2.0


_WORK = threading.local()  # per-thread scratch buffers: front ends may run in worker threads


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
    points_xy_m: FloatArray, angles_rad: FloatArray, bin_m: float
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Hard-binned histograms of the rotated points' x and y coordinates, one row per angle.

    Returns (hist_x, hist_y), each (K, B).
    """
    k = angles_rad.shape[0]
    idx, width = _hard_indices(points_xy_m, angles_rad, bin_m)
    h = np.bincount(idx.ravel(), minlength=2 * k * width).astype(np.float64)
    h2: FloatArray = np.asarray(h[: 2 * k * width], dtype=np.float64).reshape(2 * k, width)
    return h2[:k], h2[k:]


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
    return kernels.hard_energies(points_xy_m, columns, float(lo), width).astype(np.float64)


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
    hx, hy = _projection_histograms(pts, np.array([best]), bin_m)
    n = max(1, pts.shape[0])
    return HeadingMeasurement(angle_rad=best, peak_fraction=(float(hx.max()) + float(hy.max())) / n)
