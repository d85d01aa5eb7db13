"""`ScanMatcherFrontEnd`: predict → match → update, one scan at a time.

    predict   constant velocity (or odometry), capped in time, σ growing with the gap
    match     one objective: the scan against the active submap + the motion prior + the walls'
              heading prior (`matcher`, `walls`)
    update    the velocity's Kalman step, weighed by what the scan measured; the scan into the
              submaps when it moved enough; the covariance relative to the latest keyframe
              (what the pose graph weighs)

Submaps are Cartographer's pair: every keyframe goes into the two newest; the older one, holding
between `scans_per_submap` and twice that, is what the scan is matched against.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from clients.wire import PoseFlag
from service.core.frontend.likelihood import LikelihoodGrid
from service.core.frontend.matcher import MatchOptions, Priors, broad_covariance, match
from service.core.frontend.walls import WallOptions, WallState, heading_prior, measure, observe
from service.core.maps.grid import OccupancyGrid
from service.core.maps.submaps import voxel_thin
from service.core.types import (
    Covariance3,
    FloatArray,
    LaserScan,
    Pose2D,
    PoseEstimate,
    fields_by_name,
    frozen_array,
    rotate_points,
)

log = logging.getLogger(__name__)

# The velocity's covariance where nothing is known of it (the start, after a pause): 1 m/s, 1 rad/s.
_UNKNOWN_VELOCITY_COV = frozen_array(np.diag([1.0, 1.0, 1.0]))


@dataclass(frozen=True, slots=True)
class MatcherParams:
    """Every tunable of the front end, a line each."""

    # --- the scan
    voxel_m: float = 0.05  # points matched: one per voxel of this size
    max_range_m: float = 30.0  # returns beyond this are not used (the UTM-30LX's reach)
    matched_reach: float = 0.75  # points matched within this share of the inserted reach
    min_points: int = 20  # fewer: DEGENERATE, the pose is the prediction
    # --- submaps
    resolution_m: float = 0.05  # likelihood grid cell
    hit_sigma_m: float = 0.05  # width of a hit's Gaussian in the grid
    surface_max_gap_m: float = 0.5  # neighbouring returns closer than this are one surface ...
    surface_gap_per_range: float = 0.1  # ... or than this × their range (grazing walls)
    scans_per_submap: int = 30  # a new submap every this many keyframes
    # Rays lower the field where they saw through (a person's trail), up to this short of
    # their return (None: no carving)
    carve_margin_m: float | None = 0.1
    # --- keyframes (the motion filter): the paper's scan spacing
    keyframe_distance_m: float = 0.3
    keyframe_angle_deg: float = 10.0
    # --- prediction
    use_odometry: bool = True  # odometry (when the scan carries it) is the motion prior
    max_extrapolation_s: float = 0.5  # constant velocity is extrapolated at most this long
    velocity_window_s: float = 0.2  # the velocity is measured over at least this much time
    # The velocity's random walk (a Kalman filter): along the robot's heading a speed changes
    # slowly; across it a weave or a holonomic base jumps. One σ for both would let a sideways
    # jump, measured well, leak into an unmeasured speed along a corridor.
    forward_accel_sigma_m_s2: float = 0.3
    lateral_accel_sigma_m_s2: float = 2.0
    angular_accel_sigma_deg_s2: float = 90.0  # the turn rate's
    gap_speed_m_s: float = 0.5  # σ grows by this × the gap beyond max_extrapolation_s ...
    gap_turn_rate_deg_s: float = 60.0  # ... and σ_θ by this
    position_floor_m: float = 0.01
    heading_floor_deg: float = 0.2
    odometry_sigma_ratio: float = 0.1  # odometry's σ per metre / radian of its motion
    # ... scaled by how far the matches have disagreed with it, over about this many scans (a
    # robot's odometry is as good as its wheels and floor, not as the defaults above guess)
    odometry_noise_memory_scans: int = 50
    # Wheels of unequal size turn the odometry's heading by a bias per metre (Borenstein's
    # UMBmark). Held tight against the walls' prior, a biased heading would win scan by scan;
    # the bias is estimated from the matches' heading innovations (a scalar Kalman filter) and
    # taken off the odometry. Its prior σ (0: not estimated) and random walk, per metre:
    odometry_heading_bias_sigma_deg_per_m: float = 1.0
    odometry_heading_bias_walk_deg_per_m: float = 0.01
    # --- match and walls
    match: MatchOptions = field(default_factory=MatchOptions)
    walls: WallOptions = field(default_factory=WallOptions)
    wall_prior: bool = True  # False: no walls' heading prior (a plain 2-D matcher)
    ambiguous_ratio: float = 0.01  # scan information this much weaker on one axis: AMBIGUOUS


@dataclass
class FrontEndStats:
    scans: int = 0
    degenerate: int = 0
    stamp_backwards: int = 0  # scans not after the previous one: not matched


STATE_VERSION = 3  # of `MatcherState`: a checkpoint of another version is refused, not guessed


@dataclass
class MatcherState:
    """Everything the front end carries from one scan to the next: what a checkpoint saves."""

    version: int
    pose: Pose2D | None
    stamp_ns: int | None
    velocity: FloatArray  # (vx, vy, ω) per second, robot frame
    velocity_cov: FloatArray
    velocity_anchor: tuple[Pose2D, int, FloatArray] | None  # (pose, stamp_ns, pose_cov) of the
    # velocity's last measurement
    pose_cov: FloatArray  # the pose's covariance against the submap (map axes)
    odom: Pose2D | None
    odom_noise_scale2: FloatArray  # (translation, rotation): the odometry's variance scale
    submaps: list[LikelihoodGrid]
    keyframe_pose: Pose2D | None
    cov_since_keyframe: FloatArray
    walls: WallState
    stats: FrontEndStats
    # (bias in rad per metre of odometry travel, its variance): `_learn_odometry_bias`
    odom_heading_bias: tuple[float, float]


def surface_points(
    points_xy_m: FloatArray, max_gap_m: float, gap_per_range: float, spacing_m: float
) -> FloatArray:
    """The scan as surfaces: consecutive returns closer than `max_gap_m`, or than
    `gap_per_range` × their range (a wall far away at a grazing angle), joined by points every
    `spacing_m`. A grid of bare hits has bumps where this scan's beams happened to land, and a
    later scan, landing elsewhere on the same wall, would be pulled along the wall by them."""
    n = points_xy_m.shape[0]
    if n < 2:
        return points_xy_m
    d = np.diff(points_xy_m, axis=0)
    length = np.hypot(d[:, 0], d[:, 1])
    range_m = np.hypot(points_xy_m[:-1, 0], points_xy_m[:-1, 1])
    joined = length <= np.maximum(max_gap_m, gap_per_range * range_m)
    # Evenly spaced by arc length along the joined runs (gaps have no length here): an even
    # spacing leaves no bumps in the grid's density where beams happened to fall.
    along = np.where(joined, length, 0.0)
    cum = np.concatenate(([0.0], np.cumsum(along)))
    targets = np.arange(0.0, cum[-1], spacing_m)
    seg = np.clip(np.searchsorted(cum, targets, side="right") - 1, 0, n - 2)
    frac = (targets - cum[seg]) / np.maximum(along[seg], 1e-12)
    dense = points_xy_m[seg] + d[seg] * frac[:, None]
    # Returns on no joined run (a post, a far lone hit) are kept as they are.
    touches = np.zeros(n, dtype=np.bool_)
    touches[:-1] |= joined
    touches[1:] |= joined
    return np.vstack((dense, points_xy_m[~touches]))


def surface_in_map(points_xy_m: FloatArray, pose: Pose2D, params: MatcherParams) -> FloatArray:
    """A keyframe's returns (laser frame) as the surface points its submaps take, in the map
    frame at `pose`."""
    pts = surface_points(
        points_xy_m, params.surface_max_gap_m, params.surface_gap_per_range, params.resolution_m / 2
    )
    world: FloatArray = rotate_points(pts, pose.theta_rad) + np.array([pose.x_m, pose.y_m])
    return world


def _covariance3(m: FloatArray) -> Covariance3:
    a = [float(v) for v in m.ravel()]
    return (a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8])


class ScanMatcherFrontEnd:
    """Tracks the robot's pose against its own submaps; the map frame is the first scan's."""

    def __init__(self, params: MatcherParams | None = None) -> None:
        self.params = params if params is not None else MatcherParams()
        self.reset()

    def reset(self) -> None:
        self._pose: Pose2D | None = None
        self._stamp_ns: int | None = None
        self._velocity = np.zeros(3)  # (vx, vy, ω) per second, robot frame
        self._velocity_cov = _UNKNOWN_VELOCITY_COV  # its covariance
        self._velocity_anchor: tuple[Pose2D, int, FloatArray] | None = None
        self._pose_cov = np.zeros((3, 3))
        self._odom: Pose2D | None = None
        self._odom_noise_scale2 = np.ones(2)
        self._odom_heading_bias = self._odom_heading_bias_prior()
        self._submaps: list[LikelihoodGrid] = []
        self._keyframe_pose: Pose2D | None = None
        self._cov_since_keyframe = np.zeros((3, 3))
        self._walls = WallState()
        self.stats = FrontEndStats()

    @property
    def wall_families_rad(self) -> tuple[float, ...]:
        return tuple(self._walls.families_rad)

    def state(self) -> MatcherState:
        return MatcherState(
            STATE_VERSION,
            self._pose,
            self._stamp_ns,
            self._velocity,
            self._velocity_cov,
            self._velocity_anchor,
            self._pose_cov,
            self._odom,
            self._odom_noise_scale2,
            self._submaps,
            self._keyframe_pose,
            self._cov_since_keyframe,
            self._walls,
            self.stats,
            self._odom_heading_bias,
        )

    def __getstate__(self) -> dict[str, object]:
        return {"params": fields_by_name(self.params), "state": self.state()}

    def __setstate__(self, saved: dict[str, Any]) -> None:
        state = saved["state"]
        if not isinstance(state, MatcherState) or state.version != STATE_VERSION:
            version = getattr(state, "version", None)
            raise ValueError(f"front-end state version {version}, expected {STATE_VERSION}")
        self.params = MatcherParams(**saved["params"])
        self._pose, self._stamp_ns = state.pose, state.stamp_ns
        self._velocity, self._velocity_cov = state.velocity, state.velocity_cov
        self._velocity_anchor, self._pose_cov = state.velocity_anchor, state.pose_cov
        self._odom, self._submaps = state.odom, state.submaps
        # (a state saved before the odometry's noise was learnt starts from its defaults)
        self._odom_noise_scale2 = getattr(state, "odom_noise_scale2", np.ones(2))
        self._keyframe_pose, self._cov_since_keyframe = (
            state.keyframe_pose,
            state.cov_since_keyframe,
        )
        self._walls, self.stats = state.walls, state.stats
        # (a state saved before the bias was estimated starts from its prior)
        self._odom_heading_bias = getattr(
            state, "odom_heading_bias", self._odom_heading_bias_prior()
        )

    # ------------------------------------------------------------------ public
    def process(self, scan: LaserScan) -> PoseEstimate:
        """The pose of `scan`. Never raises on bad data: returns the prediction, flagged."""
        self.stats.scans += 1
        if self._stamp_ns is not None and scan.stamp_ns <= self._stamp_ns:
            self.stats.stamp_backwards += 1
            if self.stats.stamp_backwards == 1 or self.stats.stamp_backwards % 1000 == 0:
                log.warning(
                    "scan stamp %d is not after the previous %d: not matched (%d so far)",
                    scan.stamp_ns,
                    self._stamp_ns,
                    self.stats.stamp_backwards,
                )
            pose = self._pose if self._pose is not None else Pose2D(0.0, 0.0, 0.0)
            return PoseEstimate(scan.stamp_ns, pose, 0.0, PoseFlag.DEGENERATE)
        try:
            return self._process(scan)
        except (ValueError, FloatingPointError, IndexError, np.linalg.LinAlgError) as exc:
            log.warning("front end could not match scan %d: %s", scan.stamp_ns, exc)
            predicted, cov, flags = self._predict(scan)
            return self._degenerate(scan, predicted, cov, flags)

    # ------------------------------------------------------------------ steps
    def _points(self, scan: LaserScan, pts: FloatArray) -> FloatArray:
        """The returns `pts` (laser frame) that are matched: within reach, one per voxel."""
        # Matched well inside the reach the submap was drawn to: its walls end where the
        # keyframes' reach ended, and a point past that end, within the search window, would
        # pull the scan back along a corridor.
        reach_m = self.params.matched_reach * min(self.params.max_range_m, scan.range_max_m)
        keep = np.hypot(pts[:, 0], pts[:, 1]) <= reach_m
        return voxel_thin(pts[keep], self.params.voxel_m)

    def _predict(self, scan: LaserScan) -> tuple[Pose2D, FloatArray, PoseFlag]:
        """Predicted pose, its covariance (map axes), and the ODOMETRY_PRIOR flag if used."""
        odometry = self._odometry_prediction(scan)
        if odometry is None:
            pose, cov = self._velocity_prediction(scan)
            return pose, cov, PoseFlag.NONE
        return *odometry, PoseFlag.ODOMETRY_PRIOR

    def _odometry_prediction(self, scan: LaserScan) -> tuple[Pose2D, FloatArray] | None:
        """The pose odometry predicts and its covariance (map axes); None without odometry."""
        p = self.params
        odom = scan.odom if p.use_odometry else None
        if odom is None or self._odom is None:
            return None
        pose = self._pose if self._pose is not None else Pose2D(0.0, 0.0, 0.0)
        delta = self._odom.between(odom)
        dist = math.hypot(delta.x_m, delta.y_m)
        delta = Pose2D(delta.x_m, delta.y_m, delta.theta_rad - self._odom_heading_bias[0] * dist)
        sig_xy = p.position_floor_m + p.odometry_sigma_ratio * dist
        sig_t = math.radians(p.heading_floor_deg) + p.odometry_sigma_ratio * abs(delta.theta_rad)
        scale = np.sqrt(np.maximum(self._odom_noise_scale2, 1.0))
        sig_xy, sig_t = sig_xy * float(scale[0]), sig_t * float(scale[1])
        return pose.compose(delta), np.diag([sig_xy**2, sig_xy**2, sig_t**2])

    def _velocity_prediction(self, scan: LaserScan) -> tuple[Pose2D, FloatArray]:
        """The pose constant velocity predicts and its covariance (map axes)."""
        p = self.params
        pose = self._pose if self._pose is not None else Pose2D(0.0, 0.0, 0.0)
        gap_s = 0.0 if self._stamp_ns is None else max(0.0, (scan.stamp_ns - self._stamp_ns) * 1e-9)
        t = min(gap_s, p.max_extrapolation_s)
        v = self._velocity
        delta = Pose2D(v[0] * t, v[1] * t, v[2] * t)
        # The velocity's own uncertainty over the extrapolated time, and beyond it, what the
        # robot may have done during a pause nobody saw.
        anchor = self._velocity_anchor
        since_s = gap_s if anchor is None else (scan.stamp_ns - anchor[1]) * 1e-9
        var = np.diag(self._velocity_cov + self._velocity_noise(since_s)) * t * t
        beyond_s = gap_s - t
        sig_xy = math.sqrt(max(var[0], var[1]) + (p.gap_speed_m_s * beyond_s) ** 2)
        sig_xy += p.position_floor_m
        sig_t = math.sqrt(var[2] + math.radians(p.gap_turn_rate_deg_s * beyond_s) ** 2)
        sig_t += math.radians(p.heading_floor_deg)
        return pose.compose(delta), np.diag([sig_xy**2, sig_xy**2, sig_t**2])

    def _process(self, scan: LaserScan) -> PoseEstimate:
        p = self.params
        ranges = np.asarray(scan.ranges_m, dtype=np.float64)
        returns = scan.points_xy_m() if ranges.ndim == 1 and ranges.size else np.zeros((0, 2))
        pts = self._points(scan, returns)
        predicted, cov_pred, flags = self._predict(scan)
        predicted_cov = cov_pred  # the prediction's own (cov_pred becomes the winning prior's)
        if pts.shape[0] < p.min_points:
            return self._degenerate(scan, predicted, cov_pred, flags)
        wall_meas = measure(pts, p.walls) if p.wall_prior else None
        odometry_won = False  # the match kept odometry's component of the motion prior
        if self._pose is None:  # the first scan defines the map frame
            pose, h_scan, score = Pose2D(0.0, 0.0, 0.0), np.eye(3) * 1e6, 1.0
        else:
            wall_rad, wall_sigma = heading_prior(
                self._walls, wall_meas, predicted.theta_rad, p.walls
            )
            # With odometry, constant velocity is the motion prior's second component: a
            # wheel's slip or a glitch of its heading is outvoted by how the robot was moving.
            second = self._velocity_prediction(scan) if flags & PoseFlag.ODOMETRY_PRIOR else None
            priors = Priors(predicted, cov_pred, wall_rad, wall_sigma, second)
            result = match(self._submaps[0], pts, priors, p.match)
            pose, h_scan, score = result.pose, result.scan_information, result.score
            odometry_won = bool(flags & PoseFlag.ODOMETRY_PRIOR) and not (
                result.second or result.broad
            )
            if result.second and second is not None:
                cov_pred = second[1]
            if result.broad:
                # The prediction was wrong: the motion since it is as loose as the broad window,
                # and the velocity starts again from this scan, as after a pause.
                flags |= PoseFlag.RELOCALISED
                cov_pred = broad_covariance(p.match)
                self._velocity, self._velocity_cov = np.zeros(3), _UNKNOWN_VELOCITY_COV
                self._velocity_anchor = None
        travel = (
            0.0
            if self._pose is None
            else math.hypot(pose.x_m - self._pose.x_m, pose.y_m - self._pose.y_m)
        )
        if p.wall_prior and not observe(self._walls, wall_meas, pose.theta_rad, travel, p.walls):
            flags |= (
                PoseFlag.NON_MANHATTAN
                if wall_meas and wall_meas.weight > 0
                else PoseFlag.NO_DOMINANT_WALL
            )
        flags |= self._ambiguity(h_scan)
        learnt = PoseFlag.ODOMETRY_PRIOR | PoseFlag.RELOCALISED
        if flags & learnt == PoseFlag.ODOMETRY_PRIOR and self._pose is not None:
            self._learn_odometry_noise(pose, predicted, predicted_cov)  # odometry's prediction
        if odometry_won and scan.odom is not None and self._odom is not None:
            self._learn_odometry_bias(self._odom.between(scan.odom), pose, predicted, predicted_cov)
        # The covariance relative to the latest keyframe: a Kalman step of the motion since it.
        prior_cov = self._cov_since_keyframe + cov_pred
        cov = np.linalg.inv(np.linalg.inv(prior_cov) + h_scan)
        cov = 0.5 * (cov + cov.T)
        self._update_motion(
            scan, pose, h_scan, cov_pred, predicted.theta_rad if odometry_won else None
        )
        keyframe = self._is_keyframe(pose)
        if keyframe:
            self._insert(scan, returns, pose)
            self._cov_since_keyframe = np.zeros((3, 3))
        else:
            self._cov_since_keyframe = cov
        return PoseEstimate(
            scan.stamp_ns,
            pose,
            float(np.clip(score, 0.0, 1.0)),
            flags,
            keyframe,
            _covariance3(cov),
        )

    def _degenerate(
        self, scan: LaserScan, predicted: Pose2D, cov_pred: FloatArray, flags: PoseFlag
    ) -> PoseEstimate:
        """The prediction, flagged: time and pose move on, nothing is learnt from the scan."""
        self.stats.degenerate += 1
        self._cov_since_keyframe = self._cov_since_keyframe + cov_pred
        self._pose_cov = self._pose_cov + cov_pred
        if self._pose is not None:
            self._pose = predicted
        if self._stamp_ns is None or scan.stamp_ns > self._stamp_ns:
            self._stamp_ns = scan.stamp_ns
        if scan.odom is not None:
            self._odom = scan.odom
        cov = _covariance3(self._cov_since_keyframe)
        return PoseEstimate(scan.stamp_ns, predicted, 0.0, flags | PoseFlag.DEGENERATE, False, cov)

    def _ambiguity(self, h_scan: FloatArray) -> PoseFlag:
        """AMBIGUOUS_X/Y where the scan's translation information is weak along that axis."""
        evals, evecs = np.linalg.eigh(h_scan[:2, :2])
        if evals[1] <= 0.0 or evals[0] >= self.params.ambiguous_ratio * evals[1]:
            return PoseFlag.NONE
        weak = evecs[:, 0]
        return PoseFlag.AMBIGUOUS_X if abs(weak[0]) >= abs(weak[1]) else PoseFlag.AMBIGUOUS_Y

    def _learn_odometry_noise(self, pose: Pose2D, predicted: Pose2D, cov_pred: FloatArray) -> None:
        """The odometry's variance scale (translation, rotation): a running mean of its
        innovations' square in units of its default σ, each capped at 10² (a slip or a
        relocalisation is one scan's outlier, not the odometry's noise)."""
        d = np.array(
            [pose.x_m - predicted.x_m, pose.y_m - predicted.y_m, predicted.between(pose).theta_rad]
        )
        z2 = d * d / np.diag(cov_pred)  # in units of the σ used, which the scale widened
        scale2 = np.maximum(self._odom_noise_scale2, 1.0)
        measured = np.array([0.5 * (z2[0] + z2[1]) * scale2[0], z2[2] * scale2[1]])
        alpha = 1.0 / max(1, self.params.odometry_noise_memory_scans)
        self._odom_noise_scale2 = (1.0 - alpha) * self._odom_noise_scale2 + alpha * np.minimum(
            measured, 100.0
        )

    def _odom_heading_bias_prior(self) -> tuple[float, float]:
        """The odometry heading bias's estimate before any scan: (0 rad/m, its prior variance)."""
        sigma = math.radians(self.params.odometry_heading_bias_sigma_deg_per_m)
        return 0.0, sigma * sigma

    def _learn_odometry_bias(
        self, odom_delta: Pose2D, pose: Pose2D, predicted: Pose2D, cov_pred: FloatArray
    ) -> None:
        """A Kalman step of the odometry's heading bias per metre: the matched heading minus
        odometry's (bias taken off) says what the bias still owes, over the distance odometry
        travelled, as sure as odometry's σ_θ over that distance, and at most 3σ of it. (The
        match is pulled towards odometry, so this says less than the bias owes; the estimate
        keeps integrating what is left until the innovations centre on zero.)"""
        p = self.params
        if p.odometry_heading_bias_sigma_deg_per_m <= 0.0:
            return
        dist = math.hypot(odom_delta.x_m, odom_delta.y_m)
        if dist < 1e-3:  # a turn in place says nothing about a bias per metre
            return
        bias, var = self._odom_heading_bias
        var += math.radians(p.odometry_heading_bias_walk_deg_per_m) ** 2 * dist
        owed = -predicted.between(pose).theta_rad / dist
        noise = cov_pred[2, 2] / (dist * dist)
        reach = 3.0 * math.sqrt(var + noise)
        gain = var / (var + noise)
        self._odom_heading_bias = (
            bias + gain * min(max(owed, -reach), reach),
            (1.0 - gain) * var,
        )

    def _velocity_noise(self, gap_s: float) -> FloatArray:
        p = self.params
        fwd, lat = p.forward_accel_sigma_m_s2 * gap_s, p.lateral_accel_sigma_m_s2 * gap_s
        alpha = math.radians(p.angular_accel_sigma_deg_s2) * gap_s
        return np.diag([fwd * fwd, lat * lat, alpha * alpha])

    def _update_motion(
        self,
        scan: LaserScan,
        pose: Pose2D,
        h_scan: FloatArray,
        cov_pred: FloatArray,
        odometry_theta_rad: float | None = None,
    ) -> None:
        """Kalman step of the velocity: the motion since the previous step, over at least
        `velocity_window_s` (real logs hold scans 1 ms apart, over which a match's noise would
        be a huge speed), counts as much as both its ends are known against the submap. Along
        a corridor the scan says nothing, so the velocity keeps its prediction there (a slipped
        match does not become a speed); and where a door pins the pose again after a plain
        stretch, the correction says where the robot is, not how fast it went (the anchor's
        position along the corridor was loose). A heading the match corrected, beyond the turn
        the prediction made (odometry's, `odometry_theta_rad`, when odometry predicted the scan;
        else the velocity's), says where the robot faces, not that its motion turned: the
        velocity (robot frame) is turned back by the correction, so that its direction in the
        map is kept."""
        p = self.params
        self._pose_cov = np.asarray(
            np.linalg.inv(np.linalg.inv(self._pose_cov + cov_pred) + h_scan), dtype=np.float64
        )
        anchor = self._velocity_anchor
        turn_rate_rad_s = float(self._velocity[2])  # the velocity's, as it predicted this scan
        gap_s = 0.0 if self._stamp_ns is None else (scan.stamp_ns - self._stamp_ns) * 1e-9
        if anchor is None or gap_s > p.max_extrapolation_s:
            if anchor is not None:
                self._velocity = np.zeros(3)  # after a pause: at rest until it moves again
                self._velocity_cov = _UNKNOWN_VELOCITY_COV
            self._velocity_anchor = (pose, scan.stamp_ns, self._pose_cov)
        elif (span_s := (scan.stamp_ns - anchor[1]) * 1e-9) >= p.velocity_window_s:
            d = anchor[0].between(pose)
            measured = np.array([d.x_m, d.y_m, d.theta_rad]) / span_s
            c, s = math.cos(anchor[0].theta_rad), math.sin(anchor[0].theta_rad)
            rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # map -> robot
            r = rot @ (anchor[2] + self._pose_cov) @ rot.T / (span_s * span_s)
            p_v = self._velocity_cov + self._velocity_noise(span_s)
            gain = p_v @ np.linalg.inv(p_v + r)
            self._velocity = self._velocity + gain @ (measured - self._velocity)
            self._velocity_cov = (np.eye(3) - gain) @ p_v
            self._velocity_anchor = (pose, scan.stamp_ns, self._pose_cov)
        if self._pose is not None and anchor is not None:
            t = min(max(gap_s, 0.0), p.max_extrapolation_s)
            predicted_theta_rad = (
                self._pose.theta_rad + turn_rate_rad_s * t
                if odometry_theta_rad is None
                else odometry_theta_rad
            )
            correction = math.remainder(pose.theta_rad - predicted_theta_rad, 2 * math.pi)
            c, s = math.cos(correction), math.sin(correction)
            vx, vy, omega = self._velocity
            self._velocity = np.array([c * vx + s * vy, -s * vx + c * vy, omega])
        self._pose = pose
        self._stamp_ns = scan.stamp_ns
        if scan.odom is not None:
            self._odom = scan.odom

    def _is_keyframe(self, pose: Pose2D) -> bool:
        k = self._keyframe_pose
        if k is None:
            return True
        d = k.between(pose)
        return math.hypot(d.x_m, d.y_m) >= self.params.keyframe_distance_m or abs(
            d.theta_rad
        ) >= math.radians(self.params.keyframe_angle_deg)

    def _insert(self, scan: LaserScan, returns: FloatArray, pose: Pose2D) -> None:
        p = self.params
        self._keyframe_pose = pose
        pts = returns[
            np.hypot(returns[:, 0], returns[:, 1]) <= min(p.max_range_m, scan.range_max_m)
        ]
        world = surface_in_map(pts, pose, p)
        ends = rotate_points(pts, pose.theta_rad) + np.array([pose.x_m, pose.y_m])
        if not self._submaps or self._submaps[-1].inserted >= p.scans_per_submap:
            self._submaps.append(LikelihoodGrid(p.resolution_m, p.hit_sigma_m, p.carve_margin_m))
        for grid in self._submaps:
            grid.insert(world, (pose.x_m, pose.y_m), ends)
        if len(self._submaps) > 2:
            self._submaps.pop(0)  # it holds 2 × scans_per_submap: the next one takes over


