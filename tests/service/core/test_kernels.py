"""The compiled inner loops (`service.core.frontend.kernels`) compute what the numpy code they
stand for computes: bit for bit, the search's lookups and the submaps' inserts; to rounding, the
refinement's sums over the field's bicubic interpolation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scenes import PARAMS, grid_of, matched_points, scan_of, world_of

from service.core.frontend import heading, kernels
from service.core.frontend.likelihood import LikelihoodGrid, off_surface_cost, residual_sq
from service.core.frontend.scan_matcher import surface_in_map
from service.core.frontend.search import build_pyramid
from service.core.maps.submaps import sliding_max
from service.core.types import Pose2D, rotate_points

pytestmark = pytest.mark.timeout(120)


def _room() -> tuple[LikelihoodGrid, np.ndarray, np.random.Generator]:
    rng = np.random.default_rng(4)
    segs = [[0, 0, 10, 0], [10, 0, 10, 7], [10, 7, 0, 7], [0, 7, 0, 0], [4, 2, 5, 2], [5, 2, 5, 3]]
    world = world_of(segs, 10.0, 7.0)
    poses = [Pose2D(3.0, 3.5, 0.1), Pose2D(3.3, 3.6, 0.15)]
    grid = grid_of([(scan_of(world, p, rng), p) for p in poses])
    pts = matched_points(scan_of(world, Pose2D(3.1, 3.4, 0.12), rng))
    return grid, pts, rng


def _numpy_terms(
    grid: LikelihoodGrid, pts: np.ndarray, pose: Pose2D
) -> tuple[np.ndarray, np.ndarray]:
    """Each point's field value and r² at `pose`, as numpy computes them (the reference)."""
    q = rotate_points(pts, pose.theta_rad) + np.array([pose.x_m, pose.y_m])
    value, _ = grid.interpolate(q)
    return value, residual_sq(value, 3.0)


def _scan_terms(
    grid: LikelihoodGrid, pts: np.ndarray, pose: Pose2D
) -> tuple[float, float, np.ndarray, np.ndarray]:
    ox, oy = grid.origin_m
    c, s = math.cos(pose.theta_rad), math.sin(pose.theta_rad)
    return kernels.scan_terms(
        grid.values, ox, oy, grid.resolution_m, pts, c, s, pose.x_m, pose.y_m, 3.0
    )


@pytest.mark.parametrize("seed", range(5))
def test_scan_terms_sum_the_grids_own_field(seed: int) -> None:
    """The one-pass sums Σ r² and Σ M are numpy's over `LikelihoodGrid.interpolate` and
    `residual_sq`, to rounding (the sums' order differs: sequential, not pairwise), on the
    submap and far off it (points off the grid read 0, at the cap)."""
    grid, pts, _ = _room()
    rng = np.random.default_rng(seed)
    for _ in range(20):
        pose = Pose2D(rng.uniform(-20, 30), rng.uniform(-20, 30), rng.uniform(-math.pi, math.pi))
        if rng.integers(0, 2):
            pose = Pose2D(rng.normal(3.1, 0.2), rng.normal(3.4, 0.2), rng.normal(0.12, 0.05))
        value, r_sq = _numpy_terms(grid, pts, pose)
        sum_r_sq, sum_value, _, _ = _scan_terms(grid, pts, pose)
        assert sum_r_sq == pytest.approx(float(r_sq.sum()), rel=1e-12, abs=1e-12)
        assert sum_value == pytest.approx(float(value.sum()), rel=1e-12, abs=1e-12)


