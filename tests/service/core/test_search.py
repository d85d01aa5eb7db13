"""The branch-and-bound search (`service.core.frontend.search`) returns the brute force's lattice
optimum: on random submaps, scans and priors, with and without the walls' prior, predictions off
the grid's edge, and grids that hold nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scenes import PARAMS, grid_of, matched_points, scan_of, world_of

from sensor_agent.sim.world import World
from service.core.frontend.likelihood import LikelihoodGrid, off_surface_cost
from service.core.frontend.matcher import (
    MatchOptions,
    Priors,
    _brute_force_search,
    _scored_points,
    _window,
    search,
)
from service.core.frontend.scan_matcher import surface_in_map
from service.core.frontend.search import (
    _SLACK,
    MAX_LEVEL,
    CostPyramid,
    Lattice,
    _Problem,
    build_pyramid,
    pyramid_of,
)
from service.core.types import Pose2D, wrap_angle

pytestmark = pytest.mark.timeout(120)

CAP = off_surface_cost(3.0)


def _world(rng: np.random.Generator) -> World:
    """A 12 × 9 m room with random boxes and wall stubs inside."""
    segs = [[0, 0, 12, 0], [12, 0, 12, 9], [12, 9, 0, 9], [0, 9, 0, 0]]
    for _ in range(int(rng.integers(3, 8))):
        x, y = rng.uniform(1.0, 11.0), rng.uniform(1.0, 8.0)
        w, h = rng.uniform(0.2, 1.2), rng.uniform(0.2, 1.2)
        segs += [[x, y, x + w, y], [x + w, y, x + w, y + h], [x + w, y + h, x, y + h]]
        segs += [[x, y + h, x, y]]
    return world_of(segs, 12.0, 9.0)


def _random_cov(rng: np.random.Generator, sigma_m: float, sigma_rad: float) -> np.ndarray:
    """A full covariance (correlated axes) of roughly these σ."""
    a = rng.normal(size=(3, 3)) * 0.4 + np.eye(3)
    s = np.diag([sigma_m, sigma_m, sigma_rad])
    return s @ (a @ a.T) @ s / 2.0 + np.diag([1e-6, 1e-6, 1e-8])


def _random_case(seed: int) -> tuple[LikelihoodGrid, np.ndarray, Priors, MatchOptions]:
    rng = np.random.default_rng(seed)
    world = _world(rng)
    poses = [Pose2D(rng.uniform(3, 9), rng.uniform(2.5, 6.5), rng.uniform(-math.pi, math.pi))]
    for _ in range(int(rng.integers(0, 3))):
        p = poses[-1]
        poses.append(Pose2D(p.x_m + rng.normal(0, 0.3), p.y_m + rng.normal(0, 0.3), p.theta_rad))
    grid = grid_of([(scan_of(world, p, rng), p) for p in poses])
    truth = Pose2D(
        poses[0].x_m + rng.normal(0, 0.2),
        poses[0].y_m + rng.normal(0, 0.2),
        poses[0].theta_rad + rng.normal(0, 0.05),
    )
    pts = matched_points(scan_of(world, truth, rng))
    wide = bool(rng.integers(0, 2))  # the paper's spacing, or 40 Hz
    cov = _random_cov(rng, 0.2, math.radians(8.0)) if wide else _random_cov(rng, 0.02, 0.02)
    predicted = Pose2D(
        truth.x_m + rng.normal(0, 1.5 * math.sqrt(cov[0, 0])),
        truth.y_m + rng.normal(0, 1.5 * math.sqrt(cov[1, 1])),
        truth.theta_rad + rng.normal(0, 1.5 * math.sqrt(cov[2, 2])),
    )
    wall, wall_sigma = None, math.inf
    if rng.integers(0, 2):
        wall = truth.theta_rad + rng.normal(0, math.radians(1.0))
        wall_sigma = math.radians(rng.uniform(0.2, 3.0))
    opts = MatchOptions(search_points=int(rng.choice([50, 200])))
    return grid, pts, Priors(predicted, cov, wall, wall_sigma), opts


@pytest.mark.parametrize("seed", range(60))
def test_branch_and_bound_returns_the_brute_force_optimum(seed: int) -> None:
    grid, pts, priors, opts = _random_case(seed)
    expected, _ = _brute_force_search(grid, pts, priors, opts)
    got, scored = search(grid, pts, priors, opts)
    assert got == expected
    assert scored > 0


@pytest.mark.parametrize("seed", range(4))
def test_the_same_optimum_with_a_huber_wall_prior_far_off(seed: int) -> None:
    """A wall prior that disagrees with the prediction (its linear, Huber part in play)."""
    grid, pts, priors, opts = _random_case(100 + seed)
    off = Priors(priors.predicted, priors.cov_pred, priors.predicted.theta_rad + 0.05, 0.002)
    assert search(grid, pts, off, opts)[0] == _brute_force_search(grid, pts, off, opts)[0]


@pytest.mark.parametrize("dx_m", [-30.0, -6.2, 6.5, 40.0])
def test_the_same_optimum_off_the_grid_edge(dx_m: float) -> None:
    """A prediction past the submap's edge: part or all of the scan lands off the grid, where
    cells cost what no surface costs."""
    grid, pts, priors, opts = _random_case(7)
    w = grid.values.shape[1]
    edge_x = grid.origin_m[0] + (w if dx_m > 0 else 0) * grid.resolution_m
    p = Pose2D(edge_x + (dx_m if abs(dx_m) > 10 else 0.3 * dx_m / abs(dx_m)), 4.0, 0.2)
    for wall in (None, 0.21):
        pr = Priors(p, priors.cov_pred, wall, math.radians(1.0) if wall else math.inf)
        assert search(grid, pts, pr, opts)[0] == _brute_force_search(grid, pts, pr, opts)[0]


def test_the_search_reaches_the_edge_of_its_window() -> None:
    """The window is ±3σ of the prediction rounded up to whole cells: with σ = 9.5 cm, six
    cells (30 cm) each way. A scan whose truth is six cells off in x and in y (and in -x, -y)
    is found there, on the lattice, exactly; a window a cell short would stop 5 cm away."""
    rng = np.random.default_rng(12)
    world = _world(rng)
    truth = Pose2D(6.0, 4.5, 0.4)
    scan = scan_of(world, truth, rng)
    grid = grid_of([(scan, truth)])
    pts = matched_points(scan)
    cov = np.diag([0.095**2, 0.095**2, math.radians(2.0) ** 2])
    for sx, sy in ((1, 1), (-1, -1), (1, -1)):
        predicted = Pose2D(truth.x_m + sx * 0.30, truth.y_m + sy * 0.30, truth.theta_rad)
        got, _ = search(grid, pts, Priors(predicted, cov), MatchOptions())
        assert abs(got.x_m - truth.x_m) < 1e-6
        assert abs(got.y_m - truth.y_m) < 1e-6
        assert abs(got.theta_rad - truth.theta_rad) < 1e-9


def _problem(seed: int, wall_off_rad: float | None, wall_sigma_rad: float) -> _Problem:
    """The search's problem (`matcher.search`'s lattice) of a random case, with a walls' prior
    `wall_off_rad` from the prediction (None: none)."""
    grid, pts, priors, opts = _random_case(seed)
    p = priors.predicted
    wall = None if wall_off_rad is None else p.theta_rad + wall_off_rad
    pr = Priors(p, priors.cov_pred, wall, wall_sigma_rad if wall is not None else math.inf)
    pts = _scored_points(pts, opts)
    thetas, ny, nx = _window(grid, pts, pr, opts)
    lattice = Lattice(
        thetas, ny, nx, (p.x_m, p.y_m), p.theta_rad, np.linalg.inv(pr.cov_pred),
        opts.scan_weight, pr.wall_heading_rad, pr.wall_sigma_rad, opts.wall_huber,
    )  # fmt: skip
    costs = grid.residual_costs(opts.max_residual_sigmas)
    return _Problem(grid, pyramid_of(grid, costs, CAP), pts, lattice)


@pytest.mark.parametrize(("wall_off_rad", "wall_sigma_rad"), [(None, 0.0), (0.03, 0.002)])
def test_a_blocks_bound_is_below_every_pose_in_it(
    wall_off_rad: float | None, wall_sigma_rad: float
) -> None:
    """What branch and bound rests on: a block's bound is at most the exact cost of every pose
    in it (up to the pruning slack), for blocks of every size anywhere on the lattice, with
    correlated priors and with a tight walls' prior off the prediction (its Huber part)."""
    checked = 0
    for seed in range(8):
        prob = _problem(seed, wall_off_rad, wall_sigma_rad)
        rng = np.random.default_rng(seed)
        for _ in range(40):
            ka, d = int(rng.integers(0, 5)), int(rng.integers(0, 4))
            k0 = int(rng.integers(0, prob.n_rot))
            a0, b0 = int(rng.integers(0, prob.n_rows)), int(rng.integers(0, prob.n_cols))
            one = np.ones(1, dtype=np.int64)
            bound = float(prob.bound(k0 * one, a0 * one, b0 * one, ka, d)[0])
            k1 = min(k0 + (1 << ka), prob.n_rot)
            a1, b1 = min(a0 + (1 << d), prob.n_rows), min(b0 + (1 << d), prob.n_cols)
            kk, aa, bb = (
                g.ravel().astype(np.int64)
                for g in np.meshgrid(
                    np.arange(k0, k1), np.arange(a0, a1), np.arange(b0, b1), indexing="ij"
                )
            )
            lowest = float(prob.exact(kk, aa, bb).min())
            assert bound <= lowest + _SLACK * (1.0 + abs(lowest)), (seed, k0, a0, b0, ka, d)
            checked += 1
    assert checked == 320


