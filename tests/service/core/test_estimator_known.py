"""Known-answer tests of the estimator on tiny ray-cast worlds built here."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from clients.wire import PoseFlag
from service.core.frontend.estimator import ManhattanEstimator
from service.core.frontend.heading import (
    measure_heading,
    resolve_heading,
    thin_points,
    wrap_quarter,
)
from service.core.frontend.params import EstimatorParams
from service.core.types import LaserScan, Pose2D, wrap_angle

Segments = np.ndarray  # (S, 4): x0, y0, x1, y1


def box(x0: float, y0: float, x1: float, y1: float) -> list[tuple[float, float, float, float]]:
    return [(x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)]


def room() -> Segments:
    """A 10 m × 6 m room with a pillar and a cupboard, so both axes are constrained."""
    segs = box(-5.0, -3.0, 5.0, 3.0) + box(1.0, 0.8, 1.4, 1.2) + box(-3.5, -3.0, -2.0, -2.4)
    segs += [(2.5, -3.0, 2.5, -1.8)]  # a partition stub
    return np.array(segs, dtype=np.float64)


def l_corridor() -> Segments:
    """A corridor along x (y in ±1, x from -12 to 1) turning left into one along y."""
    segs = [
        (-12.0, -1.0, 1.0, -1.0),
        (1.0, -1.0, 1.0, 14.0),
        (-12.0, 1.0, -1.0, 1.0),
        (-1.0, 1.0, -1.0, 14.0),
        (-12.0, -1.0, -12.0, 1.0),
        (-1.0, 14.0, 1.0, 14.0),
    ]
    # Door recesses so that the corridors are not perfectly featureless along their axis.
    for x in (-9.0, -6.0, -3.0):
        segs += [(x, 1.0, x, 1.3), (x, 1.3, x + 0.9, 1.3), (x + 0.9, 1.3, x + 0.9, 1.0)]
    for y in (4.0, 7.0, 10.0):
        segs += [(1.0, y, 1.3, y), (1.3, y, 1.3, y + 0.9), (1.3, y + 0.9, 1.0, y + 0.9)]
    return np.array(segs, dtype=np.float64)


def cast(
    segs: Segments,
    pose: Pose2D,
    *,
    fov_deg: float = 270.0,
    beams: int = 1081,
    range_max_m: float = 30.0,
    noise_m: float = 0.0,
    rng: np.random.Generator | None = None,
    stamp_ns: int = 0,
) -> LaserScan:
    """Ray-cast `segs` from `pose` (laser frame = robot frame)."""
    inc = math.radians(fov_deg) / (beams - 1)
    a_min = -math.radians(fov_deg) / 2.0
    ang = pose.theta_rad + a_min + inc * np.arange(beams)
    d = np.stack((np.cos(ang), np.sin(ang)), axis=1)  # (B, 2)
    p0 = segs[:, :2]
    e = segs[:, 2:] - p0  # (S, 2)
    w = p0 - np.array([pose.x_m, pose.y_m])  # (S, 2)
    # Solve pose + t·d = p0 + u·e for every (beam, segment).
    den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[None, :, 0] * e[None, :, 1] - w[None, :, 1] * e[None, :, 0]) / den
        u = (w[None, :, 0] * d[:, None, 1] - w[None, :, 1] * d[:, None, 0]) / den
    hit = (np.abs(den) > 1e-12) & (t > 0.0) & (u >= 0.0) & (u <= 1.0)
    r = np.where(hit, t, np.inf).min(axis=1)
    if noise_m > 0.0 and rng is not None:
        r = r + rng.normal(0.0, noise_m, r.shape)
    r = np.where(np.isfinite(r) & (r < range_max_m), r, range_max_m)
    return LaserScan(stamp_ns, a_min, inc, r, 0.02, range_max_m)


def test_thinning_spacing() -> None:
    pts = np.column_stack((np.linspace(0.0, 5.0, 1001), np.zeros(1001)))
    thin = thin_points(pts, 0.05)
    gaps = np.diff(thin[:, 0])
    assert 95 <= thin.shape[0] <= 105
    assert np.all(gaps > 0.04)
    assert np.all(gaps < 0.06)


@pytest.mark.parametrize("heading_deg", list(range(0, 360, 7)))
def test_manhattan_angle_every_7_degrees(heading_deg: int) -> None:
    truth = math.radians(heading_deg)
    scan = cast(room(), Pose2D(0.3, -0.4, truth))
    m = measure_heading(scan.points_xy_m(), None, 0.0, math.radians(0.1), 0.02)
    # Rotating laser points by the heading aligns them with the map: angle ≡ heading mod 90°.
    err = math.degrees(float(wrap_quarter(m.angle_rad - truth)))
    assert abs(err) < 0.2


def test_heading_tracked_through_full_turn() -> None:
    """Rotating in place 7° per scan: the ±45° rule keeps the absolute heading for 360°."""
    est = ManhattanEstimator()
    segs = room()
    first = math.radians(3.0)
    for k in range(53):
        truth = first + math.radians(7.0 * k)
        out = est.process(cast(segs, Pose2D(0.3, -0.4, truth), stamp_ns=k * 100_000_000))
        assert abs(math.degrees(wrap_angle(out.theta_rad - truth))) < 0.2, k
        assert math.hypot(out.x_m, out.y_m) < 0.02, k  # 53 chained matches


def test_resolve_heading_switch_rule() -> None:
    q = math.pi / 2.0
    assert resolve_heading(math.radians(40.0), math.radians(44.0)) == pytest.approx(
        math.radians(40.0)
    )
    # Relative wall angle jumps from +44° to -44°: the wall is the perpendicular one now.
    assert resolve_heading(math.radians(-44.0), math.radians(44.0)) == pytest.approx(
        math.radians(-44.0) + q
    )
    assert resolve_heading(math.radians(10.0), math.radians(185.0)) == pytest.approx(
        math.radians(190.0)
    )


@pytest.mark.parametrize("seed", range(6))
def test_known_translation_within_1cm(seed: int) -> None:
    rng = np.random.default_rng(seed)
    segs = room()
    theta = math.radians(rng.uniform(-30.0, 30.0))
    start = Pose2D(-0.5, 0.2, theta)
    dx, dy = rng.uniform(-0.35, 0.35, size=2)
    est = ManhattanEstimator()
    est.process(cast(segs, start, stamp_ns=0))
    out = est.process(cast(segs, Pose2D(start.x_m + dx, start.y_m + dy, theta), stamp_ns=10**8))
    assert math.hypot(out.x_m - dx, out.y_m - dy) < 0.01, (out.pose, dx, dy)
    assert abs(math.degrees(out.theta_rad - theta)) < 0.2


def test_translation_paper_mode_full_window() -> None:
    """The literal paper settings (no prediction, previous scan) recover a 0.3 m move too."""
    params = EstimatorParams(
        use_prediction=False,
        reference="previous",
        refine_2d=False,
        orientation_weighting=False,
        heading_score="max",
    )
    segs = room()
    est = ManhattanEstimator(params)
    est.process(cast(segs, Pose2D(0.0, 0.0, 0.1), stamp_ns=0))
    out = est.process(cast(segs, Pose2D(0.02, 0.3, 0.1), stamp_ns=10**8))
    assert math.hypot(out.x_m - 0.02, out.y_m - 0.3) < 0.015


def test_l_corridor_heading_switch() -> None:
    """Down a corridor along x, turn left into one along y: the major wall changes family."""
    segs = l_corridor()
    est = ManhattanEstimator()
    rng = np.random.default_rng(1)
    poses = [Pose2D(-10.0 + 0.3 * i, 0.0, 0.0) for i in range(34)]  # to x = -0.1
    poses += [Pose2D(0.0, 0.0, math.radians(10.0 * k)) for k in range(1, 10)]
    poses += [Pose2D(0.0, 0.3 * i, math.pi / 2.0) for i in range(1, 35)]
    flags = PoseFlag.NONE
    for k, truth in enumerate(poses):
        scan = cast(segs, truth, noise_m=0.01, rng=rng, stamp_ns=k * 200_000_000)
        out = est.process(scan)
        flags |= out.flags
        assert abs(math.degrees(wrap_angle(out.theta_rad - truth.theta_rad))) < 0.5, k
        rel = Pose2D(truth.x_m - poses[0].x_m, truth.y_m - poses[0].y_m, 0.0)
        assert math.hypot(out.x_m - rel.x_m, out.y_m - rel.y_m) < 0.15, (k, out.pose, rel)
    assert flags & PoseFlag.HEADING_SWITCH


def test_corridor_is_flagged_ambiguous() -> None:
    segs = np.array([(-50.0, -1.0, 50.0, -1.0), (-50.0, 1.0, 50.0, 1.0)])
    est = ManhattanEstimator()
    est.process(cast(segs, Pose2D(0.0, 0.0, 0.0), stamp_ns=0))
    out = est.process(cast(segs, Pose2D(0.3, 0.1, 0.0), stamp_ns=10**8))
    assert out.flags & PoseFlag.AMBIGUOUS_X
    assert not out.flags & PoseFlag.AMBIGUOUS_Y
    assert abs(out.y_m - 0.1) < 0.01
    assert out.quality < 0.9


def _degenerate_scans() -> list[LaserScan]:
    inc = math.radians(0.25)
    full = cast(room(), Pose2D(0.0, 0.0, 0.0))
    three = np.full(1081, 30.0)
    three[[10, 500, 900]] = 2.0
    return [
        LaserScan(1, -2.35, inc, np.empty(0), 0.02, 30.0),
        LaserScan(2, -2.35, inc, three, 0.02, 30.0),
        LaserScan(3, -2.35, inc, np.full(1081, 30.0), 0.02, 30.0),
        LaserScan(4, -2.35, inc, np.full(1081, np.nan), 0.02, 30.0),
        LaserScan(
            5, -2.35, inc, np.where(np.arange(1081) % 2 == 0, np.nan, full.ranges_m), 0.02, 30.0
        ),
        LaserScan(6, math.nan, inc, full.ranges_m, 0.02, 30.0),
        LaserScan(7, -2.35, inc, np.full(1081, np.inf), 0.02, 30.0),
        LaserScan(8, -2.35, inc, np.zeros(1081), 0.02, 30.0),
    ]


@pytest.mark.parametrize("initialised", [False, True])
def test_degenerate_inputs_are_flagged_not_raised(initialised: bool) -> None:
    est = ManhattanEstimator()
    if initialised:
        est.process(cast(room(), Pose2D(0.0, 0.0, 0.0), stamp_ns=0))
    for scan in _degenerate_scans():
        out = est.process(scan)
        assert 0.0 <= out.quality <= 1.0
        if scan.stamp_ns != 5:  # half the beams of a good scan is still a good scan
            assert out.flags & PoseFlag.DEGENERATE, scan.stamp_ns
            assert out.quality == 0.0
        assert all(math.isfinite(v) for v in out.pose)


def test_odometry_prior_flag_and_reset() -> None:
    segs = room()
    est = ManhattanEstimator()
    s0 = cast(segs, Pose2D(0.0, 0.0, 0.0), stamp_ns=0)
    s1 = cast(segs, Pose2D(0.2, 0.1, 0.05), stamp_ns=10**8)
    est.process(
        LaserScan(
            0,
            s0.angle_min_rad,
            s0.angle_increment_rad,
            s0.ranges_m,
            0.02,
            30.0,
            Pose2D(5.0, 5.0, 1.0),
        )
    )
    odom1 = Pose2D(5.0, 5.0, 1.0).compose(Pose2D(0.2, 0.1, 0.05))
    out = est.process(
        LaserScan(10**8, s1.angle_min_rad, s1.angle_increment_rad, s1.ranges_m, 0.02, 30.0, odom1)
    )
    assert out.flags & PoseFlag.ODOMETRY_PRIOR
    assert math.hypot(out.x_m - 0.2, out.y_m - 0.1) < 0.01
    est.reset()
    again = est.process(s1)
    assert again.pose == pytest.approx((0.0, 0.0, 0.05), abs=2e-3)


def test_odometry_prediction_carries_a_motion_beyond_the_search_window() -> None:
    """0.6 m between two scans, more than the ±0.25 m searched around an odometry prediction:
    found only if the prediction really is the previous pose moved by the odometry delta."""
    segs = room()
    motion = Pose2D(0.6, -0.3, 0.1)
    assert math.hypot(motion.x_m, motion.y_m) > EstimatorParams().translation_window_odom_m
    est = ManhattanEstimator()
    odom0 = Pose2D(5.0, 5.0, 1.0)
    for stamp_ns, pose, odom in [
        (0, Pose2D(0.0, 0.0, 0.0), odom0),
        (10**8, motion, odom0.compose(motion)),
    ]:
        s = cast(segs, pose, stamp_ns=stamp_ns)
        out = est.process(
            LaserScan(
                stamp_ns, s.angle_min_rad, s.angle_increment_rad, s.ranges_m, 0.02, 30.0, odom
            )
        )
    assert out.flags & PoseFlag.ODOMETRY_PRIOR
    assert math.hypot(out.x_m - motion.x_m, out.y_m - motion.y_m) < 0.01, out.pose
    assert abs(wrap_angle(out.theta_rad - motion.theta_rad)) < math.radians(0.5), out.pose


def plain_corridor(length_m: float = 40.0, half_width_m: float = 1.2) -> Segments:
    """Two plain walls and two end walls: nothing along the corridor but its ends."""
    w = half_width_m
    return np.array(
        [
            (0.0, -w, length_m, -w),
            (0.0, w, length_m, w),
            (0.0, -w, 0.0, w),
            (length_m, -w, length_m, w),
        ],
        dtype=np.float64,
    )


def test_plain_corridor_from_a_standing_start() -> None:
    """40 m from a standing start at 10 Hz. For the first 10 m the far end is beyond the 30 m
    range and the walls say nothing along the corridor: that stretch must be reported as
    unobservable (AMBIGUOUS_X), not measured, with a covariance that covers what the carried
    motion gets wrong. Once the end wall is in view, the motion along the corridor is
    measured: the whole corridor within 2 % of its length.

    It used to stand still the whole way, unflagged, with a 6 mm σ.
    """
    segs = plain_corridor()
    rng = np.random.default_rng(3)
    est = ManhattanEstimator(EstimatorParams(use_odometry=False))
    x_m, speed_m_s, dt_s = 0.5, 0.0, 0.1
    blind: list[PoseFlag] = []  # true x in 2..9 m: nothing in range along the corridor
    worst_z = 0.0  # along-corridor error since the latest keyframe, in its reported σ
    keyframe = (x_m, 0.0)  # (true x, estimated x) at the latest keyframe
    first: tuple[float, float] | None = None
    k = 0
    while x_m < 39.0:
        out = est.process(
            cast(segs, Pose2D(x_m, 0.0, 0.0), noise_m=0.01, rng=rng, stamp_ns=round(k * dt_s * 1e9))
        )
        first = first or (x_m, out.pose.x_m)
        error_m = (out.pose.x_m - keyframe[1]) - (x_m - keyframe[0])
        if 2.0 < x_m < 9.0:
            blind.append(out.flags)
            assert out.covariance is not None
            worst_z = max(worst_z, abs(error_m) / math.sqrt(out.covariance[0]))
        if out.is_keyframe:
            keyframe = (x_m, out.pose.x_m)
        assert abs(out.pose.y_m) < 0.05, k
        assert abs(math.degrees(wrap_angle(out.theta_rad))) < 0.5, k
        speed_m_s = min(0.7, speed_m_s + 0.5 * dt_s)  # accelerates at 0.5 m/s² to 0.7 m/s
        x_m += speed_m_s * dt_s
        k += 1
    assert sum(bool(f & PoseFlag.AMBIGUOUS_X) for f in blind) > 0.9 * len(blind)
    assert worst_z < 3.0
    true_m = x_m - speed_m_s * dt_s - first[0]
    estimated_m = out.pose.x_m - first[1]
    assert abs(estimated_m - true_m) < 0.02 * true_m, (estimated_m, true_m)


def test_plain_corridor_with_a_person_walking_beside_the_robot() -> None:
    """90 m of corridor at 1 m/s and 10 Hz; in one scan of ten a person walks beside the robot,
    0.6 m to its left. Jambs every 3 m up to 30 m measure the speed; from 30 to 60 m nothing
    along the corridor is in range, so the motion is carried. The person moves with the robot:
    matched, each such scan would say "standing still" and cut the carried speed. Their
    points are where the previous scan saw free space, so they are left out: the blind 30 m
    come out within 3 %.
    """
    jambs = [(x, side * 1.2, x, side * 1.05) for x in range(3, 30, 3) for side in (-1, 1)]
    segs = np.vstack((plain_corridor(90.0), np.array(jambs, dtype=np.float64)))
    rng = np.random.default_rng(5)
    est = ManhattanEstimator(EstimatorParams(use_odometry=False))
    x_m, speed_m_s, dt_s = 1.0, 0.0, 0.1
    blind: list[tuple[float, float]] = []  # (true x, estimated x) with neither end in range
    k = 0
    while x_m < 62.0:
        walls = segs
        if rng.random() < 0.1:
            walls = np.vstack((segs, np.array(box(x_m - 0.2, 0.4, x_m + 0.2, 0.8))))
        scan = cast(
            walls, Pose2D(x_m, 0.0, 0.0), noise_m=0.01, rng=rng, stamp_ns=round(k * dt_s * 1e9)
        )
        out = est.process(scan)
        if 31.0 < x_m < 59.0:
            blind.append((x_m, out.pose.x_m))
        speed_m_s = min(1.0, speed_m_s + 0.5 * dt_s)
        x_m += speed_m_s * dt_s
        k += 1
    true_m = blind[-1][0] - blind[0][0]
    estimated_m = blind[-1][1] - blind[0][1]
    assert abs(estimated_m - true_m) < 0.03 * true_m, (estimated_m, true_m)


def _placed(
    segs: list[tuple[float, float, float, float]], origin: np.ndarray, angle_rad: float
) -> list[tuple[float, float, float, float]]:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    out = []
    for x0, y0, x1, y1 in segs:
        out.append(
            (
                float(origin[0] + c * x0 - s * y0),
                float(origin[1] + s * x0 + c * y0),
                float(origin[0] + c * x1 - s * y1),
                float(origin[1] + s * x1 + c * y1),
            )
        )
    return out


def wing_building(
    angle_deg: float, connector_m: float = 8.0, half_width_m: float = 1.1
) -> tuple[Segments, list[np.ndarray]]:
    """An aligned 14 × 8 m room, a corridor at `angle_deg` from its east door, and a 12 × 8 m
    wing room at the same angle; returns the walls and a route into the wing, round it and back.
    """
    a = math.radians(angle_deg)
    door = half_width_m / math.cos(a)  # the corridor's width where it meets the east wall
    segs = [(-2.0, -4.0, 12.0, -4.0), (12.0, -4.0, 12.0, -door), (12.0, door, 12.0, 4.0)]
    segs += [(12.0, 4.0, -2.0, 4.0), (-2.0, 4.0, -2.0, -4.0)]
    segs += box(3.0, 1.5, 3.5, 2.0) + box(6.0, -4.0, 7.5, -3.2) + [(9.0, 4.0, 9.0, 2.8)]
    along, across = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
    east = np.array([12.0, 0.0])
    for v in (-half_width_m, half_width_m):
        p = east + v * math.tan(a) * along + v * across
        q = east + connector_m * along + v * across
        segs.append((float(p[0]), float(p[1]), float(q[0]), float(q[1])))
    origin = east + connector_m * along
    wing = [(0.0, -4.0, 12.0, -4.0), (12.0, -4.0, 12.0, 4.0), (12.0, 4.0, 0.0, 4.0)]
    wing += [(0.0, 4.0, 0.0, half_width_m), (0.0, -half_width_m, 0.0, -4.0)]
    wing += box(4.0, -2.2, 4.5, -1.7) + box(8.0, 3.0, 9.5, 4.0) + [(6.5, -4.0, 6.5, -2.9)]
    segs += _placed(wing, origin, a)

    def in_wing(u: float, v: float) -> np.ndarray:
        return origin + u * along + v * across

    route = [np.array([1.0, 0.0]), np.array([10.5, 0.0]), in_wing(2.0, 0.0), in_wing(9.5, 0.0)]
    route += [in_wing(9.5, 2.0), in_wing(2.5, 2.0), in_wing(2.0, 0.0), np.array([10.5, 0.0])]
    route += [np.array([1.0, 0.0])]
    return np.array(segs, dtype=np.float64), route


def drive(route: list[np.ndarray], step_m: float, turn_deg: float) -> list[Pose2D]:
    """Straight legs `step_m` per scan, turning in place `turn_deg` per scan at each corner."""
    poses: list[Pose2D] = []
    theta = 0.0
    for p, q in itertools.pairwise(route):
        d = q - p
        heading = math.atan2(float(d[1]), float(d[0]))
        turn = wrap_angle(heading - theta)
        k = max(1, int(abs(turn) / math.radians(turn_deg)))
        poses += [Pose2D(float(p[0]), float(p[1]), theta + turn * i / k) for i in range(1, k + 1)]
        theta = heading
        m = max(1, int(float(np.hypot(*d)) / step_m))
        poses += [Pose2D(*(p + d * i / m), heading) for i in range(1, m + 1)]
    return poses


@pytest.mark.parametrize("angle_deg", [30.0, 45.0])
def test_angled_wing_and_back_heading_within_half_a_degree(angle_deg: float) -> None:
    """From an aligned room into a wing at 30° (and 45°) and back, 0.1 m per scan.

    The wing's walls are Manhattan among themselves but not with the room's: measured against
    the room's family they fold the heading by the wing's angle (31° in the issue's office).
    The wing must become a wall family of its own, with the heading within 0.5° everywhere
    and the position within 0.15 m.
    """
    segs, route = wing_building(angle_deg)
    rng = np.random.default_rng(1)
    est = ManhattanEstimator(EstimatorParams(use_odometry=False))
    poses = drive(route, 0.1, 5.0)
    start = poses[0]
    for k, truth in enumerate(poses):
        scan = cast(segs, truth, noise_m=0.01, rng=rng, stamp_ns=k * 100_000_000)
        out = est.process(scan)
        err_deg = math.degrees(wrap_angle(out.theta_rad - truth.theta_rad))
        assert abs(err_deg) < 0.5, (k, truth, err_deg)
        err_m = math.hypot(out.x_m - (truth.x_m - start.x_m), out.y_m - (truth.y_m - start.y_m))
        assert err_m < 0.15, (k, truth, err_m)
    wing_family = float(wrap_quarter(math.radians(angle_deg)))
    families = est._frames.angles_rad
    assert any(abs(math.degrees(f - wing_family)) < 0.3 for f in families), families
