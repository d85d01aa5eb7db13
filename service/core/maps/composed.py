"""The map drawn at the optimised poses: occupancy chunks composed by their anchors' corrections.

Every node's scan goes into the chunk of its stretch of travel (`nodes_per_chunk` consecutive
nodes), a log-odds grid (`OccupancyGrid`) on the map axes at the front-end poses. A full chunk is
frozen: cropped to its known cells, float32, never changed again. Drawing the map moves each
chunk by its anchor node's correction (optimised ∘ front-end⁻¹: a translation and, for a
Manhattan building, a rotation of a fraction of a degree), sums the log-odds and clamps them.
The resampling is an inverse warp, nearest cell: every map cell looks up the chunk cell it came
from, so no holes open under a rotation.

Memory is the chunks' known cells: proportional to the area seen per stretch of travel, times
the stretches (a place seen on several passes is held once per pass). Why chunks and not a
re-integration of every scan after a closure: a render is one gather per chunk, not a ray cast
per scan (measured in docs/backend.md, "Live").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from service.core.maps.grid import GridImage, OccupancyGrid, log_odds_image
from service.core.types import LaserScan, Pose2D, frozen_array

F32Array = npt.NDArray[np.float32]


@dataclass(slots=True)
class MapChunk:
    """Consecutive nodes' scans on the map axes; `grid` while filling, `frozen` once full."""

    anchor_node: int
    nodes: int = 0
    grid: OccupancyGrid | None = None
    frozen: F32Array | None = None  # dense log-odds, cropped to its known cells
    cell_i0: int = 0  # map cell (row, column) of frozen[0, 0]
    cell_j0: int = 0

    def log_odds(self) -> tuple[F32Array, int, int]:
        if self.frozen is not None:
            return self.frozen, self.cell_i0, self.cell_j0
        assert self.grid is not None
        return self.grid.log_odds()

    def freeze(self) -> None:
        assert self.grid is not None
        dense, i0, j0 = self.grid.log_odds()
        known = dense != 0.0
        rows = np.nonzero(known.any(axis=1))[0]
        cols = np.nonzero(known.any(axis=0))[0]
        if rows.shape[0] == 0:
            self.frozen = frozen_array(np.zeros((0, 0), dtype=np.float32))
        else:
            r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
            self.frozen = frozen_array(dense[r0:r1, c0:c1])
            i0, j0 = i0 + r0, j0 + c0
        self.cell_i0, self.cell_j0 = i0, j0
        self.grid = None

    @property
    def nbytes(self) -> int:
        if self.frozen is not None:
            return int(self.frozen.nbytes)
        return self.grid.memory_bytes() if self.grid is not None else 0


