"""OccupancyGrid: ray-cast free space, hits, sparse growth, snapshot conventions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sensor_agent.sim import LaserModel, World, simulate_scan
from service.core.maps.grid import TILE_CELLS, GridError, GridImage, OccupancyGrid
from service.core.maps.raycast import mark_cells
from service.core.types import LaserScan, Pose2D

RES = 0.05


def room(half_m: float = 3.0) -> World:
    h = half_m
    seg = np.array([[-h, -h, h, -h], [h, -h, h, h], [h, h, -h, h], [-h, h, -h, -h]], dtype=float)
    return World(0, "test", 2 * h, 2 * h, 2 * h, seg, np.zeros((0, 2)), np.ones((1, 1), bool))


def scan_of(world: World, pose: Pose2D, model: LaserModel | None = None) -> LaserScan:
    m = (model or LaserModel.utm30lx()).with_(noise_sigma_m=0.0, dropout_prob=0.0)
    s = simulate_scan(world, pose, m, np.random.default_rng(0))
    return LaserScan(
        0, m.angle_min_rad, m.angle_increment_rad, s.ranges_m, m.range_min_m, m.range_max_m
    )


def cell_value(img: GridImage, x: float, y: float) -> int:
    j = math.floor((x - img.origin_x_m) / img.resolution_m)
    i = math.floor((y - img.origin_y_m) / img.resolution_m)
    assert 0 <= i < img.height
    assert 0 <= j < img.width
    return int(img.occupancy[i, j])


def test_empty_grid_snapshot() -> None:
    g = OccupancyGrid()
    img = g.snapshot()
    assert img.occupancy.shape == (0, 0)
    assert img.resolution_m == 0.05
    assert g.tile_count == 0


def test_bad_parameters() -> None:
    with pytest.raises(GridError):
        OccupancyGrid(0.0)
    with pytest.raises(GridError):
        OccupancyGrid(l_free=0.2)


@pytest.mark.parametrize("pose", [Pose2D(0.0, 0.0, 0.0), Pose2D(0.7, -1.1, 2.0)])
def test_single_scan_in_a_room(pose: Pose2D) -> None:
    g = OccupancyGrid(RES)
    g.integrate(scan_of(room(3.0), pose), pose)
    img = g.snapshot()
    assert img.occupancy.dtype == np.int8
    # The wall ahead (x = +3) is occupied; the space between robot and wall is free.
    ahead = pose.theta_rad
    hit = cell_value(img, 2.99, pose.y_m) if abs(ahead) < 1.0 else None
    if hit is not None:
        assert hit > 65
    assert cell_value(img, pose.x_m + 0.5 * math.cos(ahead), pose.y_m + 0.5 * math.sin(ahead)) < 50
    # Walls seen in the 270 deg field of view are occupied cells, interior is free.
    occupied = img.occupancy > 50
    free = (img.occupancy >= 0) & (img.occupancy < 50)
    assert occupied.sum() > 200
    assert free.sum() > 5000
    # Nothing beyond the walls: the image ends at the walls.
    assert img.origin_x_m >= -3.0 - RES - 1e-9
    assert img.origin_x_m + img.width * RES <= 3.0 + RES + 1e-9


def test_row_zero_is_lowest_y() -> None:
    seg = np.array([[-5.0, 2.02, 5.0, 2.02]])  # a single wall above the robot
    w = World(0, "test", 10, 10, 10, seg, np.zeros((0, 2)), np.ones((1, 1), bool))
    g = OccupancyGrid(RES)
    pose = Pose2D(0.0, 0.0, math.pi / 2)
    g.integrate(scan_of(w, pose), pose)
    img = g.snapshot()
    occ_rows = np.nonzero((img.occupancy > 50).any(axis=1))[0]
    assert occ_rows.min() == img.height - 1  # the wall is the top (highest y) row
    assert img.origin_y_m + img.height * RES == pytest.approx(2.05, abs=1e-9)
    assert img.origin_y_m <= 0.0  # starts at the robot, below the wall


def test_each_cell_updated_once_per_scan_and_hits_win() -> None:
    g = OccupancyGrid(RES, l_occ=0.85, l_free=-0.4)
    pose = Pose2D(0.0, 0.0, 0.0)
    scan = scan_of(room(3.0), pose)
    g.integrate(scan, pose)
    g.integrate(scan, pose)
    img = g.snapshot()
    # Right next to the robot every beam passes the same cells: still only one update per scan.
    expected_free = round(100.0 / (1.0 + math.exp(0.8)))
    assert cell_value(img, 0.3, 0.0) == expected_free
    expected_occ = round(100.0 / (1.0 + math.exp(-1.7)))
    assert cell_value(img, 2.99, 0.0) == expected_occ


def test_log_odds_are_clamped() -> None:
    g = OccupancyGrid(RES, l_max=2.0, l_min=-1.0)
    pose = Pose2D(0.0, 0.0, 0.0)
    scan = scan_of(room(3.0), pose)
    for _ in range(10):
        g.integrate(scan, pose)
    dense, _, _ = g.log_odds()
    assert dense.max() == pytest.approx(2.0)
    assert dense.min() == pytest.approx(-1.0)


def test_invalid_beams_do_not_update() -> None:
    g = OccupancyGrid(RES)
    n = 1081
    ranges = np.full(n, np.nan)
    ranges[::7] = 35.0  # beyond range_max: invalid too
    scan = LaserScan(0, -3 * math.pi / 4, math.radians(0.25), ranges, 0.023, 30.0)
    g.integrate(scan, Pose2D(0.0, 0.0, 0.0))
    assert g.snapshot().occupancy.shape == (0, 0)
    assert g.scans_integrated == 1


def test_grows_sparsely_with_exploration() -> None:
    g = OccupancyGrid(RES)
    w = room(2.0)
    g.integrate(scan_of(w, Pose2D(0, 0, 0)), Pose2D(0, 0, 0))
    tiles_one, mem_one = g.tile_count, g.memory_bytes()
    # The same room seen 500 m away (negative coordinates): a second patch, not a 500 m map.
    far = Pose2D(-500.0, -300.0, 1.0)
    g.integrate(scan_of(w, Pose2D(0, 0, 1.0)), far)
    assert g.tile_count == pytest.approx(2 * tiles_one, abs=4)
    assert g.memory_bytes() < 20 * mem_one
    img = g.snapshot()
    side = TILE_CELLS * RES
    assert img.width * RES > 500.0 - 2 * side  # the snapshot spans both patches
    assert cell_value(img, -500.0 + 0.3 * math.cos(1.0), -300.0 + 0.3 * math.sin(1.0)) < 50


@pytest.mark.parametrize(
    "model", [LaserModel.utm30lx(), LaserModel.sick_lms200(), LaserModel.urg04lx()]
)
def test_sensor_agnostic(model: LaserModel) -> None:
    g = OccupancyGrid(RES)
    pose = Pose2D(0.2, 0.1, 0.3)
    g.integrate(scan_of(room(2.5), pose, model), pose)
    img = g.snapshot()
    assert (img.occupancy > 50).sum() > 50
    assert cell_value(img, 0.2 + math.cos(0.3), 0.1 + math.sin(0.3)) < 50


def test_free_space_has_no_holes_near_robot() -> None:
    # The near-field beam subsets must still cover every cell inside the field of view.
    g = OccupancyGrid(RES)
    pose = Pose2D(0.0, 0.0, 0.0)
    g.integrate(scan_of(room(3.0), pose), pose)
    img = g.snapshot()
    r = np.linspace(0.1, 2.8, 60)
    a = np.linspace(-2.2, 2.2, 120)
    rr, aa = np.meshgrid(r, a)
    for x, y in zip((rr * np.cos(aa)).ravel(), (rr * np.sin(aa)).ravel(), strict=True):
        if max(abs(x), abs(y)) < 2.85:
            assert 0 <= cell_value(img, float(x), float(y)) < 50


def _numpy_ray_samples(
    start_m: np.ndarray, end_m: np.ndarray, step_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The numpy ray casting the compiled one replaced (`maps.raycast`): (beam, t)."""
    counts = np.maximum(np.ceil((end_m - start_m) / step_m), 0.0).astype(np.int64)
    first = np.cumsum(counts) - counts
    beam_of = np.repeat(np.arange(start_m.shape[0], dtype=np.int64), counts)
    t = np.repeat(start_m, counts) + step_m * (
        np.arange(int(counts.sum())) - np.repeat(first, counts)
    )
    return beam_of, t