def test_scan_terms_derivatives_are_the_residuals() -> None:
    """Σ ∂(r²/2)/∂(x, y, θ) and the Gauss-Newton Σ JᵀJ (J = ∂r/∂pose) against central
    differences of numpy's r = √(-2 ln M) over the pose, on the points where r is smooth (well
    off the surface, where it is held off 0, and inside the cap): within 1e-4 (measured:
    1e-7)."""
    grid, pts, _ = _room()
    pose = Pose2D(3.12, 3.38, 0.125)
    r = np.sqrt(_numpy_terms(grid, pts, pose)[1])
    smooth = (r > 0.5) & (r < 2.5)
    assert smooth.sum() > 100
    pts = np.ascontiguousarray(pts[smooth])
    steps = (1e-5, 1e-5, 1e-6)
    num = np.zeros((pts.shape[0], 3))
    for axis, h in enumerate(steps):
        e = np.zeros(3)
        e[axis] = h
        plus = _numpy_terms(
            grid, pts, Pose2D(pose.x_m + e[0], pose.y_m + e[1], pose.theta_rad + e[2])
        )
        minus = _numpy_terms(
            grid, pts, Pose2D(pose.x_m - e[0], pose.y_m - e[1], pose.theta_rad - e[2])
        )
        num[:, axis] = (np.sqrt(plus[1]) - np.sqrt(minus[1])) / (2.0 * h)
    _, _, half_grad, jtj = _scan_terms(grid, pts, pose)
    r = r[smooth]
    want_half = (r[:, None] * num).sum(axis=0)  # ∂(r²/2) = r ∂r
    assert np.linalg.norm(half_grad - want_half) <= 1e-4 * np.linalg.norm(want_half)
    want_jtj = num.T @ num
    assert np.linalg.norm(jtj - want_jtj) <= 1e-4 * np.linalg.norm(want_jtj)


def test_lattice_gather_is_numpys_lookup_bit_for_bit() -> None:
    """30 poses on 8 rotations, so each rotation's cells are computed once and reused."""
    grid, pts, rng = _room()
    cap = off_surface_cost(3.0)
    pyr = build_pyramid(grid.residual_costs(3.0), cap)
    thetas = rng.uniform(-math.pi, math.pi, 8)
    k = rng.integers(0, 8, 30)
    cos_t, sin_t = np.cos(thetas), np.sin(thetas)
    di, dj = rng.integers(-40, 40, 30), rng.integers(-40, 40, 30)
    px, py = np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1])
    tx, ty = 3.1, 3.4
    ox, oy = grid.origin_m
    res = grid.resolution_m
    cells = np.empty((8, 2, px.shape[0]), dtype=np.int64)
    celled = np.zeros(8, dtype=np.bool_)
    got = kernels.lattice_gather(
        pyr.flat, pyr.row0, pyr.col0, pyr.height, pyr.width, px, py, cos_t, sin_t, k, di, dj,
        tx, ty, ox, oy, res, cells, celled,
    )  # fmt: skip
    assert celled[np.unique(k)].all()
    cos_k, sin_k = cos_t[k], sin_t[k]
    mx = cos_k[:, None] * px - sin_k[:, None] * py + tx
    my = sin_k[:, None] * px + cos_k[:, None] * py + ty
    rows = np.rint((my - oy) / res - 0.5).astype(np.int64) + di[:, None]
    cols = np.rint((mx - ox) / res - 0.5).astype(np.int64) + dj[:, None]
    want = pyr.lookup(np.zeros_like(rows), rows, cols)
    assert np.array_equal(got, want)


def test_the_pairwise_sum_is_numpys_mean_bit_for_bit() -> None:
    """`dense_search`'s means: numpy's `mean(axis=1, dtype=float64)` of float32 rows, bit for
    bit, at every length to 300 (blocks of 8 and 128, their remainders, the halving above 128)
    and lengths past numpy's 8,192-value buffer, on values spread over twelve decades, on the
    cost table's few values, and on rows of -0.0 (numpy adds its sum to 0.0)."""
    rng = np.random.default_rng(2)
    lengths = [*range(1, 301), 511, 512, 1023, 1024, 1025, 8191, 8192, 8193, 10000, 20001]
    for n in lengths:
        spread = (rng.uniform(0, 9, (3, n)) * 10 ** rng.uniform(-6, 6, (3, n))).astype(np.float32)
        few = rng.choice(np.float32([8.999, 0.1, 3.3e-5, 1e-3, 7.25, -0.0]), (3, n))
        for rows in (spread, few, np.full((1, n), -0.0, dtype=np.float32)):
            ops, starts, lengths_ = kernels._pairwise_plan(n)
            sums = np.empty(64)
            got = np.array(
                [kernels._pairwise_sum(r.astype(np.float64), ops, starts, lengths_, sums) / n
                 for r in rows]
            )  # fmt: skip
            want = rows.mean(axis=1, dtype=np.float64)
            assert np.array_equal(got.view(np.int64), want.view(np.int64)), n