class ChunkedMap:
    """Map chunks of `nodes_per_chunk` nodes each; `compose` draws them at given corrections."""

    def __init__(self, resolution_m: float, nodes_per_chunk: int = 20) -> None:
        self.resolution_m = float(resolution_m)
        self.nodes_per_chunk = max(1, int(nodes_per_chunk))
        self.chunks: list[MapChunk] = []
        self._template = OccupancyGrid(self.resolution_m)  # l_occ, l_min, ... of every chunk

    def add_node(self, node: int, pose_frontend: Pose2D, scan: LaserScan) -> None:
        chunk = self.chunks[-1] if self.chunks else None
        if chunk is None or chunk.nodes >= self.nodes_per_chunk:
            if chunk is not None:
                chunk.freeze()
            chunk = MapChunk(node, grid=OccupancyGrid(self.resolution_m))
            self.chunks.append(chunk)
        assert chunk.grid is not None
        chunk.grid.integrate(scan, pose_frontend)
        chunk.nodes += 1

    @property
    def nbytes(self) -> int:
        return sum(c.nbytes for c in self.chunks)

    def compose(self, corrections: list[Pose2D]) -> GridImage:
        """The map with chunk k moved by `corrections[its anchor node]` (identity if absent)."""
        res = self.resolution_m
        parts: list[tuple[F32Array, int, int, Pose2D]] = []
        lo_i = lo_j = math.inf
        hi_i = hi_j = -math.inf
        for chunk in self.chunks:
            dense, i0, j0 = chunk.log_odds()
            if dense.size == 0:
                continue
            a = chunk.anchor_node
            c = corrections[a] if a < len(corrections) else Pose2D(0.0, 0.0, 0.0)
            h, w = dense.shape
            # The chunk's corners moved by the correction give its cells in the map.
            xs = np.array([j0, j0 + w, j0, j0 + w], dtype=np.float64) * res
            ys = np.array([i0, i0, i0 + h, i0 + h], dtype=np.float64) * res
            cs, sn = math.cos(c.theta_rad), math.sin(c.theta_rad)
            mx = c.x_m + cs * xs - sn * ys
            my = c.y_m + sn * xs + cs * ys
            lo_i, hi_i = min(lo_i, math.floor(my.min() / res)), max(hi_i, math.ceil(my.max() / res))
            lo_j, hi_j = min(lo_j, math.floor(mx.min() / res)), max(hi_j, math.ceil(mx.max() / res))
            parts.append((dense, i0, j0, c))
        t = self._template
        if not parts:
            return GridImage(np.zeros((0, 0), dtype=np.int8), 0.0, 0.0, res)
        oi, oj = int(lo_i), int(lo_j)
        total = np.zeros((int(hi_i) - oi + 1, int(hi_j) - oj + 1), dtype=np.float32)
        for dense, i0, j0, c in parts:
            _warp_add(total, oi, oj, dense, i0, j0, c, res)
        np.clip(total, t.l_min, t.l_max, out=total)
        return log_odds_image(total, oi, oj, res, t.l_min, t.l_max)


def _warp_add(  # noqa: PLR0917 - the target, the source and the move between them
    total: F32Array,
    oi: int,
    oj: int,
    dense: F32Array,
    i0: int,
    j0: int,
    c: Pose2D,
    res: float,
) -> None:
    """total += `dense` (cells from (i0, j0)) moved by `c`, nearest cell (inverse warp)."""
    h, w = dense.shape
    if abs(c.theta_rad) < 1e-9:
        di, dj = c.y_m / res, c.x_m / res
        if abs(di - round(di)) < 1e-6 and abs(dj - round(dj)) < 1e-6:
            r, q = i0 + round(di) - oi, j0 + round(dj) - oj
            total[r : r + h, q : q + w] += dense
            return
    cs, sn = math.cos(c.theta_rad), math.sin(c.theta_rad)
    xs = np.array([j0, j0 + w, j0, j0 + w], dtype=np.float64) * res
    ys = np.array([i0, i0, i0 + h, i0 + h], dtype=np.float64) * res
    mx = c.x_m + cs * xs - sn * ys
    my = c.y_m + sn * xs + cs * ys
    ti0 = max(math.floor(my.min() / res) - oi, 0)
    ti1 = min(math.ceil(my.max() / res) - oi, total.shape[0] - 1)
    tj0 = max(math.floor(mx.min() / res) - oj, 0)
    tj1 = min(math.ceil(mx.max() / res) - oj, total.shape[1] - 1)
    # Map cell centres of the target window, moved back into the chunk: (p - t) rotated by -θ.
    yc = ((np.arange(ti0, ti1 + 1) + oi + 0.5) * res - c.y_m)[:, None]
    xc = ((np.arange(tj0, tj1 + 1) + oj + 0.5) * res - c.x_m)[None, :]
    src_j = np.floor((cs * xc + sn * yc) / res).astype(np.int64) - j0
    src_i = np.floor((-sn * xc + cs * yc) / res).astype(np.int64) - i0
    ok = (src_i >= 0) & (src_i < h) & (src_j >= 0) & (src_j < w)
    window = total[ti0 : ti1 + 1, tj0 : tj1 + 1]
    window[ok] += dense[src_i[ok], src_j[ok]]
