"""The correlative search's lattice optimum by branch and bound: the brute force's answer, exactly,
for a fraction of its lookups.

The lattice (`matcher.search` defines it) is every rotation θ_k, k < K, times every whole-cell
translation (di, dj), |di| ≤ ny, |dj| ≤ nx, around the prediction. A pose's cost is

    w · mean_i C[row_i(θ_k) + di, col_i(θ_k) + dj]  +  motion prior(dx, dy, dθ)  +  wall(θ_k)

with C the submap's per-cell r² table (`LikelihoodGrid.residual_costs`; a cell off the grid costs
what its border costs: the cap, as on no surface). The brute force scores all K·(2ny+1)·(2nx+1)
poses.

Branch and bound (Cartographer's `FastCorrelativeScanMatcher2D`, Olson 2009) instead scores
*blocks* of poses with a lower bound of every cost in the block, and only opens a block whose
bound is below the best pose found so far:

- A block is 2^a consecutive rotations × 2^d × 2^d translations. Its children halve both
  (eight of them), down to single poses, whose cost is computed exactly as the brute force does.
- Scan term. Over the block's rotations point i moves at most |p_i|·δ from where the block's
  middle rotation puts it (δ: half the block's angle), so its cell stays inside a rectangle; the
  block's translations widen that rectangle by 2^d - 1 cells. The minimum of C over a square
  that holds the rectangle bounds the point's cost anywhere in the block. The squares are read
  from a min-pyramid: level m holds, per cell, the minimum of C over the 2^m × 2^m cells above
  and right of it (anchored, as Cartographer's precomputation grids are), one lookup a point.
- Motion prior: a lower bound of the quadratic over the block's box in (dx, dy, dθ), by interval
  arithmetic term by term (exact when the prior's covariance is diagonal). Wall prior: the Huber
  cost at the block's angle nearest the walls' heading (0 if the block spans it).
- Order: level by level, every surviving block opened at once (numpy works in batches, not
  one block at a time). Before each level, the single poses at the middle of the few best
  blocks are scored exactly: the best of them is the bound to beat, and it tightens as the
  blocks shrink. A block is dropped only when its bound exceeds the best cost (plus rounding
  slack), so ties survive, and ties are broken as the brute force breaks them: lowest rotation
  index, then row-major translation.

The pyramid is per submap: built on a submap's first tree search and cached beside the grid
(held weakly), then updated in place over the box each insert changed
(`LikelihoodGrid.cost_changes_since`; minima are exact in any order: a rebuild's values). It
is built over the bounding box of the cells that do not cost the cap value, padded by the
largest block and a margin for later inserts: outside that box every window holds only cells
at the cap. A lattice small enough (40 Hz) is scored whole instead, in one compiled pass that
reads the cost table itself and needs no pyramid. The inner loops are compiled (`kernels`).
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from service.core.frontend import kernels
from service.core.frontend.likelihood import F32Array, LikelihoodGrid
from service.core.types import FloatArray

IntArray = npt.NDArray[np.int64]

# The largest pyramid level: windows of 2^6 = 64 cells (3.2 m at 5 cm). A point whose block
# spans more is bounded by the table's global minimum.
MAX_LEVEL = 6
# A lattice of at most this many poses is scored whole (measured: below it the tree's numpy
# overhead per level costs more than the poses it prunes).
_DENSE_MAX_POSES = 2048
# Single poses scored before each level to tighten the bound to beat.
_PROBES = 4
# A block is pruned when its bound exceeds the best cost by more than this (relative): the
# bound and the exact cost sum the same float32 values in different orders.
_SLACK = 1e-9


@dataclass(frozen=True, slots=True)
class CostPyramid:
    """Min-pooled cost tables over a crop of the grid, flattened: level m's table is
    `flat[m·H·W : (m+1)·H·W]` (row-major, H × W), and `flat[-1]` is the table's global minimum.
    Level m at crop cell (r, c) = min of the costs over rows r .. r+2^m-1, columns c .. c+2^m-1.
    """

    flat: F32Array
    row0: int  # grid row of the crop's row 0
    col0: int  # grid column of the crop's column 0
    height: int
    width: int
    max_level: int

    def lookup(self, level: IntArray, rows: IntArray, cols: IntArray) -> F32Array:
        """Level `level`'s value anchored at grid cells (rows, cols); a level above the largest
        gives the global minimum. Anchors off the crop are clamped onto it: there, and on the
        crop's edge, every window holds only cells at the cap."""
        r = np.clip(rows - self.row0, 0, self.height - 1)
        c = np.clip(cols - self.col0, 0, self.width - 1)
        idx = (level * self.height + r) * self.width + c
        idx = np.where(level > self.max_level, self.flat.shape[0] - 1, idx)
        out: F32Array = self.flat[idx]
        return out


