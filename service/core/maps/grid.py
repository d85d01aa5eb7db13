"""Log-odds occupancy grid in sparse tiles, built from scans at their poses (numpy; the ray
casting compiled, `raycast`).

The map grows as the robot explores: cells live in 64 x 64 float32 tiles (16 KiB, 3.2 m at
0.05 m) allocated on first touch, so memory is proportional to the explored area; only a small
tile index (4 bytes per tile position) spans the bounding box. Free space comes from ray
casting: every valid beam clears the cells it crosses and marks its end cell occupied.

Each scan updates a cell at most once (a free cell crossed by many beams gets one ``l_free``; a hit
wins over free in the same scan), so dense near-field beams do not over-weight the cells next to
the robot. Beams are sampled every half cell while neighbouring beams are closer than a cell (so
no cell between them is skipped) and every cell beyond. Near the sensor, only a power-of-two
subset of beams is traced: beam ``b`` starts at the distance where beams ``lowbit(b)`` apart are
half a cell apart. A 1,081-beam indoor scan is a few tens of thousands of samples.

Invalid beams (NaN, error codes, at or beyond ``range_max_m``) do not update the map: a missing
return may be glass, a dark surface or a dropout right next to the robot, so clearing space along
it would erase real obstacles. Open areas therefore stay unknown beyond the sensor's reach.

``GridImage.occupancy`` row 0 is the LOWEST y (like a ROS ``nav_msgs/OccupancyGrid``); image
writers flip it so north is up. ``origin_x_m, origin_y_m`` is the corner of cell (row 0, col 0).

A finished map chunk (`maps.composed`) is frozen (`freeze`): its tiles kept in int8 steps,
read-only, never integrated into again.

Not thread-safe: one owner integrates and snapshots.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import numpy as np
import numpy.typing as npt

from service.core.maps.raycast import mark_cells
from service.core.types import LaserScan, Pose2D, frozen_array

TILE_SHIFT: Final = 6
TILE_CELLS: Final = 1 << TILE_SHIFT  # 64 x 64 cells per tile (3.2 m at 0.05 m)
_TILE_MASK: Final = TILE_CELLS - 1
_TILE_SIZE: Final = TILE_CELLS * TILE_CELLS
_STEP_FACTOR: Final = 0.5  # two samples per cell length along a beam: no holes between beams
_MAX_NEAR_STRIDE: Final = 64  # coarsest beam subset used in the near field

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]


class GridError(ValueError):
    """Bad grid parameters."""


@dataclass(frozen=True, slots=True, eq=False)
class GridImage:
    """A snapshot of the map.

    ``occupancy`` is (H, W) int8: -1 unknown, 0..100 occupancy probability in percent.
    Row ``i``, column ``j`` covers ``x in [origin_x_m + j*res, +res)``,
    ``y in [origin_y_m + i*res, +res)``: row 0 is the lowest y.
    """

    occupancy: npt.NDArray[np.int8]
    origin_x_m: float
    origin_y_m: float
    resolution_m: float

    @property
    def height(self) -> int:
        return int(self.occupancy.shape[0])

    @property
    def width(self) -> int:
        return int(self.occupancy.shape[1])


class OccupancyGrid:
    """Sparse log-odds occupancy grid. See the module docstring for the update rules."""

    def __init__(
        self,
        resolution_m: float = 0.05,
        *,
        l_occ: float = 0.85,
        l_free: float = -0.4,
        l_min: float = -2.0,
        l_max: float = 3.5,
    ) -> None:
        if not (resolution_m > 0.0 and np.isfinite(resolution_m)):
            raise GridError(f"resolution_m must be positive, got {resolution_m}")
        if not (l_occ > 0.0 > l_free and l_min < 0.0 < l_max):
            raise GridError("need l_occ > 0 > l_free and l_min < 0 < l_max")
        self.resolution_m = float(resolution_m)
        self.l_occ = float(l_occ)
        self.l_free = float(l_free)
        self.l_min = float(l_min)
        self.l_max = float(l_max)
        self.sample_step_m = self.resolution_m * _STEP_FACTOR
        self._near_cache: dict[tuple[int, float], FloatArray] = {}
        self.clear()

    def clear(self) -> None:
        """Forget everything."""
        # Slot 0 is a permanently empty tile: missing tiles in the index point at it.
        self._store = np.zeros((8, TILE_CELLS, TILE_CELLS), dtype=np.float32)
        self._n_tiles = 1
        self._index = np.zeros((0, 0), dtype=np.int32)  # tile row/col -> slot (0 = none)
        self._index_ti0 = 0
        self._index_tj0 = 0
        self.scans_integrated = 0
        # Once frozen (`freeze`): the tiles as int8 steps of `_frozen_step`; `_store` empty.
        self._frozen: npt.NDArray[np.int8] | None = None
        self._frozen_step = 0.0

    @property
    def tile_count(self) -> int:
        """Number of allocated tiles."""
        return self._n_tiles - 1

    def memory_bytes(self) -> int:
        """Bytes held by the tile store (allocated capacity) and the tile index."""
        frozen = self._frozen.nbytes if self._frozen is not None else 0
        return int(self._store.nbytes + self._index.nbytes + frozen)

    # ------------------------------------------------------------------------------------
    def integrate(self, scan: LaserScan, pose: Pose2D) -> None:
        """Ray-cast one scan taken at ``pose`` (laser frame = robot frame) into the map."""
        if self._frozen is not None:
            raise ValueError("this grid is frozen: read-only")
        res = self.resolution_m
        valid = scan.valid_mask()
        beams = np.nonzero(valid)[0]
        self.scans_integrated += 1
        if beams.shape[0] == 0:
            return
        ranges = scan.ranges_m[beams].astype(np.float64, copy=False)
        ang = scan.angles_rad()[beams] + pose.theta_rad
        cos_a, sin_a = np.cos(ang), np.sin(ang)
        px, py = float(pose.x_m), float(pose.y_m)

        # Free samples from the beam's near-field start to just before its end point: half a
        # cell apart while neighbouring beams are closer than a cell (no holes between them),
        # one cell apart beyond that, where every beam has its own cells anyway. Each cell
        # once per scan, and a hit wins over free: a scan-local mark per cell (`raycast`).
        starts = self._near_starts(scan.ranges_m.shape[0], scan.angle_increment_rad)[beams]
        dtheta = abs(float(scan.angle_increment_rad))
        split_m = res / dtheta if dtheta > 0.0 else np.inf
        inv = 1.0 / res  # cells in cell units
        mark, i0, j0, width = mark_cells(
            px * inv, py * inv, cos_a * inv, sin_a * inv, ranges, starts, split_m, res,
            self.sample_step_m,
        )  # fmt: skip
        free_local = np.flatnonzero(mark == 1)
        hit_local = np.flatnonzero(mark == 2)
        local = np.concatenate((free_local, hit_local))
        rows, cols = np.divmod(local, width)
        flat = self._flat_indices(rows + i0, cols + j0)
        free_flat, hit_flat = flat[: free_local.shape[0]], flat[free_local.shape[0] :]

        cells = self._store.reshape(-1)
        cells[free_flat] = np.clip(cells[free_flat] + self.l_free, self.l_min, self.l_max)
        cells[hit_flat] = np.clip(cells[hit_flat] + self.l_occ, self.l_min, self.l_max)

    def _near_starts(self, beam_count: int, increment_rad: float) -> FloatArray:
        """Per-beam distance at which tracing starts (0 for the coarsest beam subset)."""
        key = (beam_count, float(increment_rad))
        cached = self._near_cache.get(key)
        if cached is not None:
            return cached
        b = np.arange(beam_count, dtype=np.int64)
        lowbit = np.where(b == 0, _MAX_NEAR_STRIDE, b & -b)
        stride = np.minimum(lowbit, _MAX_NEAR_STRIDE).astype(np.float64)
        dtheta = abs(float(increment_rad))
        if dtheta <= 0.0 or not np.isfinite(dtheta):
            starts = np.zeros(beam_count, dtype=np.float64)
        else:
            starts = self.resolution_m / (2.0 * stride * dtheta)
            starts[stride >= _MAX_NEAR_STRIDE] = 0.0
            # The last beam closes the fan on its side.
            starts[-1] = 0.0
        self._near_cache[key] = starts
        return starts

    def _flat_indices(self, ci: IntArray, cj: IntArray) -> IntArray:
        """Flat store indices of cells (row ci, col cj), allocating tiles on first touch."""
        ti = ci >> TILE_SHIFT
        tj = cj >> TILE_SHIFT
        self._ensure_index(int(ti.min()), int(ti.max()), int(tj.min()), int(tj.max()))
        # Flat positions in the tile index: one 1-D gather is cheaper than 2-D fancy indexing.
        keys = (ti - self._index_ti0) * self._index.shape[1] + (tj - self._index_tj0)
        index_flat = self._index.reshape(-1)
        slots = index_flat[keys]
        missing = slots == 0
        if missing.any():
            new_keys = np.unique(keys[missing])
            first_slot = self._n_tiles
            self._reserve(first_slot + new_keys.shape[0])
            index_flat[new_keys] = np.arange(
                first_slot, first_slot + new_keys.shape[0], dtype=np.int32
            )
            self._n_tiles += int(new_keys.shape[0])
            slots = index_flat[keys]
        local = ((ci & _TILE_MASK) << TILE_SHIFT) | (cj & _TILE_MASK)
        flat: IntArray = slots.astype(np.int64) * _TILE_SIZE + local
        return flat

    def _ensure_index(self, ti_min: int, ti_max: int, tj_min: int, tj_max: int) -> None:
        h, w = self._index.shape
        if h and (
            ti_min >= self._index_ti0
            and ti_max < self._index_ti0 + h
            and tj_min >= self._index_tj0
            and tj_max < self._index_tj0 + w
        ):
            return
        # Grow with a margin so a robot driving on does not re-allocate every scan.
        margin = 8
        if h:
            ti_min = min(ti_min, self._index_ti0)
            ti_max = max(ti_max, self._index_ti0 + h - 1)
            tj_min = min(tj_min, self._index_tj0)
            tj_max = max(tj_max, self._index_tj0 + w - 1)
        ti0, tj0 = ti_min - margin, tj_min - margin
        grown = np.zeros((ti_max - ti0 + 1 + margin, tj_max - tj0 + 1 + margin), dtype=np.int32)
        if h:
            oi, oj = self._index_ti0 - ti0, self._index_tj0 - tj0
            grown[oi : oi + h, oj : oj + w] = self._index
        self._index = grown
        self._index_ti0, self._index_tj0 = ti0, tj0

    def _reserve(self, n_slots: int) -> None:
        capacity = self._store.shape[0]
        if n_slots <= capacity:
            return
        new_cap = max(n_slots, capacity * 2)
        grown = np.zeros((new_cap, TILE_CELLS, TILE_CELLS), dtype=np.float32)
        grown[:capacity] = self._store
        self._store = grown

    def freeze(self) -> None:
        """Never integrate again: the tiles kept are the allocated ones, as int8 steps of
        max(-l_min, l_max) / 127 (a quarter of the memory; 0.028 at the defaults, a known cell
        stays known), and the tile index is trimmed to the rows and columns that hold one;
        both read-only (`frozen_array`: a checkpoint's array pack writes them once)."""
        rows = np.nonzero((self._index != 0).any(axis=1))[0]
        cols = np.nonzero((self._index != 0).any(axis=0))[0]
        if rows.shape[0]:
            self._index = self._index[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
            self._index_ti0 += int(rows[0])
            self._index_tj0 += int(cols[0])
        else:
            self._index = np.zeros((0, 0), dtype=np.int32)
        self._index = frozen_array(self._index)
        step = max(-self.l_min, self.l_max) / 127.0
        cells = self._store[: self._n_tiles]
        steps = np.rint(cells / np.float32(step))
        tiny = (steps == 0.0) & (cells != 0.0)  # known, however close to even: kept known
        steps[tiny] = np.sign(cells[tiny])
        self._frozen = frozen_array(steps.astype(np.int8))
        self._frozen_step = step
        self._store = np.zeros((0, TILE_CELLS, TILE_CELLS), dtype=np.float32)
        self._near_cache.clear()

    # ------------------------------------------------------------------------------------
    def log_odds(self) -> tuple[npt.NDArray[np.float32], int, int]:
        """Dense log-odds over the allocated tiles: (array, first cell row, first cell col)."""
        rows = np.nonzero((self._index != 0).any(axis=1))[0]
        cols = np.nonzero((self._index != 0).any(axis=0))[0]
        if rows.shape[0] == 0:
            return np.zeros((0, 0), dtype=np.float32), 0, 0
        sub = self._index[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
        if self._frozen is not None:
            tiles = self._frozen[sub].astype(np.float32) * np.float32(self._frozen_step)
        else:
            tiles = self._store[sub]  # (th, tw, 64, 64); missing tiles read slot 0 (zeros)
        th, tw = sub.shape
        dense = tiles.transpose(0, 2, 1, 3).reshape(th * TILE_CELLS, tw * TILE_CELLS)
        cell_i0 = (int(rows[0]) + self._index_ti0) * TILE_CELLS
        cell_j0 = (int(cols[0]) + self._index_tj0) * TILE_CELLS
        return dense, cell_i0, cell_j0

    def snapshot(self) -> GridImage:
        """The map cropped to its known cells; an empty 0 x 0 image before any update."""
        dense, ci0, cj0 = self.log_odds()
        return log_odds_image(dense, ci0, cj0, self.resolution_m, self.l_min, self.l_max)


def log_odds_image(  # noqa: PLR0917 - the cells, where they start, and their scale
    dense: npt.NDArray[np.float32],
    ci0: int,
    cj0: int,
    resolution_m: float,
    l_min: float,
    l_max: float,
) -> GridImage:
    """Dense log-odds (cell (ci0, cj0) first) as an image cropped to its known cells."""
    res = resolution_m
    known = dense != 0.0
    rows = np.nonzero(known.any(axis=1))[0]
    cols = np.nonzero(known.any(axis=0))[0]
    if rows.shape[0] == 0:
        return GridImage(np.zeros((0, 0), dtype=np.int8), 0.0, 0.0, res)
    r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    lo = dense[r0:r1, c0:c1]
    # Probability in percent through a lookup table over the clamped log-odds range:
    # far cheaper than exp() over millions of cells.
    steps = 4096
    table_lo = np.linspace(l_min, l_max, steps)
    table = np.rint(100.0 / (1.0 + np.exp(-table_lo))).astype(np.int8)
    scale = np.float32((steps - 1) / (l_max - l_min))
    idx = ((lo - np.float32(l_min)) * scale + np.float32(0.5)).astype(np.int32)
    occ = table[np.clip(idx, 0, steps - 1)]
    occ[lo == 0.0] = -1
    return GridImage(
        occupancy=occ,
        origin_x_m=(cj0 + c0) * res,
        origin_y_m=(ci0 + r0) * res,
        resolution_m=res,
    )