def _numpy_insert(grid: LikelihoodGrid, points_map_m: np.ndarray) -> None:
    """`LikelihoodGrid.insert` as numpy alone computes it (the reference of the kernels)."""
    grid._ensure(points_map_m)
    res, rad = grid.resolution_m, grid.radius_cells
    v, u = grid.cell_coords(points_map_m)
    ci, cj = np.rint(v).astype(np.int64), np.rint(u).astype(np.int64)
    ii = ci[:, None] + grid._di[None, :]
    jj = cj[:, None] + grid._dj[None, :]
    d2 = ((ii - v[:, None]) ** 2 + (jj - u[:, None]) ** 2) * (res * res)
    val = np.exp(-0.5 * d2 / grid.hit_sigma_m**2).ravel()
    flat = (ii * grid.values.shape[1] + jj).ravel()
    order = np.argsort(flat, kind="stable")
    cells = flat[order]
    starts = np.flatnonzero(np.diff(cells, prepend=-1))
    grid.density.reshape(-1)[cells[starts]] += np.add.reduceat(val[order], starts).astype(
        np.float32
    )
    h, w = grid.values.shape
    i0, i1 = int(ci.min()) - rad, int(ci.max()) + rad + 1
    j0, j1 = int(cj.min()) - rad, int(cj.max()) + rad + 1
    a0, a1, b0, b1 = max(0, i0 - rad), min(h, i1 + rad), max(0, j0 - rad), min(w, j1 + rad)
    block = grid.density[a0:a1, b0:b1]
    padded = np.pad(block, ((rad, 0), (rad, 0)))
    peak = sliding_max(padded, 2 * rad + 1)[: block.shape[0], : block.shape[1]]
    field = np.where(peak > 1e-3, block / np.maximum(peak, 1e-3), 0.0).astype(np.float32)
    r0, r1, c0, c1 = max(0, i0) - a0, min(h, i1) - a0, max(0, j0) - b0, min(w, j1) - b0
    grid.values[a0 + r0 : a0 + r1, b0 + c0 : b0 + c1] = field[r0:r1, c0:c1]


def test_insert_is_numpys_bit_for_bit() -> None:
    """Scans moving through a room, inserted by the kernels and by numpy alone: the same
    density and field, bit for bit."""
    rng = np.random.default_rng(8)
    segs = [[0, 0, 10, 0], [10, 0, 10, 7], [10, 7, 0, 7], [0, 7, 0, 0], [4, 2, 5, 2], [5, 2, 5, 3]]
    world = world_of(segs, 10.0, 7.0)
    ours = LikelihoodGrid(PARAMS.resolution_m, PARAMS.hit_sigma_m)
    ref = LikelihoodGrid(PARAMS.resolution_m, PARAMS.hit_sigma_m)
    for step in range(8):
        pose = Pose2D(1.5 + 0.9 * step, 3.5 + 0.3 * math.sin(step), 0.2 * step)
        pts = surface_in_map(scan_of(world, pose, rng).points_xy_m(), pose, PARAMS)
        ours.insert(pts)
        _numpy_insert(ref, pts)
        assert ours.origin_m == ref.origin_m
        assert np.array_equal(ours.density, ref.density)
        assert np.array_equal(ours.values, ref.values)