def _numpy_mark(grid: OccupancyGrid, scan: LaserScan, pose: Pose2D) -> tuple[np.ndarray, int, int]:
    """The scan-local window of cells crossed (1) and hit (2), as numpy drew it: (mark, i0, j0)."""
    res = grid.resolution_m
    beams = np.nonzero(scan.valid_mask())[0]
    ranges = scan.ranges_m[beams]
    ang = scan.angles_rad()[beams] + pose.theta_rad
    starts = grid._near_starts(scan.ranges_m.shape[0], scan.angle_increment_rad)[beams]
    ends = ranges - 0.5 * res
    split_m = res / abs(scan.angle_increment_rad)
    fine_end = np.minimum(ends, split_m)
    b_fine, t_fine = _numpy_ray_samples(starts, fine_end, grid.sample_step_m)
    b_coarse, t_coarse = _numpy_ray_samples(np.maximum(starts, fine_end), ends, res)
    beam_of, t = np.concatenate((b_fine, b_coarse)), np.concatenate((t_fine, t_coarse))
    cs, sn = np.cos(ang) * (1.0 / res), np.sin(ang) * (1.0 / res)
    fx, fy = pose.x_m * (1.0 / res), pose.y_m * (1.0 / res)
    free_i = np.floor(fy + t * sn[beam_of]).astype(np.int64)
    free_j = np.floor(fx + t * cs[beam_of]).astype(np.int64)
    hit_i = np.floor(fy + ranges * sn).astype(np.int64)
    hit_j = np.floor(fx + ranges * cs).astype(np.int64)
    i0 = min(int(hit_i.min()), math.floor(fy))
    j0 = min(int(hit_j.min()), math.floor(fx))
    i1 = max(int(hit_i.max()), math.floor(fy))
    j1 = max(int(hit_j.max()), math.floor(fx))
    width = j1 - j0 + 1
    mark = np.zeros((i1 - i0 + 1) * width, dtype=np.int8)
    mark[(free_i - i0) * width + (free_j - j0)] = 1
    mark[(hit_i - i0) * width + (hit_j - j0)] = 2
    return mark, i0, j0


