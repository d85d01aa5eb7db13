"""Submaps: the scans of a stretch of travel, in the frame of its first node, frozen once full.

A submap holds the scan points of a few consecutive nodes, placed with the front end's relative
poses (exact within the stretch, since the front end is good locally), in the frame of its
anchor node. Once it holds `nodes_per_submap` nodes it is finished: its points and its
likelihood field never change again, only the anchor's pose does when the graph is optimised.

The likelihood field is what the loop search scores a scan against: each cell holds
exp(-d² / 2σ²), d being the distance to the nearest hit, on a grid of `resolution_m`. Beside it,
a mask of the space the submap's rays observed. A scan point outside it (beyond the submap's
reach) is scored at the field's prior, its mean over observed space: the chance that a point
lands on a wall where nothing is known. Scoring it as a miss (0) makes a closure slide to the
placement that overlaps the submap most (it folded ACES' central corridor by 4 m in a first
attempt); leaving it out makes it slide to where its misfits fall outside (0.2 m along a
synthetic corridor in a second one). The field is the maximum of Gaussian bumps, each stamped
around its hit. A second, coarse field is its sliding maximum over a block of `coarse_factor`
cells: a score on it bounds every fine score inside that block (branch and bound).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from service.core.maps.grid import OccupancyGrid
from service.core.types import FloatArray, LaserScan, Pose2D, frozen_array, rotate_points

F32Array = npt.NDArray[np.float32]


@dataclass(frozen=True, slots=True)
class SubmapParams:
    nodes_per_submap: int = 20  # nodes (keyframes) in a finished submap; half of them overlap
    resolution_m: float = 0.05  # cell of the likelihood field
    hit_sigma_m: float = 0.07  # width of a hit's Gaussian in the field
    observed_resolution_m: float = 0.2  # cell of the ray-cast mask of observed space
    coarse_factor: int = 4  # coarse field block (cells): 0.2 m at 0.05 m
    max_points_per_node: int = 400  # a node's scan points kept (voxel-thinned first)
    voxel_m: float = 0.05  # thinning of the points kept per node
    cached_fields: int = 24  # likelihood fields kept for the loop search (built on demand)


@dataclass(frozen=True, slots=True)
class LikelihoodField:
    """exp(-d²/2σ²) to the nearest hit, in the submap frame, with a coarse upper-bound copy."""

    origin_m: tuple[float, float]  # (x, y) of cell (0, 0)'s lower corner
    resolution_m: float
    fine: F32Array  # (H, W): row = y, column = x
    coarse: F32Array  # (H, W): max of `fine` over [i, i + k) × [j, j + k)
    coarse_factor: int
    known: F32Array  # (H, W): 1 where the submap's rays observed the space, else 0
    unknown_value: float  # the field's mean over observed space: the score of an unknown cell

    # Saved without what is derived (checkpoints): the coarse field is the fine one's sliding
    # maximum, the mask is 0/1. The encoder's deflate of three float grids took ~1 s a loop.
    def __getstate__(self) -> dict[str, object]:
        return {
            "origin_m": self.origin_m,
            "resolution_m": self.resolution_m,
            "fine": self.fine,
            "coarse_factor": self.coarse_factor,
            "known": self.known.astype(np.bool_),
            "unknown_value": self.unknown_value,
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        fine = np.asarray(state["fine"], dtype=np.float32)
        coarse = sliding_max(fine, int(state["coarse_factor"]))
        np.maximum(coarse, np.float32(state["unknown_value"]), out=coarse)
        values = {
            **state,
            "origin_m": tuple(state["origin_m"]),
            "fine": fine,
            "coarse": coarse,
            "known": np.asarray(state["known"]).astype(np.float32),
        }
        for name in self.__slots__:
            object.__setattr__(self, name, values[name])

    def interpolate(self, xy_m: FloatArray) -> FloatArray:
        """Fine field values at (..., 2) points, interpolated between cell centres; outside the
        grid, the field's prior (sub-cell matches: the front end's 2-D search, a closure's peak)."""
        grid = self.fine
        h, w = grid.shape
        u = (xy_m[..., 0] - self.origin_m[0]) / self.resolution_m - 0.5
        v = (xy_m[..., 1] - self.origin_m[1]) / self.resolution_m - 0.5
        j0 = np.floor(u)
        i0 = np.floor(v)
        fu = u - j0
        fv = v - i0
        j0i = j0.astype(np.int64)
        i0i = i0.astype(np.int64)
        inside = (i0i >= 0) & (i0i < h - 1) & (j0i >= 0) & (j0i < w - 1)
        out = np.full(u.shape, float(self.unknown_value))
        ii, jj, a, b = i0i[inside], j0i[inside], fu[inside], fv[inside]
        out[inside] = (
            grid[ii, jj] * (1 - a) * (1 - b)
            + grid[ii, jj + 1] * a * (1 - b)
            + grid[ii + 1, jj] * (1 - a) * b
            + grid[ii + 1, jj + 1] * a * b
        )
        return out

    def lookup(self, xy_m: FloatArray, coarse: bool = False, known: bool = False) -> F32Array:
        """Field (or known-mask) values at (..., 2) points; 0 outside the grid."""
        grid = self.known if known else self.coarse if coarse else self.fine
        h, w = grid.shape
        j = np.floor((xy_m[..., 0] - self.origin_m[0]) / self.resolution_m).astype(np.int64)
        i = np.floor((xy_m[..., 1] - self.origin_m[1]) / self.resolution_m).astype(np.int64)
        inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)
        out = np.zeros(i.shape, dtype=np.float32)
        out[inside] = grid[i[inside], j[inside]]
        return out