def _numpy_hard_counts(points: np.ndarray, angles: np.ndarray, bin_m: float) -> np.ndarray:
    """The hard projection histograms (2K, width) as numpy computes them: each coordinate
    x·c₀ + y·c₁ in bin units as two products and a sum (a matrix product may round otherwise),
    shifted by `_hard_offset`, truncated to its bin and counted by `np.bincount`."""
    k = angles.shape[0]
    lo, width = heading._hard_offset(points, bin_m)
    columns = heading._rotation_columns(angles, bin_m)
    proj = points[:, 0:1] * columns[0] + points[:, 1:2] * columns[1]
    idx = (proj - float(lo)).astype(np.intp) + np.arange(2 * k, dtype=np.intp) * width
    counts = np.bincount(idx.ravel(), minlength=2 * k * width)[: 2 * k * width]
    return counts.reshape(2 * k, width)


def _numpy_carved_insert(
    grid: LikelihoodGrid, points_map_m: np.ndarray, origin_m: tuple[float, float], ends: np.ndarray
) -> None:
    """`LikelihoodGrid.insert` with free space carved, as numpy computes it (the reference of
    the fused kernels): the stamps (`_numpy_insert`), a hit and this insert's mark per stamped
    cell, the field × hits / max(hits + misses, 1) over the whole box in float32 with numpy's
    temporaries, then the rays (`kernels.carve`, as the grid calls it)."""
    grid.inserted += 1
    grid._ensure(np.vstack((points_map_m, [origin_m], ends)))
    rad = grid.radius_cells
    v, u = grid.cell_coords(points_map_m)
    ci, cj = np.rint(v).astype(np.int64), np.rint(u).astype(np.int64)
    cells = np.unique(
        ((ci[:, None] + grid._di) * grid.values.shape[1] + cj[:, None] + grid._dj).ravel()
    )
    _numpy_insert(grid, points_map_m)
    grid.hits.reshape(-1)[cells] += np.float32(1.0)
    grid.stamped.reshape(-1)[cells] = grid.inserted
    h, w = grid.values.shape
    i0, i1 = max(0, int(ci.min()) - rad), min(h, int(ci.max()) + rad + 1)
    j0, j1 = max(0, int(cj.min()) - rad), min(w, int(cj.max()) + rad + 1)
    hits = grid.hits[i0:i1, j0:j1]
    seen = hits + grid.misses[i0:i1, j0:j1]
    ratio = np.where(seen > 0.0, hits / np.maximum(seen, 1.0), 1.0).astype(np.float32)
    grid.values[i0:i1, j0:j1] *= ratio
    orig_v, orig_u = grid.cell_coords(np.asarray([origin_m]))
    end_v, end_u = grid.cell_coords(ends)
    kernels.carve(
        grid.density, grid.values, grid.hits, grid.misses, grid.stamped, grid.inserted, rad,
        float(orig_v[0]), float(orig_u[0]), end_v, end_u, grid.carve_margin_m / grid.resolution_m,
    )  # fmt: skip


def test_carved_insert_is_numpys_bit_for_bit() -> None:
    """Keyframes moving through a room past a walking person, inserted with free space carved
    by the fused kernels and by numpy alone: every array the same, bit for bit (the field's
    cells re-normalised where the rays of earlier keyframes wrote them, and where the hits ×
    seen ratio is exactly 0 or 1)."""
    rng = np.random.default_rng(9)
    margin_m = 0.1
    ours = LikelihoodGrid(PARAMS.resolution_m, PARAMS.hit_sigma_m, margin_m)
    ref = LikelihoodGrid(PARAMS.resolution_m, PARAMS.hit_sigma_m, margin_m)
    room = [[0, 0, 10, 0], [10, 0, 10, 7], [10, 7, 0, 7], [0, 7, 0, 0], [4, 2, 5, 2], [5, 2, 5, 3]]
    for step in range(10):
        x_m = 1.5 + 0.6 * step
        person = [[x_m + 1.5, 4.8, x_m + 1.9, 4.8], [x_m + 1.9, 4.8, x_m + 1.9, 5.2]]
        world = world_of([*room, *person], 10.0, 7.0)
        pose = Pose2D(x_m, 3.5 + 0.3 * math.sin(step), 0.2 * step)
        returns = scan_of(world, pose, rng).points_xy_m()
        pts = surface_in_map(returns, pose, PARAMS)
        ends = rotate_points(returns, pose.theta_rad) + np.array([pose.x_m, pose.y_m])
        ours.insert(pts, (pose.x_m, pose.y_m), ends)
        _numpy_carved_insert(ref, pts, (pose.x_m, pose.y_m), ends)
        assert ours.origin_m == ref.origin_m
        for name in ("values", "density", "hits", "misses", "stamped"):
            a, b = getattr(ours, name), getattr(ref, name)
            assert a.dtype == b.dtype
            assert np.array_equal(a.view(np.int32), b.view(np.int32)), (step, name)
    assert np.any(ref.misses > 0.0)  # the rays carved
    assert np.any((ref.values > 0.0) & (ref.values < 0.5))  # and faded some of the field