def test_an_empty_grid_returns_the_prediction() -> None:
    _, pts, priors, opts = _random_case(3)
    grid = LikelihoodGrid(PARAMS.resolution_m, PARAMS.hit_sigma_m)
    assert search(grid, pts, priors, opts) == (priors.predicted, 0)
    grid.insert(np.zeros((0, 2)))  # a scan with no points: still nothing
    assert search(grid, pts, priors, opts) == (priors.predicted, 0)
    assert search(grid, pts[:0], priors, opts) == (priors.predicted, 0)


def test_a_grid_without_surfaces_gives_the_priors_optimum() -> None:
    """Every cell costs the same: the priors alone decide, as they do in the brute force."""
    _, pts, priors, opts = _random_case(5)
    grid = LikelihoodGrid(PARAMS.resolution_m, PARAMS.hit_sigma_m)
    grid.values = np.zeros((64, 64), dtype=np.float32)
    grid.known = np.zeros((16, 16), dtype=np.bool_)
    grid.origin_m = (priors.predicted.x_m - 1.0, priors.predicted.y_m - 1.0)
    for wall in (None, priors.predicted.theta_rad + 0.01):
        pr = Priors(priors.predicted, priors.cov_pred, wall, 0.01 if wall else math.inf)
        assert search(grid, pts, pr, opts)[0] == _brute_force_search(grid, pts, pr, opts)[0]