def warm_up() -> None:
    """Match three scans of a made-up room and draw the last into a grid, so that the compiled
    kernels (`kernels` and the map's `raycast`, numba) are loaded from their cache, or
    compiled, before a robot's first scan waits on them: a fraction of a second from the
    cache, tens of seconds to compile on a busy machine, while that robot's scans queue."""
    half_m = np.array([4.0, 3.0])  # the room: 8 m × 6 m around the origin
    angles = np.linspace(-0.75 * math.pi, 0.75 * math.pi, 1081)  # a UTM-30LX
    front = ScanMatcherFrontEnd(MatcherParams(use_odometry=False))
    for i in range(3):  # 0.2 m apart: the third is a keyframe (an insert, carving)
        pose = Pose2D(0.2 * i, 0.1 * i, 0.05 * i)
        d = np.column_stack((np.cos(angles + pose.theta_rad), np.sin(angles + pose.theta_rad)))
        start = np.array([pose.x_m, pose.y_m])
        with np.errstate(divide="ignore", invalid="ignore"):  # parallel beams never meet it
            to_wall = (np.sign(d) * half_m - start) / d
        ranges = np.min(np.where(to_wall > 0.0, to_wall, np.inf), axis=1)
        scan = LaserScan(i * 25_000_000, -0.75 * math.pi, angles[1] - angles[0], ranges, 0.1, 30.0)
        front.process(scan)
    OccupancyGrid().integrate(scan, pose)
