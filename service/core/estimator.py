"""`ManhattanEstimator`: scan-to-map pose tracking from Manhattan walls (the paper, made robust).

Per scan:
1. valid points, thinned to ~0.05 m (paper §II-A.1);
2. motion prediction: odometry when the scan carries it, else constant velocity;
3. heading modulo 90° from projection histograms, searched around the predicted heading,
   resolved to the absolute heading by the ±45° rule (paper §II); without odometry, while
   turning, the quadrant is re-anchored on the local map's geometry (`_check_heading`);
4. translation from 1-D histogram correlations along the map axes (paper §III) against a local
   map of recent keyframes, centred on the prediction, sub-bin refined, with ambiguity checks;
5. a joint 2-D check of the 1-D peak candidates and a small 2-D/rotation refinement.

The map frame is set by the first scan: axes along its major walls (the member of the Manhattan
family nearest the robot's forward direction is x), origin at the first scan's position.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from clients.wire import PoseFlag
from service.core.heading import (
    QUARTER,
    HeadingMeasurement,
    measure_heading,
    resolve_heading,
    thin_points,
)
from service.core.params import EstimatorParams
from service.core.refine import OccupiedCells
from service.core.rotation import direction_histogram, match_rotation, tangent_directions
from service.core.translation import AxisMatch, correlate_axis, orientation_weights, pick_peak
from service.core.types import FloatArray, LaserScan, Pose2D, PoseEstimate, wrap_angle

log = logging.getLogger(__name__)


def _rotate(points_xy_m: FloatArray, theta_rad: float) -> FloatArray:
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    out = np.empty_like(points_xy_m)
    out[:, 0] = c * points_xy_m[:, 0] - s * points_xy_m[:, 1]
    out[:, 1] = s * points_xy_m[:, 0] + c * points_xy_m[:, 1]
    return out


@dataclass(slots=True)
class _Keyframe:
    pose: Pose2D
    points_map_m: FloatArray  # (M, 2) in the map frame
    weights: FloatArray  # (M, 2) orientation weights (x, y)
    directions_rad: FloatArray  # surface directions of the reliable points, map frame


@dataclass(slots=True)
class _ScanWork:
    """Per-scan intermediate results of `_process`, reused by `_commit` (speed)."""

    dirs_rad: FloatArray
    dirs_ok: npt.NDArray[np.bool_]
    theta_rad: float | None = None  # the heading `rotated_m` and `weights` were computed at
    rotated_m: FloatArray | None = None
    weights: FloatArray | None = None


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
        self._last_scan: _Keyframe | None = None
        self._grid: OccupiedCells | None = None
        self._grid_dirty = True
        self._dir_hist: FloatArray | None = None
        self._periods_s: deque[float] = deque(maxlen=51)  # recent scan periods (stamps)
        # Local map as one array pair, rebuilt only when a keyframe is added (speed).
        self._local_map: tuple[FloatArray, FloatArray] | None = None
        self._local_box: tuple[float, float, float, float] | None = None  # x0, y0, x1, y1

    def __setstate__(self, state: dict[str, object]) -> None:
        # Checkpoints pickled by an older version lack the newer caches: start them empty.
        self.__dict__.update(state)
        self.__dict__.setdefault("_local_box", None)

    # ------------------------------------------------------------------ public
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
        r = ranges[mask]
        a = scan.angle_min_rad + scan.angle_increment_rad * np.flatnonzero(mask)
        pts = np.column_stack((r * np.cos(a), r * np.sin(a)))
        return thin_points(pts, self.params.thinning_m)

    def _predict(self, scan: LaserScan) -> tuple[Pose2D, PoseFlag]:
        """Predicted pose for `scan` and whether odometry produced it."""
        p = self.params
        if not self._initialised:
            return self._pose, PoseFlag.NONE
        if p.use_odometry and scan.odom is not None and self._odom is not None:
            delta = self._odom.between(scan.odom)
            return self._pose.compose(delta), PoseFlag.ODOMETRY_PRIOR
        if not p.use_prediction or self._velocity is None or self._stamp_ns is None:
            return self._pose, PoseFlag.NONE
        dt = self._dt_s(scan)
        dt = min(max(dt, 0.0), 1.0)
        v = self._velocity
        return self._pose.compose(Pose2D(v.x_m * dt, v.y_m * dt, v.theta_rad * dt)), PoseFlag.NONE

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
        assert self._stamp_ns is not None
        dt = (scan.stamp_ns - self._stamp_ns) * 1e-9
        if len(self._periods_s) >= 5 and p.period_clip_ratio > 1.0:
            typical = float(np.median(self._periods_s))
            dt = min(max(dt, typical / p.period_clip_ratio), typical * p.period_clip_ratio)
        return dt

    def _process(self, scan: LaserScan) -> PoseEstimate:
        p = self.params
        pred, flags = self._predict(scan)
        pts = self._points(scan)
        if pts.shape[0] < p.min_points:
            return self._commit(scan, pred, 0.0, flags | PoseFlag.DEGENERATE, None)

        # --- heading (paper §II) -------------------------------------------------------
        odom_prior = bool(flags & PoseFlag.ODOMETRY_PRIOR)
        predicted = self._initialised and (p.use_prediction or odom_prior)
        sigma = math.radians(
            p.heading_prior_sigma_odom_deg if odom_prior else p.heading_prior_sigma_deg
        )
        prior_theta = pred.theta_rad
        dirs, dirs_ok = tangent_directions(pts)
        work = _ScanWork(dirs, dirs_ok)
        rotation_from_dirs: float | None = None
        # Without odometry the constant-velocity heading is weak: the direction histograms
        # give a sharper prior. With odometry they only hurt (measured: ACES 0.56 -> 0.07 m).
        use_dirs = predicted and p.direction_prior and not odom_prior and bool(self._keyframes)
        if use_dirs and dirs_ok.sum() >= p.min_points:
            if self._dir_hist is None:
                self._dir_hist = direction_histogram(
                    np.concatenate([f.directions_rad for f in self._keyframes])
                )
            theta_dir, contrast = match_rotation(
                self._dir_hist,
                dirs[dirs_ok],
                pred.theta_rad,
                math.radians(p.direction_window_deg),
            )
            if contrast >= p.direction_min_contrast:
                rotation_from_dirs = theta_dir
                prior_theta = theta_dir
                sigma = math.radians(p.direction_sigma_deg)
        meas = measure_heading(
            pts,
            prior_theta if predicted else None,
            sigma,
            math.radians(p.heading_step_deg),
            p.heading_bin_m,
            score=p.heading_score,
            coarse_step_rad=math.radians(p.heading_coarse_step_deg),
            coarse_bin_m=p.heading_coarse_bin_m,
            refine=p.subbin_refinement,
            max_range_m=p.heading_max_range_m,
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
            # First scan: the map axes are its major walls; x is the one nearest the robot's
            # forward direction, so the first heading is the Manhattan angle itself.
            self._major_axis = meas.major_axis
            pose = Pose2D(0.0, 0.0, meas.angle_rad)
            return self._commit(scan, pose, 1.0 if heading_ok else 0.3, flags, pts, work=work)
        if heading_ok:
            # The ±45° rule: the member of the Manhattan family nearest the predicted heading
            # (the paper tracks it against the previous heading; the prediction is better).
            theta = resolve_heading(
                meas.angle_rad, prior_theta if predicted else self._pose.theta_rad
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
            checked = self._check_heading(pts, pred, theta, heading_ok, meas)
            if checked is not None:
                theta, absolute = checked
                if absolute and not heading_ok:
                    flags &= ~(PoseFlag.NON_MANHATTAN | PoseFlag.NO_DOMINANT_WALL)
                    heading_ok, heading_quality = True, 1.0
                elif not absolute and heading_ok:
                    flags |= PoseFlag.NON_MANHATTAN
                    heading_ok, heading_quality = False, 0.6

        # --- translation (paper §III) --------------------------------------------------
        cur = _rotate(pts, theta)
        ref = self._reference(pred)
        if ref is None:
            return self._commit(scan, Pose2D(pred.x_m, pred.y_m, theta), 0.2, flags, pts, work=work)
        ref_pts, ref_w = ref
        if p.orientation_weighting:
            cur_w = orientation_weights(cur)
            work.theta_rad, work.rotated_m, work.weights = theta, cur, cur_w
        else:
            cur_w = np.ones_like(cur)
            ref_w = np.ones_like(ref_pts)
        if p.use_prediction or odom_prior:
            half_t = p.translation_window_odom_m if odom_prior else p.translation_window_pred_m
            centre_xy = (pred.x_m, pred.y_m)
        else:
            half_t = p.translation_window_m
            centre_xy = (self._pose.x_m, self._pose.y_m)
        prior_sigma_t = 0.0
        if p.use_prediction or odom_prior:
            prior_sigma_t = (
                p.translation_prior_sigma_odom_m if odom_prior else p.translation_prior_sigma_m
            )
        matches: list[AxisMatch] = []
        for axis in (0, 1):
            shifts, energy = correlate_axis(
                ref_pts[:, axis],
                ref_w[:, axis],
                cur[:, axis],
                cur_w[:, axis],
                centre_xy[axis],
                half_t,
                p.translation_step_m,
                p.translation_bin_m,
            )
            matches.append(
                pick_peak(
                    shifts,
                    energy,
                    (pred.x_m, pred.y_m)[axis],
                    float(cur_w[:, axis].sum()),
                    min_support=p.min_axis_support,
                    ambiguity_ratio=p.ambiguity_ratio,
                    refine=p.subbin_refinement,
                    prior_sigma_m=prior_sigma_t,
                )
            )
        mx, my = matches
        x, y = mx.offset_m, my.offset_m
        if mx.ambiguous:
            flags |= PoseFlag.AMBIGUOUS_X
        if my.ambiguous:
            flags |= PoseFlag.AMBIGUOUS_Y

        if p.refine_2d and self._grid_ready():
            x, y = self._refine(cur, x, y, mx, my)

        q = heading_quality * (0.5 + 0.25 * mx.sharpness + 0.25 * my.sharpness)
        if mx.ambiguous:
            q *= 0.7
        if my.ambiguous:
            q *= 0.7
        return self._commit(scan, Pose2D(x, y, wrap_angle(theta)), q, flags, pts, work=work)

    # ------------------------------------------------------------------ heading check
    def _check_heading(
        self,
        pts: FloatArray,
        pred: Pose2D,
        theta: float,
        heading_ok: bool,
        meas: HeadingMeasurement,
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
        assert self._grid is not None
        prev = self._pose.theta_rad
        reach = math.radians(p.heading_check_max_turn_deg)
        turn = max(abs(wrap_angle(theta - prev)), abs(wrap_angle(pred.theta_rad - prev)))
        # Cheap trigger: steady motion on a confident Manhattan heading needs no check.
        if heading_ok and turn < math.radians(p.heading_check_min_turn_deg):
            return None
        free = measure_heading(
            pts,
            None,
            0.0,
            math.radians(p.heading_step_deg),
            p.heading_bin_m,
            score=p.heading_score,
            coarse_step_rad=math.radians(p.heading_coarse_step_deg),
            coarse_bin_m=p.heading_coarse_bin_m,
            refine=p.subbin_refinement,
            max_range_m=p.heading_max_range_m,
            same_points=meas,
        )
        cands: list[tuple[float, bool]] = [(theta, heading_ok)]
        angles = [meas.angle_rad]
        if free.peak_fraction >= p.min_heading_peak_fraction:
            angles.append(free.angle_rad)
        # Both the motion prediction and "no turn" (the prediction can overshoot a turn).
        anchors = (pred.theta_rad, prev)

        def offset(c: float) -> float:
            return min(abs(wrap_angle(c - a)) for a in anchors)

        for a in angles:
            base = resolve_heading(a, prev)
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
        scores = np.array(
            [float(self._grid.hit_fraction(_rotate(sub, c), grid).max()) for c, _ in uniq]
        )
        # A candidate far from the prediction must beat the current heading by more.
        far = np.array([offset(c) / reach for c, _ in uniq])
        needed = scores[0] + p.heading_check_margin * (1.0 + 2.0 * far)
        better = np.flatnonzero(scores >= needed)
        if better.size == 0:
            return None
        best = int(better[np.argmax(scores[better])])
        return wrap_angle(uniq[best][0]), uniq[best][1]

    # ------------------------------------------------------------------ reference
    def _reference(self, pred: Pose2D) -> tuple[FloatArray, FloatArray] | None:
        p = self.params
        if p.reference == "previous":
            frames = [self._last_scan] if self._last_scan is not None else []
        elif p.reference == "keyframe":
            frames = [self._keyframes[-1]] if self._keyframes else []
        else:
            frames = list(self._keyframes)
        if not frames:
            return None
        if p.reference == "local_map":
            if self._local_map is None:
                self._local_map = (
                    np.concatenate([f.points_map_m for f in frames]),
                    np.concatenate([f.weights for f in frames]),
                )
            pts, w = self._local_map
        else:
            pts = np.concatenate([f.points_map_m for f in frames])
            w = np.concatenate([f.weights for f in frames])
        if len(frames) > 1:
            if p.reference == "local_map":
                # The whole local map within the radius (its box's farthest corner is): no
                # filtering. Rounding is monotonic, so no point can compare farther.
                if self._local_box is None:
                    self._local_box = (*pts.min(axis=0).tolist(), *pts.max(axis=0).tolist())
                x0, y0, x1, y1 = self._local_box
                dx = max(abs(x0 - pred.x_m), abs(x1 - pred.x_m))
                dy = max(abs(y0 - pred.y_m), abs(y1 - pred.y_m))
                if dx**2 + dy**2 <= p.local_map_radius_m**2:
                    return pts, w
            d2 = (pts[:, 0] - pred.x_m) ** 2 + (pts[:, 1] - pred.y_m) ** 2
            # `take` of indices: (n, 2) boolean indexing is ~10x slower.
            keep = np.flatnonzero(d2 <= p.local_map_radius_m**2)
            if keep.shape[0] >= p.min_points:
                pts, w = pts.take(keep, axis=0), w.take(keep, axis=0)
        return pts, w

    def _grid_ready(self) -> bool:
        if not self._keyframes:
            return False
        if self._grid is None or self._grid_dirty:
            pts = np.concatenate([f.points_map_m for f in self._keyframes])
            self._grid = OccupiedCells(pts)
            self._grid_dirty = False
        return True

    def _refine(
        self, cur: FloatArray, x: float, y: float, mx: AxisMatch, my: AxisMatch
    ) -> tuple[float, float]:
        """Joint 2-D choice among the 1-D peak candidates (the paper's axes are independent)."""
        assert self._grid is not None
        xs = [x] + [c for c in mx.peak_offsets_m if abs(c - x) > 0.02]
        ys = [y] + [c for c in my.peak_offsets_m if abs(c - y) > 0.02]
        if len(xs) == 1 and len(ys) == 1:
            return x, y
        cand = np.array([(cx, cy) for cx in xs for cy in ys])
        scores = self._grid.hit_fraction(cur, cand)
        best = int(np.argmax(scores))
        # Switch only for a clearly better combination: the 1-D answer is sub-bin refined.
        if scores[best] > scores[0] + 0.05:
            return float(cand[best, 0]), float(cand[best, 1])
        return x, y

    # ------------------------------------------------------------------ bookkeeping
    def _commit(
        self,
        scan: LaserScan,
        pose: Pose2D,
        quality: float,
        flags: PoseFlag,
        pts: FloatArray | None,
        *,
        work: _ScanWork | None = None,
    ) -> PoseEstimate:
        p = self.params
        if self._initialised and self._stamp_ns is not None:
            dt = self._dt_s(scan)
            # An ambiguous match says little about the motion: keep the previous velocity, so
            # that a featureless corridor does not stop the robot (the stationary-lock failure).
            unsure = PoseFlag.DEGENERATE | PoseFlag.AMBIGUOUS_X | PoseFlag.AMBIGUOUS_Y
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
                    if flags & unsure:
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
                    weak = PoseFlag.DEGENERATE | PoseFlag.NON_MANHATTAN | PoseFlag.NO_DOMINANT_WALL
                    if flags & weak:
                        w = p.turn_rate_decay * v.theta_rad
                self._velocity = Pose2D(vx, vy, w)
        if scan.odom is not None:
            self._odom = scan.odom
        is_kf = False
        if pts is not None and not flags & PoseFlag.DEGENERATE:
            # Reuse what `_process` computed for this scan (same values: same inputs).
            if (
                work is not None
                and work.rotated_m is not None
                and work.weights is not None
                and work.theta_rad == pose.theta_rad
            ):
                cur, cur_w = work.rotated_m, work.weights
            else:
                cur = _rotate(pts, pose.theta_rad)
                cur_w = orientation_weights(cur)
            dirs, ok = (
                (work.dirs_rad, work.dirs_ok) if work is not None else tangent_directions(pts)
            )
            frame = _Keyframe(
                pose,
                cur + np.array([pose.x_m, pose.y_m]),
                cur_w,
                (dirs[ok] + pose.theta_rad) % math.pi,
            )
            self._last_scan = frame
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
            if is_kf:
                self._keyframes.append(frame)
                self._grid_dirty = True
                self._dir_hist = None
                self._local_map = None
                self._local_box = None
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
            quality=float(np.clip(quality, 0.0, 1.0)),
            flags=flags,
            is_keyframe=is_kf,
        )