@pytest.mark.parametrize("seed", range(16))
def test_a_small_lattice_scored_whole_is_the_brute_force_ties_included(seed: int) -> None:
    """A lattice small enough is scored whole (`kernels.dense_search`, reading the cost table
    itself, without the pyramid). On tables of one value (every pose costs the same) or two
    (the cap and 0: poses with as many points on a surface cost the same), with priors too
    broad to break the ties, and points partly off the grid: the brute force's pose, its first
    minimum (lowest rotation, then row, then column), with and without the walls' prior."""
    rng = np.random.default_rng(seed)
    grid = LikelihoodGrid(PARAMS.resolution_m, PARAMS.hit_sigma_m)
    h, w = (int(x) for x in rng.integers(6, 50, size=2))
    surface = 0.0 if seed % 4 == 1 else rng.uniform(0.02, 0.5)
    grid.values = (rng.random((h, w)) < surface).astype(np.float32)
    grid.known = np.zeros((h // 4 + 1, w // 4 + 1), dtype=np.bool_)
    grid.origin_m = (rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0))
    res = grid.resolution_m
    centre = np.array(grid.origin_m) + rng.uniform(-0.2, 1.2, size=2) * (w * res, h * res)
    pts = rng.normal(0.0, rng.uniform(0.2, 2.0), size=(int(rng.integers(1, 300)), 2))
    # Broad: the priors' terms (1e-16 × under 0.03 m² or rad²) vanish against any scan cost but
    # 0 (the least is 50 × the cap / 300 points: its half ulp is 1e-16).
    broad = np.diag([1e16, 1e16, 1e16]) if seed % 2 else np.diag([1e-2, 4e-2, 1e-3])
    opts = MatchOptions(
        search_points=int(rng.choice([7, 50, 200])),
        search_max_m=float(rng.choice([0.05, 0.1, 0.15])),
        search_max_rad=math.radians(float(rng.uniform(0.5, 3.0))),
    )
    predicted = Pose2D(float(centre[0]), float(centre[1]), float(rng.uniform(-math.pi, math.pi)))
    for wall in (None, predicted.theta_rad + 0.005):
        priors = Priors(predicted, broad, wall, 1e8 if wall is not None else math.inf)
        got, scored = search(grid, pts, priors, opts)
        want, poses = _brute_force_search(grid, pts, priors, opts)
        assert poses <= 2048  # scored whole
        assert (got, scored) == (want, poses)
        if surface == 0.0:  # every pose ties: the first
            thetas, ny, nx = _window(grid, _scored_points(pts, opts), priors, opts)
            first = Pose2D(
                predicted.x_m - nx * res, predicted.y_m - ny * res, wrap_angle(thetas[0])
            )
            assert got == first


def test_pyramid_levels_are_the_minimum_over_their_window() -> None:
    """Level m at a cell = min of the costs over the 2^m × 2^m cells above and right of it,
    with everything off the table costing the cap, wherever the anchor is."""
    rng = np.random.default_rng(0)
    costs = np.full((40, 50), CAP, dtype=np.float32)
    costs[5:30, 8:45] = rng.uniform(0.0, 9.0, size=(25, 37)).astype(np.float32)
    pyr = build_pyramid(costs, CAP, max_level=4)
    big = np.full((300, 300), CAP, dtype=np.float32)
    big[100:140, 100:150] = costs  # the table, off-table cells at the cap, table at (100, 100)
    rows = rng.integers(-90, 130, size=400)
    cols = rng.integers(-90, 140, size=400)
    levels = rng.integers(0, 6, size=400)
    got = pyr.lookup(levels, rows, cols)
    for r, c, m, g in zip(rows, cols, levels, got, strict=True):
        if m > 4:
            assert g == min(costs.min(), np.float32(CAP))
        else:
            s = 1 << m
            assert g == big[100 + r : 100 + r + s, 100 + c : 100 + c + s].min()


def test_the_pyramid_is_cached_until_the_submap_changes() -> None:
    grid, _, _, _ = _random_case(1)
    costs = grid.residual_costs(3.0)
    first = pyramid_of(grid, costs, CAP)
    assert pyramid_of(grid, grid.residual_costs(3.0), CAP) is first
    version = grid.costs_version
    grid.insert(np.array([[5.0, 5.0], [5.1, 5.0]]))
    assert grid.residual_costs(3.0) is costs  # updated in place, over the inserted box
    assert grid.costs_version > version


def _same_lookups(a: CostPyramid, b: CostPyramid, rng: np.random.Generator, box: tuple) -> None:
    r0, r1, c0, c1 = box
    rows = rng.integers(r0 - 80, r1 + 80, size=20000)
    cols = rng.integers(c0 - 80, c1 + 80, size=20000)
    levels = rng.integers(0, MAX_LEVEL + 2, size=20000)
    assert np.array_equal(a.lookup(levels, rows, cols), b.lookup(levels, rows, cols))


def test_inserts_update_the_cost_table_and_pyramid_as_rebuilding_them_would() -> None:
    """Scan after scan into one submap, moving out of what it held (in place where the crop
    holds the change, rebuilt where it does not): the cost table is the one computed whole, bit
    for bit, and the pyramid looks up what a pyramid built afresh looks up."""
    rng = np.random.default_rng(11)
    world = _world(rng)
    grid = LikelihoodGrid(PARAMS.resolution_m, PARAMS.hit_sigma_m)
    pose = Pose2D(2.0, 2.0, 0.3)
    for step in range(12):
        scan = scan_of(world, pose, rng)
        grid.insert(surface_in_map(scan.points_xy_m(), pose, PARAMS))
        costs = grid.residual_costs(3.0)
        fresh = LikelihoodGrid(PARAMS.resolution_m, PARAMS.hit_sigma_m)
        fresh.values = grid.values.copy()
        assert np.array_equal(costs, fresh.residual_costs(3.0))
        pyr = pyramid_of(grid, costs, CAP)
        h, w = costs.shape
        _same_lookups(pyr, build_pyramid(costs, CAP), rng, (0, h, 0, w))
        pose = Pose2D(pose.x_m + 0.7, pose.y_m + 0.4 * (step % 3 - 1), pose.theta_rad + 0.1)
