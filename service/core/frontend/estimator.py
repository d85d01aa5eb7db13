"""`ManhattanEstimator`: scan-to-map pose tracking from Manhattan walls (the paper, made robust).

Per scan, each step a method of its own (`_process` runs them in order):
1. `_predict`: odometry when the scan carries it, else constant motion (and the range
   profiles' turn on slow scanners);
2. `_points`: valid points, thinned to ~0.05 m (paper §II-A.1);
3. `_heading`: the heading modulo 90° from projection histograms around the prediction,
   resolved to the absolute heading by the ±45° rule (paper §II), in the axes of the wall
   family the scan follows (`frames`); fallbacks and re-anchoring where walls fail;
4. `_without_moved`: points in space an earlier scan saw through are left out (`dynamic`);
5. `_translation`: 1-D histogram correlations along the family's axes (paper §III) against a
   local map of recent keyframes, centred on the prediction, with ambiguity checks; an open
   axis against the previous scan, then in 2-D against the local map's field; a 2-D refinement;
6. `_confidence`: the match's confidence and σ per axis; `_commit` keeps the pose, its
   covariance (`covariance`) and the keyframes.

The map frame is set by the first scan: axes along its major walls (the member of the Manhattan
family nearest the robot's forward direction is x), origin at the first scan's position.
"""

from __future__ import annotations

import logging
import math
import statistics
from collections import deque
from dataclasses import dataclass, field
from itertools import islice, product

import numpy as np
import numpy.typing as npt

from clients.wire import PoseFlag
from service.core.frontend.covariance import CovarianceTracker, axis_sigma_m
from service.core.frontend.dynamic import FreeSpace, SeenThroughParams, seen_through
from service.core.frontend.field_match import (
    FieldMatchParams,
    axis_response,
    local_field,
    surface_points,
)
from service.core.frontend.frames import WallFrames
from service.core.frontend.gated import SortedReference, correlate_axis_gated
from service.core.frontend.heading import (
    QUARTER,
    HeadingMeasurement,
    measure_heading,
    resolve_heading,
    thin_points,
    track_heading,
)
from service.core.frontend.odometry import OdometryConsistency
from service.core.frontend.params import EstimatorParams
from service.core.frontend.profile import profile_turn
from service.core.frontend.refine import OccupiedCells
from service.core.frontend.rotation import (
    direction_counts,
    direction_spectrum,
    match_rotation,
    split_tangent_directions,
)
from service.core.frontend.translation import (
    AxisDensity,
    AxisMatch,
    axis_density,
    correlate_axis,
    orientation_weights,
    pick_peak,
)
from service.core.maps.submaps import LikelihoodField
from service.core.types import (
    FloatArray,
    LaserScan,
    Pose2D,
    PoseEstimate,
    rotate_point,
    rotate_points,
    wrap_angle,
)

log = logging.getLogger(__name__)

# A pose whose position some axis of the match did not measure, and one whose heading the
# building's walls did not.
_POSITION_UNSURE = PoseFlag.DEGENERATE | PoseFlag.AMBIGUOUS_X | PoseFlag.AMBIGUOUS_Y
_HEADING_UNSURE = PoseFlag.DEGENERATE | PoseFlag.NON_MANHATTAN | PoseFlag.NO_DOMINANT_WALL


def _sides(points_map_m: FloatArray, pose: Pose2D) -> npt.NDArray[np.bool_]:
    """(M, 2): whether each point lies on the + side of its scan's sensor along x / y.

    A wall face is seen from the sensor's side, so this tells the two faces of a thin wall
    apart (their normals point opposite ways).
    """
    out = np.empty(points_map_m.shape, dtype=np.bool_)
    np.greater_equal(points_map_m[:, 0], pose.x_m, out=out[:, 0])
    np.greater_equal(points_map_m[:, 1], pose.y_m, out=out[:, 1])
    return out


def _outside(
    rotated_m: FloatArray,
    centre_xy_m: tuple[float, float],
    ref_xy_m: tuple[float, float],
    radius_m: float,
) -> npt.NDArray[np.bool_]:
    """Which points, placed at `centre_xy_m`, lie beyond `radius_m` of `ref_xy_m`."""
    dx = rotated_m[:, 0] + (centre_xy_m[0] - ref_xy_m[0])
    dy = rotated_m[:, 1] + (centre_xy_m[1] - ref_xy_m[1])
    return dx * dx + dy * dy > max(radius_m, 0.0) ** 2


def _covered(
    rotated_m: FloatArray,
    weights: FloatArray,
    centre_xy_m: tuple[float, float],
    ref_xy_m: tuple[float, float],
    radius_m: float,
) -> FloatArray:
    """`weights` with the points placed at `centre_xy_m` beyond `radius_m` of `ref_xy_m` zeroed.

    Beyond what the reference covers its density is zero: a point that a shift can move out
    of it votes for the shifts that keep it inside, i.e. for the reference's own position.
    """
    outside = _outside(rotated_m, centre_xy_m, ref_xy_m, radius_m)
    if not outside.any():
        return weights
    covered = weights.copy()
    covered[outside] = 0.0
    return covered


@dataclass(slots=True)
class _Keyframe:
    pose: Pose2D
    points_map_m: FloatArray  # (M, 2) in the map frame
    weights: FloatArray  # (M, 2) orientation weights (x, y)
    directions_rad: FloatArray  # surface directions of the reliable points, map frame
    # Derived once per keyframe, not at every reference rebuild (speed).
    sides: npt.NDArray[np.bool_] = field(init=False)  # `_sides`
    direction_counts: npt.NDArray[np.intp] = field(init=False)
    range_m: float = 30.0  # how far its sensor sees (what it did not see beyond is unknown)
    surface_map_m: FloatArray | None = None  # its points with their surfaces filled in
    # Every point's surface direction (map frame) and kind, to weigh it in another frame.
    point_directions_rad: FloatArray | None = None
    point_reliable: npt.NDArray[np.bool_] | None = None
    point_weak: npt.NDArray[np.bool_] | None = None

    def __post_init__(self) -> None:
        self.derive()

    def derive(self) -> None:
        self.sides = _sides(self.points_map_m, self.pose)
        self.direction_counts = direction_counts(self.directions_rad)

    def in_frame(self, frame_rad: float) -> _Keyframe:
        """This keyframe in the axes of a wall family at `frame_rad` (rotated by -frame_rad).

        The orientation weights say which axis a point constrains, so they are recomputed
        against that family's axes; a frame without per-point directions keeps its own.
        """
        if frame_rad == 0.0:
            return self
        weights = self.weights
        if self.point_directions_rad is not None and self.point_reliable is not None:
            weights = orientation_weights(
                self.point_directions_rad, self.point_reliable, -frame_rad, weak=self.point_weak
            )
        return _Keyframe(
            Pose2D(
                *rotate_point(self.pose.x_m, self.pose.y_m, -frame_rad),
                self.pose.theta_rad - frame_rad,
            ),
            rotate_points(self.points_map_m, -frame_rad),
            weights,
            self.directions_rad,
            self.range_m,
            None if self.surface_map_m is None else rotate_points(self.surface_map_m, -frame_rad),
        )


@dataclass(slots=True)
class _Reference:
    """What the scan is matched against: points, orientation weights, sides, axis densities."""

    points_map_m: FloatArray
    weights: FloatArray
    sides: npt.NDArray[np.bool_]  # (M, 2): on the + side of its keyframe's sensor (`_sides`)
    # What it covers: within `radius_m` of its newest frame (the local-map cut, or the
    # sensor's reach around a single frame).
    centre_xy_m: tuple[float, float]
    radius_m: float
    # Its frames' points before the local-map cut, with their sensor's reach around the newest:
    # what the 2-D field scores against (an edge far down a corridor is still an edge).
    full_points_map_m: FloatArray
    full_radius_m: float
    frame_rad: float = 0.0  # the wall family whose axes it is in (rotated by -frame_rad)
    likelihood: LikelihoodField | None = None  # its 2-D field, built on first use
    # Built on first use, per axis: the 1-D densities, and sorted points for gating.
    densities: dict[int, AxisDensity] = field(default_factory=dict)
    sorted_by_axis: dict[int, SortedReference] = field(default_factory=dict)


