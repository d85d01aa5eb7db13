"""Synthetic world generator: determinism, ray-cast known answers, beam model, trajectories."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sensor_agent.sim import (
    LaserModel,
    RobotMotion,
    SimError,
    World,
    generate_building,
    generate_trajectory,
    simulate_scan,
)
from sensor_agent.sim.world import RASTER_RES_M


def square_room(half_m: float = 5.0) -> World:
    """A closed square room centred on the origin: walls at x, y = +-half_m."""
    h = half_m
    seg = np.array(
        [[-h, -h, h, -h], [h, -h, h, h], [h, h, -h, h], [-h, h, -h, -h]], dtype=np.float64
    )
    return World(
        seed=0,
        size="test",
        width_m=2 * h,
        height_m=2 * h,
        corridor_width_m=2 * h,
        segments_m=seg,
        loop_xy_m=np.zeros((0, 2)),
        free_raster=np.ones((1, 1), dtype=bool),
    )


@pytest.fixture(scope="module")
def paper_world() -> World:
    return generate_building(7, "paper")


def test_building_is_deterministic_by_seed() -> None:
    a = generate_building(3, "small")
    b = generate_building(3, "small")
    c = generate_building(4, "small")
    assert np.array_equal(a.segments_m, b.segments_m)
    assert not np.array_equal(a.segments_m, c.segments_m)
    ta, tb = generate_trajectory(a, 1), generate_trajectory(b, 1)
    assert np.array_equal(ta.poses, tb.poses)
    assert np.array_equal(ta.stamps_ns, tb.stamps_ns)
    sa = simulate_scan(a, ta.poses[5], LaserModel.utm30lx(), np.random.default_rng(9))
    sb = simulate_scan(b, tb.poses[5], LaserModel.utm30lx(), np.random.default_rng(9))
    assert np.array_equal(sa.ranges_mm, sb.ranges_mm)


def test_unknown_size_is_refused() -> None:
    with pytest.raises(SimError):
        generate_building(1, "huge")  # type: ignore[arg-type]


def test_paper_building_scale_and_structure(paper_world: World) -> None:
    w = paper_world
    assert (w.width_m, w.height_m) == (190.0, 50.0)
    seg = w.segments_m
    assert seg.dtype == np.float64
    assert seg.shape[1] == 4
    assert 1000 < seg.shape[0] < 10000
    dx, dy = seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]
    manhattan = (np.abs(dx) < 1e-9) | (np.abs(dy) < 1e-9)
    # Mostly Manhattan, with a few non-Manhattan walls.
    assert manhattan.mean() > 0.95
    assert 3 <= (~manhattan).sum() <= 40
    assert np.all(seg[:, [0, 2]] >= 0)
    assert np.all(seg[:, [0, 2]] <= w.width_m)
    assert np.all(seg[:, [1, 3]] >= 0)
    assert np.all(seg[:, [1, 3]] <= w.height_m)


@pytest.mark.parametrize("theta", [0.0, 0.3, -2.0, math.pi / 2, math.pi])
def test_raycast_square_room_known_answers(theta: float) -> None:
    room = square_room(5.0)
    px, py = 1.0, -2.0
    angles = np.linspace(-math.pi, math.pi, 721, endpoint=False)
    ranges = room.raycast((px, py, theta), angles, 30.0)
    world_ang = angles + theta
    c, s = np.cos(world_ang), np.sin(world_ang)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (5.0 - px) / c, np.where(c < 0, (-5.0 - px) / c, np.inf))
        ty = np.where(s > 0, (5.0 - py) / s, np.where(s < 0, (-5.0 - py) / s, np.inf))
    np.testing.assert_allclose(ranges, np.minimum(tx, ty), rtol=0, atol=1e-9)


def test_raycast_max_range_gives_inf() -> None:
    room = square_room(5.0)
    ranges = room.raycast((0.0, 0.0, 0.0), np.array([0.0, math.pi / 4]), max_range_m=6.0)
    assert ranges[0] == pytest.approx(5.0)
    assert np.isinf(ranges[1])  # corner at 7.07 m


def test_raycast_matches_brute_force(paper_world: World) -> None:
    w = paper_world
    traj = generate_trajectory(w, 2)
    angles = LaserModel.utm30lx().angles_rad()
    a = w.segments_m[:, :2]
    e = w.segments_m[:, 2:] - a
    for pose in traj.poses[::97]:
        px, py, th = pose
        d = np.column_stack((np.cos(angles + th), np.sin(angles + th)))
        ap = a - (px, py)
        den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (ap[None, :, 0] * e[None, :, 1] - ap[None, :, 1] * e[None, :, 0]) / den
            u = (ap[None, :, 0] * d[:, None, 1] - ap[None, :, 1] * d[:, None, 0]) / den
        ok = (np.abs(den) > 1e-12) & (t > 1e-9) & (u >= -1e-9) & (u <= 1 + 1e-9)
        brute = np.where(ok, t, np.inf).min(axis=1)
        brute[brute > 30.0] = np.inf
        np.testing.assert_array_equal(np.isinf(w.raycast(pose, angles, 30.0)), np.isinf(brute))
        fin = np.isfinite(brute)
        np.testing.assert_allclose(w.raycast(pose, angles, 30.0)[fin], brute[fin], atol=1e-9)


def test_utm30lx_geometry() -> None:
    m = LaserModel.utm30lx()
    assert m.beam_count == 1081
    assert m.angle_min_rad == pytest.approx(-3 * math.pi / 4)
    assert m.angle_max_rad == pytest.approx(3 * math.pi / 4)
    assert math.degrees(m.angle_increment_rad) == pytest.approx(0.25)
    assert m.range_max_m == 30.0
    assert LaserModel.sick_lms200().beam_count == 181
    assert math.degrees(LaserModel.sick_lms200().angle_max_rad) == pytest.approx(90.0)
    urg = LaserModel.urg04lx()
    assert urg.beam_count == 681
    assert 238.0 < math.degrees(urg.angle_max_rad - urg.angle_min_rad) < 240.0
    assert LaserModel.urg04lx(beam_count=683).beam_count == 683


def test_error_codes_far_near_and_dropouts() -> None:
    room = square_room(40.0)  # every wall beyond 30 m from the centre: all beams "no object"
    m = LaserModel.utm30lx()
    far = simulate_scan(room, (0.0, 0.0, 0.0), m, np.random.default_rng(0))
    assert far.ranges_mm.dtype == np.uint32
    assert far.ranges_mm.shape == (1081,)
    assert np.all(far.ranges_mm < 20)
    assert set(np.unique(far.ranges_mm).tolist()) <= {1, 3}
    assert (far.ranges_mm == 1).mean() > 0.95
    assert np.all(np.isnan(far.ranges_m))

    # Right against a wall: near code 4 on the beams that hit it closer than 23 mm.
    near = simulate_scan(
        square_room(5.0),
        (4.99, 0.0, 0.0),
        m.with_(noise_sigma_m=0.0, dropout_prob=0.0),
        np.random.default_rng(0),
    )
    assert near.ranges_mm[540] == 4
    assert np.isnan(near.ranges_m[540])

    # Dropouts: a code from the model's list, NaN in metres, rate about as configured.
    drop = simulate_scan(
        square_room(5.0), (0.0, 0.0, 0.0), m.with_(dropout_prob=0.2), np.random.default_rng(1)
    )
    dropped = drop.ranges_mm < 20
    assert 0.12 < dropped.mean() < 0.28
    assert set(np.unique(drop.ranges_mm[dropped]).tolist()) == {3}
    assert np.all(np.isnan(drop.ranges_m[dropped]))


def test_noise_level_and_millimetres() -> None:
    m = LaserModel.utm30lx().with_(dropout_prob=0.0, noise_sigma_m=0.01)
    s = simulate_scan(square_room(5.0), (0.5, 0.5, 0.2), m, np.random.default_rng(2))
    valid = np.isfinite(s.ranges_m)
    assert valid.all()
    np.testing.assert_array_equal(s.ranges_m, s.ranges_mm / 1000.0)
    err = s.ranges_m - s.true_ranges_m
    assert 0.007 < float(np.std(err)) < 0.013
    assert abs(float(np.mean(err))) < 0.002


def test_sick_invalid_beams_read_zero() -> None:
    m = LaserModel.sick_lms200().with_(dropout_prob=0.0)
    s = simulate_scan(square_room(100.0), (0.0, 0.0, 0.0), m, np.random.default_rng(0))
    assert np.all(s.ranges_mm == 0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_paper_trajectory_loop_closes(paper_world: World, seed: int) -> None:
    traj = generate_trajectory(paper_world, seed)
    p = traj.poses
    assert traj.loop_length_m >= 400.0
    steps = np.hypot(np.diff(p[:, 0]), np.diff(p[:, 1]))
    assert steps.sum() >= 400.0
    assert np.all(steps <= 0.3 + 0.02)
    dth = np.abs((np.diff(p[:, 2]) + math.pi) % (2 * math.pi) - math.pi)
    assert np.all(dth <= math.radians(10.5))
    # Closes: the last pose is the first one again.
    assert np.hypot(*(p[-1, :2] - p[0, :2])) < 1e-6
    assert abs((p[-1, 2] - p[0, 2] + math.pi) % (2 * math.pi) - math.pi) < 1e-6
    # Time goes forward; poses stay clear of every wall.
    assert np.all(np.diff(traj.stamps_ns) > 0)
    assert traj.stamps_ns.dtype == np.int64
    assert paper_world.clearance_ok(p[:, :2], 0.3).all()


def test_trajectory_follows_motion_direction() -> None:
    w = generate_building(5, "small")
    p = generate_trajectory(w, 5).poses
    dx, dy = np.diff(p[:, 0]), np.diff(p[:, 1])
    moving = np.hypot(dx, dy) > 0.2
    travel = np.arctan2(dy, dx)[moving]
    err = (travel - p[:-1, 2][moving] + math.pi) % (2 * math.pi) - math.pi
    assert np.max(np.abs(err)) < math.radians(12.0)


def test_robot_motion_loops_forever_and_is_smooth() -> None:
    w = generate_building(2, "small")
    motion = RobotMotion(w, seed=4, speed_mps=0.7)
    period = motion.loop_period_s
    t = np.arange(0.0, period * 2.2, 0.025)  # 40 Hz over more than two laps
    poses = motion.poses_at(t)
    steps = np.hypot(np.diff(poses[:, 0]), np.diff(poses[:, 1]))
    assert np.all(steps < 0.7 * 0.025 * 1.3)
    assert w.clearance_ok(poses[::10, :2], 0.3).all()
    a, b = motion.pose_at(3.0), motion.pose_at(3.0 + period)
    assert np.allclose(a[:2], b[:2], atol=1e-6)
    assert isinstance(motion.pose_at(0.0)[0], float)


def test_clearance_raster_matches_walls(paper_world: World) -> None:
    # Points sampled at wall midpoints of Manhattan segments are next to solid cells.
    seg = paper_world.segments_m[:50]
    mid = (seg[:, :2] + seg[:, 2:]) / 2
    assert not paper_world.clearance_ok(mid, RASTER_RES_M * 1.5).any()