def voxel_thin(points_m: FloatArray, voxel_m: float) -> FloatArray:
    """One point per voxel (the first), order kept."""
    if points_m.shape[0] == 0:
        return points_m
    keys = np.floor(points_m / voxel_m).astype(np.int64)
    _, first = np.unique(keys[:, 0] * 1_000_003 + keys[:, 1], return_index=True)
    out: FloatArray = points_m[np.sort(first)]
    return out


def sliding_max(grid: F32Array, k: int) -> F32Array:
    """out[i, j] = max of grid[i:i+k, j:j+k] (clipped at the far edges)."""
    out = grid.copy()
    for axis in (0, 1):
        src = out.copy()
        n = src.shape[axis]
        for s in range(1, k):
            if s >= n:
                break
            lo = [slice(None)] * 2
            hi = [slice(None)] * 2
            lo[axis], hi[axis] = slice(0, n - s), slice(s, n)
            np.maximum(out[tuple(lo)], src[tuple(hi)], out=out[tuple(lo)])
    return out


@dataclass(frozen=True, slots=True)
class ObservedMask:
    """The cells a submap's rays observed: (H, W) booleans, row = y, from cell (i0, j0)."""

    seen: npt.NDArray[np.bool_]
    i0: int
    j0: int
    resolution_m: float

    @classmethod
    def of(cls, grid: OccupancyGrid) -> ObservedMask:
        log_odds, i0, j0 = grid.log_odds()
        return cls(frozen_array(log_odds != 0.0), int(i0), int(j0), grid.resolution_m)

    @property
    def nbytes(self) -> int:
        return int(self.seen.nbytes)


