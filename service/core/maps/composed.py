"""The map drawn at the optimised poses: occupancy chunks composed by their anchors' corrections.

Every drawn scan goes, once, into the chunk of its stretch of travel: the `nodes_per_chunk`
consecutive graph nodes its latest node belongs to (scans before the first node: a chunk of
their own, never moved). A chunk is a log-odds grid (`OccupancyGrid`, sparse tiles) on the map
axes at the front-end poses, i.e. fixed in its anchor's (first node's) front-end frame. When a
scan of the next stretch comes, the chunk is frozen: its tile store trimmed and read-only, never
changed again. Drawing the map moves each chunk by its anchor node's correction (optimised ∘
front-end⁻¹: a translation and, for a Manhattan building, a rotation of a fraction of a degree)
and adds its log-odds, chunk after chunk in the order travelled, clamping after each (as a grid
clamps after each scan: a wall seen in one stretch is not outvoted by the sum of every other
stretch's clamped free space). The resampling is an inverse warp, nearest cell: every map
cell looks up the chunk cell it came from, so no holes open under a rotation.

So a drawing costs one gather per chunk, whatever the number of scans, and memory is the
chunks' tiles: the area seen per stretch of travel, times the stretches (a place seen on
several passes is held once per pass). It grows with the keyframes (the distance travelled),
not with the scans: a robot standing still adds nothing. The approximation: a scan is moved by
its chunk's anchor's correction, not its own node's (they differ by how much the graph bends
within the stretch).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Final

import numpy as np
import numpy.typing as npt

from service.core.maps.grid import GridImage, OccupancyGrid, log_odds_image
from service.core.types import LaserScan, Pose2D

F32Array = npt.NDArray[np.float32]

NODES_PER_CHUNK: Final = 20  # a chunk's stretch of travel, in graph nodes (as a submap's)


@dataclass(slots=True)
class MapChunk:
    """The scans of one stretch of travel at their front-end poses; `frozen` once the next
    stretch began. `anchor_node` -1: the scans before the first node."""

    anchor_node: int
    grid: OccupancyGrid
    frozen: bool = False
    scans: int = 0

    @property
    def nbytes(self) -> int:
        return self.grid.memory_bytes()


@dataclass(slots=True)
class ChunkedMap:
    """Map chunks of `nodes_per_chunk` nodes each; `compose` draws them at given corrections."""

    resolution_m: float
    nodes_per_chunk: int = NODES_PER_CHUNK
    chunks: list[MapChunk] = field(default_factory=list)

    def draw(self, scan: LaserScan, pose_frontend: Pose2D, node: int) -> None:
        """Ray-cast `scan` at its front-end pose into its chunk: that of its latest graph
        `node` (-1: none yet). A scan of a new stretch freezes the chunk before it."""
        anchor = node - node % self.nodes_per_chunk if node >= 0 else -1
        chunk = self.chunks[-1] if self.chunks else None
        if chunk is None or chunk.anchor_node != anchor:
            if chunk is not None:
                chunk.grid.freeze()
                chunk.frozen = True
            chunk = MapChunk(anchor, OccupancyGrid(self.resolution_m))
            self.chunks.append(chunk)
        chunk.grid.integrate(scan, pose_frontend)
        chunk.scans += 1

    @property
    def nbytes(self) -> int:
        return sum(c.nbytes for c in self.chunks)

    @property
    def scans(self) -> int:
        return sum(c.scans for c in self.chunks)

    def compose(self, corrections: list[Pose2D]) -> GridImage:
        """The map with each chunk moved by `corrections[its anchor node]` (identity for the
        chunk before the first node, or an anchor without a correction yet)."""
        res = self.resolution_m
        parts: list[tuple[F32Array, int, int, Pose2D]] = []
        lo_i = lo_j = math.inf
        hi_i = hi_j = -math.inf
        for chunk in self.chunks:
            dense, i0, j0 = chunk.grid.log_odds()
            if dense.size == 0:
                continue
            a = chunk.anchor_node
            c = corrections[a] if 0 <= a < len(corrections) else Pose2D(0.0, 0.0, 0.0)
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
        if not parts:
            return GridImage(np.zeros((0, 0), dtype=np.int8), 0.0, 0.0, res)
        t = self.chunks[0].grid  # l_min, l_max of every chunk
        oi, oj = int(lo_i), int(lo_j)
        total = np.zeros((int(hi_i) - oi + 1, int(hi_j) - oj + 1), dtype=np.float32)
        for dense, i0, j0, c in parts:
            _warp_add(total, oi, oj, dense, i0, j0, c, res, t.l_min, t.l_max)
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
    l_min: float,
    l_max: float,
) -> None:
    """total += `dense` (cells from (i0, j0)) moved by `c`, nearest cell (inverse warp)."""
    h, w = dense.shape
    if abs(c.theta_rad) < 1e-9:
        di, dj = c.y_m / res, c.x_m / res
        if abs(di - round(di)) < 1e-6 and abs(dj - round(dj)) < 1e-6:
            r, q = i0 + round(di) - oi, j0 + round(dj) - oj
            target = total[r : r + h, q : q + w]
            target += dense
            np.clip(target, l_min, l_max, out=target)
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
    window[ok] = np.clip(window[ok] + dense[src_i[ok], src_j[ok]], l_min, l_max)