def _plain_carve(  # noqa: PLR0917 - kernels.carve's arguments
    density: np.ndarray,
    values: np.ndarray,
    hits: np.ndarray,
    misses: np.ndarray,
    stamped: np.ndarray,
    this_insert: int,
    rad: int,
    origin_row: float,
    origin_col: float,
    end_rows: np.ndarray,
    end_cols: np.ndarray,
    margin_cells: float,
) -> tuple[int, int, int, int]:
    """`kernels.carve` written plainly, step by step (the reference of its compiled passes)."""
    h, w = density.shape
    box = [h, 0, w, 0]
    for end_row, end_col in zip(end_rows, end_cols, strict=True):
        dr, dc = float(end_row) - origin_row, float(end_col) - origin_col
        length = math.sqrt(dr * dr + dc * dc)
        free = length - margin_cells
        if free <= 0.0:
            continue
        prev = (-1, -1)
        for s in range(int(free * 2.0) + 1):
            t = 0.5 * s / length
            i = math.floor(origin_row + dr * t + 0.5)
            j = math.floor(origin_col + dc * t + 0.5)
            if (i, j) == prev or not (0 <= i < h and 0 <= j < w):
                continue
            prev = (i, j)
            if stamped[i, j] == this_insert:
                continue
            misses[i, j] += np.float32(1.0)
            if not density[i, j] > 0.0:
                continue
            window = density[max(0, i - rad) : i + rad + 1, max(0, j - rad) : j + rad + 1]
            peak = window.max()
            surface = density[i, j] / max(peak, np.float32(1e-3)) if peak > 1e-3 else 0.0
            values[i, j] = np.float32(surface) * hits[i, j] / (hits[i, j] + misses[i, j])
            box = [min(box[0], i), max(box[1], i + 1), min(box[2], j), max(box[3], j + 1)]
    return box[0], box[1], box[2], box[3]


@pytest.mark.parametrize("origin", [(20.3, 30.6), (-6.2, 12.9), (45.5, 70.2)])
def test_carve_is_the_plain_step_by_step_loop(origin: tuple[float, float]) -> None:
    """Rays from inside and from outside the grid, ending on it and off it, over a random
    surface: the compiled carve counts the same misses and writes the same field, bit for bit,
    and returns the same box, as the plain loop over every step."""
    rng = np.random.default_rng(3)
    h, w, rad = 50, 60, 3
    density = np.where(rng.random((h, w)) < 0.3, rng.random((h, w)), 0.0).astype(np.float32)
    hits = np.where(density > 0.0, rng.integers(1, 5, (h, w)), 0).astype(np.float32)
    misses = rng.integers(0, 3, (h, w)).astype(np.float32)
    stamped = rng.integers(0, 3, (h, w)).astype(np.int32)
    values = rng.random((h, w)).astype(np.float32)
    angles = rng.uniform(-math.pi, math.pi, 300)
    reach = rng.uniform(0.5, 60.0, 300)
    end_rows = origin[0] + reach * np.sin(angles)
    end_cols = origin[1] + reach * np.cos(angles)
    ours = [a.copy() for a in (values, misses)]
    ref = [a.copy() for a in (values, misses)]
    args = (origin[0], origin[1], end_rows, end_cols, 2.0)
    got = kernels.carve(density, ours[0], hits, ours[1], stamped, 2, rad, *args)
    want = _plain_carve(density, ref[0], hits, ref[1], stamped, 2, rad, *args)
    assert got == want
    assert np.array_equal(ours[0].view(np.int32), ref[0].view(np.int32))
    assert np.array_equal(ours[1].view(np.int32), ref[1].view(np.int32))
    assert want[1] > want[0]  # (surfaces were crossed)