@dataclass(slots=True)
class _ScanWork:
    """Per-scan intermediate results of `_process`, reused by `_commit` (speed)."""

    dirs_rad: FloatArray
    dirs_ok: npt.NDArray[np.bool_]
    dirs_weak: npt.NDArray[np.bool_]  # directions from far, collinear neighbours only
    theta_rad: float | None = None  # the heading `rotated_m` and `weights` were computed at
    rotated_m: FloatArray | None = None
    weights: FloatArray | None = None


@dataclass(frozen=True, slots=True)
class _Heading:
    """The heading step's answer."""

    theta_rad: float
    measured: bool  # from the scan's walls (else a fallback: directions or the prediction)
    quality: float  # 1 measured, 0.6 relative to the local map, 0.3 the prediction
    flags: PoseFlag
    measurement: HeadingMeasurement


@dataclass(frozen=True, slots=True)
class _Translation:
    """The translation step's answer, on the axes of the wall family at `frame_rad`."""

    x_m: float
    y_m: float
    along_x: AxisMatch
    along_y: AxisMatch
    frame_rad: float
    flags: PoseFlag  # the heading's, with AMBIGUOUS_X / AMBIGUOUS_Y
    field_sigmas_m: dict[int, float]  # σ of the axes the 2-D field measured
    # Axes measured against the previous scan: the motion since it, not the position.
    step_axes: tuple[bool, bool] = (False, False)