def build_pyramid(
    costs: F32Array, off_surface: float, max_level: int = MAX_LEVEL, margin: int = 0
) -> CostPyramid:
    """The min-pyramid of a cost table whose border cells (and everything off it) cost
    `off_surface`, over the cells that do not cost it padded by the largest window and
    `margin` more (room for later inserts: a crop of more cap cells looks up the same)."""
    pad = (1 << max_level) + margin
    differs = costs != np.float32(off_surface)
    rows_any, cols_any = np.flatnonzero(differs.any(axis=1)), np.flatnonzero(differs.any(axis=0))
    if rows_any.size:
        r0, r1 = int(rows_any[0]), int(rows_any[-1]) + 1
        c0, c1 = int(cols_any[0]), int(cols_any[-1]) + 1
    else:
        r0 = r1 = c0 = c1 = 0  # all at the cap: a crop of such cells only
    height, width = r1 - r0 + 2 * pad, c1 - c0 + 2 * pad
    flat = np.empty((max_level + 1) * height * width + 1, dtype=np.float32)
    levels = flat[:-1].reshape(max_level + 1, height, width)
    levels[0].fill(np.float32(off_surface))
    levels[0, pad : pad + r1 - r0, pad : pad + c1 - c0] = costs[r0:r1, c0:c1]
    for m in range(max_level):  # whole levels: numpy's vectorised minima beat a loop here
        s = 1 << m
        src, dst = levels[m], levels[m + 1]
        # Rows then columns: the window doubles in each. Cells past the crop's end cost the cap.
        tmp = src.copy()
        np.minimum(src[:-s], src[s:], out=tmp[:-s])
        np.minimum(tmp[:, :-s], tmp[:, s:], out=dst[:, :-s])
        np.minimum(tmp[:, -s:], np.float32(off_surface), out=dst[:, -s:])
        dst[-s:] = np.minimum(dst[-s:], np.float32(off_surface))
    flat[-1] = min(float(levels[0].min()), off_surface)
    return CostPyramid(flat, r0 - pad, c0 - pad, height, width, max_level)


def update_pyramid(
    pyramid: CostPyramid, costs: F32Array, off_surface: float, box: tuple[int, int, int, int]
) -> bool:
    """Bring `pyramid` up to date in place after `costs` changed in rows i0:i1, columns j0:j1
    (`box`); False (nothing done) when a cell that does not cost the cap now lies where the
    crop cannot hold it: the pyramid must be rebuilt."""
    i0, i1, j0, j1 = box
    if i0 >= i1 or j0 >= j1:
        return True
    pad = 1 << pyramid.max_level
    differs = costs[i0:i1, j0:j1] != np.float32(off_surface)
    rows_any, cols_any = np.flatnonzero(differs.any(axis=1)), np.flatnonzero(differs.any(axis=0))
    if rows_any.size and (
        i0 + int(rows_any[0]) < pyramid.row0 + pad
        or i0 + int(rows_any[-1]) >= pyramid.row0 + pyramid.height - pad
        or j0 + int(cols_any[0]) < pyramid.col0 + pad
        or j0 + int(cols_any[-1]) >= pyramid.col0 + pyramid.width - pad
    ):
        return False
    # Cells of the box off the crop cost the cap, before and after: only the overlap changes.
    r0, r1 = max(i0, pyramid.row0), min(i1, pyramid.row0 + pyramid.height)
    c0, c1 = max(j0, pyramid.col0), min(j1, pyramid.col0 + pyramid.width)
    if r0 >= r1 or c0 >= c1:
        return True
    flat = pyramid.flat
    levels = flat[:-1].reshape(pyramid.max_level + 1, pyramid.height, pyramid.width)
    a0, a1, b0, b1 = r0 - pyramid.row0, r1 - pyramid.row0, c0 - pyramid.col0, c1 - pyramid.col0
    levels[0, a0:a1, b0:b1] = costs[r0:r1, c0:c1]
    kernels.pyramid_update(levels, off_surface, a0, a1, b0, b1)
    flat[-1] = min(float(levels[0].min()), off_surface)
    return True


