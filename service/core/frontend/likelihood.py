"""The front end's submap as a likelihood grid: what a scan point scores where it lands.

Every hit adds a Gaussian exp(-d²/2σ²) to a surface density (d from the cell's centre to the
hit, exact, not snapped to the cell). The field is that density divided by its own maximum
within the stamp's radius: across a wall it is a Gaussian profile peaking at 1 on the *mean* of
the wall's hits, so noisy hits from many scans sharpen the wall instead of widening it (a
maximum of Gaussians would flatten its top by the noise). Smooth enough for Gauss-Newton on
bicubic interpolation (hector's `ScanMatcher` uses bilinear), cheap enough to look up by cell in the
correlative search.

A point far from every surface costs the same whether its space was seen empty or never seen:
the residual's cap, an outlier. Scoring unseen space any better would pull a scan out of the
submap, into what it has not mapped, wherever that is cheaper than fitting its walls.

Free space is carved (with `carve_margin_m`): each keyframe's rays count a miss in every cell
they cross, up to that margin short of their return, and the field is the normalised density
× hits / (hits + misses), per cell. A person walking ahead leaves hits where each keyframe saw
them; the next keyframes look through those spots, so the trail fades instead of pulling the
next scan back along it (with only the walls of a plain corridor, a trail ending at the last
place the person was seen makes lagging behind cheaper than keeping up). A cell this keyframe's
own surfaces stamp is seen now, not free: rays grazing a wall do not erode it.

The grid grows in whole blocks as the robot moves.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from service.core.frontend import kernels
from service.core.types import FloatArray

F32Array = npt.NDArray[np.float32]

_GROW_CELLS = 128  # margin added on each side when a hit falls outside (6.4 m at 5 cm)


def residual_sq(field: npt.NDArray[np.floating], max_residual_sigmas: float) -> FloatArray:
    """The match's r² = -2 ln M at field values M (d²/σ² to the nearest surface), capped at
    max_residual_sigmas²."""
    floor = math.exp(-0.5 * max_residual_sigmas**2)
    return np.asarray(-2.0 * np.log(np.clip(field, floor, 1.0)))


def off_surface_cost(max_residual_sigmas: float) -> float:
    """What a point on no surface (seen empty, or never seen) costs in the cost table: the cap."""
    return float(np.float32(residual_sq(np.asarray(0.0), max_residual_sigmas)))


def _catmull_rom(t: FloatArray) -> tuple[list[FloatArray], list[FloatArray]]:
    """The four Catmull-Rom weights at fractions `t` of a cell, and their derivatives."""
    t2, t3 = t * t, t * t * t
    weights = [
        0.5 * (-t3 + 2.0 * t2 - t),
        0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
        0.5 * (-3.0 * t3 + 4.0 * t2 + t),
        0.5 * (t3 - t2),
    ]
    slopes = [
        0.5 * (-3.0 * t2 + 4.0 * t - 1.0),
        0.5 * (9.0 * t2 - 10.0 * t),
        0.5 * (-9.0 * t2 + 8.0 * t + 1.0),
        0.5 * (3.0 * t2 - 2.0 * t),
    ]
    return weights, slopes


class LikelihoodGrid:
    """A growing likelihood field in the map frame. Row = y, column = x; cell (i, j)'s centre
    is at origin + ((j + 0.5)·res, (i + 0.5)·res)."""

    def __init__(
        self, resolution_m: float, hit_sigma_m: float, carve_margin_m: float | None = None
    ) -> None:
        self.resolution_m = resolution_m
        self.hit_sigma_m = hit_sigma_m
        self.radius_cells = max(1, math.ceil(3.0 * hit_sigma_m / resolution_m))
        self.origin_m = (0.0, 0.0)
        self.values: F32Array = np.zeros((0, 0), dtype=np.float32)
        self.density: F32Array = np.zeros((0, 0), dtype=np.float32)  # Σ of the hits' Gaussians
        self.inserted = 0  # scans inserted
        # With free space carved (`carve_margin_m` not None: rays carve up to that much short
        # of their return): per cell, the keyframes that hit within a stamp of it and the rays
        # that crossed it; the field is the normalised density × hits / (hits + misses).
        self.carve_margin_m = carve_margin_m
        self.hits: F32Array = np.zeros((0, 0), dtype=np.float32)
        self.misses: F32Array = np.zeros((0, 0), dtype=np.float32)
        self.stamped = np.zeros((0, 0), dtype=np.int32)  # the insert that last stamped a cell
        self._costs: tuple[float, F32Array] | None = None  # (cap, `residual_costs`), a cache
        # Cells (rows i0:i1, columns j0:j1) whose field changed since the cached cost table was
        # brought up to date: an insert touches its scan's box, not the whole submap.
        self._dirty: tuple[int, int, int, int] | None = None
        self.costs_version = 0  # bumped whenever the cached cost table changes in place ...
        self._cost_log: list[tuple[int, tuple[int, int, int, int]]] = []  # ... and where
        r = np.arange(-self.radius_cells, self.radius_cells + 1)
        self._di, self._dj = (a.ravel() for a in np.meshgrid(r, r, indexing="ij"))

    def __getstate__(self) -> dict[str, object]:
        state = dict(self.__dict__)
        state["_costs"] = None  # a cache, rebuilt on first use
        state["_dirty"] = None
        state["_cost_log"] = []
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        # The caches start empty, also in a checkpoint written before they existed.
        self.__dict__.update(state)
        self._costs, self._dirty, self._cost_log = None, None, []
        if "carve_margin_m" not in state:  # written before free space was carved
            self.carve_margin_m = None
            self.hits = np.zeros((0, 0), dtype=np.float32)
            self.misses = np.zeros((0, 0), dtype=np.float32)
            self.stamped = np.zeros((0, 0), dtype=np.int32)
        version = state.get("costs_version", 0)
        self.costs_version = version if isinstance(version, int) else 0

    # ------------------------------------------------------------------ building
    def insert(
        self,
        points_map_m: FloatArray,
        origin_m: tuple[float, float] | None = None,
        ray_ends_m: FloatArray | None = None,
    ) -> None:
        """Add every hit's Gaussian to the surface density and renormalise the field around
        them; with free space carved, the rays from `origin_m` to `ray_ends_m` (the scan's
        returns) count misses in the cells they cross."""
        self.inserted += 1
        if points_map_m.shape[0] == 0:
            return
        shape = self.values.shape
        margin_m = self.carve_margin_m
        rays = None  # (the rays' origin as a (1, 2) array, their ends) when they carve
        if margin_m is not None and origin_m is not None and ray_ends_m is not None:
            rays = (np.asarray([origin_m], dtype=np.float64), ray_ends_m)
        self._ensure(points_map_m if rays is None else np.vstack((points_map_m, *rays)))
        if self.values.shape != shape:
            self._costs = None  # grown: the cost table is rebuilt whole
        res = self.resolution_m
        v, u = self.cell_coords(points_map_m)
        ci, cj = np.rint(v).astype(np.int64), np.rint(u).astype(np.int64)
        # Each hit's Gaussian at every cell of its stamp, summed per cell in hit order (the
        # grouping is compiled; the exp and the sums stay numpy's, so the same bits).
        arg = kernels.stamp_arguments(
            v, u, ci, cj, self._di, self._dj, res * res, self.hit_sigma_m**2
        )
        val = np.exp(arg)
        grouped, cells, starts = kernels.stamp_cells(
            ci, cj, self._di, self._dj, self.values.shape[1], val
        )
        added = np.add.reduceat(grouped, starts)
        carved = margin_m is not None
        kernels.stamp_add(
            self.density, self.hits, self.stamped, cells, added, self.inserted, carved
        )
        rad = self.radius_cells
        box = (
            int(ci.min()) - rad,
            int(ci.max()) + rad + 1,
            int(cj.min()) - rad,
            int(cj.max()) + rad + 1,
        )
        self._normalise(*box)
        if rays is None or margin_m is None:
            return
        orig_v, orig_u = self.cell_coords(rays[0])
        end_v, end_u = self.cell_coords(rays[1])
        changed = kernels.carve(
            self.density,
            self.values,
            self.hits,
            self.misses,
            self.stamped,
            self.inserted,
            rad,
            float(orig_v[0]),
            float(orig_u[0]),
            end_v,
            end_u,
            margin_m / self.resolution_m,
        )
        if changed[1] > changed[0]:
            self._mark_dirty(changed)

    def _normalise(self, i0: int, i1: int, j0: int, j1: int) -> tuple[int, int, int, int]:
        """field = density / its maximum within the stamp radius, over rows i0:i1, columns
        j0:j1: the surface's profile across it, peaking at 1 on the mean of its hits; with free
        space carved, times hits / (hits + misses) (at least 1) where a cell was seen."""
        h, w = self.values.shape
        changed = (max(0, i0), min(h, i1), max(0, j0), min(w, j1))
        kernels.normalise(
            self.density,
            self.values,
            self.hits,
            self.misses,
            self.carve_margin_m is not None,
            self.radius_cells,
            *changed,
        )
        self._mark_dirty(changed)
        return changed

    def _mark_dirty(self, changed: tuple[int, int, int, int]) -> None:
        d = self._dirty
        self._dirty = (
            changed
            if d is None
            else (
                min(d[0], changed[0]),
                max(d[1], changed[1]),
                min(d[2], changed[2]),
                max(d[3], changed[3]),
            )
        )

    def _ensure(self, points_map_m: FloatArray) -> None:
        """Grow the grid so every point's stamp fits inside it."""
        res, pad = self.resolution_m, (self.radius_cells + 2) * self.resolution_m
        x0, y0 = float(points_map_m[:, 0].min()) - pad, float(points_map_m[:, 1].min()) - pad
        x1, y1 = float(points_map_m[:, 0].max()) + pad, float(points_map_m[:, 1].max()) + pad
        h, w = self.values.shape
        ox, oy = self.origin_m
        if h and x0 >= ox and y0 >= oy and x1 < ox + w * res and y1 < oy + h * res:
            return
        if not h:
            ox = math.floor(x0 / res) * res - _GROW_CELLS * res
            oy = math.floor(y0 / res) * res - _GROW_CELLS * res
            nx = math.ceil((x1 - x0) / res) + 2 * _GROW_CELLS
            ny = math.ceil((y1 - y0) / res) + 2 * _GROW_CELLS
            self.origin_m = (ox, oy)
            self.values = np.zeros((ny, nx), dtype=np.float32)
            self.density = np.zeros((ny, nx), dtype=np.float32)
            if self.carve_margin_m is not None:
                self.hits = np.zeros((ny, nx), dtype=np.float32)
                self.misses = np.zeros((ny, nx), dtype=np.float32)
                self.stamped = np.zeros((ny, nx), dtype=np.int32)
            return

        def extra(short_m: float) -> int:  # cells to add on a side short by `short_m`
            return math.ceil(short_m / res) + _GROW_CELLS if short_m > 0.0 else 0

        add_left, add_down = extra(ox - x0), extra(oy - y0)
        add_right, add_up = extra(x1 - (ox + w * res)), extra(y1 - (oy + h * res))
        shape = (h + add_down + add_up, w + add_left + add_right)

        def grow(layer: F32Array) -> F32Array:
            grown = np.zeros(shape, dtype=np.float32)
            grown[add_down : add_down + h, add_left : add_left + w] = layer
            return grown

        self.values, self.density = grow(self.values), grow(self.density)
        if self.carve_margin_m is not None:
            self.hits, self.misses = grow(self.hits), grow(self.misses)
            stamped = np.zeros(shape, dtype=np.int32)
            stamped[add_down : add_down + h, add_left : add_left + w] = self.stamped
            self.stamped = stamped
        self.origin_m = (ox - add_left * res, oy - add_down * res)

    # ------------------------------------------------------------------ reading
    def cell_coords(self, points_map_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Continuous (row, column) of points: integer values at cell centres."""
        res = self.resolution_m
        u = (points_map_m[:, 0] - self.origin_m[0]) / res - 0.5
        v = (points_map_m[:, 1] - self.origin_m[1]) / res - 0.5
        return v, u

    def interpolate(self, points_map_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Bicubic (Catmull-Rom) field value at each point, and its gradient (per metre, map x
        and y). Bilinear would flatten a wall's peak that falls between two cell centres."""
        n = points_map_m.shape[0]
        h, w = self.values.shape
        if h < 4 or w < 4 or n == 0:
            return np.zeros(n), np.zeros((n, 2))
        v, u = self.cell_coords(points_map_m)
        i0 = np.floor(v).astype(np.int64)
        j0 = np.floor(u).astype(np.int64)
        inside = (i0 >= 1) & (j0 >= 1) & (i0 < h - 2) & (j0 < w - 2)
        i0 = np.where(inside, i0, 1)
        j0 = np.where(inside, j0, 1)
        wv, dwv = _catmull_rom(v - i0)
        wu, dwu = _catmull_rom(u - j0)
        vals = self.values
        value = np.zeros(n)
        d_du = np.zeros(n)
        d_dv = np.zeros(n)
        for a in range(4):
            row = np.zeros(n)
            drow = np.zeros(n)
            for b in range(4):
                f = vals[i0 - 1 + a, j0 - 1 + b].astype(np.float64)
                row += wu[b] * f
                drow += dwu[b] * f
            value += wv[a] * row
            d_dv += dwv[a] * row
            d_du += wv[a] * drow
        grad = np.column_stack((d_du, d_dv)) / self.resolution_m
        value[~inside] = 0.0
        grad[~inside] = 0.0
        return np.clip(value, 0.0, 1.0), grad

    def residual_costs(self, max_residual_sigmas: float) -> F32Array:
        """Per cell, the match's r² = -2 ln M (capped), with a border at the cap: the
        correlative search gathers from it with clipped indices and no other test (it scores
        thousands of poses per scan)."""
        if self._costs is not None and self._costs[0] == max_residual_sigmas:
            costs = self._costs[1]
            if self._dirty is not None:  # only what the inserts since touched
                i0, i1, j0, j1 = self._dirty
                block = np.ascontiguousarray(self.values[i0:i1, j0:j1])
                costs[i0:i1, j0:j1] = residual_sq(block, max_residual_sigmas)
                self._cap_border(costs, max_residual_sigmas)
                self.costs_version += 1
                self._cost_log = [*self._cost_log[-7:], (self.costs_version, self._dirty)]
                self._dirty = None
            return costs
        costs = residual_sq(self.values, max_residual_sigmas).astype(np.float32)
        self._cap_border(costs, max_residual_sigmas)
        self._costs = (max_residual_sigmas, costs)
        self._dirty = None
        self.costs_version += 1
        self._cost_log = []
        return costs

    @staticmethod
    def _cap_border(costs: F32Array, max_residual_sigmas: float) -> None:
        if costs.size:
            cap = off_surface_cost(max_residual_sigmas)
            costs[[0, -1], :] = cap
            costs[:, [0, -1]] = cap

    def cost_changes_since(self, version: int) -> tuple[int, int, int, int] | None:
        """The cells (rows i0:i1, columns j0:j1) of the cached cost table changed in place since
        `costs_version` was `version` (an empty box if none), or None when that is not known
        (the table was rebuilt, or too long ago)."""
        if version == self.costs_version:
            return (0, 0, 0, 0)
        since = [box for v, box in self._cost_log if v > version]
        if len(since) != self.costs_version - version:
            return None
        return (
            min(b[0] for b in since),
            max(b[1] for b in since),
            min(b[2] for b in since),
            max(b[3] for b in since),
        )
