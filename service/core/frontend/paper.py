"""`--front-end paper`: the IROS 2010 method as the paper states it, kept small.

The paper (docs/paper-frontend.md; ../shared/docs/paper.txt) in four steps, nothing added to
the estimate:

1. Points (§II-A 1): valid returns, thinned to roughly `thinning_m` apart.
2. Relative wall angle (§II-A 2-5): for every θ in [0°, 180°) at `heading_step_deg`, the points
   rotated by θ are projected on x and histogrammed in `heading_bin_m` bins; hmax(θ) is the
   largest bin, and the θ with the largest hmax(θ) turns the major wall onto the y axis.
3. Absolute heading (§II-B): the first scan's major wall is the standard direction (the map's
   y axis, so the first heading is its θ). Later, the change of θ since the previous scan is
   taken modulo 180°; beyond ±`switch_deg` the major wall is the perpendicular one (±90°).
4. Translation (§III): the scan, rotated into the map axes, is shifted by x′ (and y′) in steps of
   `translation_step_m` over ±`translation_window_m`; E(x′) = Σ_i h_ref(i)·h_cur(i, x′) with
   `translation_bin_m` bins, and the translation is the argmax, each axis on its own. The
   reference is the latest keyframe: the paper's robot took a scan every `keyframe_distance_m`
   or `keyframe_angle_deg` (§IV-A), which here decides, from the match, when a scan becomes
   the next reference. No motion prediction, no odometry (the paper uses none).

Covariance (relative to the reference, map axes, diagonal): per axis, the shifts whose
correlation is at least half way from a floor to the peak are counted over the whole window (a
second, as high peak widens it too); the floor is the window's minimum, at most half the peak,
so that a flat correlation along a corridor is as wide as the window. That width is read as a
Gaussian's full width at half maximum: σ = count · step / 2.355, at least bin / √12. The
heading's σ is the same reading of hmax(θ) within ±45° of its peak; its variance is this scan's
plus the reference's. An axis at least `ambiguous_width_m` wide is flagged AMBIGUOUS_X/Y, a
heading σ above `no_wall_sigma_deg` NO_DOMINANT_WALL (flags only). Quality is 1 minus the larger
share of a window above half maximum. Bad scans (fewer than `min_points`) and stamps not after
the previous one return the last pose flagged DEGENERATE, quality 0, unmatched.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from clients.wire import PoseFlag
from service.core.types import (
    ZERO_COVARIANCE,
    FloatArray,
    LaserScan,
    Pose2D,
    PoseEstimate,
    rotate_points,
    wrap_angle,
)

log = logging.getLogger(__name__)

_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))  # 2.3548
_ANGLE_CHUNK = 200  # hmax(θ) for this many angles at a time (bounded memory)


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


@dataclass(frozen=True, slots=True)
class PaperOptions:
    thinning_m: float = 0.05  # §II-A 1): points thinned to roughly this interval
    heading_step_deg: float = 0.1  # §II-A 2): rotation step of the wall-angle search
    heading_bin_m: float = 0.02  # §II-A 3): bin of the x projection's histogram
    switch_deg: float = 45.0  # §II-B: a larger change of the wall angle = the perpendicular wall
    translation_bin_m: float = 0.03  # §III-A/B: bin of the x and y histograms
    translation_step_m: float = 0.005  # §III-B: pitch of the current scan's shifts
    translation_window_m: float = 0.8  # §III-B: shifts searched, ± this
    keyframe_distance_m: float = 0.3  # §IV-A: the next reference scan after this translation ...
    keyframe_angle_deg: float = 10.0  # ... or this rotation
    max_range_m: float = 30.0  # the paper's UTM-30LX reaches 30 m: farther returns are dropped
    min_points: int = 10  # fewer thinned points: DEGENERATE, the last pose (not in the paper)
    ambiguous_width_m: float = 0.3  # correlation this wide: AMBIGUOUS_X/Y (flag only)
    no_wall_sigma_deg: float = 2.0  # heading σ above this: NO_DOMINANT_WALL (flag only)


@dataclass(frozen=True, slots=True)
class WallAngle:
    angle_rad: float  # θ in [0, π) putting the major wall on the y axis
    sigma_rad: float  # from hmax(θ)'s peak width


@dataclass(frozen=True, slots=True)
class AxisShift:
    shift_m: float  # argmax of E: where the current scan's points land on the reference's
    sigma_m: float  # from E's width at half maximum
    width_m: float  # that width: the shifts above half maximum, counted, times the step
    window_share: float  # share of the window above half maximum


def _half_max_count(values: FloatArray) -> int:
    """How many values are at least half way from the floor to the largest, the floor being
    the smallest value but at most half the largest (a peak on a high, flat background is as
    wide as the background)."""
    hi = float(values.max())
    lo = min(float(values.min()), 0.5 * hi)
    if hi <= lo:
        return int(values.shape[0])
    return int(np.count_nonzero(values >= lo + 0.5 * (hi - lo)))


def wall_angle(points_xy_m: FloatArray, opts: PaperOptions) -> WallAngle:
    """§II-A: the rotation θ in [0, π) with the largest hmax(θ), vectorised over angles."""
    step = math.radians(opts.heading_step_deg)
    angles = np.arange(round(math.pi / step)) * step
    hmax = np.empty(angles.shape[0])
    x, y = points_xy_m[:, 0], points_xy_m[:, 1]
    for start in range(0, angles.shape[0], _ANGLE_CHUNK):
        a = angles[start : start + _ANGLE_CHUNK]
        proj = np.cos(a)[:, None] * x[None, :] - np.sin(a)[:, None] * y[None, :]
        idx = np.floor(proj / opts.heading_bin_m).astype(np.int64)
        idx -= idx.min(axis=1, keepdims=True)
        width = int(idx.max()) + 1
        idx += (np.arange(a.shape[0]) * width)[:, None]
        counts = np.bincount(idx.ravel(), minlength=a.shape[0] * width)
        hmax[start : start + a.shape[0]] = counts.reshape(a.shape[0], width).max(axis=1)
    k = int(np.argmax(hmax))
    # The peak's width: angles within ±45° of it (modulo 180°: the wall is a line).
    near = np.abs((angles - angles[k] + math.pi / 2.0) % math.pi - math.pi / 2.0) < math.pi / 4.0
    width_rad = _half_max_count(hmax[near]) * step
    sigma = max(width_rad / _FWHM_PER_SIGMA, step / math.sqrt(12.0))
    return WallAngle(float(angles[k]), sigma)


def correlate_axis(ref_m: FloatArray, cur_m: FloatArray, opts: PaperOptions) -> AxisShift:
    """§III-B: argmax over x′ of E(x′) = Σ_i h_ref(i)·h_cur(i, x′).

    Σ_i h_ref(i)·h_cur(i, x′) is Σ over the current points of h_ref at each shifted point's bin:
    one gather per (shift, point), every shift re-binned as the paper does, no loop.
    """
    bin_m, window = opts.translation_bin_m, opts.translation_window_m
    n_half = round(window / opts.translation_step_m)
    shifts = np.arange(-n_half, n_half + 1) * opts.translation_step_m
    lo = min(float(ref_m.min()), float(cur_m.min())) - window - bin_m
    hi = max(float(ref_m.max()), float(cur_m.max())) + window + bin_m
    n_bins = math.ceil((hi - lo) / bin_m) + 1
    h_ref = np.bincount(np.floor((ref_m - lo) / bin_m).astype(np.int64), minlength=n_bins)
    idx = np.floor((cur_m[None, :] + shifts[:, None] - lo) / bin_m).astype(np.int64)
    energy = h_ref[idx].sum(axis=1).astype(np.float64)
    k = int(np.argmax(energy))
    count = _half_max_count(energy)
    width_m = count * opts.translation_step_m
    sigma = max(width_m / _FWHM_PER_SIGMA, bin_m / math.sqrt(12.0))
    return AxisShift(float(shifts[k]), sigma, width_m, count / energy.shape[0])


class PaperFrontEnd:
    """The paper's scan-to-reference matching (module docstring); never raises on bad scans."""

    def __init__(self, options: PaperOptions | None = None) -> None:
        self.options = options if options is not None else PaperOptions()
        self.reset()

    def reset(self) -> None:
        self.stamp_backwards = 0  # scans not after the previous one: not matched
        self._stamp_ns: int | None = None
        self._pose = Pose2D(0.0, 0.0, 0.0)
        self._rel_rad: float | None = None  # the previous scan's wall angle θ
        self._ref_points: FloatArray | None = None  # the reference, map axes, at its own origin
        self._ref_pose = Pose2D(0.0, 0.0, 0.0)
        self._ref_sigma_rad = 0.0

    @property
    def wall_families_rad(self) -> tuple[float, ...]:
        """The map's axes are the walls' by construction (§II-B): one family, at 0."""
        return () if self._rel_rad is None else (0.0,)

    def process(self, scan: LaserScan) -> PoseEstimate:
        if self._stamp_ns is not None and scan.stamp_ns <= self._stamp_ns:
            self.stamp_backwards += 1
            if self.stamp_backwards == 1 or self.stamp_backwards % 1000 == 0:
                log.warning(
                    "scan stamp %d is not after the previous %d: not matched (%d so far)",
                    scan.stamp_ns,
                    self._stamp_ns,
                    self.stamp_backwards,
                )
            return PoseEstimate(scan.stamp_ns, self._pose, 0.0, PoseFlag.DEGENERATE)
        self._stamp_ns = scan.stamp_ns
        opts = self.options
        with np.errstate(invalid="ignore", over="ignore"):
            pts = scan.points_xy_m()
            keep = np.isfinite(pts).all(axis=1) & (
                np.hypot(pts[:, 0], pts[:, 1]) <= opts.max_range_m
            )
        pts = thin_points(pts[keep], opts.thinning_m)
        if pts.shape[0] < opts.min_points:
            return PoseEstimate(scan.stamp_ns, self._pose, 0.0, PoseFlag.DEGENERATE)
        return self._match(scan.stamp_ns, pts)

    def _heading(self, wall: WallAngle) -> tuple[float, PoseFlag]:
        """§II-B: the absolute heading from the wall angle's change since the previous scan."""
        if self._rel_rad is None:
            return wall.angle_rad, PoseFlag.NONE  # the first major wall is the map's y axis
        change = (wall.angle_rad - self._rel_rad + math.pi / 2.0) % math.pi - math.pi / 2.0
        switch = math.radians(self.options.switch_deg)
        flags = PoseFlag.NONE
        if change > switch:
            change -= math.pi / 2.0
            flags = PoseFlag.HEADING_SWITCH
        elif change < -switch:
            change += math.pi / 2.0
            flags = PoseFlag.HEADING_SWITCH
        return wrap_angle(self._pose.theta_rad + change), flags

    def _match(self, stamp_ns: int, pts: FloatArray) -> PoseEstimate:
        opts = self.options
        wall = wall_angle(pts, opts)
        theta, flags = self._heading(wall)
        self._rel_rad = wall.angle_rad
        if wall.sigma_rad > math.radians(opts.no_wall_sigma_deg):
            flags |= PoseFlag.NO_DOMINANT_WALL
        cur = rotate_points(pts, theta)  # map axes, at the scan's own origin
        if self._ref_points is None:
            self._pose = Pose2D(0.0, 0.0, theta)
            self._keep_reference(cur, wall.sigma_rad)
            return PoseEstimate(stamp_ns, self._pose, 1.0, flags, True, ZERO_COVARIANCE)
        ref = self._ref_points
        sx = correlate_axis(ref[:, 0], cur[:, 0], opts)
        sy = correlate_axis(ref[:, 1], cur[:, 1], opts)
        for axis, flag in ((sx, PoseFlag.AMBIGUOUS_X), (sy, PoseFlag.AMBIGUOUS_Y)):
            if axis.width_m >= opts.ambiguous_width_m:
                flags |= flag
        self._pose = Pose2D(self._ref_pose.x_m + sx.shift_m, self._ref_pose.y_m + sy.shift_m, theta)
        var_theta = wall.sigma_rad**2 + self._ref_sigma_rad**2
        cov = (sx.sigma_m**2, 0.0, 0.0, 0.0, sy.sigma_m**2, 0.0, 0.0, 0.0, var_theta)
        quality = 1.0 - max(sx.window_share, sy.window_share)
        turn = abs(wrap_angle(theta - self._ref_pose.theta_rad))
        keyframe = math.hypot(sx.shift_m, sy.shift_m) >= opts.keyframe_distance_m or turn >= (
            math.radians(opts.keyframe_angle_deg)
        )
        if keyframe:
            self._ref_pose = self._pose
            self._keep_reference(cur, wall.sigma_rad)
        return PoseEstimate(stamp_ns, self._pose, quality, flags, keyframe, cov)

    def _keep_reference(self, cur: FloatArray, sigma_rad: float) -> None:
        self._ref_points = cur
        self._ref_sigma_rad = sigma_rad