# Cells of cap added around a rebuilt pyramid's crop, so that the next inserts (a robot moving
# into what its submap has not seen) update it in place rather than rebuild it.
_CROP_MARGIN = 96

# Per grid: (the cost table the pyramid was built from, its version, the pyramid). Weak keys: a
# submap that is dropped takes its pyramid with it.
_PYRAMIDS: weakref.WeakKeyDictionary[LikelihoodGrid, tuple[F32Array, int, CostPyramid]] = (
    weakref.WeakKeyDictionary()
)


def pyramid_of(grid: LikelihoodGrid, costs: F32Array, off_surface: float) -> CostPyramid:
    """The grid's pyramid of `costs` (its current `residual_costs`): built on first use, then
    updated over the cells each insert changed (`LikelihoodGrid.cost_changes_since`)."""
    cached = _PYRAMIDS.get(grid)
    version = grid.costs_version
    if cached is not None and cached[0] is costs:
        if cached[1] == version:
            return cached[2]
        box = grid.cost_changes_since(cached[1])
        if box is not None and update_pyramid(cached[2], costs, off_surface, box):
            _PYRAMIDS[grid] = (costs, version, cached[2])
            return cached[2]
    pyramid = build_pyramid(costs, off_surface, margin=_CROP_MARGIN)
    _PYRAMIDS[grid] = (costs, version, pyramid)
    return pyramid


@dataclass(frozen=True, slots=True)
class Lattice:
    """The search's poses and objective, as `matcher.search` defines them."""

    thetas_rad: FloatArray  # (K,) rotations, ascending
    half_rows: int  # ny: row offsets -ny .. ny (map y, cells)
    half_cols: int  # nx: column offsets -nx .. nx (map x, cells)
    predicted_xy_m: tuple[float, float]  # translation at offset (0, 0)
    predicted_theta_rad: float
    info_pred: FloatArray  # (3, 3) inverse covariance of the prediction
    scan_weight: float
    wall_heading_rad: float | None  # None: no wall prior
    wall_sigma_rad: float
    wall_huber: float


def _wrap(theta_rad: FloatArray) -> FloatArray:
    """`types.wrap_angle`, elementwise (same operations, so the same bits)."""
    out: FloatArray = np.asarray((theta_rad + math.pi) % (2.0 * math.pi) - math.pi, np.float64)
    return out


def _huber(z: FloatArray, huber: float) -> FloatArray:
    """The wall prior's cost at residuals z (σ), as `matcher._wall_cost` computes it."""
    a = np.abs(z)
    out: FloatArray = np.where(a <= huber, z * z, 2.0 * huber * a - huber * huber)
    return out