@pytest.mark.parametrize("bin_m", [0.02, 0.05, 0.1])
def test_hard_counts_are_numpys_bincount_bit_for_bit(bin_m: float) -> None:
    """The walls' hard histograms: Σ h² per angle (the coarse search) and the largest bin (the
    peak fraction), as `np.bincount` of the bin indices gives them (points on bin edges
    included: a point a bin apart changes the score)."""
    grid, pts, rng = _room()
    del grid
    edge = np.round(pts / bin_m) * bin_m  # points exactly on bin edges at α = 0
    for points in (pts, edge, pts[::3], rng.normal(0.0, 8.0, (500, 2))):
        angles = np.concatenate(([0.0], rng.uniform(-math.pi / 4, math.pi / 4, 40)))
        counts = _numpy_hard_counts(points, angles, bin_m)
        k = angles.shape[0]
        sq = np.einsum("ij,ij->i", counts, counts)
        want = (sq[:k] + sq[k:]).astype(np.float64)
        got = heading.heading_scores(points, angles, bin_m, soft=False)
        assert np.array_equal(got, want)
        for a in (0, 7, 40):
            one = _numpy_hard_counts(points, angles[a : a + 1], bin_m)
            assert heading._peaks(points, float(angles[a]), bin_m) == one.max(axis=1).sum()


def _numpy_soft_histograms(points: np.ndarray, angles: np.ndarray, bin_m: float) -> np.ndarray:
    """The soft histograms (2K, width) as numpy computes them: every coordinate in bin units,
    shifted positive, its two bins' shares counted by `np.bincount` (the kernel's reference)."""
    k = angles.shape[0]
    columns = heading._rotation_columns(angles, bin_m)
    proj = points[:, 0:1] * columns[0] + points[:, 1:2] * columns[1]
    lo = math.floor(float(proj.min())) - 1
    width = math.ceil(float(proj.max())) - lo + 2
    proj -= lo
    idx = proj.astype(np.intp) + np.arange(2 * k, dtype=np.intp) * width
    frac = proj - np.floor(proj)
    n_bins = 2 * k * width
    h = np.bincount(idx.ravel(), weights=(1.0 - frac).ravel(), minlength=n_bins)
    h += np.bincount(idx.ravel() + 1, weights=frac.ravel(), minlength=n_bins)[: h.shape[0]]
    return np.asarray(h[:n_bins].reshape(2 * k, width))


@pytest.mark.parametrize("bin_m", [0.02, 0.05])
def test_soft_histograms_are_numpys_bincount_bit_for_bit(bin_m: float) -> None:
    """The walls' fine histograms: each point split between two bins by its fraction, summed in
    `np.bincount`'s order, so the fine score (Σ h², numpy's) is the same bits."""
    grid, pts, rng = _room()
    del grid
    edge = np.round(pts / bin_m) * bin_m  # points exactly on bin edges at α = 0
    for points in (pts, edge, pts[::3], rng.normal(0.0, 8.0, (500, 2))):
        angles = np.concatenate(([0.0], rng.uniform(-math.pi / 4, math.pi / 4, 14)))
        got, width = kernels.soft_histograms(points, heading._rotation_columns(angles, bin_m))
        want = _numpy_soft_histograms(points, angles, bin_m)
        assert got.shape == want.shape == (2 * angles.shape[0], width)
        assert np.array_equal(got, want)
