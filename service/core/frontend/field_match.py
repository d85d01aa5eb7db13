"""An axis the 1-D correlations leave open, decided in 2-D against the local map's likelihood field.

The paper's 1-D histograms see only what a point says about one axis, so they weigh each point
by the walls' direction, and a wall seen along a corridor says nothing about the corridor's
axis. What does say something there, an opening's edge, a jamb, a box, a far wall at grazing
angle that ends, is a handful of points among hundreds. Scored in 2-D, every point counts for
what it is: a wall point slid along its own wall stays on it (no vote either way), an edge or a
box moves off (a vote), and a point beyond what the local map observed scores the field's
prior at every shift (no vote for where the map ends: the pull to standing still).

The answer is the response's mean and spread over the shifts (a likelihood with a temperature
in points, times the motion prediction's Gaussian): a clear peak is a measurement with its σ; a
flat or multi-peaked response leaves the prediction, and the axis stays flagged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from service.core.maps.submaps import LikelihoodField, SubmapParams, likelihood_field
from service.core.types import FloatArray


@dataclass(frozen=True, slots=True)
class FieldMatchParams:
    resolution_m: float = 0.05  # cell of the local likelihood field
    hit_sigma_m: float = 0.05  # width of a hit's Gaussian
    step_m: float = 0.01  # shift step of the axis search
    temperature_points: float = 2.0  # response ∝ exp(Σ field / T): T points' worth of evidence
    informative_ratio: float = 0.7  # the response measures the axis if it narrows the prior so
    sigma_floor_m: float = 0.01
    max_points: int = 400  # scan points scored (evenly subsampled)
    fill_max_gap_m: float = 5.0  # neighbours on one surface farther apart stay apart
    fill_max_beams: float = 2.5  # ... and so do those with a missing beam between them
    fill_tolerance_deg: float = 10.0  # the chord must run along both points' surface


@dataclass(frozen=True, slots=True)
class AxisResponse:
    offset_m: float  # the response's mean
    sigma_m: float  # its spread
    measured: bool  # one clear peak inside the window
    prior_spread_m: float  # the prior's own spread as the window sees it


def surface_points(
    points_laser_m: FloatArray,
    directions_rad: FloatArray,
    has_direction: npt.NDArray[np.bool_],
    increment_rad: float,
    params: FieldMatchParams,
) -> FloatArray:
    """The points, plus fill along each surface between neighbouring beams.

    Far along a wall the beams land metres apart, at places fixed relative to the robot: as
    samples in the field they would pull every later scan back onto them. Filled, the wall is
    a wall. Only consecutive beams are joined (a missing beam may be an opening), and only
    along both points' own surface direction (not across a jump in depth).
    """
    n = points_laser_m.shape[0]
    if n < 2:
        return points_laser_m
    a, b = points_laser_m[:-1], points_laser_m[1:]
    chord = b - a
    gap = np.hypot(chord[:, 0], chord[:, 1])
    bearing = np.arctan2(points_laser_m[:, 1], points_laser_m[:, 0])
    beams = np.abs(np.diff(bearing)) / max(abs(increment_rad), 1e-9)
    along = np.arctan2(chord[:, 1], chord[:, 0]) % math.pi
    tol = math.radians(params.fill_tolerance_deg)

    def agrees(d: FloatArray) -> npt.NDArray[np.bool_]:
        off = np.abs(along - d % math.pi)
        return np.minimum(off, math.pi - off) <= tol

    join = (
        (gap > params.resolution_m)
        & (gap <= params.fill_max_gap_m)
        & (beams <= params.fill_max_beams)
        & has_direction[:-1]
        & has_direction[1:]
        & agrees(directions_rad[:-1])
        & agrees(directions_rad[1:])
    )
    idx = np.flatnonzero(join)
    if idx.size == 0:
        return points_laser_m
    counts = np.floor(gap[idx] / params.resolution_m).astype(np.intp)  # fill points per gap
    owner = np.repeat(idx, counts)
    step = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts) + 1
    t = step / np.repeat(counts + 1, counts)
    fill = a[owner] + chord[owner] * t[:, None]
    return np.concatenate((points_laser_m, fill))


def local_field(
    points_map_m: FloatArray,
    centre_xy_m: tuple[float, float],
    radius_m: float,
    params: FieldMatchParams,
) -> LikelihoodField:
    """The field of the local map's points; known within `radius_m` of `centre_xy_m` (what the
    map's sensor reached), unknown beyond."""
    base = likelihood_field(
        points_map_m,
        SubmapParams(resolution_m=params.resolution_m, hit_sigma_m=params.hit_sigma_m),
        bound=False,
    )
    h, w = base.fine.shape
    res = base.resolution_m
    xs = base.origin_m[0] + (np.arange(w) + 0.5) * res - centre_xy_m[0]
    ys = base.origin_m[1] + (np.arange(h) + 0.5) * res - centre_xy_m[1]
    known = (ys[:, None] ** 2 + xs[None, :] ** 2) <= radius_m**2
    prior = float(base.fine[known].mean()) if known.any() else 0.0
    # Unknown cells read the prior straight from `fine` (what `axis_response` interpolates).
    fine = np.where(known, base.fine, np.float32(prior)).astype(np.float32)
    # Only `fine` is read (`LikelihoodField.interpolate`): the mask is not kept (memory: a 30 m
    # reach is a 1,200-cell square), and the coarse bound was never built.
    empty = np.zeros((0, 0), dtype=np.float32)
    return replace(base, fine=fine, known=empty, unknown_value=prior)


def axis_response(
    field: LikelihoodField,
    points_map_m: FloatArray,
    axis: int,
    half_window_m: float,
    params: FieldMatchParams,
    *,
    prior_sigma_m: float,
) -> AxisResponse:
    """Shift `points_map_m` (placed at the search centre, the prediction) along `axis` within
    ±half_window; the response times the prediction's Gaussian prior of σ `prior_sigma_m`.

    With the prior, a flat response leaves the prediction where it is and a clear peak moves
    it: no threshold on the response alone decides (one that flipped on a barely peaked
    response stopped a robot at the start of a corridor).
    """
    n = points_map_m.shape[0]
    if n > params.max_points:
        points_map_m = points_map_m[:: math.ceil(n / params.max_points)]
    n_half = max(1, round(half_window_m / params.step_m))
    shifts = params.step_m * np.arange(-n_half, n_half + 1, dtype=np.float64)
    moved = np.repeat(points_map_m[None, :, :], shifts.shape[0], axis=0)
    moved[:, :, axis] += shifts[:, None]
    score = field.interpolate(moved).sum(axis=1)
    log_w = score / params.temperature_points - 0.5 * (shifts / prior_sigma_m) ** 2
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    mean = float((w * shifts).sum())
    sigma = math.sqrt(float((w * (shifts - mean) ** 2).sum()))
    # A peak at the window's edge may be a slope that goes on outside it.
    inside = abs(mean) <= half_window_m - 3.0 * params.step_m
    # Narrowed against the prior as the window sees it: a prior wider than the window is
    # the window's own spread, which a flat response keeps (it must not read as a peak).
    prior_w = np.exp(-0.5 * (shifts / prior_sigma_m) ** 2)
    prior_spread = math.sqrt(float((prior_w * shifts**2).sum() / prior_w.sum()))
    measured = inside and sigma <= params.informative_ratio * prior_spread
    return AxisResponse(mean, max(sigma, params.sigma_floor_m), measured, prior_spread)