def test_the_compiled_ray_casting_marks_the_cells_numpy_did() -> None:
    """`maps.raycast.mark_cells` does numpy's floating-point operations in numpy's order: the
    same cells, over poses anywhere (negative cells, headings all round) and dropouts."""
    rng = np.random.default_rng(7)
    world = room(12.0)
    grid = OccupancyGrid(RES)
    for _ in range(40):
        pose = Pose2D(*rng.uniform(-11.0, 11.0, 2), float(rng.uniform(-math.pi, math.pi)))
        scan = scan_of(world, pose)
        ranges = scan.ranges_m.copy()
        ranges[rng.random(ranges.shape[0]) < 0.1] = np.nan
        scan = LaserScan(0, scan.angle_min_rad, scan.angle_increment_rad, ranges, 0.02, 30.0)
        expected, i0, j0 = _numpy_mark(grid, scan, pose)
        beams = np.nonzero(scan.valid_mask())[0]
        ang = scan.angles_rad()[beams] + pose.theta_rad
        inv = 1.0 / RES
        starts = grid._near_starts(ranges.shape[0], scan.angle_increment_rad)[beams]
        split_m = RES / abs(scan.angle_increment_rad)
        mark, ci0, cj0, _ = mark_cells(
            pose.x_m * inv, pose.y_m * inv, np.cos(ang) * inv, np.sin(ang) * inv,
            scan.ranges_m[beams], starts, split_m, RES, grid.sample_step_m,
        )  # fmt: skip
        assert (ci0, cj0) == (i0, j0)
        np.testing.assert_array_equal(mark, expected)