class ManhattanEstimator:
    """Tracks the robot pose in the Manhattan map frame, one scan at a time."""

    def __init__(self, params: EstimatorParams | None = None) -> None:
        self.params = params if params is not None else EstimatorParams()
        self.reset()

    def reset(self) -> None:
        """Forget everything: the next scan defines a new map frame."""
        self._initialised = False
        self._pose = Pose2D(0.0, 0.0, 0.0)
        self._stamp_ns: int | None = None
        self._velocity: Pose2D | None = None  # last motion per second, robot frame
        self._odom: Pose2D | None = None
        self._major_axis: int | None = None
        self._keyframes: deque[_Keyframe] = deque(maxlen=max(1, self.params.local_map_keyframes))
        # The previous scan (reference "previous", `previous_scan_fallback`) and its densities.
        self._last_scan: _Keyframe | None = None
        self._last_scan_densities: dict[tuple[int, float], AxisDensity] = {}
        # The previous scan's (angle_min, increment), ranges and range limits, for
        # `profile_turn`; masked only when a turn is measured (not at 40 Hz: speed).
        self._last_profile: tuple[tuple[float, float], FloatArray, float, float] | None = None
        self._grid: OccupiedCells | None = None
        self._grid_dirty = True
        self._dir_spectrum: npt.NDArray[np.complex128] | None = None
        self._periods_s: deque[float] = deque(maxlen=51)  # recent scan periods (stamps)
        # The reference and its axis densities, rebuilt only when it changes (speed).
        self._ref: _Reference | None = None
        self._heading_measured = False  # the last pose's heading came from its Manhattan walls
        self._beams: tuple[tuple[float, float, int], FloatArray] | None = None
        self._covariance = CovarianceTracker()  # of the pose relative to the latest keyframe
        self._odometry = OdometryConsistency()  # how far the odometry's heading holds
        self._sensor_range_m = self.params.max_range_used_m  # the current scan's, set by `_points`
        self._field_params = FieldMatchParams()
        self._increment_rad = math.radians(0.25)  # the current scan's beam step, set by `_points`
        self._frames = WallFrames(self.params.frames)  # the building's wall families
        # What the previous scan and the newest keyframes saw free (`dynamic`, dense scans).
        self._last_free: FreeSpace | None = None
        self._seen_keyframes: deque[FreeSpace] = deque(maxlen=self.params.seen_through.keyframes)

    def __getstate__(self) -> dict[str, object]:
        # The reference is a cache (rebuilt from the keyframes on first use): its 2-D field
        # alone is megabytes, which a checkpoint need not carry.
        state = dict(self.__dict__)
        state["_ref"] = None
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        # Checkpoints pickled by an older version lack the newer caches: start them empty.
        self.__dict__.update(state)
        for stale in ("_local_map", "_local_box", "_dir_hist"):
            self.__dict__.pop(stale, None)
        self.__dict__.setdefault("_ref", None)
        self.__dict__.setdefault("_dir_spectrum", None)
        self.__dict__.setdefault("_beams", None)
        self.__dict__.setdefault("_heading_measured", False)
        self.__dict__["_last_scan_densities"] = {}  # a cache (older keys: axis alone)
        self.__dict__.setdefault("_last_profile", None)
        self.__dict__.setdefault("_covariance", CovarianceTracker())
        self.__dict__.setdefault("_odometry", OdometryConsistency())
        self.__dict__.setdefault("_sensor_range_m", self.params.max_range_used_m)
        self.__dict__["_field_params"] = FieldMatchParams()  # defaults, pickled by position
        self.__dict__.setdefault("_increment_rad", math.radians(0.25))
        self.__dict__.setdefault("_frames", WallFrames(self.params.frames))
        self.__dict__.setdefault("_seen_keyframes", deque(maxlen=SeenThroughParams().keyframes))
        self.__dict__.setdefault("_last_free", None)
        for frame in [*self.__dict__.get("_keyframes", ()), self.__dict__.get("_last_scan")]:
            if frame is not None and not hasattr(frame, "direction_counts"):
                frame.derive()
            if frame is not None and not hasattr(frame, "range_m"):
                frame.range_m = self.params.max_range_used_m
            if frame is not None and not hasattr(frame, "surface_map_m"):
                frame.surface_map_m = None

    # ------------------------------------------------------------------ public
    @property
    def wall_families_rad(self) -> tuple[float, ...]:
        """The wall families found so far, map-frame angles modulo 90° (the first is 0)."""
        return tuple(self._frames.angles_rad)

    def process(self, scan: LaserScan) -> PoseEstimate:
        """Estimate the pose of `scan`. Never raises on bad data: returns a flagged pose."""
        try:
            return self._process(scan)
        except (ValueError, FloatingPointError, IndexError) as exc:  # defensive: bad geometry
            log.warning("estimator could not match scan %d: %s", scan.stamp_ns, exc)
            pred, flags = self._predict(scan)
            return self._commit(scan, pred, 0.0, flags | PoseFlag.DEGENERATE, None)

    # ------------------------------------------------------------------ steps
    def _points(self, scan: LaserScan) -> FloatArray:
        """Step 2: the scan's valid returns in the laser frame, thinned."""
        ranges = np.asarray(scan.ranges_m, dtype=np.float64)
        if ranges.ndim != 1 or ranges.size == 0:
            return np.empty((0, 2))
        if not (math.isfinite(scan.angle_min_rad) and math.isfinite(scan.angle_increment_rad)):
            return np.empty((0, 2))
        with np.errstate(invalid="ignore"):
            mask = (
                np.isfinite(ranges)
                & (ranges > 0.0)
                & (ranges >= scan.range_min_m)
                & (ranges < scan.range_max_m)
                & (ranges <= self.params.max_range_used_m)
            )
        self._sensor_range_m = min(scan.range_max_m, self.params.max_range_used_m)
        self._increment_rad = scan.angle_increment_rad
        idx = np.flatnonzero(mask)
        r = ranges.take(idx)
        cos_sin = self._beam_directions(scan.angle_min_rad, scan.angle_increment_rad, ranges.size)
        pts = cos_sin.take(idx, axis=0)
        pts *= r[:, None]
        return thin_points(pts, self.params.thinning_m)

    def _dense(self, points: FloatArray) -> bool:
        """A dense scan (a UTM-30LX's, not a 180-beam SICK's): the steps measured to help only
        on such scans run on it."""
        return int(points.shape[0]) >= self.params.translation_gate_min_points

    def _beam_directions(self, angle_min_rad: float, increment_rad: float, n: int) -> FloatArray:
        """(n, 2) cos/sin of every beam, computed once per scanner geometry (speed)."""
        key = (angle_min_rad, increment_rad, n)
        if self._beams is None or self._beams[0] != key:
            a = angle_min_rad + increment_rad * np.arange(n, dtype=np.float64)
            self._beams = (key, np.column_stack((np.cos(a), np.sin(a))))
        return self._beams[1]

    def _predict(self, scan: LaserScan) -> tuple[Pose2D, PoseFlag]:
        """Step 1: the predicted pose for `scan`, and whether odometry produced it."""
        p = self.params
        if not self._initialised:
            return self._pose, PoseFlag.NONE
        if p.use_odometry and scan.odom is not None and self._odom is not None:
            delta = self._odom.between(scan.odom)
            return self._pose.compose(delta), PoseFlag.ODOMETRY_PRIOR
        if not p.use_prediction:
            return self._pose, PoseFlag.NONE
        pred = self._pose
        if self._velocity is not None and self._stamp_ns is not None:
            dt = self._dt_s(scan)
            dt = min(max(dt, 0.0), 1.0)
            v = self._velocity
            pred = self._pose.compose(Pose2D(v.x_m * dt, v.y_m * dt, v.theta_rad * dt))
        # Between frequent scans (40 Hz) the robot cannot turn far: the turn rate will do.
        fast = self._fast_steady_scans(scan, p.profile_turn_min_period_s)
        turn = self._profile_turn(scan) if p.profile_turn and not fast else None
        if turn is not None:
            pred = Pose2D(pred.x_m, pred.y_m, wrap_angle(self._pose.theta_rad + turn))
        return pred, PoseFlag.NONE

    def _profile_ranges(self, r: FloatArray, range_min_m: float, range_max_m: float) -> FloatArray:
        """The ranges the estimator uses, NaN elsewhere (for `profile_turn`)."""
        with np.errstate(invalid="ignore"):
            ok = (r >= max(range_min_m, 1e-6)) & (r < range_max_m)
            ok &= r <= self.params.max_range_used_m
        return np.where(ok, r, np.nan)

    def _profile_turn(self, scan: LaserScan) -> float | None:
        """The turn since the previous scan from the range profiles, if they agree on one."""
        p = self.params
        last = self._last_profile
        if last is None or last[0] != (scan.angle_min_rad, scan.angle_increment_rad):
            return None
        max_turn = math.radians(p.profile_turn_max_deg)
        if self._stamp_ns is not None and scan.stamp_ns > self._stamp_ns:
            # As far as the robot can turn since the previous scan: short on fast scanners
            # (speed), long over a gap in a log (ACES: 75° in a 3 s gap).
            gap_s = (scan.stamp_ns - self._stamp_ns) * 1e-9
            reach = 2.0 * math.radians(p.max_turn_rate_deg_s) * gap_s
            max_turn = min(max_turn, max(reach, math.radians(2.0)))
        previous = self._profile_ranges(*last[1:])
        current = self._profile_ranges(
            np.asarray(scan.ranges_m, dtype=np.float64), scan.range_min_m, scan.range_max_m
        )
        turn = profile_turn(previous, current, scan.angle_increment_rad, max_turn)
        if turn is None or turn.score < p.profile_turn_min_score:
            return None
        return turn.turn_rad

    def _dt_s(self, scan: LaserScan) -> float:
        """Time since the previous scan for the motion model, robust to bursty stamps.

        Logged stamps can be bursty (Intel: 1 ms to 1.5 s between consecutive scans) although
        the robot moves about the same per scan, so the step is clipped to a factor of the
        recent median period (ACES: 0.08-0.35 s, mostly unchanged). `scan_period_s > 0` uses
        that nominal period for every scan (constant motion per scan).
        """
        p = self.params
        if p.scan_period_s > 0.0:
            return p.scan_period_s
        return self._step_s(scan)

    def _step_s(self, scan: LaserScan) -> float:
        """Time since the previous scan by the stamps (0 for the first), clipped to a factor
        of the recent median period (bursty logged stamps); what the covariance grows with."""
        p = self.params
        if self._stamp_ns is None:
            return 0.0
        dt = (scan.stamp_ns - self._stamp_ns) * 1e-9
        if len(self._periods_s) >= 5 and p.period_clip_ratio > 1.0:
            typical = statistics.median(self._periods_s)  # np.median's value, bit for bit
            dt = min(max(dt, typical / p.period_clip_ratio), typical * p.period_clip_ratio)
        return dt

    def _longest_period_s(self, scan: LaserScan) -> float | None:
        """The longest recent gap between scan stamps, this scan's included (None: too few).

        The longest, not the median: logged stamps can be bursty (Intel) while the robot moves
        evenly per scan, and a search bounded by a burst's 1 ms would miss the motion.
        """
        if len(self._periods_s) < 5 or self._stamp_ns is None:
            return None
        return max(*self._periods_s, (scan.stamp_ns - self._stamp_ns) * 1e-9)

    def _fast_steady_scans(self, scan: LaserScan, max_period_s: float) -> bool:
        """This scan and the recent ones came at most `max_period_s` apart, at a steady rate.

        Steady: the short recent periods are at least half the median, which rules out bursty
        logged stamps (Intel: 1 ms then 0.5 s) where a short stamp gap says nothing about the
        motion. A few long gaps (scans dropped under load) do not stop tracking.
        """
        if len(self._periods_s) < 5 or self._stamp_ns is None:
            return False
        if (scan.stamp_ns - self._stamp_ns) * 1e-9 > max_period_s:
            return False
        recent = sorted(self._periods_s)
        median = recent[len(recent) // 2]
        return median <= max_period_s and recent[len(recent) // 10] >= 0.5 * median

    def _track_heading(
        self, pts: FloatArray, pred: Pose2D, scan: LaserScan
    ) -> HeadingMeasurement | None:
        """The fine heading search alone, on a fast scanner going straight on a measured heading.

        Only for fast scanners: at the paper's spacing (0.3 m, 5 Hz logs) the coarse search and
        the direction prior still matter on straight runs (synthetic seed 2: 1.9 -> 6.5 m error).
        """
        p = self.params
        if p.heading_tracking_max_turn_deg <= 0.0 or not self._heading_measured:
            return None
        if not self._fast_steady_scans(scan, p.heading_tracking_max_period_s):
            return None
        if abs(wrap_angle(pred.theta_rad - self._pose.theta_rad)) >= math.radians(
            p.heading_tracking_max_turn_deg
        ):
            return None
        meas = track_heading(
            pts,
            pred.theta_rad - self._frames.angle_rad,
            math.radians(p.heading_step_deg),
            p.heading_bin_m,
            score=p.heading_score,
            refine=p.subbin_refinement,
            max_range_m=p.heading_max_range_m,
        )
        if meas is None or meas.peak_fraction < p.min_heading_peak_fraction:
            return None
        return meas

    def _process(self, scan: LaserScan) -> PoseEstimate:
        """One scan through the steps, in order: prediction, points, heading, moving objects
        left out, translation, confidence and σ; `_commit` keeps the result."""
        pred, flags = self._predict(scan)
        pts = self._points(scan)
        if pts.shape[0] < self.params.min_points:
            return self._commit(scan, pred, 0.0, flags | PoseFlag.DEGENERATE, None)
        work = _ScanWork(*self._directions(pts))
        heading = self._heading(scan, pred, flags, pts, work)
        if not self._initialised:
            return self._first_pose(scan, pts, heading, work)
        at = Pose2D(pred.x_m, pred.y_m, heading.theta_rad)
        pts, work = self._without_moved(scan, pts, work, at)
        move = self._translation(scan, pred, heading, pts, work)
        if move is None:  # nothing to match against yet
            return self._commit(scan, at, 0.2, heading.flags, pts, work=work)
        quality, sigmas = self._confidence(heading, move)
        phi = move.frame_rad
        pose = Pose2D(*rotate_point(move.x_m, move.y_m, phi), heading.theta_rad)  # map axes
        return self._commit(
            scan,
            pose,
            quality,
            move.flags,
            pts,
            work=work,
            sigmas_m=sigmas,
            frame_rad=phi,
            steps=move.step_axes,
        )

    def _heading(
        self, scan: LaserScan, pred: Pose2D, flags: PoseFlag, pts: FloatArray, work: _ScanWork
    ) -> _Heading:
        """Step 3, the heading (paper §II): the Manhattan angle of the scan's walls, resolved
        to the absolute heading near the prediction, with the fallbacks where walls fail.

        Updates the wall families (`frames`) and the major axis; on the first scan, before
        the map frame exists, only measures.
        """
        p = self.params
        odom_prior = bool(flags & PoseFlag.ODOMETRY_PRIOR)
        predicted = self._initialised and (p.use_prediction or odom_prior)
        sigma = math.radians(p.heading_prior_sigma_deg)
        # How far a relative heading may have drifted from the walls, for re-anchoring on
        # them: without odometry up to `wall_reanchor_max_deg`; with it, as far as the
        # odometry's own errors carry it since the walls last measured it (`odometry`), and
        # its prior no narrower than that (no wider than the constant-velocity one).
        reanchor_max = math.radians(p.wall_reanchor_max_deg)
        if odom_prior:
            odom_sigma = math.radians(p.heading_prior_sigma_odom_deg)
            drift = self._odometry.heading_drift_rad() if p.odometry_consistency else 0.0
            reanchor_max = min(reanchor_max, 3.0 * drift) if drift > odom_sigma else 0.0
            sigma = min(math.hypot(odom_sigma, drift), sigma)
        prior_theta = pred.theta_rad
        dirs, dirs_ok = work.dirs_rad, work.dirs_ok
        if predicted and p.wall_frames:
            # The wall family the scan's surfaces follow: its walls give the heading.
            frame_before = self._frames.current
            if self._frames.select(dirs[dirs_ok] + pred.theta_rad) != frame_before:
                self._major_axis = None  # another family's walls: not a heading switch
        phi = self._frames.angle_rad
        rotation_from_dirs: float | None = None
        meas = self._track_heading(pts, pred, scan) if predicted else None
        # Without odometry the constant-velocity heading is weak: the direction histograms
        # give a sharper prior. With odometry they only hurt (measured: ACES 0.56 -> 0.07 m).
        use_dirs = predicted and p.direction_prior and not odom_prior and bool(self._keyframes)
        if meas is None and use_dirs and dirs_ok.sum() >= p.min_points:
            if self._dir_spectrum is None:
                counts = self._keyframes[0].direction_counts
                for f in islice(self._keyframes, 1, None):
                    counts = counts + f.direction_counts
                self._dir_spectrum = direction_spectrum(counts)
            theta_dir, contrast = match_rotation(
                self._dir_spectrum,
                dirs[dirs_ok],
                pred.theta_rad,
                math.radians(p.direction_window_deg),
            )
            if contrast >= p.direction_min_contrast:
                rotation_from_dirs = theta_dir
                prior_theta = theta_dir
                sigma = math.radians(p.direction_sigma_deg)
        if meas is None:
            meas = self._measure_heading(
                pts,
                prior_theta - phi if predicted else None,
                sigma,
                coarse_half_rad=(
                    p.heading_coarse_window_sigmas * sigma
                    if p.heading_coarse_window_sigmas > 0.0
                    else QUARTER / 2.0
                ),
            )
        heading_ok = meas.peak_fraction >= p.min_heading_peak_fraction
        heading_quality = 1.0
        if not heading_ok:
            flags |= PoseFlag.NO_DOMINANT_WALL
        if predicted and abs(meas.prior_offset_rad) > p.heading_max_offset_sigmas * sigma:
            flags |= PoseFlag.NON_MANHATTAN
            heading_ok = False
        if not self._initialised:
            return _Heading(meas.angle_rad, heading_ok, 1.0 if heading_ok else 0.3, flags, meas)
        if heading_ok:
            # The ±45° rule: the member of the Manhattan family nearest the predicted heading
            # (the paper tracks it against the previous heading; the prediction is better).
            theta = resolve_heading(
                meas.angle_rad + phi, prior_theta if predicted else self._pose.theta_rad
            )
            if self._major_axis is not None and meas.major_axis != self._major_axis:
                flags |= PoseFlag.HEADING_SWITCH  # the major wall changed to a perpendicular one
            self._major_axis = meas.major_axis
        elif rotation_from_dirs is not None:
            theta = rotation_from_dirs  # relative, but consistent with the local map
            heading_quality = 0.6
        else:
            theta = pred.theta_rad
            heading_quality = 0.3
        if predicted and p.heading_check and not odom_prior and self._grid_ready():
            last_ns = self._stamp_ns if self._stamp_ns is not None else scan.stamp_ns
            gap_s = (scan.stamp_ns - last_ns) * 1e-9
            checked = self._check_heading(pts, pred, theta, heading_ok, meas, gap_s=gap_s)
            if checked is not None:
                theta, absolute = checked
                if absolute and not heading_ok:
                    flags &= ~(PoseFlag.NON_MANHATTAN | PoseFlag.NO_DOMINANT_WALL)
                    heading_ok, heading_quality = True, 1.0
                elif not absolute and heading_ok:
                    flags |= PoseFlag.NON_MANHATTAN
                    heading_ok, heading_quality = False, 0.6

        new_family = False
        # Dense scans only: on the two real logs (SICK, 180 beams) families were found that
        # are not in the building (Intel, five starts: median 0.49 -> 1.44 m).
        if predicted and p.wall_frames and self._dense(pts):
            # The heading that measures a new family must stand on strong walls: a heading
            # walked off along a curved wall measures its own error as a "family" (hall worlds).
            strong = meas.peak_fraction >= p.frames.new_anchor_peak_fraction
            new_family = self._observe_frames(
                pts, dirs[dirs_ok], theta, anchored=heading_ok and strong
            )
        if (
            predicted
            and not heading_ok
            and not new_family
            and reanchor_max > 0.0
            and p.wall_reanchor_fraction > 0.0
        ):
            anchored = self._reanchor_on_walls(pts, meas, theta, reanchor_max)
            if anchored is not None:
                theta = anchored
                flags &= ~(PoseFlag.NON_MANHATTAN | PoseFlag.NO_DOMINANT_WALL)
                heading_ok, heading_quality = True, 1.0
        # Wrapped: the pose's heading (`_commit` reuses the rotated points when it matches).
        return _Heading(wrap_angle(theta), heading_ok, heading_quality, flags, meas)

    def _first_pose(
        self, scan: LaserScan, pts: FloatArray, heading: _Heading, work: _ScanWork
    ) -> PoseEstimate:
        """The first scan sets the map frame: its heading, at the origin."""
        p = self.params
        # First scan: the map axes are its major walls; x is the one nearest the robot's
        # forward direction, so the first heading is the Manhattan angle itself.
        self._major_axis = heading.measurement.major_axis
        # Weak walls (a curved wall, clutter): the first family the robot measures on
        # strong walls replaces them (`frames`), instead of being folded onto them.
        self._frames.provisional = (
            p.wall_frames
            and self._dense(pts)
            and heading.measurement.peak_fraction < p.frames.new_anchor_peak_fraction
        )
        pose = Pose2D(0.0, 0.0, heading.theta_rad)
        return self._commit(scan, pose, heading.quality, heading.flags, pts, work=work)

    def _without_moved(
        self, scan: LaserScan, pts: FloatArray, work: _ScanWork, pose: Pose2D
    ) -> tuple[FloatArray, _ScanWork]:
        """Step 4: the scan without the points that moved in (`dynamic`), at `pose` (the
        predicted position and the measured heading)."""
        p = self.params
        # Dense scans only: on the two real logs (SICK, 180 beams, a pose per 0.1-0.5 s) it
        # measured worse (five starts: ACES median 0.14 -> 0.16 m, Intel 0.49 -> 1.85 m).
        if not (p.dynamic_rejection and self._dense(pts)):
            return pts, work
        keep = self._static(scan, pts, pose)
        if keep is None:
            return pts, work
        return pts[keep], _ScanWork(work.dirs_rad[keep], work.dirs_ok[keep], work.dirs_weak[keep])

    def _translation(
        self,
        scan: LaserScan,
        pred: Pose2D,
        heading: _Heading,
        pts: FloatArray,
        work: _ScanWork,
    ) -> _Translation | None:
        """Step 5, the translation (paper §III): 1-D correlations along the wall family's axes
        against the local map, each open axis tried against the previous scan, then in 2-D
        against the local map's field, then refined in 2-D. None: no local map yet.
        """
        p = self.params
        theta, heading_ok, flags = heading.theta_rad, heading.measured, heading.flags
        odom_prior = bool(flags & PoseFlag.ODOMETRY_PRIOR)
        dirs, dirs_ok, dirs_weak = work.dirs_rad, work.dirs_ok, work.dirs_weak
        # Correlated along the axes of the wall family the heading came from (`frames`): in
        # a 30° wing the map axes would cut its walls at 30° and blur every histogram.
        phi = self._frames.angle_rad if p.wall_frames else 0.0
        pred_xy = rotate_point(pred.x_m, pred.y_m, -phi)
        cur = rotate_points(pts, theta - phi)
        ref = self._reference(phi)
        if ref is None:
            return None
        if p.orientation_weighting:
            cur_w = orientation_weights(dirs, dirs_ok, theta - phi, weak=dirs_weak)
            if phi == 0.0:
                work.theta_rad, work.rotated_m, work.weights = theta, cur, cur_w
        else:
            cur_w = np.ones_like(cur)
        if p.use_prediction or odom_prior:
            half_t = p.translation_window_odom_m if odom_prior else p.translation_window_pred_m
            period_s = self._longest_period_s(scan)
            if p.bounded_search and period_s is not None:
                # The robot cannot move farther than this in one scan period (fast scanners).
                reach_m = max(2.0 * p.max_speed_m_s * period_s, p.translation_window_min_m)
                half_t = min(half_t, reach_m)
            centre_xy = pred_xy
        else:
            half_t = p.translation_window_m
            centre_xy = rotate_point(self._pose.x_m, self._pose.y_m, -phi)
        # Only where the reference observed: a current point beyond its coverage reads zero
        # at every shift that moves it out, and the edge of coverage then pulls the match
        # back to the reference's own position (a plain corridor "mapped" at zero length).
        # Dense scans only (a UTM-30LX, not a 180-beam SICK): on both real logs, SICK scans,
        # the coverage cut and the 2-D search measured worse (ACES 0.14 -> 0.15-0.26 m, Intel
        # 0.49 -> 0.47-1.33 m, medians over five starts), the way items 11 and 17 did.
        dense = self._dense(cur)
        cut = p.coverage_cut and dense
        cur_w_all = cur_w
        if cut:
            cur_w = _covered(cur, cur_w, centre_xy, ref.centre_xy_m, ref.radius_m - half_t)
        prior_sigma_t = (0.0, 0.0)
        if odom_prior:
            prior_sigma_t = (p.translation_prior_sigma_odom_m,) * 2
        elif p.use_prediction:
            # No narrower than the motion model's own uncertainty relative to the reference
            # (`covariance`): from a standing start, or after a long carry, the speed is
            # unknown and "standing still" is only a guess. Dense scans only: on both real
            # logs (180-beam SICK) it measured worse (five starts: ACES 0.17 -> 0.23 m, Intel
            # 0.40 -> 0.64 m), as items 11, 19 and 20 did.
            carried_sigma = (0.0, 0.0)
            if p.translation_prior_carried and dense:
                carried_sigma = self._covariance.predicted_sigmas_m(self._step_s(scan), phi)
            prior_sigma_t = (
                max(p.translation_prior_sigma_m, carried_sigma[0]),
                max(p.translation_prior_sigma_m, carried_sigma[1]),
            )
        support = (float(cur_w[:, 0].sum()), float(cur_w[:, 1].sum()))
        gated: tuple[int, ...] = ()
        # The band needs the heading: on a fallback heading the 1-D projections are kept. On
        # sparse scans (180-beam SICK) it measured worse: too few points pair in the band.
        if p.translation_gate_m > 0.0 and heading_ok and dense:
            # The axis with fewer constraining points is the along-corridor one, where a few
            # faces decide and projection aliasing bites (`service.core.frontend.gated`).
            gated = (0, 1) if p.translation_gate_both else (int(support[1] < support[0]),)

        def peak(axis: int, curve: tuple[FloatArray, FloatArray], min_support: float) -> AxisMatch:
            return pick_peak(
                *curve,
                pred_xy[axis],
                support[axis],
                min_support=min_support,
                ambiguity_ratio=p.ambiguity_ratio,
                refine=p.subbin_refinement,
                prior_sigma_m=prior_sigma_t[axis],
            )

        matches: dict[int, AxisMatch] = {}
        for axis in (0, 1) if len(gated) != 1 else (1 - gated[0],):
            curve = correlate_axis(
                self._density(ref, axis), cur[:, axis], cur_w[:, axis], centre_xy[axis], half_t
            )
            matches[axis] = peak(axis, curve, p.min_axis_support)
        # Each gated axis within a band around the other axis' 1-D answer.
        band = {axis: matches[1 - axis].offset_m for axis in gated}
        for axis in gated:
            curve = self._gated_correlation(
                ref, axis, cur, cur_w, band[axis], centre_xy[axis], half_t
            )
            matches[axis] = peak(axis, curve, p.min_axis_support)
        # An axis the local map leaves ambiguous may still be clear against the previous scan:
        # a crisp reference (the local map is blurred by its keyframes' own errors) and, over one
        # scan, a small motion, so a few points suffice (ACES: a robot stopped in a corridor
        # was predicted on at its last speed).
        steps = [False, False]
        if p.previous_scan_fallback and not odom_prior and self._last_scan is not None:
            last = self._last_scan.in_frame(phi)
            last_w: FloatArray | None = None  # the weights against it, once for both axes
            for axis in (0, 1):
                if not matches[axis].ambiguous:
                    continue
                if last_w is None:
                    last_w = cur_w_all
                    if cut:
                        last_xy = (last.pose.x_m, last.pose.y_m)
                        radius = last.range_m - half_t
                        last_w = _covered(cur, cur_w_all, centre_xy, last_xy, radius)
                curve = correlate_axis(
                    self._last_scan_density(last, axis, phi),
                    cur[:, axis],
                    last_w[:, axis],
                    centre_xy[axis],
                    half_t,
                )
                fallback = peak(axis, curve, p.previous_scan_min_support)
                if not fallback.ambiguous:
                    matches[axis] = fallback
                    steps[axis] = True
        # An axis still open: every point in 2-D, against the local map's likelihood field.
        field_sigmas: dict[int, float] = {}
        if p.field_match and dense:
            for axis in (0, 1):
                if not matches[axis].ambiguous:
                    continue
                at = [matches[0].offset_m, matches[1].offset_m]
                at[axis] = centre_xy[axis]
                prior_sigma = prior_sigma_t[axis] if prior_sigma_t[axis] > 0.0 else half_t
                # As in 1-D: a point a shift can carry out of the field's known disc votes
                # for the shifts that keep it in (the reference's own position).
                reach = ref.full_radius_m - half_t
                inside = np.flatnonzero(~_outside(cur, (at[0], at[1]), ref.centre_xy_m, reach))
                if inside.shape[0] < p.min_points:
                    continue
                response = axis_response(
                    self._field(ref),
                    cur.take(inside, axis=0) + np.array(at),
                    axis,
                    half_t,
                    self._field_params,
                    prior_sigma_m=prior_sigma,
                )
                if response.measured:
                    value = centre_xy[axis] + response.offset_m
                    sharp = 1.0 - response.sigma_m / response.prior_spread_m
                    matches[axis] = AxisMatch(value, (value,), sharp, support[axis], False)
                    field_sigmas[axis] = response.sigma_m
        mx, my = matches[0], matches[1]
        x, y = mx.offset_m, my.offset_m
        if mx.ambiguous:
            flags |= PoseFlag.AMBIGUOUS_X
        if my.ambiguous:
            flags |= PoseFlag.AMBIGUOUS_Y

        # A gated axis is already 2-D checked, and side-aware, which the occupied cells are
        # not (measured on the synthetic building: the cells then undo right gated answers).
        if p.refine_2d and (not gated or p.refine_2d_gated) and self._grid_ready():
            x, y = self._refine(cur, x, y, mx, my, phi)

        return _Translation(x, y, mx, my, phi, flags, field_sigmas, (steps[0], steps[1]))

    def _confidence(
        self, heading: _Heading, move: _Translation
    ) -> tuple[float, tuple[float | None, float | None]]:
        """Step 6: the match's confidence in [0, 1] and its σ along both axes of its frame
        (the 2-D field's where it measured an axis, else from the 1-D peak's shape)."""
        mx, my, field_sigmas = move.along_x, move.along_y, move.field_sigmas_m
        q = heading.quality * (0.5 + 0.25 * mx.sharpness + 0.25 * my.sharpness)
        if mx.ambiguous:
            q *= 0.7
        if my.ambiguous:
            q *= 0.7
        cov = self._covariance.params
        sigmas = (
            field_sigmas.get(0, axis_sigma_m(mx, cov)),
            field_sigmas.get(1, axis_sigma_m(my, cov)),
        )
        return q, sigmas

    def _static(
        self, scan: LaserScan, pts: FloatArray, pose: Pose2D
    ) -> npt.NDArray[np.bool_] | None:
        """The points not in space that the previous scan or the oldest of the recent
        keyframes saw through (None: keep them all). A keyframe too: a person beside the robot
        for several scans is in the previous one, but not where the robot was a metre ago."""
        p = self.params
        seen = [self._seen_keyframes[0]] if self._seen_keyframes else []
        if self._last_free is not None:
            seen.append(self._last_free)
        moved = np.zeros(pts.shape[0], dtype=bool)
        for free in seen:
            if free.matches(scan.angle_min_rad, scan.angle_increment_rad, len(scan.ranges_m)):
                moved |= seen_through(pts, pose, free, p.seen_through)
        if not moved.any() or pts.shape[0] - int(moved.sum()) < p.min_points:
            return None
        return ~moved

    def _gated_correlation(  # noqa: PLR0917 - the correlation's inputs plus the band
        self,
        ref: _Reference,
        axis: int,
        cur: FloatArray,
        cur_w: FloatArray,
        other_m: float,
        centre_m: float,
        half_t: float,
    ) -> tuple[FloatArray, FloatArray]:
        """One axis' correlation, pairs only within a band of `other_m` on the other axis."""
        p = self.params
        other = 1 - axis
        sides = p.translation_gate_sides
        sorted_ref = ref.sorted_by_axis.get(axis)
        if sorted_ref is None:  # once per reference, like the densities
            sorted_ref = SortedReference(
                ref.points_map_m,
                ref.weights,
                ref.sides if sides else None,
                axis,
                p.translation_gate_min_weight,
            )
            ref.sorted_by_axis[axis] = sorted_ref
        # A heading error moves far points across the band: widen it with the range.
        gate = p.translation_gate_m + np.hypot(cur[:, 0], cur[:, 1]) * math.tan(
            math.radians(p.translation_gate_heading_deg)
        )
        return correlate_axis_gated(
            sorted_ref,
            cur[:, axis],
            cur[:, other] + other_m,
            cur_w[:, axis],
            cur[:, axis] >= 0.0 if sides else None,
            centre_m,
            half_t,
            p.translation_step_m,
            p.translation_bin_m,
            gate,
            p.translation_gate_min_weight,
        )

    # ------------------------------------------------------------------ heading check
    def _check_heading(
        self,
        pts: FloatArray,
        pred: Pose2D,
        theta: float,
        heading_ok: bool,
        meas: HeadingMeasurement,
        *,
        gap_s: float,
    ) -> tuple[float, bool] | None:
        """Re-anchor the heading: the candidate that best fits the local map's geometry.

        The Manhattan angle is absolute modulo 90°; only its quadrant (and, after a wrong
        prediction, the peak itself) can be lost. Candidates: the members of the measured and
        of the strongest (prior-free, the paper's) Manhattan family within reach of the previous
        heading, plus the prediction. Each is scored by the share of scan points on occupied
        local-map cells over a coarse translation grid, which does not depend on the Manhattan
        prior. Returns (heading, is_manhattan) when another candidate is clearly better.
        """
        p = self.params
        prev = self._pose.theta_rad
        reach = math.radians(p.heading_check_max_turn_deg)
        # Over a gap in the log the robot may have turned anywhere (ACES: 75° in 3 s).
        reach = max(reach, min(math.pi, 0.5 * math.radians(p.max_turn_rate_deg_s) * gap_s))
        turn = max(abs(wrap_angle(theta - prev)), abs(wrap_angle(pred.theta_rad - prev)))
        # Cheap trigger: steady motion on a confident Manhattan heading needs no check.
        if heading_ok and turn < math.radians(p.heading_check_min_turn_deg):
            return None
        free = self._free_heading(pts, meas)
        cands: list[tuple[float, bool]] = [(theta, heading_ok)]
        angles = [meas.angle_rad]
        if free.peak_fraction >= p.min_heading_peak_fraction:
            angles.append(free.angle_rad)
        # Both the motion prediction and "no turn" (the prediction can overshoot a turn).
        anchors = (pred.theta_rad, prev)

        def offset(c: float) -> float:
            return min(abs(wrap_angle(c - a)) for a in anchors)

        # Every family's member (only the first without `wall_frames`: none is learnt).
        for a, f in product(angles, self._frames.angles_rad):
            base = resolve_heading(a + f, prev)
            for k in (-1, 0, 1, 2):
                c = base + k * QUARTER
                if offset(c) <= reach:
                    cands.append((c, True))
        cands.extend((a, False) for a in anchors)
        uniq: list[tuple[float, bool]] = []
        for c, absolute in cands:
            if all(abs(wrap_angle(c - u)) > math.radians(0.5) for u, _ in uniq):
                uniq.append((c, absolute))
        if len(uniq) == 1:
            return None
        step = max(1, pts.shape[0] // p.heading_check_points)
        sub = pts[::step]
        n = max(1, round(p.heading_check_window_m / p.heading_check_step_m))
        g = p.heading_check_step_m * np.arange(-n, n + 1, dtype=np.float64)
        grid = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
        grid += np.array([pred.x_m, pred.y_m])
        cells = self._occupied()
        scores = np.array(
            [float(cells.hit_fraction(rotate_points(sub, c), grid).max()) for c, _ in uniq]
        )
        # A candidate far from the prediction must beat the current heading by more.
        far = np.array([offset(c) / reach for c, _ in uniq])
        needed = scores[0] + p.heading_check_margin * (1.0 + 2.0 * far)
        better = np.flatnonzero(scores >= needed)
        if better.size == 0:
            return None
        best = int(better[np.argmax(scores[better])])
        return wrap_angle(uniq[best][0]), uniq[best][1]

    def _measure_heading(
        self,
        pts: FloatArray,
        prior_rad: float | None,
        sigma_rad: float,
        *,
        coarse_half_rad: float = QUARTER / 2.0,
        same_points: HeadingMeasurement | None = None,
    ) -> HeadingMeasurement:
        """`heading.measure_heading` with this estimator's search settings."""
        p = self.params
        return measure_heading(
            pts,
            prior_rad,
            sigma_rad,
            math.radians(p.heading_step_deg),
            p.heading_bin_m,
            score=p.heading_score,
            coarse_step_rad=math.radians(p.heading_coarse_step_deg),
            coarse_bin_m=p.heading_coarse_bin_m,
            refine=p.subbin_refinement,
            max_range_m=p.heading_max_range_m,
            same_points=same_points,
            coarse_half_rad=coarse_half_rad,
        )

    def _free_heading(self, pts: FloatArray, meas: HeadingMeasurement) -> HeadingMeasurement:
        """The paper's heading search, without a prior, on the points `meas` measured."""
        return self._measure_heading(pts, None, 0.0, same_points=meas)

    def _observe_frames(
        self, pts: FloatArray, directions_rad: FloatArray, theta: float, *, anchored: bool
    ) -> bool:
        """Whether this scan shows a wall family that is being learnt (counted when trusted).

        Trusted: the heading was measured in this scan on the current family, whose walls are
        in view too. The angle between the two families is then measured within one scan,
        free of drift. A heading measured on walls that are not the family's (a drifted one
        that locked onto a curved wall: hall worlds) sees the old walls at its own error; that
        "family" is the error, and is not counted. Also True for a family that earlier trusted
        scans are learning: the caller must not re-anchor it onto an old one.
        """
        p = self.params
        frames = self._frames
        map_directions = directions_rad + theta
        rough = frames.candidate(map_directions)
        if rough is None:
            return False
        if anchored and frames.provisional and frames.current == 0:
            frames.provisional = False  # the first family is measured on strong walls after all
        trusted = anchored and (
            frames.current_support(map_directions) >= frames.params.new_min_points
        )
        # While the first family is provisional, the heading is relative to the first scan,
        # whose walls were weak: what strong walls it sees are the building's.
        if not (trusted or frames.provisional):
            return frames.is_pending(rough)
        meas = track_heading(
            pts,
            theta - rough,
            math.radians(p.heading_step_deg),
            p.heading_bin_m,
            score=p.heading_score,
            fine_half_rad=math.radians(frames.params.tolerance_deg),
            refine=p.subbin_refinement,
            max_range_m=p.heading_max_range_m,
        )
        if meas is None or meas.peak_fraction < p.min_heading_peak_fraction:
            return frames.is_pending(rough)
        provisional = frames.provisional
        if frames.observe(theta - meas.angle_rad, self._pose.x_m, self._pose.y_m):
            if provisional:
                log.info(
                    "the first scan's walls were weak: the building's walls at %.2f deg are the "
                    "first wall family instead",
                    math.degrees(frames.angles_rad[0]),
                )
                return True
            log.info(
                "wall family at %.2f deg added (families: %s)",
                math.degrees(frames.angles_rad[-1]),
                ", ".join(f"{math.degrees(a):.2f}" for a in frames.angles_rad),
            )
        return True

    def _reanchor_on_walls(
        self, pts: FloatArray, meas: HeadingMeasurement, theta: float, max_rad: float
    ) -> float | None:
        """The paper's absolute heading again, after a relative one drifted from the walls.

        A relative heading (direction histograms, range profiles, the prediction) drifts, and
        the Manhattan search around it then no longer reaches the walls: each scan is 'without
        a dominant wall' and the drift stays (Intel: 24° from scan ~420 on). When the paper's
        prior-free search finds strong walls, the member of their family nearest the current
        heading is taken (the ±45° rule), if the correction is plausible as drift (`max_rad`).
        """
        p = self.params
        free = self._free_heading(pts, meas)
        if free.peak_fraction < p.wall_reanchor_fraction:
            return None
        anchored, _ = self._frames.nearest_member(free.angle_rad, theta)
        if abs(wrap_angle(anchored - theta)) > max_rad:
            return None
        return anchored

    # ------------------------------------------------------------------ reference
    def _reference(self, frame_rad: float = 0.0) -> _Reference | None:
        """The reference of the current scan in a family's axes, cached until it changes."""
        p = self.params
        if self._ref is not None and self._ref.frame_rad == frame_rad:
            return self._ref
        if p.reference == "previous":
            frames = [self._last_scan] if self._last_scan is not None else []
        elif p.reference == "keyframe":
            frames = [self._keyframes[-1]] if self._keyframes else []
        else:
            frames = list(self._keyframes)
        if not frames:
            return None
        frames = [f.in_frame(frame_rad) for f in frames]
        pts = np.concatenate([f.points_map_m for f in frames])
        w = np.concatenate([f.weights for f in frames])
        sides = np.concatenate([f.sides for f in frames])
        centre = (frames[-1].pose.x_m, frames[-1].pose.y_m)
        radius = full_radius = frames[-1].range_m
        full_pts = np.concatenate(
            [f.surface_map_m if f.surface_map_m is not None else f.points_map_m for f in frames]
        )
        if len(frames) > 1:
            # The local map within the radius of its newest keyframe (not of the prediction,
            # so that the reference stays the same from one keyframe to the next).
            x, y = frames[-1].pose.x_m, frames[-1].pose.y_m
            d2 = (pts[:, 0] - x) ** 2 + (pts[:, 1] - y) ** 2
            # `take` of indices: (n, 2) boolean indexing is ~10x slower.
            keep = np.flatnonzero(d2 <= p.local_map_radius_m**2)
            if p.min_points <= keep.shape[0] < pts.shape[0]:
                pts, w = pts.take(keep, axis=0), w.take(keep, axis=0)
                sides = sides.take(keep, axis=0)
                radius = min(radius, p.local_map_radius_m)
        if not p.orientation_weighting:
            w = np.ones_like(pts)
        self._ref = _Reference(pts, w, sides, centre, radius, full_pts, full_radius, frame_rad)
        return self._ref

    def _field(self, ref: _Reference) -> LikelihoodField:
        """The reference's 2-D likelihood field, built on first use."""
        if ref.likelihood is None:
            ref.likelihood = local_field(
                ref.full_points_map_m, ref.centre_xy_m, ref.full_radius_m, self._field_params
            )
        return ref.likelihood

    def _density(self, ref: _Reference, axis: int) -> AxisDensity:
        """The reference's density along `axis`, built on first use (a gated axis needs none)."""
        density = ref.densities.get(axis)
        if density is None:
            p = self.params
            widest = max(
                p.translation_window_m, p.translation_window_pred_m, p.translation_window_odom_m
            )
            density = axis_density(
                np.ascontiguousarray(ref.points_map_m[:, axis]),
                np.ascontiguousarray(ref.weights[:, axis]),
                p.translation_step_m,
                p.translation_bin_m,
                widest,
            )
            ref.densities[axis] = density
        return density

    def _last_scan_density(self, last: _Keyframe, axis: int, frame_rad: float) -> AxisDensity:
        """The previous scan's density along `axis` (`last`: it in the axes of `frame_rad`)."""
        key = (axis, frame_rad)
        density = self._last_scan_densities.get(key)
        if density is None:
            p = self.params
            density = axis_density(
                np.ascontiguousarray(last.points_map_m[:, axis]),
                np.ascontiguousarray(last.weights[:, axis]),
                p.translation_step_m,
                p.translation_bin_m,
                max(p.translation_window_m, p.translation_window_pred_m),
            )
            self._last_scan_densities[key] = density
        return density

    def _grid_ready(self) -> bool:
        return bool(self._keyframes)

    def _occupied(self) -> OccupiedCells:
        """The local map's occupied cells, built on first use after a keyframe."""
        # On first use (speed): the heading check and the 2-D refinement mostly return early.
        if self._grid is None or self._grid_dirty:
            pts = np.concatenate([f.points_map_m for f in self._keyframes])
            self._grid = OccupiedCells(pts)
            self._grid_dirty = False
        return self._grid

    def _refine(  # noqa: PLR0917 - the 1-D answers and the axes they are in
        self, cur: FloatArray, x: float, y: float, mx: AxisMatch, my: AxisMatch, frame_rad: float
    ) -> tuple[float, float]:
        """Joint 2-D choice among the 1-D peak candidates (the paper's axes are independent).

        `cur`, the answers and the result are in the axes of the wall family at `frame_rad`.
        """
        xs = [x] + [c for c in mx.peak_offsets_m if abs(c - x) > 0.02]
        ys = [y] + [c for c in my.peak_offsets_m if abs(c - y) > 0.02]
        if len(xs) == 1 and len(ys) == 1:
            return x, y
        cand = np.array([(cx, cy) for cx in xs for cy in ys])
        if frame_rad != 0.0:  # the occupied cells are in the map frame
            scores = self._occupied().hit_fraction(
                rotate_points(cur, frame_rad), rotate_points(cand, frame_rad)
            )
        else:
            scores = self._occupied().hit_fraction(cur, cand)
        best = int(np.argmax(scores))
        # Switch only for a clearly better combination: the 1-D answer is sub-bin refined.
        if scores[best] > scores[0] + 0.05:
            return float(cand[best, 0]), float(cand[best, 1])
        return x, y

    def _directions(
        self, pts: FloatArray
    ) -> tuple[FloatArray, npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
        """Surface directions: (angles, reliable, weak).

        On sparse scans far, collinear neighbours make a direction reliable. On a dense one
        (the UTM-30LX) they only make it `weak`: full weight across the wall measured worse
        (synthetic loop gap 0.02 -> 1.6 m, the heading error carried at long range), but the
        direction still stops a grazing wall point from voting along its wall.
        """
        p = self.params
        dense = self._dense(pts)
        dirs, close, line = split_tangent_directions(
            pts,
            max_line_deviation=p.direction_line_deviation,
            one_sided=dense and p.end_directions,
        )
        if not dense:
            return dirs, close | line, np.zeros_like(line)
        if not p.weak_directions:
            line[:] = False
        return dirs, close, line

    # ------------------------------------------------------------------ bookkeeping
    def _frame(
        self, pts: FloatArray, pose: Pose2D, work: _ScanWork | None, *, surfaces: bool = True
    ) -> _Keyframe:
        """The scan as a keyframe at `pose`, reusing what `_process` computed for it; without
        `surfaces`, no filled surfaces (only the 2-D field reads them, from the local map)."""
        if work is not None:
            dirs, ok, weak = work.dirs_rad, work.dirs_ok, work.dirs_weak
        else:
            dirs, ok, weak = self._directions(pts)
        if (
            work is not None
            and work.rotated_m is not None
            and work.weights is not None
            and work.theta_rad == pose.theta_rad
        ):
            cur, cur_w = work.rotated_m, work.weights
        else:
            cur = rotate_points(pts, pose.theta_rad)
            cur_w = orientation_weights(dirs, ok, pose.theta_rad, weak=weak)
        origin = np.array([pose.x_m, pose.y_m])
        surface = None
        if surfaces:
            filled = surface_points(pts, dirs, ok | weak, self._increment_rad, self._field_params)
            surface = rotate_points(filled, pose.theta_rad) + origin
        return _Keyframe(
            pose,
            cur + origin,
            cur_w,
            (dirs[ok] + pose.theta_rad) % math.pi,
            self._sensor_range_m,
            surface,
            dirs + pose.theta_rad,
            ok,
            weak,
        )

    def _commit(
        self,
        scan: LaserScan,
        pose: Pose2D,
        quality: float,
        flags: PoseFlag,
        pts: FloatArray | None,
        *,
        work: _ScanWork | None = None,
        sigmas_m: tuple[float | None, float | None] = (None, None),
        frame_rad: float = 0.0,
        steps: tuple[bool, bool] = (False, False),
    ) -> PoseEstimate:
        """Keep the pose and its motion; `sigmas_m` are the match σ (None: not measured) along
        the axes of the wall family at `frame_rad`, of the motion since the previous scan
        where `steps`."""
        p = self.params
        if self._initialised and self._stamp_ns is not None:
            dt = self._dt_s(scan)
            # An ambiguous match says little about the motion: keep the previous velocity, so
            # that a featureless corridor does not stop the robot (the stationary-lock failure).
            if 1e-4 < dt < 2.0:
                d = self._pose.between(pose)
                vx, vy, w = d.x_m / dt, d.y_m / dt, d.theta_rad / dt
                speed = math.hypot(vx, vy)
                if speed > p.max_speed_m_s:
                    vx, vy = vx * p.max_speed_m_s / speed, vy * p.max_speed_m_s / speed
                w_max = math.radians(p.max_turn_rate_deg_s)
                w = min(max(w, -w_max), w_max)
                if self._velocity is not None:  # light smoothing against single bad matches
                    v = self._velocity
                    vx, vy, w = (
                        0.3 * v.x_m + 0.7 * vx,
                        0.3 * v.y_m + 0.7 * vy,
                        0.3 * v.theta_rad + 0.7 * w,
                    )
                    if flags & _POSITION_UNSURE:
                        vx, vy = v.x_m, v.y_m
                    # Bounded acceleration: a match one door period ahead along a corridor
                    # must not feed back into a faster and faster prediction (runaway).
                    dv_max = p.max_accel_m_s2 * dt
                    dvx, dvy = vx - v.x_m, vy - v.y_m
                    dv = math.hypot(dvx, dvy)
                    if dv > dv_max > 0.0:
                        vx, vy = v.x_m + dvx * dv_max / dv, v.y_m + dvy * dv_max / dv
                    # The turn rate is measured only by a confident heading; otherwise it decays,
                    # so that a turn does not go on being predicted through a corridor or
                    # clutter (the overshoot that lost the heading quadrant).
                    if flags & _HEADING_UNSURE:
                        w = p.turn_rate_decay * v.theta_rad
                self._velocity = Pose2D(vx, vy, w)
        odom_before = self._odom
        if scan.odom is not None:
            self._odom = scan.odom
        if p.profile_turn and p.use_prediction:
            key = (scan.angle_min_rad, scan.angle_increment_rad)
            ranges = np.array(scan.ranges_m, dtype=np.float64)  # a copy: the caller's may change
            self._last_profile = (key, ranges, scan.range_min_m, scan.range_max_m)
        self._last_free = None
        if p.dynamic_rejection and pts is not None and self._dense(pts):
            self._last_free = FreeSpace.of(
                pose,
                np.asarray(scan.ranges_m, dtype=np.float64),
                scan.range_min_m,
                scan.range_max_m,
                scan.angle_min_rad,
                scan.angle_increment_rad,
                p.seen_through,
            )
        is_kf = False
        if pts is not None and not flags & PoseFlag.DEGENERATE:
            if not self._keyframes:
                is_kf = True
            else:
                last = self._keyframes[-1].pose
                dist = math.hypot(pose.x_m - last.x_m, pose.y_m - last.y_m)
                dang = abs(wrap_angle(pose.theta_rad - last.theta_rad))
                is_kf = dist >= p.keyframe_distance_m or dang >= math.radians(p.keyframe_angle_deg)
                # Do not pollute the map with poorly constrained scans. An ambiguous match
                # (periodic doors, corridor) enters only when the map would otherwise go stale.
                if quality < 0.35:
                    is_kf = False
                ambiguous = PoseFlag.AMBIGUOUS_X | PoseFlag.AMBIGUOUS_Y
                if flags & ambiguous and dist < p.keyframe_ambiguous_distance_m:
                    is_kf = False
            keep_last = p.reference == "previous" or p.previous_scan_fallback
            surfaces = is_kf or p.reference == "previous"  # what the 2-D field reads
            frame = self._frame(pts, pose, work, surfaces=surfaces) if is_kf or keep_last else None
            if keep_last:
                self._last_scan = frame
                self._last_scan_densities = {}
            if p.reference == "previous":
                self._ref = None
            if is_kf and frame is not None:
                self._keyframes.append(frame)
                if self._last_free is not None:
                    self._seen_keyframes.append(self._last_free)
                self._grid_dirty = True
                self._dir_spectrum = None
                if p.reference != "previous":
                    self._ref = None
        measured_before = self._heading_measured
        self._heading_measured = pts is not None and not flags & _HEADING_UNSURE
        if flags & PoseFlag.ODOMETRY_PRIOR and odom_before is not None and scan.odom is not None:
            innovation: float | None = None
            if measured_before and self._heading_measured:  # the odometry's error over one scan
                turn = wrap_angle(scan.odom.theta_rad - odom_before.theta_rad)
                innovation = wrap_angle(pose.theta_rad - self._pose.theta_rad - turn)
            self._odometry.observe(innovation, self._heading_measured)
        if not self._initialised:
            covariance = self._covariance.covariance()  # the first pose defines the map frame
        else:
            covariance = self._covariance.update(
                *sigmas_m,
                heading_anchored=self._heading_measured,
                dt_s=self._step_s(scan),
                frame_rad=frame_rad,
                steps=steps,
            )
        if is_kf:
            self._covariance.restart()
        self._initialised = self._initialised or (
            pts is not None and not flags & PoseFlag.DEGENERATE
        )
        self._pose = pose
        if self._stamp_ns is not None and scan.stamp_ns > self._stamp_ns:
            self._periods_s.append((scan.stamp_ns - self._stamp_ns) * 1e-9)
        self._stamp_ns = scan.stamp_ns
        return PoseEstimate(
            stamp_ns=scan.stamp_ns,
            pose=pose,
            quality=min(max(float(quality), 0.0), 1.0),
            flags=flags,
            is_keyframe=is_kf,
            covariance=covariance,
        )