def likelihood_field(
    points_m: FloatArray,
    params: SubmapParams,
    observed: ObservedMask | None = None,
    *,
    bound: bool = True,
) -> LikelihoodField:
    """The field of an (N, 2) point set, N > 0, with a margin of 3σ around it.

    `observed` (a multiple of the field's resolution) gives the known mask; without it every
    cell is known. `bound` False leaves out the coarse upper bound (empty), for callers that
    never search it.
    """
    res = params.resolution_m
    radius = max(1, math.ceil(3.0 * params.hit_sigma_m / res))
    lo = np.floor(points_m.min(axis=0) / res) - radius
    hi = np.floor(points_m.max(axis=0) / res) + radius + 1
    dense = None
    if observed is not None:
        # The observed grid is coarser by an integer factor: its cells, repeated, on ours.
        k = max(1, round(observed.resolution_m / res))
        dense = np.repeat(np.repeat(observed.seen, k, axis=0), k, axis=1)
        ci0, cj0 = observed.i0 * k, observed.j0 * k
        if dense.size:
            lo = np.minimum(lo, (cj0 - radius, ci0 - radius))
            hi = np.maximum(hi, (cj0 + dense.shape[1] + radius, ci0 + dense.shape[0] + radius))
    w, h = int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1
    j = (np.floor(points_m[:, 0] / res) - lo[0]).astype(np.int64)
    i = (np.floor(points_m[:, 1] / res) - lo[1]).astype(np.int64)
    # Each hit stamps its Gaussian (cell-centred distances) on the field: work in the points,
    # not in the grid, which is mostly empty.
    d = np.arange(-radius, radius + 1, dtype=np.int64)
    di, dj = np.meshgrid(d, d, indexing="ij")
    bump = np.exp(-0.5 * ((di**2 + dj**2) * res**2) / params.hit_sigma_m**2).astype(np.float32)
    fine = np.zeros((h, w), dtype=np.float32)
    cells = i * w + j
    # One bump offset at a time: within an offset every hit in a cell writes the same value
    # (the cell's old value or the bump's), so a plain gather-max-scatter is exact even where
    # hits share a cell (`np.maximum.at` is ~3x slower).
    flat = fine.reshape(-1)
    for offset, value in zip((di * w + dj).ravel().tolist(), bump.ravel().tolist(), strict=True):
        idx = cells + offset
        flat[idx] = np.maximum(flat[idx], np.float32(value))
    coarse = sliding_max(fine, params.coarse_factor) if bound else np.zeros((0, 0), np.float32)
    if dense is not None and dense.size:
        seen = np.zeros((h, w), dtype=np.float32)
        r0, c0 = int(ci0 - lo[1]), int(cj0 - lo[0])
        seen[r0 : r0 + dense.shape[0], c0 : c0 + dense.shape[1]] = dense
        # A hit just beyond the last observed cell is still a hit: its bump counts as observed.
        known = np.maximum(seen, (fine > 1e-3).astype(np.float32))
    else:
        known = np.ones((h, w), dtype=np.float32)
    prior = float((fine * known).sum() / max(float(known.sum()), 1.0))
    if bound:
        np.maximum(coarse, np.float32(prior), out=coarse)  # the bound covers unknown cells too
    origin = (float(lo[0] * res), float(lo[1] * res))
    return LikelihoodField(origin, res, fine, coarse, params.coarse_factor, known, prior)


@dataclass(slots=True)
class Submap:
    """Consecutive nodes' scan points in the anchor node's frame.

    A finished submap keeps its thinned points and the mask of what its rays observed; its
    likelihood field (megabytes: a 30 m reach at 0.05 m) is built when the loop search needs
    it and kept only in the builder's small cache, never in a checkpoint.
    """

    index: int
    anchor_node: int
    anchor_pose_frontend: Pose2D  # the anchor's front-end pose (places the points)
    nodes: list[int] = field(default_factory=list)
    chunks: list[FloatArray] = field(default_factory=list)
    observed: OccupancyGrid | None = None  # ray-cast while active, for the known mask
    node_xy_m: list[tuple[float, float]] = field(default_factory=list)  # anchor frame
    observed_mask: ObservedMask | None = None  # set when finished
    finished: bool = False
    likelihood: LikelihoodField | None = None  # a cache (`SubmapBuilder.field_of`)

    def __getstate__(self) -> dict[str, object]:
        state = {name: getattr(self, name) for name in self.__slots__}
        state["likelihood"] = None
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        old_field = state.get("likelihood")
        for name in self.__slots__:
            object.__setattr__(self, name, state.get(name))
        self.nodes = self.nodes or []
        self.chunks = self.chunks or []
        self.node_xy_m = self.node_xy_m or []
        self.likelihood = None
        if old_field is not None and "finished" not in state:
            # Saved by a version that kept the field: its known mask, at the field's cells.
            ri = round(old_field.origin_m[1] / old_field.resolution_m)
            rj = round(old_field.origin_m[0] / old_field.resolution_m)
            seen = np.asarray(old_field.known) > 0.5
            self.observed_mask = ObservedMask(seen, ri, rj, old_field.resolution_m)
            self.finished = True
        self.finished = bool(self.finished)

    def insert(
        self,
        node: int,
        pose_frontend: Pose2D,
        points_laser_m: FloatArray,
        scan: LaserScan | None = None,
        observed_resolution_m: float = 0.2,
    ) -> None:
        """Add a node's points (laser frame) at its front-end pose; its rays, if `scan`."""
        rel = self.anchor_pose_frontend.between(pose_frontend)
        if scan is not None:
            if self.observed is None:
                self.observed = OccupancyGrid(observed_resolution_m)
            self.observed.integrate(scan, rel)
        pts = rotate_points(points_laser_m, rel.theta_rad) + np.array([rel.x_m, rel.y_m])
        self.nodes.append(node)
        self.chunks.append(pts)
        self.node_xy_m.append((rel.x_m, rel.y_m))

    def finish(self, params: SubmapParams) -> None:
        pts = np.concatenate(self.chunks) if self.chunks else np.zeros((0, 2))
        if pts.shape[0] == 0:
            pts = np.zeros((1, 2))
        self.chunks = [frozen_array(voxel_thin(pts, params.resolution_m))]  # the field's points
        self.observed_mask = ObservedMask.of(self.observed) if self.observed is not None else None
        self.observed = None  # the mask is all the loop search needs of it
        self.finished = True

    def build_field(self, params: SubmapParams) -> LikelihoodField:
        assert self.finished
        return likelihood_field(self.chunks[0], params, self.observed_mask)

    @property
    def nbytes(self) -> int:
        """What it holds for good (not the field's cache)."""
        held = sum(int(c.nbytes) for c in self.chunks)
        if self.observed_mask is not None:
            held += self.observed_mask.nbytes
        if self.observed is not None:
            held += self.observed.memory_bytes()
        return held