def _rotation_terms(lat: Lattice) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per rotation of the lattice, once: its offset from the prediction, and from the walls'
    heading (σ) with the walls' cost there; the last two empty without the walls' prior
    (elementwise, so the same bits as computed pose by pose)."""
    dt = _wrap(lat.thetas_rad - lat.predicted_theta_rad)
    if lat.wall_heading_rad is None or not math.isfinite(lat.wall_sigma_rad):
        return dt, np.zeros(0), np.zeros(0)
    wall_z = _wrap(lat.thetas_rad - lat.wall_heading_rad) / lat.wall_sigma_rad
    return dt, wall_z, _huber(wall_z, lat.wall_huber)


class _Problem:
    """One search: the points, the lattice, the table, and the two ways to score."""

    def __init__(
        self, grid: LikelihoodGrid, pyramid: CostPyramid, pts: FloatArray, lat: Lattice
    ) -> None:
        self.pyr = pyramid
        self.lat = lat
        self.px, self.py = np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1])
        self.range_m = np.hypot(self.px, self.py)
        self.res = grid.resolution_m
        self.origin = grid.origin_m
        self.cos, self.sin = np.cos(lat.thetas_rad), np.sin(lat.thetas_rad)
        self.n_rot = lat.thetas_rad.shape[0]
        # Each rotation's cells of the points at the prediction, filled in by the first exact
        # score at that rotation (`kernels.lattice_gather`).
        self.cells = np.empty((self.n_rot, 2, self.px.shape[0]), dtype=np.int64)
        self.celled = np.zeros(self.n_rot, dtype=np.bool_)
        self.n_rows, self.n_cols = 2 * lat.half_rows + 1, 2 * lat.half_cols + 1
        self.dt, self.wall_z, self.wall_cost = _rotation_terms(lat)
        self.has_wall = self.wall_cost.shape[0] > 0
        self.pts = np.ascontiguousarray(pts)
        self.pyramid_shape = np.array(
            [pyramid.row0, pyramid.col0, pyramid.height, pyramid.width, pyramid.max_level]
        )
        self.frame = np.array(
            [
                lat.predicted_xy_m[0],
                lat.predicted_xy_m[1],
                self.origin[0],
                self.origin[1],
                self.res,
                lat.scan_weight,
                lat.wall_huber,
            ]
        )

    # ------------------------------------------------------------------ single poses
    def exact(self, k: IntArray, a: IntArray, b: IntArray) -> FloatArray:
        """The cost of poses (rotation k, row offset a - ny, column offset b - nx), with the
        brute force's operations in the brute force's order: the same bits."""
        lat, res, pyr = self.lat, self.res, self.pyr
        di, dj = a - lat.half_rows, b - lat.half_cols
        looked_up = kernels.lattice_gather(
            pyr.flat,
            pyr.row0,
            pyr.col0,
            pyr.height,
            pyr.width,
            self.px,
            self.py,
            self.cos,
            self.sin,
            k,
            di,
            dj,
            lat.predicted_xy_m[0],
            lat.predicted_xy_m[1],
            self.origin[0],
            self.origin[1],
            res,
            self.cells,
            self.celled,
        )
        scan = lat.scan_weight * looked_up.mean(axis=1, dtype=np.float64)
        info = lat.info_pred
        dx, dy = dj * res, di * res
        total: FloatArray = scan + kernels.prior_cost(info, dx, dy, self.dt[k])
        if self.has_wall:
            total = total + self.wall_cost[k]
        return total

    # ------------------------------------------------------------------ blocks
    def bound(self, k0: IntArray, a0: IntArray, b0: IntArray, ka: int, d: int) -> FloatArray:
        """A lower bound of the cost over each block: rotations k0 .. k0+2^ka-1, row offsets
        a0 .. a0+2^d-1, column offsets b0 .. b0+2^d-1 (each clipped to the lattice)
        (`kernels.block_bounds`: the scan term, the motion prior's, the walls')."""
        lat = self.lat
        k1 = np.minimum(k0 + (1 << ka), self.n_rot) - 1
        a1 = np.minimum(a0 + (1 << d), self.n_rows) - 1
        b1 = np.minimum(b0 + (1 << d), self.n_cols) - 1
        bound: FloatArray = kernels.block_bounds(
            self.pyr.flat,
            self.pyramid_shape,
            self.pts,
            self.range_m,
            lat.thetas_rad,
            self.dt,
            self.wall_z,
            k0,
            k1,
            a0 - lat.half_rows,
            b0 - lat.half_cols,
            a1 - a0 + 1,
            b1 - b0 + 1,
            self.frame,
            lat.info_pred,
        )
        return bound


def _dense_search(
    grid: LikelihoodGrid, costs: F32Array, pts: FloatArray, lat: Lattice
) -> tuple[int, int, int, int]:
    """`lattice_search` on a small lattice (40 Hz: a few cells, a few dozen rotations): every
    pose scored in one compiled pass (`kernels.dense_search`), which costs less than the tree's
    levels of small batches, and is the brute force. It reads `costs` itself, not the pyramid's
    level 0: the two look up the same value at every cell, on the table or off it (the
    table's border and the crop's edge both cost the cap, and the crop holds every cell that
    does not), so the pyramid is neither built nor updated here (the next tree search on the
    submap updates it over the inserts since, or rebuilds it: the same values). The rotations'
    cos and sin and `_rotation_terms` are numpy's, as `_Problem`'s."""
    thetas = lat.thetas_rad
    dt, _, wall_cost = _rotation_terms(lat)
    k, a, b, scored = kernels.dense_search(
        costs, np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1]),
        np.cos(thetas), np.sin(thetas), lat.half_rows, lat.half_cols,
        lat.predicted_xy_m[0], lat.predicted_xy_m[1], grid.origin_m[0], grid.origin_m[1],
        grid.resolution_m, lat.scan_weight, lat.info_pred, dt, wall_cost,
    )  # fmt: skip
    return k, a - lat.half_rows, b - lat.half_cols, scored


def lattice_search(
    grid: LikelihoodGrid,
    costs: F32Array,
    off_surface: float,
    pts: FloatArray,
    lat: Lattice,
) -> tuple[int, int, int, int]:
    """The brute force's lowest-cost lattice pose: (rotation index k, row offset di, column
    offset dj, poses and blocks scored). `costs` is `grid.residual_costs(...)`, whose border
    and everything off the grid cost `off_surface`; `pts` holds at least one point."""
    n_rot, n_rows, n_cols = lat.thetas_rad.shape[0], 2 * lat.half_rows + 1, 2 * lat.half_cols + 1
    if n_rot * n_rows * n_cols <= _DENSE_MAX_POSES:
        return _dense_search(grid, costs, pts, lat)
    prob = _Problem(grid, pyramid_of(grid, costs, off_surface), pts, lat)
    depth_t = max(0, (max(n_rows, n_cols) - 1).bit_length())  # 2^depth_t ≥ the window
    # Root rotation blocks of 2^(depth_t + 1): the farthest point then moves about as far as a
    # root block translates.
    depth_r = min(depth_t + 1, max(0, (n_rot - 1).bit_length()))
    scored = 0
    best_key = (math.inf, n_rot, n_rows, n_cols)  # (cost, k, a, b): the brute force's order

    def consider(k: IntArray, a: IntArray, b: IntArray) -> None:
        nonlocal best_key, scored
        cost = prob.exact(k, a, b)
        scored += int(cost.shape[0])
        i = int(np.lexsort((b, a, k, cost))[0])
        key = (float(cost[i]), int(k[i]), int(a[i]), int(b[i]))
        best_key = min(best_key, key)

    # The pose at the prediction: a first bound to beat.
    k_pred = int(np.argmin(np.abs(_wrap(lat.thetas_rad - lat.predicted_theta_rad))))
    one = np.ones(1, dtype=np.int64)
    consider(k_pred * one, lat.half_rows * one, lat.half_cols * one)

    k0 = np.arange(0, n_rot, 1 << depth_r, dtype=np.int64)
    a0 = np.zeros_like(k0)
    b0 = np.zeros_like(k0)
    ka, d = depth_r, depth_t
    while k0.shape[0]:
        if ka == 0 and d == 0:
            consider(k0, a0, b0)
            break
        bnd = prob.bound(k0, a0, b0, ka, d)
        scored += int(bnd.shape[0])
        keep = bnd <= best_key[0] + _SLACK * (1.0 + abs(best_key[0]))
        k0, a0, b0, bnd = k0[keep], a0[keep], b0[keep], bnd[keep]
        if not k0.shape[0]:
            break
        # The middle pose of the few best blocks, scored exactly: a tighter bound to beat.
        top = np.argsort(bnd, kind="stable")[:_PROBES]
        consider(
            np.minimum(k0[top] + (1 << ka) // 2, n_rot - 1),
            np.minimum(a0[top] + (1 << d) // 2, n_rows - 1),
            np.minimum(b0[top] + (1 << d) // 2, n_cols - 1),
        )
        keep = bnd <= best_key[0] + _SLACK * (1.0 + abs(best_key[0]))
        k0, a0, b0 = k0[keep], a0[keep], b0[keep]
        # Every survivor's children: halve the rotations and each translation axis.
        dk = [0, 1 << (ka - 1)] if ka else [0]
        dt = [0, 1 << (d - 1)] if d else [0]
        offsets = np.array([(i, j, m) for i in dk for j in dt for m in dt], dtype=np.int64)
        k0 = (k0[:, None] + offsets[None, :, 0]).ravel()
        a0 = (a0[:, None] + offsets[None, :, 1]).ravel()
        b0 = (b0[:, None] + offsets[None, :, 2]).ravel()
        inside = (k0 < n_rot) & (a0 < n_rows) & (b0 < n_cols)
        k0, a0, b0 = k0[inside], a0[inside], b0[inside]
        ka, d = max(ka - 1, 0), max(d - 1, 0)
    _, k, a, b = best_key
    return k, a - lat.half_rows, b - lat.half_cols, scored