class SubmapBuilder:
    """Overlapping submaps: every node goes into the two submaps active at its index."""

    def __init__(self, params: SubmapParams | None = None) -> None:
        self.params = params if params is not None else SubmapParams()
        self.submaps: list[Submap] = []
        self._active: list[Submap] = []
        self._half = max(1, self.params.nodes_per_submap // 2)
        self._cached: list[Submap] = []  # submaps holding a field, least recently used first

    def __getstate__(self) -> dict[str, object]:
        state = dict(self.__dict__)
        state["_cached"] = []
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.__dict__.setdefault("_cached", [])

    def field_of(self, submap: Submap) -> LikelihoodField:
        """A finished submap's likelihood field, from the cache of the `cached_fields` most
        recently searched (a loop search looks at the same few submaps query after query)."""
        if submap.likelihood is not None:
            self._cached.remove(submap)
        else:
            submap.likelihood = submap.build_field(self.params)
            while len(self._cached) >= max(1, self.params.cached_fields):
                self._cached.pop(0).likelihood = None
        self._cached.append(submap)
        return submap.likelihood

    @property
    def nbytes(self) -> int:
        """What the submaps hold, and the fields cached beside it."""
        held = sum(sub.nbytes for sub in self.submaps)
        cached = sum(_field_bytes(sub.likelihood) for sub in self._cached if sub.likelihood)
        return held + cached

    def node_points(self, points_laser_m: FloatArray) -> FloatArray:
        """What a node keeps of its scan: voxel-thinned, at most `max_points_per_node`."""
        pts = voxel_thin(points_laser_m, self.params.voxel_m)
        n = self.params.max_points_per_node
        if pts.shape[0] > n:
            pts = pts[np.linspace(0, pts.shape[0] - 1, n).astype(np.int64)]
        return pts

    def add_node(
        self,
        node: int,
        pose_frontend: Pose2D,
        points_laser_m: FloatArray,
        scan: LaserScan | None = None,
    ) -> list[Submap]:
        """Insert a node (and its rays, if `scan`); returns the submaps it finished."""
        if node % self._half == 0:
            sub = Submap(len(self.submaps), node, pose_frontend)
            self.submaps.append(sub)
            self._active.append(sub)
        finished = []
        for sub in self._active:
            sub.insert(node, pose_frontend, points_laser_m, scan, self.params.observed_resolution_m)
        for sub in list(self._active):
            if len(sub.nodes) >= self.params.nodes_per_submap:
                sub.finish(self.params)
                self._active.remove(sub)
                finished.append(sub)
        return finished


def _field_bytes(f: LikelihoodField) -> int:
    return int(f.fine.nbytes + f.coarse.nbytes + f.known.nbytes)
